"""Shared fixtures: the smoke preset's synthetic data and one trained smoke model, made once."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="session")
def smoke_data(tmp_path_factory) -> Path:
    """``data/`` folder holding the smoke preset's synthetic set and its segment caches."""
    from cloudpose.config import resolve
    from cloudpose.data.cache import ensure_dataset

    root = tmp_path_factory.mktemp("smoke-data")
    ensure_dataset(resolve("shared-0", "smoke").data, project_dir=root, progress=False)
    return root / "data"


def make_project(path: Path, smoke_data: Path, monkeypatch) -> Path:
    """A fresh project folder (own MLflow store and runs/) reusing the rendered smoke data."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    path.mkdir(parents=True)
    shutil.copytree(smoke_data, path / "data", symlinks=True)
    return path


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory, smoke_data):
    """(project folder, TrainOutcome) of shared-0 trained on the smoke preset."""
    from cloudpose.config import resolve
    from cloudpose.train import train

    mp = pytest.MonkeyPatch()
    try:
        proj = make_project(tmp_path_factory.mktemp("smoke-run") / "proj", smoke_data, mp)
        out = train(resolve("shared-0", "smoke", seed=1), project_dir=proj, progress=False)
    finally:
        mp.undo()
    return proj, out


@pytest.fixture
def smoke_project(smoke_run, monkeypatch):
    """(project folder, TrainOutcome) of :func:`smoke_run`, as the current directory and store."""
    proj, out = smoke_run
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(proj)
    return proj, out
