"""The rendering commands in a clean clone write only what they name (issue 62).

Each test clones this checkout's HEAD (``git clone --shared`` into a temporary folder: the
committed tree, the committed reports and compact stores included, nothing of the working
copy's), runs one rendering command there from a store of its own (three synthetic shared-0
runs of the default preset, made here in seconds: no training), and checks that ``git status``
of the clone lists only files the command named in its output (a file, or a folder it said it
wrote into). A user's store that lacks the committed runs, or holds runs of other data, renders
beside the committed reports (``runs/reports/PRESET``, which git ignores), leaving the tracked
ones as they are; ``make ablation-shared DRY=1`` plans from the committed sweep and writes
nothing git lists. The command runs in this process with this checkout's code (the line ``make``
would run, read with ``make -n``); the clone is reset between tests. Writes nothing outside
temporary folders.

``tests/probes/clone_writes.py`` runs the long ones (``make occlusion-report`` on the committed
sweep, ``cloudpose report``, ``predict``, ``ship``) the same way, ~15 min.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.conftest import REPO, cli

PRESET = "cpu-online"
COMMITTED_DATA = "8e4152877c28cf59"
"""The data key of the committed cpu-online runs (``reports/cpu-online/mlflow-store``)."""
OTHER_DATA = "f00dfeed12345678"


def _git(*args: str, cwd: Path) -> str:
    return subprocess.run(
        ["git", *args], cwd=cwd, capture_output=True, text=True, check=True, timeout=120
    ).stdout


@pytest.fixture(scope="module")
def clone(tmp_path_factory) -> Path:
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip("needs git and a git checkout")
    if not (REPO / "reports" / PRESET / "mlflow-store" / "runs").is_dir():
        pytest.skip(f"the checkout commits no compact store of {PRESET}")
    folder = tmp_path_factory.mktemp("clone") / "cloudpose"
    _git("clone", "-q", "--shared", str(REPO), str(folder), cwd=folder.parent)
    return folder


@pytest.fixture
def clean_clone(clone, monkeypatch) -> Path:
    """The clone as committed, as the current folder; reset afterwards."""
    assert _changed(clone) == [], "the clone is not clean before the test"
    monkeypatch.chdir(clone)
    yield clone
    _git("checkout", "-q", "--", ".", cwd=clone)
    _git("clean", "-q", "-f", "-d", "-x", cwd=clone)


def _store(root: Path, data: str) -> Path:
    """An MLflow store in ``root`` with shared-0 seeds 1-3 of the default preset on ``data``,
    each finished with its test metrics and instance table (synthetic numbers)."""
    from cloudpose.registry import resolve
    from cloudpose.store import tracking

    root.mkdir(parents=True)
    rng = np.random.default_rng(0)
    m = 60
    occlusion = rng.uniform(0.0, 1.0, m)  # one test set, as every seed of a preset has
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{root / 'mlflow.db'}")
        mp.chdir(root)  # the artifacts' folder follows the current one
        client = tracking.setup(root)
        exp = tracking.experiment_id(client, "shared", root)
        for seed in (1, 2, 3):
            tags = {
                "variant": "shared-0",
                "group": "shared",
                "preset": PRESET,
                "seed": str(seed),
                "data": data,
                "git_commit": "abc1234def",
                "config": resolve("shared-0", PRESET, seed).fingerprint(),
            }
            rid = client.create_run(exp, tags=tags, run_name=f"shared-0/{PRESET}/seed{seed}")
            rid = rid.info.run_id
            for key in ("ads_auc", "ad_auc", "ads_lt_1cm", "rot_lt_10deg", "trans_lt_1cm"):
                client.log_metric(rid, f"test/{key}", 0.5 + 0.01 * seed)
                client.log_metric(rid, f"test_icp/{key}", 0.6 + 0.01 * seed)
            client.log_param(rid, "data.root", "")
            client.log_param(rid, "data.synth_seed", "0")
            ads = rng.exponential(0.012, m)
            table = pd.DataFrame(
                {
                    "frame_id": [f"0048/{i:06d}" for i in range(m)],
                    "instance": 0,
                    "cls_id": 1,
                    "class": "002_master_chef_can",
                    "occlusion": occlusion,
                    "points": 500,
                    "miss": False,
                    "net_ad": ads,
                    "net_ads": ads,
                    "net_rot_err_deg": 5.0,
                    "net_trans_err": ads,
                    "icp_ad": ads / 2,
                    "icp_ads": ads / 2,
                    "icp_rot_err_deg": 3.0,
                    "icp_trans_err": ads / 2,
                    "icp_fitness": 0.9,
                }
            )
            path = root / "logged" / rid / "instances.csv"
            path.parent.mkdir(parents=True)
            table.to_csv(path, index=False)
            client.log_artifact(rid, str(path), artifact_path="eval/test")
            client.set_terminated(rid, "FINISHED")
    return root / "mlflow.db"


@pytest.fixture(scope="module")
def same_store(tmp_path_factory) -> Path:
    """A user's store: three runs on the committed runs' data (fewer than they are)."""
    return _store(tmp_path_factory.mktemp("stores") / "same", COMMITTED_DATA)


@pytest.fixture(scope="module")
def other_store(tmp_path_factory) -> Path:
    """A user's store: three runs on other data than the committed runs'."""
    return _store(tmp_path_factory.mktemp("stores") / "other", OTHER_DATA)


def _changed(clone: Path) -> list[str]:
    """What ``git status`` lists in the clone: changed tracked files and untracked ones (the
    ignored ones, ``runs/`` and ``stores/``, are git's to leave out)."""
    out = _git("status", "--porcelain", "--untracked-files=all", cwd=clone)
    return sorted(line[3:] for line in out.splitlines())


def _unnamed(clone: Path, changed: list[str], output: str) -> list[str]:
    """The changed paths the command's output names neither as a file nor by a folder."""

    def said(path: Path) -> bool:  # a whole path, not the start of a longer one
        return re.search(rf"(?<![\w./-]){re.escape(str(path))}/?(?![\w./-])", output) is not None

    def named(path: str) -> bool:
        rel = Path(path)
        return any(said(p) or said(clone / p) for p in (rel, *rel.parents[:-1]))

    return [p for p in changed if not named(p)]


def _render(clone: Path, store: Path, monkeypatch, *args: str):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{store}")
    res = cli(*args)
    assert res.exit_code == 0, res.output
    changed = _changed(clone)
    assert not _unnamed(clone, changed, res.output), (changed, res.output)
    return res, changed


def _occlusion_report(clone: Path, store: Path, monkeypatch, *extra: str):
    """:func:`_render` of ``occlusion-report`` of the preset's 3 seeds, with ``extra`` options."""
    return _render(
        clone,
        store,
        monkeypatch,
        "occlusion-report",
        "--preset",
        PRESET,
        "--seeds",
        "3",
        "--no-progress",
        *extra,
    )


def test_occlusion_report_of_a_smaller_sweep_leaves_the_committed_reports(
    clean_clone, same_store, monkeypatch
):
    res, changed = _occlusion_report(clean_clone, same_store, monkeypatch)
    assert changed == []
    assert f"rendering into runs/reports/{PRESET}/ and leaving reports/{PRESET}/" in res.output
    written = clean_clone / "runs" / "reports" / PRESET
    assert sorted(p.name for p in written.iterdir()) == ["occlusion.csv", "occlusion.png"]


def test_occlusion_report_over_the_committed_reports_writes_its_own_files_only(
    clean_clone, same_store, monkeypatch
):
    """Named by the user, the committed folder is written, with a warning: the occlusion plot
    and its table, and none of the tables, claims or index beside them."""
    res, changed = _occlusion_report(
        clean_clone, same_store, monkeypatch, "--out", f"reports/{PRESET}"
    )
    assert f"warning: replacing reports/{PRESET}/ by --out" in res.output
    assert changed == [f"reports/{PRESET}/occlusion.csv", f"reports/{PRESET}/occlusion.png"]


@pytest.mark.slow
def test_report_of_runs_on_other_data_leaves_the_committed_reports(
    clean_clone, other_store, monkeypatch
):
    """A sweep on other data includes none of the committed runs: its tables, claims and plots
    go beside the committed ones, said in one line (they were written over them before)."""
    res, changed = _render(
        clean_clone, other_store, monkeypatch, "report", "--preset", PRESET, "--no-mlflow"
    )
    assert changed == []
    assert "the committed reports are of other data" in res.output
    assert (clean_clone / "runs" / "reports" / PRESET / "table1_overall.md").is_file()


@pytest.mark.slow
def test_report_into_a_folder_writes_there_only(clean_clone, same_store, monkeypatch):
    _, changed = _render(
        clean_clone,
        same_store,
        monkeypatch,
        "report",
        "--preset",
        PRESET,
        "--no-mlflow",
        "--out",
        "mine",
    )
    assert changed and all(p.startswith("mine/") for p in changed), changed
    assert "mine/table1_overall.md" in changed


def test_the_check_names_a_file_the_command_did_not(tmp_path):
    said = f"wrote {tmp_path / 'out'}\nreports/x/a.csv"
    changed = ["out/a.png", "reports/x/a.csv", "reports/x/b.md", "README.md"]
    assert _unnamed(tmp_path, changed, said) == ["reports/x/b.md", "README.md"]


def _make_line(clone: Path, *target: str) -> list[str]:
    """The one CLI call ``make TARGET`` runs (``make -n``), without the ``cloudpose``."""
    if shutil.which("make") is None:
        pytest.skip("needs make")
    out = _stdout(["make", "-n", *target, "CLI=cloudpose"], clone)
    calls = [line.split() for line in out.splitlines() if line.startswith("cloudpose ")]
    assert len(calls) == 1, out
    return calls[0][1:]


def _stdout(argv: list[str], cwd: Path) -> str:
    return subprocess.run(
        argv, cwd=cwd, capture_output=True, text=True, check=True, timeout=60
    ).stdout


@pytest.mark.slow
def test_the_ablation_plan_of_a_fresh_clone_reuses_the_committed_sweep(clean_clone, monkeypatch):
    """``make ablation-shared DRY=1`` on a fresh clone: the committed store unpacked (into
    ``stores/``, ignored), every run of the plan found finished there, nothing written that git
    lists."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    args = _make_line(clean_clone, "ablation-shared", "DRY=1")
    assert "--dry-run" in args, args
    try:
        res = cli(*args)
    finally:
        os.environ.pop("MLFLOW_TRACKING_URI", None)  # the command set it for its process
    assert res.exit_code == 0, res.output
    assert res.output.startswith(f"store: stores/{PRESET}/mlflow.db (unpacked now from"), res.output
    assert "finished before (skipped), 0 to train" in res.output, res.output
    assert _changed(clean_clone) == []
