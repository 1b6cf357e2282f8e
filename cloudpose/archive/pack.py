"""A project's MLflow store packed to commit beside its reports, unpacked anywhere: as one
``.tar.xz``, or as a folder in the compact form that git stores run by run
(:mod:`cloudpose.archive.compact`; :func:`pack_store` writes it for any name not ending in
``.tar.xz``, :func:`unpack_store` reads both).

A project's store is its SQLite ``mlflow.db`` and its artifact folder ``mlartifacts/``
(:func:`cloudpose.store.tracking.experiment_id`). MLflow records every run's artifact folder as an
absolute ``file://`` address, so a store copied to another folder or machine points back to the
one it came from. :func:`pack_store` writes ``mlflow.db`` (a consistent SQLite backup: runs
may be writing) and every run's artifacts into a ``.tar.xz``, with every address made relative
to the project (``mlartifacts/GROUP/RUN/artifacts``), and checkpoints (``*.pt``, the bulk of a
store) left out but for the runs named; every ``run_dir`` tag is written relative too, and a
run left RUNNING by a process that is gone as KILLED (:func:`_mark_dead`). A run's artifacts
are taken from where its address points when that is not under ``mlartifacts/`` (MLflow's
``./mlruns`` of a store named by
``MLFLOW_TRACKING_URI=sqlite:///...``); a store whose artifacts are not on this machine's disk
(a tracking server's, an object store's) is refused, never packed without them. An existing
archive is replaced only when asked (``force``, ``--force``).

:func:`unpack_store` extracts such an archive into a hidden folder inside the target, points
every address into the target's ``mlartifacts/`` relative to the store's folder (whatever
machine the addresses came from: archives packed by hand, with absolute addresses, included),
writes each run's ``run_dir`` tag relative to it too (``runs/VARIANT/PRESET/FOLDER``), and only
then moves the store into place, ``mlflow.db`` last: an unpack that is stopped (Ctrl-C,
SIGTERM, an error) leaves no store behind, and its rerun is not refused. Into an
``mlartifacts/`` already there (an earlier unpack's, its ``mlflow.db`` removed), each run's
artifact folder replaces the one of the same address, so that a run's artifacts are the
store's and no others (a folder that held other files is named in a warning); folders of runs
the store does not hold are left as they are. Nothing in the
unpacked ``mlflow.db`` names the folder it was unpacked into: the folder can be moved or
copied, and every command reads its artifacts against the store's folder
(:func:`cloudpose.store.tracking.artifact_address`). An archive with a member outside the folder (``../``,
an absolute path, a link leading out) is refused before anything is written. Then
``cloudpose report``, ``cloudpose mlflow-ui`` and ``cloudpose ablate`` work in that folder as
in the original project.
"""

from __future__ import annotations

import contextlib
import filecmp
import json
import lzma
import os
import shutil
import sqlite3
import tarfile
import tempfile
import time
import warnings
import zlib
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import NamedTuple

from cloudpose.archive.checkpoints import PoseCheck
from cloudpose.archive.compact import (
    CHECKPOINT_SUFFIX,
    RunSource,
    check_compact,
    extract_compact,
    held_checkpoints,
    write_compact,
)
from cloudpose.failures import disk_full, sigterm_as_interrupt
from cloudpose.files import atomic_write, checked_members
from cloudpose.store import tracking
from cloudpose.store.liveness import KILLED_TAG, STALE_AFTER_S, dead_runs
from cloudpose.store.runs import INFO, TRAINING_PREFIXES, folder_locked, lock_path
from cloudpose.store.tracking import ARTIFACT_DIR, EXPERIMENT_PREFIX, STORE_DB

"""Files left out of a packed store but for the runs named to keep them."""

UNPACK_PREFIX = ".store-unpack-"
"""The hidden folder inside the target that an unpack extracts into before moving in
(``.store-unpack-PID-XXXX``)."""

PACK_PREFIX = "cloudpose-store-pack-"
"""The temporary folder of a pack's database copy (``cloudpose-store-pack-PID-XXXX``)."""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process
        return True
    return True


def _remove_stale(folder: Path, pattern: str, prefix: str) -> None:
    """Remove what a killed (``kill -9``) pack or unpack left in ``folder``: the entries
    matching ``pattern`` whose name, after ``prefix``, starts with the id of a process that is
    gone. Every other exit path removes its own."""
    for entry in folder.glob(pattern) if folder.is_dir() else []:
        pid = entry.name[len(prefix) :].split(".")[0].split("-")[0]
        if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)


@dataclass(frozen=True)
class PackSummary:
    """What :func:`pack_store` wrote: runs in the store, artifact files packed, checkpoints kept
    and left out, the archive's size in bytes, and the runs whose artifact folder is missing
    (ids; report runs, which have no artifacts, not counted)."""

    runs: int
    files: int
    checkpoints_kept: int
    checkpoints_left_out: int
    bytes: int
    without_artifacts: tuple[str, ...] = ()
    checked: tuple[tuple[str, dict], ...] = ()
    """(run id, record) of each checkpoint whose form was checked (compact form only:
    :mod:`cloudpose.archive.checkpoints`)."""
    killed: tuple[tuple[str, str], ...] = ()
    """(run name, why) of each run left RUNNING by a process that is gone, packed KILLED."""
    running: tuple[tuple[str, str], ...] = ()
    """(run name, what is packed of it) of each run packed RUNNING: its process may live."""
    held: tuple[str, ...] = ()
    """Run ids whose checkpoints a compact folder being updated held and keeps, not named."""


def _relative(uri: str) -> str | None:
    """``mlartifacts/...`` of an address under some project's artifact folder, else None."""
    if uri.startswith(f"{ARTIFACT_DIR}/"):
        return uri
    i = uri.find(f"/{ARTIFACT_DIR}/")
    return uri[i + 1 :] if i >= 0 else None


def _rewrite(db: Path, to: Callable[[str], str | None]) -> int:
    """Replace each run's artifact address and each experiment's artifact location ``uri`` by
    ``to(uri)`` where that is not None; returns how many runs the store holds."""
    con = sqlite3.connect(db)
    try:
        with con:
            for table, key, column in (
                ("runs", "run_uuid", "artifact_uri"),
                ("experiments", "experiment_id", "artifact_location"),
            ):
                rows = con.execute(f"SELECT {key}, {column} FROM {table}").fetchall()
                for k, uri in rows:
                    new = to(uri or "")
                    if new is not None and new != uri:
                        con.execute(f"UPDATE {table} SET {column} = ? WHERE {key} = ?", (new, k))
        return con.execute("SELECT COUNT(*) FROM runs").fetchone()[0]
    finally:
        con.close()


DEFAULT_ARTIFACTS = "mlruns"
"""MLflow's own artifact folder of a store (its ``Default`` experiment's location)."""


def _portable(uri: str) -> str | None:
    """``to`` of :func:`_rewrite` at unpacking (and at packing, for an address the pack does
    not move: an experiment's location): an address under an artifact folder as
    ``mlartifacts/...``, a local one under MLflow's :data:`DEFAULT_ARTIFACTS` as ``mlruns/...``,
    both relative to the store's folder; None (kept) for any other."""
    rel = _relative(uri)
    if rel is not None or tracking.is_relative_address(uri):
        return rel
    local = tracking.local_artifact(uri, "")
    if local is None:
        return None
    parts = local.parts
    if DEFAULT_ARTIFACTS in parts:
        i = len(parts) - 1 - parts[::-1].index(DEFAULT_ARTIFACTS)
        return "/".join(parts[i:])
    return None


RUN_DIR_TAG = "run_dir"
"""Tag of a training run: its run folder (``runs/VARIANT/PRESET/FOLDER`` of the project)."""


def relative_run_dir(
    value: str, project: Path | None, exists: Callable[[Path], bool] = Path.exists
) -> str | None:
    """The ``run_dir`` tag to write instead of ``value``, or None to keep it: a folder inside
    ``project`` relative to it; one that is not on this machine (``exists``) the run folder's
    place in this project, ``runs/{variant}/{preset}/{folder}`` (its last three parts)."""
    path = Path(value)
    if not value or not path.is_absolute():
        return None
    if project is not None:
        with contextlib.suppress(ValueError):
            return str(PurePosixPath(path.relative_to(project)))
    if exists(path) or len(path.parts) < 4:
        return None
    return str(PurePosixPath("runs", *path.parts[-3:]))


def _relative_run_dirs(db: Path, project: Path | None = None) -> None:
    """Write each absolute ``run_dir`` tag relative to the store's folder
    (:func:`cloudpose.store.tracking.store_path` reads it there), by :func:`relative_run_dir`
    with no run folder taken as on this machine: a folder inside ``project`` (the folder of the
    store packed) relative to it, any other as its place in the store's project."""
    project = project.resolve() if project is not None else None
    con = sqlite3.connect(db)
    try:
        with con:
            rows = con.execute(
                "SELECT run_uuid, value FROM tags WHERE key = ?", (RUN_DIR_TAG,)
            ).fetchall()
            for run_id, value in rows:
                rel = relative_run_dir(value or "", project, exists=lambda _: False)
                if rel is not None:
                    con.execute(
                        "UPDATE tags SET value = ? WHERE run_uuid = ? AND key = ?",
                        (rel, run_id, RUN_DIR_TAG),
                    )
    finally:
        con.close()


LOCK_HELD = "held"
LOCK_RELEASED = "released"


def _lock_state(run_id: str, run_dir: str, project: Path) -> str | None:
    """How the run folder ``run_dir`` (a relative one under ``project``) of the run ``run_id``
    stands on this machine: :data:`LOCK_HELD` while a process holds its lock (it trains);
    :data:`LOCK_RELEASED` when the folder is here, its ``run.json`` names this run and no
    process holds its lock file (the one that trained it is gone: the system releases a dead
    process's lock); else None (nothing here to ask)."""
    if not run_dir:
        return None
    folder = Path(run_dir) if Path(run_dir).is_absolute() else project / run_dir
    if folder_locked(folder):
        return LOCK_HELD
    if not lock_path(folder).is_file():
        return None
    try:
        info = json.loads((folder / INFO).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return LOCK_RELEASED if isinstance(info, dict) and info.get("run_id") == run_id else None


def _utc(ms: int) -> str:
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(ms / 1000))


class Marked(NamedTuple):
    """What :func:`_mark_dead` found of the runs left RUNNING: (run name, why) of each
    recorded KILLED, (run name, what is packed of it) of each packed RUNNING."""

    killed: list[tuple[str, str]]
    running: list[tuple[str, str]]


def _mark_dead(
    db: Path, project: Path, keep: Collection[str] = (), now_ms: int | None = None
) -> Marked:
    """Record as KILLED (end time: its last activity; tag ``marked_killed``: why) each active
    run of the store copy ``db`` left RUNNING by a process that is gone, by the rule of
    :mod:`cloudpose.store.liveness` (:func:`~cloudpose.store.liveness.dead_runs`): its run
    folder is here and no process holds its lock; or, with no folder here to ask, a later run
    of the same variant, preset, seed and config started after its last activity, or it
    logged nothing for :data:`~cloudpose.store.liveness.STALE_AFTER_S`. Every other RUNNING run
    is packed RUNNING as it stands; ``keep``: the runs whose checkpoints are packed."""
    now_ms = int(time.time() * 1000) if now_ms is None else now_ms
    con = sqlite3.connect(db)
    try:
        runs = con.execute(
            "SELECT run_uuid, name, status, start_time FROM runs WHERE lifecycle_stage = 'active'"
        ).fetchall()
        tags: dict[str, dict[str, str]] = {r[0]: {} for r in runs}
        for rid, key, value in con.execute("SELECT run_uuid, key, value FROM tags"):
            if rid in tags:
                tags[rid][key] = value
        start_of = {rid: start or 0 for rid, _, _, start in runs}
        name_of = {rid: name for rid, name, _, _ in runs}

        def training(rid: str) -> tuple[int, int | None]:
            """(last activity ms, last training step or None) of a run."""
            last, step = start_of[rid], None
            for key, ts, top in con.execute(
                "SELECT key, MAX(timestamp), MAX(step) FROM metrics WHERE run_uuid = ? "
                "GROUP BY key",
                (rid,),
            ):
                if key.split("/")[0] in TRAINING_PREFIXES:
                    last, step = max(last, ts), max(step or 0, top)
            return last, step

        state: dict[str, str | None] = {}

        def lock(rid: str) -> str | None:
            if rid not in state:
                state[rid] = _lock_state(rid, tags[rid].get(RUN_DIR_TAG, ""), project)
            return state[rid]

        config = ("variant", "preset", "seed", "config")
        dead = dead_runs(
            [
                (rid, status, start, tuple(tags[rid].get(k) for k in config))
                for rid, _, status, start in runs
            ],
            now_ms,
            lambda rid: training(rid)[0],
            lambda rid: lock(rid) == LOCK_HELD,
            lambda rid: lock(rid) == LOCK_RELEASED,
        )
        killed = []
        with con:
            for d in dead:
                rid, last, later = d.run, d.last_activity_ms, d.later_start_ms
                # said without the time of packing, so that a repack writes the same tag
                if d.lock_released:
                    why = (
                        f"RUNNING when packed, but no process holds its run folder's lock: the "
                        f"process that trained it is gone (last activity {_utc(last)})"
                    )
                elif later is not None and later > last:
                    why = (
                        f"RUNNING when packed, but a later run of the same config started "
                        f"{_utc(later)}, after its last activity ({_utc(last)})"
                    )
                else:
                    why = (
                        f"RUNNING when packed, but nothing logged since {_utc(last)}, over "
                        f"{STALE_AFTER_S / 3600:.0f} h before (a live run logs every epoch)"
                    )
                con.execute(
                    "UPDATE runs SET status = 'KILLED', end_time = ? WHERE run_uuid = ?",
                    (last, rid),
                )
                con.execute(
                    "INSERT OR REPLACE INTO tags (key, value, run_uuid) VALUES (?, ?, ?)",
                    (KILLED_TAG, f"{why}; marked by cloudpose store-pack", rid),
                )
                killed.append((name_of[rid], why))
        gone = {d.run for d in dead}
        running = []
        for rid, name, status, _ in runs:
            if status != "RUNNING" or rid in gone:
                continue
            last, step = training(rid)
            if lock(rid) == LOCK_HELD:
                alive = "its process holds its run folder's lock"
            else:
                alive = (
                    "its process may live: no run folder of it here to ask, and it logged "
                    f"within {STALE_AFTER_S / 3600:.0f} h"
                )
            logged = (
                f"training metrics to step {step}, {_utc(last)}"
                if step is not None
                else f"no training metric yet, started {_utc(last)}"
            )
            ckpt = ", its checkpoints as they are now" if rid in keep else ""
            what = f"{alive}; packed RUNNING as it stands ({logged}{ckpt}): pack again when it ends"
            running.append((name, what))
        return Marked(killed, running)
    finally:
        con.close()


def _under_artifacts(base: str) -> Callable[[str], str | None]:
    """``to`` of :func:`_rewrite`: an address under an artifact folder moved under ``base``
    (the ``mlartifacts`` folder's URI, or ``mlartifacts`` itself for relative addresses)."""

    def to(uri: str) -> str | None:
        rel = _relative(uri)
        return None if rel is None else base + rel.removeprefix(ARTIFACT_DIR)

    return to


def _checkpoint_runs(
    copy: Path, store: Path, named: list[str], dropped: list[str], folder: Path | None
) -> tuple[set[str], set[str]]:
    """(run ids whose checkpoints to pack, those of them kept only because the compact
    ``folder`` being updated held them): the runs ``named`` (``--checkpoint``) and the ones
    ``folder`` holds, less the runs ``dropped`` (``--drop-checkpoint``)."""
    keep = _run_ids(copy, named, store)
    drop = _run_ids(copy, dropped, store, "--drop-checkpoint")
    if keep & drop:
        raise ValueError(
            f"--checkpoint and --drop-checkpoint both name run {sorted(keep & drop)[0]}; "
            "nothing packed"
        )
    if folder is None or not folder.is_dir():
        return keep, set()
    con = sqlite3.connect(copy)
    try:
        known = {r for (r,) in con.execute("SELECT run_uuid FROM runs")}
    finally:
        con.close()
    held = (held_checkpoints(folder) & known) - keep - drop
    return keep | held, held


def _run_ids(db: Path, names: list[str], store: Path, option: str = "--checkpoint") -> set[str]:
    """Run ids of ``names`` (given with ``option``): each a run id, or a run name (its newest
    active run), looked up in ``db`` (a copy of the store ``store``, which a message names)."""
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
                some = [
                    n
                    for (n,) in con.execute(
                        "SELECT DISTINCT name FROM runs WHERE lifecycle_stage = 'active' "
                        "ORDER BY name LIMIT 3"
                    )
                ]
                given = f"e.g. {', '.join(some)}" if some else "it holds no run"
                raise ValueError(
                    f"{option} {name!r}: no run of {store} has that id or name (expected a "
                    f"run id or a run name: {given}); nothing packed"
                )
            ids.add(row[0])
        return ids
    finally:
        con.close()


@dataclass(frozen=True)
class _RunArtifacts:
    """Where one run's artifacts are read from and where they go in the archive."""

    run_id: str
    source: Path
    """The run's artifact folder on this machine (it may not exist: a run without artifacts)."""
    member: str
    """``mlartifacts/GROUP/RUN_ID/artifacts``: the folder in the archive and its new address."""
    expected: bool = True
    """Whether the run should have artifacts (a report run, ``kind=report``, has none)."""


def _artifact_plan(db: Path, project: Path) -> tuple[list[_RunArtifacts], dict[str, str]]:
    """Every run's artifacts, and the addresses to rewrite (old -> ``mlartifacts/...``).

    An address under an artifact folder is read from this project's ``mlartifacts/`` (where a
    store copied from elsewhere has them), else from where it points; any other local address
    (MLflow's ``./mlruns``) from where it points, packed under
    ``mlartifacts/{group}/{run}/artifacts``. A remote address (``s3://``, a tracking server's
    ``mlflow-artifacts:``) is refused: its files are not on this disk.
    """
    con = sqlite3.connect(db)
    try:
        exps = dict(con.execute("SELECT experiment_id, name FROM experiments").fetchall())
        rows = con.execute(
            "SELECT run_uuid, experiment_id, artifact_uri FROM runs ORDER BY run_uuid"
        ).fetchall()
        reports = {
            r
            for (r,) in con.execute(
                "SELECT run_uuid FROM tags WHERE key = 'kind' AND value = 'report'"
            )
        }
    finally:
        con.close()
    plan, moved = [], {}
    for run_id, exp_id, uri in rows:
        uri = uri or ""
        rel = _relative(uri)
        local = tracking.local_artifact(uri, "", f"sqlite:///{project / STORE_DB}") if uri else None
        if rel is not None:
            source = project / rel
            if not source.exists() and local is not None:
                source = local
        elif local is not None:
            name = str(exps.get(exp_id, "")).removeprefix(EXPERIMENT_PREFIX)
            try:
                group = tracking.check_name("group", name)
            except ValueError:
                group = f"experiment-{exp_id}"
            rel = f"{ARTIFACT_DIR}/{group}/{run_id}/artifacts"
            source = local if local.is_absolute() else project / local
            moved[uri] = rel
        else:
            raise ValueError(
                f"{db}: run {run_id} keeps its artifacts at {uri!r}, which store-pack cannot "
                "read (not a folder on this machine); packing would leave them out, so nothing "
                "was packed: download them first, or pack on the machine that holds them"
            )
        plan.append(_RunArtifacts(run_id, source, rel, run_id not in reports))
    return plan, moved


def store_database(project_dir: Path) -> Path:
    """The SQLite store of ``project_dir``: the one ``MLFLOW_TRACKING_URI`` names when it is
    set (``sqlite:///...``), else ``project_dir/mlflow.db``; ``ValueError`` for a store that is
    not a local SQLite file (a tracking server)."""
    if not os.environ.get("MLFLOW_TRACKING_URI"):
        return Path(project_dir) / STORE_DB
    uri = tracking.tracking_uri(project_dir)
    db = tracking.sqlite_path(uri)
    if db is None:
        raise ValueError(
            f"MLFLOW_TRACKING_URI={uri} is not a local SQLite store: store-pack packs an "
            "mlflow.db and its artifact folders (unset MLFLOW_TRACKING_URI to pack this "
            "folder's, or pack on the tracking server's machine)"
        )
    return db if db.is_absolute() else Path.cwd() / db


ARCHIVE_SUFFIX = ".tar.xz"
"""The ending of an archive's name; :func:`pack_store` writes any other name as a folder in
the compact form (:mod:`cloudpose.archive.compact`)."""


@contextlib.contextmanager
def _full_disk_named(path: Path, then: str) -> Iterator[None]:
    """Within the block, an ``OSError`` of a full disk is raised as the one-line
    :class:`~cloudpose.failures.DiskFullError` naming ``path`` and what to do ``then``
    (:func:`~cloudpose.failures.disk_full`); any other as it is."""
    try:
        yield
    except OSError as exc:
        full = disk_full(exc, path, then=then)
        if full is None:
            raise
        raise full from exc


def is_archive_name(path: Path) -> bool:
    """Whether ``path`` names a ``.tar.xz`` archive (else a compact store's folder)."""
    return Path(path).name.endswith(ARCHIVE_SUFFIX)


def pack_store(
    project_dir: Path,
    out: Path,
    checkpoints: Sequence[str] = (),
    force: bool = False,
    reduce_checkpoints: bool = True,
    drop_checkpoints: Sequence[str] = (),
) -> PackSummary:
    """Pack the store of ``project_dir`` into ``out``: a ``.tar.xz`` archive written
    atomically, or under any other name a folder in the compact form
    (:func:`cloudpose.archive.compact.write_compact`: one folder per run, instance tables as
    Parquet float32), in which only what changed is rewritten.

    Args:
        project_dir: the folder holding ``mlflow.db`` and ``mlartifacts/`` (the store
            ``MLFLOW_TRACKING_URI`` names instead, when it names a ``sqlite:///`` file:
            :func:`store_database`).
        out: the archive or compact folder to write.
        checkpoints: runs (ids or names; a name means its newest active run) whose ``*.pt``
            files are packed; every other run's are left out, but where a compact folder is
            updated, the runs whose checkpoints it holds keep them.
        drop_checkpoints: runs (ids or names) whose checkpoints an updated compact folder holds
            and leaves out now: the one way a repack drops a checkpoint the folder held.
        force: replace (update, for a compact folder) ``out`` if it exists (else
            ``FileExistsError``).
        reduce_checkpoints: in a compact folder, store a kept checkpoint in fewer bytes where
            its poses do not move (:mod:`cloudpose.archive.checkpoints`); False keeps float32.

    In what it writes, every ``run_dir`` tag is relative (:func:`_relative_run_dirs`) and a run
    left RUNNING by a process that is gone is KILLED (:func:`_mark_dead`).
    """
    out = Path(out)
    compact = not is_archive_name(out)
    if out.exists() and not force:
        raise FileExistsError(f"{out} exists: pass --force to replace it")
    if compact and out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} is a file: a compact store is a folder (or name a .tar.xz)")
    if not compact and out.is_dir():
        raise FileExistsError(f"{out} is a folder: an archive is a file")
    db = store_database(Path(project_dir))
    project = db.parent
    if not db.is_file():
        raise FileNotFoundError(f"{db}: no MLflow store to pack (expected a project's {STORE_DB})")
    _remove_stale(Path(tempfile.gettempdir()), f"{PACK_PREFIX}*", PACK_PREFIX)
    _remove_stale(out.parent, f".{out.name}.*.tmp*", f".{out.name}.")  # files.atomic_write's
    prefix = f"{PACK_PREFIX}{os.getpid()}-"
    with sigterm_as_interrupt(), tempfile.TemporaryDirectory(prefix=prefix) as tmp:
        copy = Path(tmp) / STORE_DB
        src = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
        dst = sqlite3.connect(copy)
        try:
            src.backup(dst)
        finally:
            src.close()
            dst.close()
        keep, held = _checkpoint_runs(
            copy, db, list(checkpoints), list(drop_checkpoints), out if compact else None
        )
        plan, moved = _artifact_plan(copy, project)
        runs = _rewrite(
            copy,
            lambda uri: moved.get(uri) or _under_artifacts(ARTIFACT_DIR)(uri) or _portable(uri),
        )
        marked = _mark_dead(copy, project, keep)
        killed, running = tuple(marked.killed), tuple(marked.running)
        _relative_run_dirs(copy, project)
        files = kept = left = 0
        without = tuple(r.run_id for r in plan if r.expected and not r.source.is_dir())
        if compact:
            sources = [RunSource(r.run_id, r.source, r.run_id in keep) for r in plan]
            check = PoseCheck(project) if reduce_checkpoints else None
            with _full_disk_named(out, f"pack again (cloudpose store-pack {out} --force)"):
                c = write_compact(copy, sources, out, check)
            return PackSummary(
                runs,
                c.files,
                c.checkpoints_kept,
                c.checkpoints_left_out,
                c.bytes,
                without,
                c.checked,
                killed,
                running,
                tuple(sorted(held)),
            )

        def write(path: Path) -> None:
            nonlocal files, kept, left
            files = kept = left = 0
            with tarfile.open(path, "w:xz", preset=6, dereference=True) as tar:
                tar.add(copy, arcname=STORE_DB)
                for r in plan:
                    if not r.source.is_dir():
                        continue
                    for f in sorted(r.source.rglob("*")):
                        if not f.is_file():
                            continue
                        if f.suffix == CHECKPOINT_SUFFIX:
                            if r.run_id not in keep:
                                left += 1
                                continue
                            kept += 1
                        tar.add(f, arcname=f"{r.member}/{f.relative_to(r.source).as_posix()}")
                        files += 1

        with _full_disk_named(out, f"pack again (cloudpose store-pack {out})"):
            atomic_write(out, write, suffix=".tar.xz")
    return PackSummary(
        runs, files, kept, left, out.stat().st_size, without, killed=killed, running=running
    )


def _unreadable(archive: Path, exc: BaseException) -> ValueError:
    if archive.stat().st_size == 0:
        why = "empty: 0 bytes"
    else:
        reason = " ".join(str(exc).split())
        reason = reason if len(reason) <= 100 else reason[:100] + "..."
        why = f"{type(exc).__name__}: {reason}; truncated, or not a .tar.xz"
    return ValueError(
        f"{archive} is not a readable store archive ({why}): pack it again (cloudpose "
        "store-pack) or fetch it whole"
    )


_ARCHIVE_ERRORS = (tarfile.TarError, EOFError, lzma.LZMAError, zlib.error)
"""What reading a truncated, empty or foreign archive raises (gzip's and bzip2's too)."""


def _checked_members(archive: Path, tar: tarfile.TarFile, staging: str) -> list[tarfile.TarInfo]:
    """The archive's members, each checked: ``mlflow.db`` or under ``mlartifacts/``, and
    nothing that :func:`tarfile.data_filter` refuses (a path or link outside the folder, a
    device); ``ValueError`` naming the first bad one, before anything is written."""
    members = checked_members(
        archive,
        tar,
        staging,
        lambda name: name == STORE_DB or name.split("/")[0] == ARTIFACT_DIR,
        f"{STORE_DB} or under {ARTIFACT_DIR}/ (a packed cloudpose store holds nothing else)",
    )
    if not any(m.name.removeprefix("./") == STORE_DB for m in members):
        raise ValueError(f"{archive}: no {STORE_DB} in the archive (not a packed cloudpose store)")
    return members


def _run_folders(db: Path) -> list[str]:
    """The artifact folder of each run of the unpacked store ``db`` that lies under
    ``mlartifacts/`` (``mlartifacts/GROUP/RUN_ID/artifacts``, relative to the store's folder)."""
    con = sqlite3.connect(db)
    try:
        rows = con.execute("SELECT artifact_uri FROM runs").fetchall()
    finally:
        con.close()
    out = set()
    for (uri,) in rows:
        parts = PurePosixPath(uri or "").parts
        if len(parts) > 2 and parts[0] == ARTIFACT_DIR and ".." not in parts:
            out.add("/".join(parts))
    return sorted(out)


def _same_tree(a: Path, b: Path) -> bool:
    """Whether the folders ``a`` and ``b`` (either may be missing) hold the same files."""

    def files(d: Path) -> dict[str, Path]:
        found = d.rglob("*") if d.is_dir() else []
        return {p.relative_to(d).as_posix(): p for p in found if p.is_file() or p.is_symlink()}

    fa, fb = files(a), files(b)
    return fa.keys() == fb.keys() and all(filecmp.cmp(fa[k], fb[k], shallow=False) for k in fa)


def _move_in(staging: Path, into: Path, run_folders: Sequence[str]) -> list[str]:
    """Move an unpacked store from ``staging`` into ``into``: the artifacts, then ``mlflow.db``,
    last. Into an artifact folder already there, each run's folder (``run_folders``) replaces
    the one there (a run's artifacts are the store's, with no file of an earlier unpack left
    among them), and any other file is moved in beside what is there.

    Returns:
        The run folders that held other files than the store's (replaced).
    """
    art, dest = staging / ARTIFACT_DIR, into / ARTIFACT_DIR
    replaced = []
    if art.is_dir() and not dest.exists():
        os.replace(art, dest)
    elif dest.exists():
        for rel in run_folders:  # every old folder out first: an address may hold another
            old = into / rel
            if old.is_symlink() or old.is_file():
                old.unlink()
                replaced.append(rel)
            elif old.is_dir():
                if not _same_tree(old, staging / rel):
                    replaced.append(rel)
                shutil.rmtree(old)
        for rel in run_folders:
            if (staging / rel).is_dir():
                (into / rel).parent.mkdir(parents=True, exist_ok=True)
                os.replace(staging / rel, into / rel)
        for f in sorted(art.rglob("*")) if art.is_dir() else []:
            target = dest / f.relative_to(art)
            if f.is_dir() and not f.is_symlink():
                target.mkdir(parents=True, exist_ok=True)
            else:
                target.parent.mkdir(parents=True, exist_ok=True)
                os.replace(f, target)
    os.replace(staging / STORE_DB, into / STORE_DB)
    return replaced


def _outside_addresses(db: Path) -> list[str]:
    """Run artifact addresses that are not under an artifact folder (the archive lacks them)."""
    con = sqlite3.connect(db)
    try:
        rows = con.execute("SELECT artifact_uri FROM runs").fetchall()
    finally:
        con.close()
    return [u for (u,) in rows if u and _relative(u) is None]


def unpack_store(archive: Path, into: Path) -> int:
    """Extract a packed store into ``into``, its artifact addresses and ``run_dir`` tags
    relative to that folder (which can then move).

    Args:
        archive: a ``.tar.xz`` of ``mlflow.db`` and ``mlartifacts/`` (from :func:`pack_store`,
            or packed by hand with absolute addresses of another machine), or a folder in the
            compact form (:mod:`cloudpose.archive.compact`; every file checked against its index
            before anything is written, and ``mlflow.db`` rebuilt).
        into: the folder to hold the store; it must not hold an ``mlflow.db`` yet. Each run's
            artifact folder under its ``mlartifacts/`` is replaced by the store's
            (:func:`_move_in`).

    Returns:
        The number of runs in the store. Nothing is left in ``into`` when it fails or is
        stopped (:data:`UNPACK_PREFIX`).
    """
    archive, into = Path(archive), Path(into)
    if (into / STORE_DB).exists():
        raise FileExistsError(
            f"{into / STORE_DB} exists: unpack into a folder without a store (this one's runs would be "
            "replaced)"
        )
    folder = archive.is_dir()
    if not folder and not archive.is_file():
        raise FileNotFoundError(f"{archive}: no such store archive or compact store folder")
    made = not into.exists()
    staging = None
    with sigterm_as_interrupt():
        try:
            with _full_disk_named(into, "unpack again"):
                try:
                    with contextlib.ExitStack() as stack:
                        if folder:
                            entries = check_compact(archive)
                        else:
                            tar = stack.enter_context(tarfile.open(archive, "r:*"))
                            members = _checked_members(archive, tar, str(into / UNPACK_PREFIX))
                        into.mkdir(parents=True, exist_ok=True)
                        _remove_stale(into, f"{UNPACK_PREFIX}*", UNPACK_PREFIX)
                        prefix = f"{UNPACK_PREFIX}{os.getpid()}-"
                        staging = Path(tempfile.mkdtemp(prefix=prefix, dir=into))
                        if folder:
                            extract_compact(archive, entries, staging)
                        else:
                            tar.extractall(staging, members=members, filter="data")
                except _ARCHIVE_ERRORS as exc:
                    if folder:
                        raise
                    raise _unreadable(archive, exc) from exc
            try:
                n = _rewrite(staging / STORE_DB, _portable)
                _relative_run_dirs(staging / STORE_DB)
            except sqlite3.DatabaseError as exc:
                raise ValueError(
                    f"{archive}: its {STORE_DB} is not an MLflow store ({exc}); nothing unpacked"
                ) from exc
            outside = _outside_addresses(staging / STORE_DB)
            replaced = _move_in(staging, into, _run_folders(staging / STORE_DB))
        finally:
            if staging is not None:
                shutil.rmtree(staging, ignore_errors=True)
            if made and into.is_dir() and not any(into.iterdir()):
                into.rmdir()  # made here for a store that did not come
    if outside:
        warnings.warn(
            f"{len(outside)} of {n} runs in {archive} keep their artifacts outside it (e.g. "
            f"{outside[0]}): their artifacts are not in {into / ARTIFACT_DIR}",
            stacklevel=2,
        )
    if replaced:
        warnings.warn(
            f"{len(replaced)} runs' artifact folders under {into / ARTIFACT_DIR} held other "
            f"files than {archive} (e.g. {into / replaced[0]}, left by an earlier unpack?): "
            "replaced by the store's",
            stacklevel=2,
        )
    return n
