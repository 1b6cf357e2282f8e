"""A project's MLflow store as a folder of small files, which git stores run by run.

A packed ``.tar.xz`` (:mod:`cloudpose.archive.pack`) is one blob: every repack adds the whole
store to a repository's history again. The compact form keeps each run in a folder of its own
and the database as text, so a new sweep round adds only its new runs' files (and a few lines
of the index) and git stores nothing again of the runs it had::

    DIR/index.tsv                  a format line, then path, bytes and SHA-256 of every file
    DIR/experiments.json           the experiments (ids kept) and their tags
    DIR/runs/RUN_ID/run.json       the run's row (name, status, times, experiment), tags, params
    DIR/runs/RUN_ID/metrics.tsv    every logged value of every metric (key, step, timestamp,
                                   value as Python's shortest exact repr, is_nan), sorted
    DIR/runs/RUN_ID/artifacts/     the run's artifacts; instance tables packed
                                   (:mod:`cloudpose.archive.packed`), checkpoints only of the
                                   runs named, in fewer bytes where the poses do not move
                                   (:mod:`cloudpose.archive.checkpoints`)
    DIR/shared/SHA.parquet         the data's columns of instance tables, one per set of rows

:func:`write_compact` writes it from a packed database copy (addresses made relative by
:func:`cloudpose.archive.pack.pack_store`); a file whose content did not change keeps its
bytes (an instance table is compared by its values, so a repack with another pyarrow leaves it
as it is). :func:`check_compact` checks the index against the folder before anything is
written: every file it lists there whole, every file there listed, every run listed with its
record and metrics; it names the first file that is not; :func:`extract_compact` rebuilds
``mlflow.db``: an empty store made by the installed MLflow (its schema, whatever its version),
then the stored rows written into it with their run and experiment ids, and each metric's
latest value derived as MLflow derives it (highest step, then timestamp, then value).

What the form keeps of a store: experiments and their tags, runs, tags, params, metrics
(``latest_metrics`` follows from them). Rows of other tables (datasets, traces, registered
models: the suite logs none) are left out with a warning.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import sqlite3
import tempfile
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cloudpose.archive import checkpoints, packed
from cloudpose.files import CorruptFileError, atomic_text, why
from cloudpose.store import instances
from cloudpose.store.tracking import ARTIFACT_DIR, STORE_DB

FORMAT = "# cloudpose MLflow store, compact form 3"
"""First line of :data:`INDEX` as :func:`write_compact` writes it."""

FORMATS = (
    "# cloudpose MLflow store, compact form 1",
    "# cloudpose MLflow store, compact form 2",
    FORMAT,
)
"""First lines of the indexes this version reads: form 1 keeps each instance table in the
evaluation's form, form 2 packed (:mod:`cloudpose.archive.packed`), form 3 also checkpoints
(:mod:`cloudpose.archive.checkpoints`: ``model.fp16.pt``, ``model.f24.pt``, which a reader of
form 2 would not unpack)."""

INDEX = "index.tsv"
EXPERIMENTS = "experiments.json"
RUNS = "runs"
RUN_FILE = "run.json"
METRICS_FILE = "metrics.tsv"
ARTIFACTS = "artifacts"
METRIC_COLUMNS = ("key", "step", "timestamp", "value", "is_nan")
"""Columns of :data:`METRICS_FILE` (its header line)."""

_KEPT = {"experiments", "experiment_tags", "runs", "tags", "params", "metrics", "latest_metrics"}
_MADE_BY_MLFLOW = {"alembic_version", "workspaces"}

CHECKPOINT_SUFFIX = ".pt"
"""Suffix of a run's checkpoint artifacts (``model.pt``): kept only for the runs named."""


@dataclass(frozen=True)
class RunSource:
    """One run's artifacts to pack: where they are read from, and which checkpoints to keep."""

    run_id: str
    source: Path
    keep_checkpoints: bool


@dataclass(frozen=True)
class CompactSummary:
    """Files written (artifact files packed, checkpoints kept and left out), the folder's size
    in bytes, and (run id, record) of each checkpoint whose form was checked
    (:mod:`cloudpose.archive.checkpoints`)."""

    files: int
    checkpoints_kept: int
    checkpoints_left_out: int
    bytes: int
    checked: tuple[tuple[str, dict], ...] = ()


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _rows(con: sqlite3.Connection, sql: str, args: Sequence = ()) -> list[dict]:
    cur = con.execute(sql, args)
    names = [d[0] for d in cur.description]
    return [dict(zip(names, row, strict=True)) for row in cur.fetchall()]


def _json(obj) -> str:
    return json.dumps(obj, indent=1, sort_keys=True, ensure_ascii=False) + "\n"


def _metrics_text(rows: Iterable[tuple]) -> str:
    """:data:`METRICS_FILE` of a run's metric rows ``(key, step, timestamp, value, is_nan)``."""
    lines = ["\t".join(METRIC_COLUMNS)]
    for key, step, ts, value, is_nan in sorted(rows, key=lambda r: (r[0], r[1], r[2], r[3])):
        if "\t" in key or "\n" in key:
            raise ValueError(f"metric key {key!r} holds a tab or a line end: not storable")
        lines.append(f"{key}\t{int(step)}\t{int(ts)}\t{float(value)!r}\t{int(bool(is_nan))}")
    return "\n".join(lines) + "\n"


def _left_out(con: sqlite3.Connection) -> list[str]:
    """``table (N rows)`` of each non-empty table the compact form does not keep."""
    tables = [t for (t,) in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
    out = []
    for t in sorted(set(tables) - _KEPT - _MADE_BY_MLFLOW):
        if t.startswith("sqlite_"):
            continue
        n = con.execute(f'SELECT COUNT(*) FROM "{t}"').fetchone()[0]
        if n:
            out.append(f"{t} ({n} rows)")
    return out


@dataclass
class _Staged:
    """Counts of :func:`_stage_artifacts`, over every run."""

    files: int = 0
    kept: int = 0
    left: int = 0
    checked: list[tuple[str, dict]] = field(default_factory=list)


def _checkpoint_record(f: Path) -> bool:
    """Whether ``f`` is the record of a checkpoint beside it (written with the checkpoint)."""
    if not f.name.endswith(checkpoints.RECORD_SUFFIX):
        return False
    stem = f.name.removesuffix(checkpoints.RECORD_SUFFIX)
    return (f.parent / f"{stem}{CHECKPOINT_SUFFIX}").is_file()


def _stage_artifacts(
    run: RunSource,
    dest: Path,
    counts: _Staged,
    check: checkpoints.PoseCheck | None,
    shipped: set[str],
) -> None:
    """Copy a run's artifacts into ``dest``, instance tables as Parquet, kept checkpoints in
    the form :func:`cloudpose.archive.checkpoints.pack_checkpoint` chooses (with ``check``);
    counts into ``counts``."""
    if not run.source.is_dir():
        return
    for f in sorted(run.source.rglob("*")):
        if not f.is_file() or _checkpoint_record(f):
            continue
        rel = f.relative_to(run.source)
        if f.suffix == CHECKPOINT_SUFFIX:
            if not run.keep_checkpoints:
                counts.left += 1
                continue
            counts.kept += 1
            counts.files += 1
            written = checkpoints.pack_checkpoint(f, (dest / rel).parent, check, shipped)
            if written.record is not None:
                counts.files += 1
                counts.checked.append((run.run_id, written.record))
            continue
        target = dest / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        if f.name == instances.CSV and not (f.parent / instances.PARQUET).is_file():
            try:
                instances.csv_to_parquet(f, target.with_name(instances.PARQUET))
            except (ValueError, UnicodeDecodeError) as exc:
                raise CorruptFileError(
                    f,
                    f"instance table of run {run.run_id} is unreadable ({why(exc)}); nothing "
                    "packed: evaluate the run again, or leave the run out",
                ) from exc
        else:
            shutil.copyfile(f, target)
        counts.files += 1


def _pack_tables(staging: Path, run_ids: Sequence[str]) -> None:
    """Pack every staged instance table (:mod:`cloudpose.archive.packed`) in place, runs in the
    order given (oldest first): the first table of each set of rows gives the shared table of
    the data's columns, written under ``shared/``."""
    shared: dict[str, tuple[object, str]] = {}
    for rid in run_ids:
        folder = staging / RUNS / rid / ARTIFACTS
        if not folder.is_dir():
            continue
        for path in sorted(folder.rglob(instances.PARQUET)):
            table = packed.read(path)
            if packed.layout_of(table) is not None:
                raise CorruptFileError(
                    path, "an artifact is already a packed table; evaluate the run again"
                )
            reduced = packed.reduce(table)
            key = packed.row_key(reduced)
            if key is None:
                packed.write(packed.encode(reduced), path)
                continue
            if key not in shared:
                base = packed.shared_table(reduced)
                ref = packed.shared_name(base)
                (staging / packed.SHARED).mkdir(exist_ok=True)
                packed.write(base, staging / ref)
                shared[key] = (base, ref)
            base, ref = shared[key]
            packed.write(packed.encode(reduced, base, ref), path)


def _stage(
    db: Path, runs: Sequence[RunSource], staging: Path, check: checkpoints.PoseCheck | None
) -> _Staged:
    """The compact form of the store ``db`` (addresses relative) and its runs' artifacts,
    written into ``staging`` (no index yet)."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        left_out = _left_out(con)
        if left_out:
            warnings.warn(
                f"{db}: the compact form keeps experiments, runs, tags, params and metrics; "
                f"left out: {', '.join(left_out)}",
                stacklevel=3,
            )
        exps = _rows(con, "SELECT * FROM experiments ORDER BY experiment_id")
        for e in exps:
            e["tags"] = dict(
                con.execute(
                    "SELECT key, value FROM experiment_tags WHERE experiment_id = ?",
                    (e["experiment_id"],),
                ).fetchall()
            )
        atomic_text(staging / EXPERIMENTS, _json({"experiments": exps}))
        by_id = {r.run_id: r for r in runs}
        counts = _Staged()
        shipped = checkpoints.shipped_digests()
        order = []
        for row in _rows(con, "SELECT * FROM runs ORDER BY run_uuid"):
            rid = row["run_uuid"]
            folder = staging / RUNS / rid
            record = {
                "run": row,
                "tags": dict(con.execute("SELECT key, value FROM tags WHERE run_uuid = ?", (rid,))),
                "params": dict(
                    con.execute("SELECT key, value FROM params WHERE run_uuid = ?", (rid,))
                ),
            }
            atomic_text(folder / RUN_FILE, _json(record))
            metrics = con.execute(
                "SELECT key, step, timestamp, value, is_nan FROM metrics WHERE run_uuid = ?",
                (rid,),
            )
            atomic_text(folder / METRICS_FILE, _metrics_text(metrics))
            if rid in by_id:
                _stage_artifacts(by_id[rid], folder / ARTIFACTS, counts, check, shipped)
            order.append((row["start_time"] or 0, rid))
        _pack_tables(staging, [rid for _, rid in sorted(order)])
        return counts
    finally:
        con.close()


def _listed(folder: Path) -> list[str]:
    """The store's files in ``folder`` (experiments, runs, shared tables), relative, sorted."""
    out = [EXPERIMENTS] if (folder / EXPERIMENTS).is_file() else []
    for sub in (RUNS, packed.SHARED):
        if (folder / sub).is_dir():
            out += [
                p.relative_to(folder).as_posix() for p in (folder / sub).rglob("*") if p.is_file()
            ]
    return sorted(out)


def held_checkpoints(folder: Path) -> set[str]:
    """Run ids of the checkpoints (``*.pt``) a compact store in ``folder`` holds (none where
    there is no such folder)."""
    return {
        rel.split("/")[1]
        for rel in _listed(Path(folder))
        if rel.startswith(f"{RUNS}/") and rel.endswith(CHECKPOINT_SUFFIX)
    }


def _same(new: Path, old: Path) -> bool:
    if not old.is_file():
        return False
    if new.stat().st_size == old.stat().st_size and new.read_bytes() == old.read_bytes():
        return True
    if checkpoints.packed_form(new.name) is not None:
        return checkpoints.same_packed(new, old)
    if new.suffix != ".parquet" or not instances.same_table(new, old):
        return False
    layouts = [packed.layout_of(packed.read(p)) for p in (new, old)]
    return layouts[0] == layouts[1]


def _sync(staging: Path, out: Path) -> None:
    """Make ``out`` hold what ``staging`` holds, keeping each file whose content is the same;
    the index goes first (an interrupted sync leaves none: unpacking refuses, a new pack mends)
    and is written last."""
    out.mkdir(parents=True, exist_ok=True)
    (out / INDEX).unlink(missing_ok=True)
    new = _listed(staging)
    keep = set(new)
    for rel in _listed(out):
        if rel not in keep:
            (out / rel).unlink()
    for rel in new:
        if not _same(staging / rel, out / rel):
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            os.replace(staging / rel, out / rel)
    for sub in (RUNS, packed.SHARED):
        for d in sorted((out / sub).rglob("*"), key=lambda p: -len(p.parts)):
            if d.is_dir() and not any(d.iterdir()):
                d.rmdir()
    if (out / packed.SHARED).is_dir() and not any((out / packed.SHARED).iterdir()):
        (out / packed.SHARED).rmdir()
    lines = [FORMAT]
    lines += [f"{rel}\t{(out / rel).stat().st_size}\t{_sha256(out / rel)}" for rel in new]
    atomic_text(out / INDEX, "\n".join(lines) + "\n")


def write_compact(
    db: Path,
    runs: Sequence[RunSource],
    out: Path,
    check: checkpoints.PoseCheck | None = None,
) -> CompactSummary:
    """Write the compact form of the store ``db`` (a copy whose addresses are relative) and
    the artifacts of ``runs`` into the folder ``out``, created or brought up to date.

    ``check``: the pose check by which a kept checkpoint is stored in fewer bytes
    (:func:`cloudpose.archive.checkpoints.pack_checkpoint`); None keeps each as it is (but for
    one that a record beside it says was packed so).

    Everything is written into a hidden folder beside ``out`` first (removed whatever
    happens), then moved in file by file where it changed.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.{os.getpid()}-", dir=out.parent))
    try:
        counts = _stage(db, runs, staging, check)
        _sync(staging, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    size = sum((out / rel).stat().st_size for rel in [INDEX, *_listed(out)])
    return CompactSummary(counts.files, counts.kept, counts.left, size, tuple(counts.checked))


# ---------------------------------------------------------------------------- reading


def _restore(path: Path) -> str:
    return f"restore it (git checkout -- {path}) or pack the store again (cloudpose store-pack)"


def check_compact(folder: Path) -> list[tuple[str, int, str]]:
    """The files the index of ``folder`` lists, each checked to be there whole (size and
    SHA-256), as ``(path, bytes, sha256)``; the folder holds no file the index does not list.

    Raises:
        FileNotFoundError: no index, a listed file is missing, or the index lists files of a
            run but not its :data:`RUN_FILE` or :data:`METRICS_FILE` (the message names it).
        CorruptFileError: the index is not one, a file differs from what it lists, or a file
            in the folder is not listed.
    """
    folder = Path(folder)
    index = folder / INDEX
    if not index.is_file():
        raise FileNotFoundError(
            f"{index}: missing, so {folder} is not a compact store (or its pack was stopped): "
            + _restore(index)
        )
    try:
        lines = index.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise CorruptFileError(index, f"not a store index ({why(exc)}); {_restore(index)}") from exc
    if not lines or lines[0] not in FORMATS:
        first = lines[0][:60] if lines else "nothing"
        raise CorruptFileError(index, f"starts with {first!r}, not {FORMAT!r}; {_restore(index)}")
    entries = []
    for n, line in enumerate(lines[1:], start=2):
        parts = line.split("\t")
        bad = len(parts) != 3 or not parts[1].isdigit() or len(parts[2]) != 64
        rel = parts[0]
        if not bad:
            bad = rel.startswith("/") or ".." in rel.split("/") or "\\" in rel
        if bad:
            raise CorruptFileError(
                index,
                f"line {n} is not 'PATH<tab>BYTES<tab>SHA-256' inside the folder; "
                + _restore(index),
            )
        entries.append((rel, int(parts[1]), parts[2]))
    if not any(rel == EXPERIMENTS for rel, _, _ in entries):
        raise CorruptFileError(index, f"lists no {EXPERIMENTS}; {_restore(index)}")
    listed = [rel for rel, _, _ in entries]
    missing = [rel for rel in listed if not (folder / rel).is_file()]
    if missing:
        path = folder / missing[0]
        raise FileNotFoundError(
            f"{path}: missing (listed in {index}){_more(missing)}; nothing unpacked: "
            + _restore(path)
        )
    unlisted = sorted(set(_files_in(folder)) - set(listed))
    if unlisted:
        raise CorruptFileError(
            folder / unlisted[0],
            f"in {folder} but not listed in {index}{_more(unlisted)}, so it would not be "
            f"unpacked; nothing unpacked: restore the index (git checkout -- {index}), pack "
            "the store again (cloudpose store-pack --force), or move the file out",
        )
    lacking = _runs_without_record(listed)
    if lacking:
        path = folder / RUNS / lacking[0][0] / lacking[0][1]
        raise FileNotFoundError(
            f"{path}: missing and not listed in {index}, which lists other files of run "
            f"{lacking[0][0]}{_more(lacking)}: the run would be lost; nothing unpacked: "
            + _restore(path)
        )
    for rel, size, sha in entries:
        path = folder / rel
        have = path.stat().st_size
        if have != size:
            what = f"{have} bytes, not the {size} bytes that {INDEX} lists"
        elif (digest := _sha256(path)) != sha:
            what = f"SHA-256 {digest[:12]}..., not the {sha[:12]}... that {INDEX} lists (same size)"
        else:
            continue
        raise CorruptFileError(path, f"damaged: {what}; nothing unpacked: {_restore(path)}")
    return entries


def _more(paths: Sequence[str]) -> str:
    """`` (and N more)`` after the first of ``paths`` that a message names."""
    return f" (and {len(paths) - 1} more)" if len(paths) > 1 else ""


def _files_in(folder: Path) -> list[str]:
    """Every file (or link) in the compact ``folder`` but its index, relative, sorted."""
    return sorted(
        p.relative_to(folder).as_posix()
        for p in folder.rglob("*")
        if (p.is_file() or p.is_symlink()) and p != folder / INDEX
    )


def _runs_without_record(listed: Iterable[str]) -> list[tuple[str, str]]:
    """(run id, :data:`RUN_FILE` or :data:`METRICS_FILE`) of each run folder of which the
    index lists files but not that one: without both, :func:`extract_compact` cannot rebuild
    the run."""
    have: dict[str, set[str]] = {}
    for rel in listed:
        parts = rel.split("/")
        if parts[0] == RUNS and len(parts) > 2:
            have.setdefault(parts[1], set()).add("/".join(parts[2:]))
    return [
        (rid, name)
        for rid, files in sorted(have.items())
        for name in (RUN_FILE, METRICS_FILE)
        if name not in files
    ]


def _new_database(db: Path) -> None:
    """An empty MLflow store at ``db``, with the schema of the installed MLflow."""
    from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore

    for name in ("alembic", "mlflow.store.db.utils"):
        logging.getLogger(name).setLevel(logging.WARNING)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        store = SqlAlchemyStore(f"sqlite:///{db}", (db.parent.resolve() / "mlruns").as_uri())
        store.engine.dispose()


def _insert(con: sqlite3.Connection, table: str, rows: list[dict], replace: bool = False) -> None:
    """Insert ``rows`` (column -> value) into ``table``: the columns the table has; a stored
    column it lacks (a schema of another MLflow) is dropped, with a warning when it holds
    values."""
    if not rows:
        return
    have = [r[1] for r in con.execute(f'PRAGMA table_info("{table}")')]
    cols = [c for c in rows[0] if c in have]
    lost = {c for r in rows for c, v in r.items() if c not in have and v is not None}
    if lost:
        warnings.warn(
            f"this MLflow's {table} table has no columns {sorted(lost)}: their values are not "
            "in the rebuilt store",
            stacklevel=3,
        )
    verb = "INSERT OR REPLACE" if replace else "INSERT"
    names = ", ".join(f'"{c}"' for c in cols)
    marks = ", ".join("?" for _ in cols)
    con.executemany(
        f'{verb} INTO "{table}" ({names}) VALUES ({marks})',
        [[r.get(c) for c in cols] for r in rows],
    )


def _read_json(path: Path, what: str):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CorruptFileError(
            path, f"{what} is not readable JSON ({why(exc)}); {_restore(path)}"
        ) from exc


def _metric_rows(path: Path, run_id: str) -> list[tuple]:
    lines = path.read_text(encoding="utf-8").splitlines()
    if not lines or tuple(lines[0].split("\t")) != METRIC_COLUMNS:
        raise CorruptFileError(path, f"lacks its header {METRIC_COLUMNS}; {_restore(path)}")
    rows = []
    for n, line in enumerate(lines[1:], start=2):
        try:
            key, step, ts, value, is_nan = line.split("\t")
            rows.append((key, float(value), int(ts), run_id, int(step), int(is_nan)))
        except ValueError:
            raise CorruptFileError(
                path,
                f"line {n} is not {len(METRIC_COLUMNS)} tab-separated fields; " + _restore(path),
            ) from None
    return rows


def _runs_of(entries: list[tuple[str, int, str]]) -> list[str]:
    return sorted(
        {
            rel.split("/")[1]
            for rel, _, _ in entries
            if rel.startswith(f"{RUNS}/") and rel.endswith(f"/{RUN_FILE}")
        }
    )


def _unpack_table(
    folder: Path, rel: str, listed: set[str], shared: dict[str, object], target: Path
) -> None:
    """Write the instance table ``rel`` of ``folder`` to ``target`` in the evaluation's form:
    a packed table decoded (its shared table read once, into ``shared``), any other copied."""
    table = packed.read(folder / rel)
    layout = packed.layout_of(table)
    if layout is None:
        shutil.copyfile(folder / rel, target)
        return
    base = None
    if layout.from_shared:
        if layout.shared not in listed:
            raise CorruptFileError(
                folder / rel,
                f"names the shared table {layout.shared}, which {INDEX} does not list; "
                + _restore(folder),
            )
        if layout.shared not in shared:
            shared[layout.shared] = packed.read(folder / layout.shared)
        base = shared[layout.shared]
    instances.write_arrow(packed.decode(table, base), target)


def extract_compact(folder: Path, entries: list[tuple[str, int, str]], staging: Path) -> int:
    """Rebuild the store of the compact ``folder`` in ``staging``: its artifacts under
    ``mlartifacts/`` where each run's (relative) address points, and ``mlflow.db``.

    Args:
        folder: the compact store.
        entries: its files, as :func:`check_compact` returned them (checked).
        staging: an empty folder.

    Returns:
        The number of runs.
    """
    folder, staging = Path(folder), Path(staging)
    run_ids = _runs_of(entries)
    exps = _read_json(folder / EXPERIMENTS, "experiment list")["experiments"]
    records = {r: _read_json(folder / RUNS / r / RUN_FILE, "run record") for r in run_ids}
    listed = {rel for rel, _, _ in entries}
    shared: dict[str, object] = {}
    for rid, rec in records.items():
        member = rec["run"].get("artifact_uri") or ""
        prefix = f"{RUNS}/{rid}/{ARTIFACTS}/"
        files = [rel for rel in listed if rel.startswith(prefix)]
        if files and not member.startswith(f"{ARTIFACT_DIR}/"):
            raise CorruptFileError(
                folder / RUNS / rid / RUN_FILE,
                f"its artifact_uri {member!r} is not under {ARTIFACT_DIR}/; {_restore(folder)}",
            )
        for rel in files:
            target = staging / member / rel[len(prefix) :]
            target.parent.mkdir(parents=True, exist_ok=True)
            if target.name == instances.PARQUET:
                _unpack_table(folder, rel, listed, shared, target)
            elif checkpoints.packed_form(target.name) is not None:
                try:
                    checkpoints.unpack_checkpoint(
                        folder / rel, target.with_name(checkpoints.unpacked_name(target.name))
                    )
                except CorruptFileError as exc:
                    raise CorruptFileError(
                        exc.path, f"{exc.message}; nothing unpacked: {_restore(exc.path)}"
                    ) from exc
            else:
                shutil.copyfile(folder / rel, target)
    db = staging / STORE_DB
    _new_database(db)
    con = sqlite3.connect(db)
    try:
        with con:
            exp_rows = [{k: v for k, v in e.items() if k != "tags"} for e in exps]
            _insert(con, "experiments", exp_rows, replace=True)
            con.execute("DELETE FROM experiment_tags")
            _insert(
                con,
                "experiment_tags",
                [
                    {"key": k, "value": v, "experiment_id": e["experiment_id"]}
                    for e in exps
                    for k, v in sorted(e["tags"].items())
                ],
            )
            _insert(con, "runs", [records[r]["run"] for r in run_ids])
            for what in ("tags", "params"):
                _insert(
                    con,
                    what,
                    [
                        {"key": k, "value": v, "run_uuid": r}
                        for r in run_ids
                        for k, v in sorted(records[r][what].items())
                    ],
                )
            for r in run_ids:
                con.executemany(
                    "INSERT INTO metrics (key, value, timestamp, run_uuid, step, is_nan) "
                    "VALUES (?, ?, ?, ?, ?, ?)",
                    _metric_rows(folder / RUNS / r / METRICS_FILE, r),
                )
            # MLflow's latest value of a metric: highest step, then timestamp, then value
            con.execute(
                "INSERT INTO latest_metrics (key, value, timestamp, step, is_nan, run_uuid) "
                "SELECT key, value, timestamp, step, is_nan, run_uuid FROM ("
                " SELECT *, ROW_NUMBER() OVER (PARTITION BY run_uuid, key"
                "  ORDER BY step DESC, timestamp DESC, value DESC) AS n FROM metrics"
                ") WHERE n = 1"
            )
    finally:
        con.close()
    return len(run_ids)
