"""The committed store of a preset: what the report commands read when the project's own
store lacks the preset's runs (a fresh clone).

A preset whose sweep the repository commits keeps its MLflow store packed at
``reports/PRESET/mlflow-store.tar.xz`` (``cloudpose store-pack``). The commands that render
from runs (``report``, ``real-report``, ``occlusion-report``) use it when the user named no
store (``MLFLOW_TRACKING_URI`` unset) and the project's own store holds none of the runs they
need: it is unpacked once into ``stores/PRESET/`` (ignored by git; :func:`unpack_store` moves it
into place only when complete) and read there, so a user's own runs and the committed ones
never mix. To work on the committed runs with any other command, point at it:
``MLFLOW_TRACKING_URI=sqlite:///stores/PRESET/mlflow.db``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

ARCHIVE = "mlflow-store.tar.xz"
"""The packed store's name in ``reports/PRESET/``."""

STORES = "stores"
"""Folder of the project where committed stores are unpacked, one sub-folder per preset."""


def committed_archive(preset: str, project_dir: Path) -> Path | None:
    """``reports/PRESET/mlflow-store.tar.xz`` of the project, if the checkout has one."""
    path = Path(project_dir) / "reports" / preset / ARCHIVE
    return path if path.is_file() else None


def committed_store(preset: str, project_dir: Path) -> Path:
    """The folder holding the preset's committed store unpacked (``stores/PRESET``), unpacked
    now if it is not there yet.

    Raises:
        FileNotFoundError: the checkout commits no store for ``preset``.
    """
    from cloudpose.store.archive import unpack_store
    from cloudpose.store.tracking import STORE_DB

    archive = committed_archive(preset, project_dir)
    if archive is None:
        raise FileNotFoundError(
            f"{Path(project_dir) / 'reports' / preset / ARCHIVE}: the checkout commits no store "
            f"for preset {preset!r}"
        )
    folder = Path(project_dir) / STORES / preset
    if not (folder / STORE_DB).is_file():
        unpack_store(archive, folder)
    return folder


def use_committed_store(
    preset: str, project_dir: Path, lacking: Callable[[], bool], echo: Callable[[str], object]
) -> bool:
    """Point this process's MLflow client at the preset's committed store when the user named
    no store, ``lacking()`` says the project's own store lacks the runs, and the checkout
    commits one; says so in one line through ``echo``. Returns whether it did."""
    from cloudpose.store.tracking import STORE_DB

    if os.environ.get("MLFLOW_TRACKING_URI") or committed_archive(preset, project_dir) is None:
        return False
    own = Path(project_dir) / STORE_DB
    if own.is_file() and not lacking():  # no store of its own lacks every run, asked or not
        return False
    fresh = not (Path(project_dir) / STORES / preset / STORE_DB).is_file()
    folder = committed_store(preset, project_dir)
    os.environ["MLFLOW_TRACKING_URI"] = f"sqlite:///{(folder / STORE_DB).resolve()}"
    shown = Path(STORES) / preset
    how = f"unpacked from reports/{preset}/{ARCHIVE} into {shown}/" if fresh else f"in {shown}/"
    echo(
        f"this project's store lacks the {preset} runs: reading the committed store ({how}; "
        f"MLFLOW_TRACKING_URI=sqlite:///{shown}/{STORE_DB} to use it with other commands)"
    )
    return True


def holds_preset(project_dir: Path, preset: str) -> bool:
    """Whether the project's own store (``MLFLOW_TRACKING_URI`` or ``./mlflow.db``) holds a
    finished run of ``preset``; False without a store (nothing is created to ask)."""
    from cloudpose.store import tracking

    uri = tracking.tracking_uri(project_dir)
    db = tracking.sqlite_path(uri)
    if db is not None and not db.is_file():
        return False
    return bool(tracking.find_runs(tracking.setup(project_dir), preset=preset))
