"""The committed store of a preset: what the report commands read when the project's own
store lacks the preset's runs (a fresh clone).

A preset whose sweep the repository commits keeps its MLflow store at ``reports/PRESET/``: the
compact form ``mlflow-store/`` (:data:`COMPACT`, one folder per run,
:mod:`cloudpose.archive.compact`, written by ``cloudpose store-pack reports/PRESET/mlflow-store
--force``), or an archive ``mlflow-store.tar.xz`` (:data:`ARCHIVE`), read when there is no compact
form. The commands that render from runs (``report``, ``real-report``, ``occlusion-report``) use it
when the user named no store (``MLFLOW_TRACKING_URI`` unset) and the project's own store holds none
of the runs they need: it is unpacked once into ``stores/PRESET/`` (ignored by git;
:func:`unpack_store` moves it into place only when complete) and read there, so a user's own runs
and the committed ones never mix. ``stores/PRESET/`` remembers the index of the compact form it came
from (:data:`SOURCE`); when the committed store has changed since (a pull brought new runs), the
command says so and reads the copy it has. To work on the committed runs with any other command,
point at it: ``MLFLOW_TRACKING_URI=sqlite:///stores/PRESET/mlflow.db``.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path

from cloudpose.archive.compact import INDEX
from cloudpose.archive.pack import unpack_store
from cloudpose.data.keys import same_data
from cloudpose.store import tracking
from cloudpose.store.runs import is_preset_fingerprint
from cloudpose.store.tracking import STORE_DB

COMPACT = "mlflow-store"
"""The compact store's folder name in ``reports/PRESET/``."""

ARCHIVE = "mlflow-store.tar.xz"
"""The packed store's name in ``reports/PRESET/`` (read when there is no :data:`COMPACT`)."""

STORES = "stores"
"""Folder of the project where committed stores are unpacked, one sub-folder per preset."""

SOURCE = ".committed-index"
"""File in ``stores/PRESET/``: the SHA-256 of the compact store's index it was unpacked from."""


def committed_archive(preset: str, project_dir: Path) -> Path | None:
    """The preset's committed store in the checkout: ``reports/PRESET/mlflow-store/`` (the
    compact form), else ``reports/PRESET/mlflow-store.tar.xz``; None if it has neither."""
    base = Path(project_dir) / "reports" / preset
    if (base / COMPACT).is_dir():
        return base / COMPACT
    return base / ARCHIVE if (base / ARCHIVE).is_file() else None


def _index_digest(store: Path) -> str | None:
    """SHA-256 of a compact store's index (None for an archive, or a folder without one)."""
    index = store / INDEX
    return hashlib.sha256(index.read_bytes()).hexdigest() if index.is_file() else None


def committed_store(preset: str, project_dir: Path) -> Path:
    """The folder holding the preset's committed store unpacked (``stores/PRESET``), unpacked
    now if it is not there yet.

    Raises:
        FileNotFoundError: the checkout commits no store for ``preset``.
    """
    archive = committed_archive(preset, project_dir)
    if archive is None:
        raise FileNotFoundError(
            f"{Path(project_dir) / 'reports' / preset / COMPACT}: the checkout commits no store "
            f"for preset {preset!r}"
        )
    folder = Path(project_dir) / STORES / preset
    if not (folder / STORE_DB).is_file():
        unpack_store(archive, folder)
        digest = _index_digest(archive)
        if digest is not None:
            (folder / SOURCE).write_text(digest + "\n")
    return folder


def is_stale(preset: str, project_dir: Path) -> bool:
    """Whether ``stores/PRESET`` was unpacked from a compact store whose index has changed
    since (the checkout commits other runs now)."""
    archive = committed_archive(preset, project_dir)
    source = Path(project_dir) / STORES / preset / SOURCE
    if archive is None or not source.is_file():
        return False
    digest = _index_digest(archive)
    return digest is not None and source.read_text().strip() != digest


def use_committed_store(
    preset: str, project_dir: Path, lacking: Callable[[], bool], echo: Callable[[str], object]
) -> bool:
    """Point this process's MLflow client at the preset's committed store when the user named
    no store, ``lacking()`` says the project's own store lacks the runs, and the checkout
    commits one; says so in one line through ``echo``. Returns whether it did."""
    if os.environ.get("MLFLOW_TRACKING_URI") or committed_archive(preset, project_dir) is None:
        return False
    own = Path(project_dir) / STORE_DB
    if own.is_file() and not lacking():  # no store of its own lacks every run, asked or not
        return False
    fresh = not (Path(project_dir) / STORES / preset / STORE_DB).is_file()
    folder = committed_store(preset, project_dir)
    os.environ["MLFLOW_TRACKING_URI"] = f"sqlite:///{(folder / STORE_DB).resolve()}"
    shown = Path(STORES) / preset
    name = committed_archive(preset, project_dir).name
    how = f"unpacked from reports/{preset}/{name} into {shown}/" if fresh else f"in {shown}/"
    echo(
        f"this project's store lacks the {preset} runs: reading the committed store ({how}; "
        f"MLFLOW_TRACKING_URI=sqlite:///{shown}/{STORE_DB} to use it with other commands)"
    )
    if is_stale(preset, project_dir):
        echo(
            f"note: reports/{preset}/{name} has changed since {shown}/ was unpacked from it; "
            f"remove {shown}/ to read the committed runs as they are now"
        )
    return True


def sweep_store(preset: str, project_dir: Path, fresh: bool, echo: Callable[[str], object]) -> str:
    """Point this process's MLflow client at the store a sweep of ``preset`` trains into, and
    say which in one line; returns the store as shown.

    A sweep reuses the committed runs: when the user named no store (``MLFLOW_TRACKING_URI``
    unset) and the checkout commits the preset's store, the sweep reads and writes its unpacked
    copy ``stores/PRESET/``, so a run finished there on the same config and data is skipped and
    a new run lands beside the committed ones (the MLflow UI and the reports then show both).
    The committed runs were trained by this code on this data (keys of other CPUs' renders are
    checked to be the same data, :mod:`cloudpose.data.keys`): retraining them repeats hours of
    work to reproduce the same distribution. ``fresh`` trains every run into the project's own
    store instead (``./mlflow.db``, or the store the user named): an independent replication,
    whose reports render beside the committed ones (:func:`report_folder`).
    """
    if os.environ.get("MLFLOW_TRACKING_URI"):
        shown = os.environ["MLFLOW_TRACKING_URI"]
        why = "--fresh: the committed runs are not reused" if fresh else "MLFLOW_TRACKING_URI"
        echo(f"store: {shown} ({why})")
        return shown
    if fresh or committed_archive(preset, project_dir) is None:
        why = (
            "--fresh: every run of the plan trains here; the committed runs are not reused"
            if fresh
            else f"the checkout commits no store of {preset}"
        )
        echo(f"store: ./{STORE_DB} ({why})")
        return f"./{STORE_DB}"
    fresh_copy = not (Path(project_dir) / STORES / preset / STORE_DB).is_file()
    folder = committed_store(preset, project_dir)
    os.environ["MLFLOW_TRACKING_URI"] = f"sqlite:///{(folder / STORE_DB).resolve()}"
    shown = f"{STORES}/{preset}/{STORE_DB}"
    name = committed_archive(preset, project_dir).name
    how = f"unpacked now from reports/{preset}/{name}" if fresh_copy else "the committed sweep"
    echo(
        f"store: {shown} ({how}; its finished runs are reused and new runs are added beside "
        f"them; FRESH=1 / --fresh trains every run into ./{STORE_DB} instead)"
    )
    if is_stale(preset, project_dir):
        echo(
            f"note: reports/{preset}/{name} has changed since {STORES}/{preset}/ was unpacked "
            f"from it; runs trained into {STORES}/{preset}/ live only there (store-pack keeps "
            "them), so it is read as it is"
        )
    return shown


def holds_preset(project_dir: Path, preset: str) -> bool:
    """Whether the project's own store (``MLFLOW_TRACKING_URI`` or ``./mlflow.db``) holds a
    finished run of ``preset``; False without a store (nothing is created to ask)."""
    uri = tracking.tracking_uri(project_dir)
    db = tracking.sqlite_path(uri)
    if db is not None and not db.is_file():
        return False
    return bool(tracking.find_runs(tracking.setup(project_dir), preset=preset))


class NoRunsError(ValueError):
    """A report command was pointed at a store that holds none of the runs it renders."""


def store_label(project_dir: Path) -> str:
    """The store this process reads, as a user named it (``MLFLOW_TRACKING_URI`` or ./mlflow.db)."""
    return tracking.tracking_uri(project_dir)


def refuse_empty(found: int, preset: str, project_dir: Path, command: str) -> None:
    """Raise :class:`NoRunsError` (one line naming the store and the preset) when ``found`` is
    0, before anything is written."""
    if found:
        return
    raise NoRunsError(
        f"{store_label(project_dir)}: no finished, evaluated run of preset {preset!r}; "
        f"{command} wrote nothing (train them with `cloudpose ablate --preset {preset}`, or "
        "leave MLFLOW_TRACKING_URI unset to read the committed runs)"
    )


def committed_pairs(
    preset: str,
    project_dir: Path,
    *,
    variants: set[str] | None = None,
    split: str = "test",
    data_key: str | None = None,
) -> set[tuple[str, int]] | None:
    """The (variant, seed) pairs of the preset's finished runs in its committed compact store
    (``reports/PRESET/mlflow-store/runs/*/run.json``): training runs of the preset's own config
    and baseline runs on ``split``, trained on ``data_key`` (or the same data under another key)
    where one is given. None when the checkout commits no compact store of it."""
    folder = Path(project_dir) / "reports" / preset / COMPACT / "runs"
    if not folder.is_dir():
        return None
    pairs: set[tuple[str, int]] = set()
    for path in folder.glob("*/run.json"):
        row = json.loads(path.read_text(encoding="utf-8"))
        tags, params = row.get("tags", {}), row.get("params", {})
        if tags.get("preset") != preset or row.get("run", {}).get("status") != "FINISHED":
            continue
        variant, seed = tags.get("variant"), tags.get("seed", "")
        if not variant or not seed.isdigit() or (variants and variant not in variants):
            continue
        if data_key and tags.get("data") and not same_data(tags["data"], data_key):
            continue
        if tags.get("kind") == "baseline":
            if tags.get("split", "test") != split:
                continue
        elif not is_preset_fingerprint(
            variant, preset, int(seed), params.get("data.root", ""), tags.get("config")
        ):
            continue
        pairs.add((variant, int(seed)))
    return pairs


def _same_folder(a: Path, b: Path) -> bool:
    return Path(a).resolve() == Path(b).resolve()


def report_folder(
    preset: str,
    project_dir: Path,
    out_dir: Path | None,
    default: Path,
    pairs: set[tuple[str, int]],
    echo: Callable[[str], object],
    *,
    variants: set[str] | None = None,
    split: str = "test",
    data_key: str | None = None,
) -> Path:
    """Where a report of ``pairs`` (the (variant, seed) pairs its runs are) may be written.

    Into the preset's committed reports (``reports/PRESET``, which commits a store) only when
    its runs include every committed run's (variant, seed): a smaller sweep of a user's renders
    into ``runs/reports/PRESET`` instead, said in one line with the counts, as does a sweep on other
    data than every committed run's (``data_key``: it includes none of them). An ``out_dir`` the
    user named is written as asked, with the same counts said first when it replaces committed
    reports with fewer runs."""
    committed_dir = Path(project_dir) / "reports" / preset
    target = Path(out_dir) if out_dir is not None else default
    if not _same_folder(target, committed_dir):
        return target
    theirs = committed_pairs(preset, project_dir, variants=variants, split=split, data_key=data_key)
    # runs on other data than every committed run's include none of them
    other_data = (
        not theirs
        and data_key is not None
        and bool(committed_pairs(preset, project_dir, variants=variants, split=split))
    )
    why = (
        f"the committed reports are of other data than this store's {len(pairs)} runs "
        f"(data {data_key})"
        if other_data
        else None
    )
    return guarded_folder(
        preset, project_dir, target, out_dir is not None, theirs, pairs, "runs", echo, why=why
    )


def guarded_folder(
    preset: str,
    project_dir: Path,
    target: Path,
    named: bool,
    theirs: set | None,
    ours: set,
    unit: str,
    echo: Callable[[str], object],
    *,
    why: str | None = None,
) -> Path:
    """Where results of ``ours`` may be rendered into ``target``, a folder of committed results
    rendered from ``theirs`` (None: it commits none); ``unit``: what their members are, as the
    counts say them (``runs``, ``result files``).

    Over the committed results only when ``ours`` includes every member of ``theirs`` (more
    members said in one line); results lacking some, or results that ``why`` says cannot stand
    for the committed ones (other data), render into ``runs/reports/PRESET`` instead, said in
    one line with the counts before and after (or ``why``), unless the user ``named`` the
    folder (``--out``): then it is written as asked, the counts said first."""
    shown = _shown(target, project_dir)
    if why is None and (not theirs or theirs <= ours):
        if theirs and ours - theirs:
            echo(
                f"rendering over {shown}/: its {len(theirs)} committed {unit} and "
                f"{len(ours - theirs)} more"
            )
        return target
    counts = why or (
        f"the committed results in {shown}/ count {len(theirs)} {unit}; these "
        f"{len(ours)} lack {len(theirs - ours)} of them"
    )
    if named:
        echo(f"warning: replacing {shown}/ by --out: {counts}")
        return target
    own = Path(project_dir) / "runs" / "reports" / preset
    echo(
        f"{counts}: rendering into {own.relative_to(project_dir)}/ and leaving {shown}/ as "
        f"committed (--out {shown} to replace them)"
    )
    return own


def _shown(folder: Path, project_dir: Path) -> str:
    """``folder`` relative to the project where it lies in it, else as it is."""
    try:
        return Path(folder).resolve().relative_to(Path(project_dir).resolve()).as_posix()
    except ValueError:
        return str(folder)
