"""A project's MLflow store as one file: packed to commit beside its reports, unpacked anywhere.

A project's store is its SQLite ``mlflow.db`` and its artifact folder ``mlartifacts/``
(:func:`cloudpose.tracking.experiment_id`). MLflow records every run's artifact folder as an
absolute ``file://`` address, so a store copied to another folder or machine points back to the
one it came from. :func:`pack_store` writes ``mlflow.db`` (a consistent SQLite backup: runs
may be writing) and the artifacts into a ``.tar.xz``, with every address under the project's
``mlartifacts/`` made relative to the project (``mlartifacts/GROUP/RUN/artifacts``), and
checkpoints (``*.pt``, the bulk of a store) left out but for the runs named.
:func:`unpack_store` extracts such an archive into a folder and points every address into that
folder's ``mlartifacts/``, whatever machine the addresses came from (archives packed by hand,
with absolute addresses, included): then ``cloudpose report``, ``cloudpose mlflow-ui`` and
``cloudpose ablate`` work in that folder as in the original project.
"""

from __future__ import annotations

import sqlite3
import tarfile
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from cloudpose.files import atomic_write
from cloudpose.tracking import ARTIFACT_DIR, STORE_DB

CHECKPOINT_SUFFIX = ".pt"
"""Files left out of a packed store but for the runs named to keep them."""


@dataclass(frozen=True)
class PackSummary:
    """What :func:`pack_store` wrote: runs in the store, artifact files packed, checkpoints kept
    and left out, the archive's size in bytes."""

    runs: int
    files: int
    checkpoints_kept: int
    checkpoints_left_out: int
    bytes: int


def _relative(uri: str) -> str | None:
    """``mlartifacts/...`` of an address under some project's artifact folder, else None."""
    if uri.startswith(f"{ARTIFACT_DIR}/"):
        return uri
    i = uri.find(f"/{ARTIFACT_DIR}/")
    return uri[i + 1 :] if i >= 0 else None


def _rewrite(db: Path, to: Callable[[str], str]) -> int:
    """Replace each run's artifact address and each experiment's artifact location that lies
    under an artifact folder by ``to(its relative form)``; returns how many runs the store
    holds."""
    con = sqlite3.connect(db)
    try:
        with con:
            for table, key, column in (
                ("runs", "run_uuid", "artifact_uri"),
                ("experiments", "experiment_id", "artifact_location"),
            ):
                rows = con.execute(f"SELECT {key}, {column} FROM {table}").fetchall()
                for k, uri in rows:
                    rel = _relative(uri or "")
                    if rel is not None:
                        con.execute(
                            f"UPDATE {table} SET {column} = ? WHERE {key} = ?", (to(rel), k)
                        )
        return con.execute("SELECT COUNT(*) FROM runs").fetchone()[0]
    finally:
        con.close()


def _run_ids(db: Path, names: list[str]) -> set[str]:
    """Run ids of ``names``: each a run id, or a run name (its newest active run)."""
    con = sqlite3.connect(db)
    try:
        ids = set()
        for name in names:
            row = con.execute("SELECT run_uuid FROM runs WHERE run_uuid = ?", (name,)).fetchone()
            row = (
                row
                or con.execute(
                    "SELECT run_uuid FROM runs WHERE name = ? AND lifecycle_stage = 'active' "
                    "ORDER BY start_time DESC LIMIT 1",
                    (name,),
                ).fetchone()
            )
            if row is None:
                raise ValueError(f"{db}: no run with the id or name {name!r}")
            ids.add(row[0])
        return ids
    finally:
        con.close()


def pack_store(project_dir: Path, out: Path, checkpoints: Sequence[str] = ()) -> PackSummary:
    """Pack the store of ``project_dir`` into ``out`` (``.tar.xz``), written atomically.

    Args:
        project_dir: the folder holding ``mlflow.db`` and ``mlartifacts/``.
        out: the archive to write.
        checkpoints: runs (ids or names; a name means its newest active run) whose ``*.pt``
            files are packed; every other run's are left out.
    """
    project_dir = Path(project_dir)
    db = project_dir / STORE_DB
    if not db.is_file():
        raise FileNotFoundError(f"{db}: no MLflow store to pack (expected a project's {STORE_DB})")
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / STORE_DB
        src = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
        dst = sqlite3.connect(copy)
        try:
            src.backup(dst)
        finally:
            src.close()
            dst.close()
        keep = _run_ids(copy, list(checkpoints))
        runs = _rewrite(copy, lambda rel: rel)
        files = kept = left = 0
        root = project_dir / ARTIFACT_DIR

        def write(path: Path) -> None:
            nonlocal files, kept, left
            with tarfile.open(path, "w:xz", preset=6) as tar:
                tar.add(copy, arcname=STORE_DB)
                for f in sorted(root.rglob("*")) if root.is_dir() else []:
                    if not f.is_file():
                        continue
                    rel = f.relative_to(project_dir)
                    if f.suffix == CHECKPOINT_SUFFIX:
                        # mlartifacts/GROUP/RUN_ID/artifacts/...
                        if len(rel.parts) < 3 or rel.parts[2] not in keep:
                            left += 1
                            continue
                        kept += 1
                    tar.add(f, arcname=rel.as_posix())
                    files += 1

        atomic_write(out, write, suffix=".tar.xz")
    return PackSummary(runs, files, kept, left, Path(out).stat().st_size)


def unpack_store(archive: Path, into: Path) -> int:
    """Extract a packed store into ``into`` and point its artifact addresses there.

    Args:
        archive: a ``.tar.xz`` of ``mlflow.db`` and ``mlartifacts/`` (from :func:`pack_store`,
            or packed by hand with absolute addresses of another machine).
        into: the folder to hold the store; it must not hold an ``mlflow.db`` yet.

    Returns:
        The number of runs in the store.
    """
    archive, into = Path(archive), Path(into)
    if (into / STORE_DB).exists():
        raise FileExistsError(
            f"{into / STORE_DB} exists: unpack into a folder without a store (this one's runs would be "
            "replaced)"
        )
    with tarfile.open(archive, "r:*") as tar:
        members, has_db = [], False
        for m in tar.getmembers():
            name = m.name.removeprefix("./")
            if name in ("", "."):
                continue
            if name != STORE_DB and name.split("/")[0] != ARTIFACT_DIR:
                raise ValueError(
                    f"{archive}: member {m.name!r} is neither {STORE_DB} nor under {ARTIFACT_DIR}/ "
                    "(not a packed cloudpose store)"
                )
            has_db |= name == STORE_DB
            members.append(m)
        if not has_db:
            raise ValueError(
                f"{archive}: no {STORE_DB} in the archive (not a packed cloudpose store)"
            )
        into.mkdir(parents=True, exist_ok=True)
        tar.extractall(into, members=members, filter="data")
    base = (into.resolve() / ARTIFACT_DIR).as_uri()
    return _rewrite(into / STORE_DB, lambda rel: base + rel.removeprefix(ARTIFACT_DIR))
