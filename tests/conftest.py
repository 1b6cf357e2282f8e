"""Shared fixtures (the smoke preset's synthetic data and one trained smoke model, made once)
and the suite's hermeticity: nothing is written into the checkout.

Caches that would land in the checkout go to ``$XDG_CACHE_HOME/cloudpose-tests`` (numba's
compiled kernels, kept between runs so only the first run compiles; hypothesis's example
database). Every test starts in an empty temporary folder, and ``MLFLOW_TRACKING_URI`` is
unset, so a command that writes into the current folder (``mlflow.db``, ``data/``, ``runs/``)
writes there. After the session the controller compares ``git status`` with the one it found at the
start and fails the run, naming the files, if the suite left anything behind.

Nor does the suite read the user's state: HOME is a temporary folder of the session's own and
Ray's, MLflow's and torch's settings from outside are dropped (:func:`_hermetic_env`).
"""

from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"
DIAGNOSTICS = Path(__file__).resolve().parents[1] / "reports" / "diagnostics"


def diagnostic_script(name: str):
    """The module of ``reports/diagnostics/NAME.py`` (a script, not a package module)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, DIAGNOSTICS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


REPO = Path(__file__).resolve().parents[1]

_CACHE = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "cloudpose-tests"
os.environ.setdefault("NUMBA_CACHE_DIR", str(_CACHE / "numba"))  # before numba is imported


def _hermetic_env() -> None:
    """HOME a temporary folder, no ``RAY_*`` / ``MLFLOW_*`` / ``TORCH_HOME`` from outside.

    Ray reads its authentication token from ``RAY_AUTH_TOKEN``, ``RAY_AUTH_TOKEN_PATH`` or
    ``$HOME/.ray/auth_token``; with a token there, ``ray start --head`` turns on token
    authentication, which a node started without ``RAY_AUTH_MODE=token`` cannot join, and a
    local ``ray.init()`` writes one. ``RAY_AUTH_MODE=disabled`` keeps the suite's clusters
    open and writes none; MLflow reads ``MLFLOW_*`` and files in HOME, torch ``TORCH_HOME``
    (else ``~/.cache/torch``), matplotlib its config folder. Set here, before those libraries
    are imported, so the clusters and servers the tests start inherit it.
    """
    for key in list(os.environ):
        if key.startswith(("RAY_", "MLFLOW_")) or key in ("TORCH_HOME", "MATPLOTLIBRC"):
            del os.environ[key]
    home = tempfile.mkdtemp(prefix="cloudpose-tests-home-")
    atexit.register(shutil.rmtree, home, ignore_errors=True)
    os.environ.update(
        HOME=home,
        TORCH_HOME=str(Path(home) / "torch"),
        MPLCONFIGDIR=str(_CACHE / "matplotlib"),  # the font cache, kept between runs
        RAY_AUTH_MODE="disabled",
        RAY_USAGE_STATS_ENABLED="0",
    )


_hermetic_env()


def _hypothesis_profile() -> None:
    try:
        from hypothesis import settings
        from hypothesis.configuration import set_hypothesis_home_dir
        from hypothesis.database import DirectoryBasedExampleDatabase
    except ImportError:  # pragma: no cover - hypothesis is a dev dependency
        return
    set_hypothesis_home_dir(str(_CACHE / "hypothesis"))  # its other caches, e.g. constants/
    settings.register_profile(
        "cloudpose", database=DirectoryBasedExampleDatabase(str(_CACHE / "hypothesis"))
    )
    settings.load_profile("cloudpose")


_hypothesis_profile()


def _git_status() -> set[str] | None:
    """Untracked paths of the checkout, ignored ones included, or None without git.

    Edits of tracked files are left out: the suite writes no tracked file, and a person may
    edit one while it runs.
    """
    try:
        out = subprocess.run(
            ["git", "status", "--porcelain", "--ignored", "--untracked-files=all"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
            check=True,
        ).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    # bytecode is Python's own business, and the virtualenv is where the suite runs from
    skip = ("__pycache__/", ".venv/", ".pytest_cache/", ".egg-info/", ".ruff_cache/")
    return {
        line[3:]
        for line in out.splitlines()
        if line[:2] in ("??", "!!") and not any(k in line for k in skip)
    }


def pytest_sessionstart(session) -> None:
    if not hasattr(session.config, "workerinput"):  # the xdist controller (or a plain run)
        session.config._git_status_before = _git_status()


def pytest_sessionfinish(session, exitstatus) -> None:
    before = getattr(session.config, "_git_status_before", None)
    if before is None:
        return
    after = _git_status() or set()
    left = sorted(after - before)
    if left:
        session.config._git_left = left
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_collection_modifyitems(config, items) -> None:
    """Tests marked ``gpu`` are skipped where torch sees no CUDA device."""
    gpu = [item for item in items if "gpu" in item.keywords]
    if not gpu:
        return
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in gpu:
        item.add_marker(skip)


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    left = getattr(config, "_git_left", None)
    if left:
        terminalreporter.section("the suite wrote into the checkout (tests must not)", red=True)
        for line in left:
            terminalreporter.write_line(line)


@pytest.fixture(autouse=True)
def _in_a_scratch_folder(tmp_path_factory, monkeypatch):
    """Every test runs in an empty folder of its own; the MLflow store follows the project
    folder (the current one unless a test names another), never a store set outside."""
    monkeypatch.chdir(tmp_path_factory.mktemp("cwd"))
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)


@pytest.fixture(scope="session")
def smoke_data(tmp_path_factory) -> Path:
    """``data/`` folder holding the smoke preset's synthetic set and its segment caches."""
    from cloudpose.data.cache import segments_for
    from cloudpose.data.dataset import prepare_data
    from cloudpose.data.layout import real_dev_root
    from cloudpose.registry import resolve

    root = tmp_path_factory.mktemp("smoke-data")
    cfg = resolve("shared-0", "smoke").data
    prepare_data(cfg, project_dir=root, progress=False)
    # the real development frames' segments, which every run's evaluation reads
    segments_for(real_dev_root(), "all", cfg, cache_dir=root / "data" / "cache", progress=False)
    return root / "data"


def make_project(path: Path, smoke_data: Path, monkeypatch) -> Path:
    """A fresh project folder (own MLflow store and runs/) reusing the rendered smoke data."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    path.mkdir(parents=True)
    shutil.copytree(smoke_data, path / "data", symlinks=True)
    return path


def train_smoke_project(folder: Path, smoke_data: Path):
    """(project folder, TrainOutcome): a new project in ``folder`` with shared-0 trained on the
    smoke preset."""
    from cloudpose.registry import resolve
    from cloudpose.suite.pipeline import train_run

    mp = pytest.MonkeyPatch()
    try:
        proj = make_project(folder / "proj", smoke_data, mp)
        out = train_run(resolve("shared-0", "smoke", seed=1), project_dir=proj, progress=False)
    finally:
        mp.undo()
    return proj, out


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory, smoke_data):
    """(project folder, TrainOutcome) of shared-0 trained on the smoke preset."""
    return train_smoke_project(tmp_path_factory.mktemp("smoke-run"), smoke_data)


@pytest.fixture
def smoke_project(smoke_run, monkeypatch):
    """(project folder, TrainOutcome) of :func:`smoke_run`, as the current directory and store."""
    proj, out = smoke_run
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(proj)
    return proj, out


@pytest.fixture(scope="module")
def empty_store(tmp_path_factory) -> Path:
    """An empty, migrated MLflow SQLite store, made once per module (migrating one takes
    seconds); copy its ``mlflow.db`` into a test's folder."""
    from cloudpose.store import tracking

    root = tmp_path_factory.mktemp("template")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{root / 'mlflow.db'}")
        mp.chdir(root)
        tracking.setup(root).search_experiments()
    return root / "mlflow.db"


def cli(*args: str):
    """``cloudpose ARGS`` in this process (typer's test runner)."""
    from typer.testing import CliRunner

    from cloudpose.cli import app

    return CliRunner().invoke(app, list(args))


def one_line_error(res, *needles: str) -> str:
    """The error of a failed command: exit 2, one line, no traceback, holding ``needles``."""
    assert res.exit_code == 2, res.output
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    assert "Traceback" not in res.output
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]
