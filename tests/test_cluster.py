"""The ablation sweep on Ray against an MLflow tracking server, all on loopback.

A Ray head node that runs no task, a worker node with its own run folders
(``CLOUDPOSE_RUNS_DIR``: no disk shared for checkpoints), an MLflow server with a SQLite store
and served artifacts. A smoke sweep of the rotation group (3 variants x 2 seeds) runs on it;
mid-sweep the worker node (its raylet, agents and workers) is killed and a fresh node joins:
Ray retries the lost tasks there and they continue from the checkpoints logged to MLflow, into
the same runs.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from benchmarks.loopback import VENV_BIN, Loopback
from cloudpose import runs, tracking
from cloudpose.cluster import RayOptions, import_ray
from tests.conftest import make_project


@pytest.fixture
def loopback() -> Iterator[Loopback]:
    with Loopback() as lb:  # every process it started is ended, even on failure
        yield lb


def test_ray_executor_without_ray_says_how_to_install_it(monkeypatch):
    from typer.testing import CliRunner

    from cloudpose.cli import app

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    cmd = ["ablate", "--group", "rotation", "--preset", "smoke", "--seeds", "1", "--executor"]
    res = CliRunner().invoke(app, [*cmd, "ray"])
    assert res.exit_code == 2
    assert "pip install -e '.[cluster]'" in res.output and len(res.output.splitlines()) == 1
    res = CliRunner().invoke(app, [*cmd, "slurm"])
    assert res.exit_code == 2 and "expected one of local, ray" in res.output
    assert not Path("data").exists()  # refused before any data was made


def _kill_node_b_at_first_checkpoint(lb, driver, node_b, gcs, proj, url, monkeypatch):
    """Kill node B (its raylet, agents and workers) as soon as a run it trains has logged a
    checkpoint, then add node C; the killed run's id."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", url)
    client = tracking.setup(proj)
    deadline = time.monotonic() + 600
    while driver.poll() is None and time.monotonic() < deadline:
        for run in tracking.find_runs(client, status="RUNNING"):
            names = [f.path for f in client.list_artifacts(run.info.run_id, "checkpoint")]
            if "checkpoint/last.pt" in names:
                lb.kill(node_b)
                lb.ray_node(lb.root / "node-c-runs", head=gcs)
                return run.info.run_id
        time.sleep(0.2)
    return None


def _final_metrics(run) -> dict[str, float]:
    skip = ("time/", "_ms_per_object")
    return {k: v for k, v in run.data.metrics.items() if not any(s in k for s in skip)}


@pytest.mark.slow
def test_sweep_on_ray_survives_a_killed_node(loopback, smoke_data, tmp_path, monkeypatch):
    import_ray()
    lb = loopback
    url = lb.mlflow_server()
    _, gcs = lb.ray_node()
    node_b, _ = lb.ray_node(lb.root / "node-b-runs", head=gcs)
    proj = make_project(tmp_path / "proj", smoke_data, monkeypatch)
    env = {**os.environ, "MLFLOW_TRACKING_URI": url, "CLOUDPOSE_NO_TCMALLOC": "1"}
    sweep = [str(VENV_BIN / "cloudpose"), "ablate", "--group", "rotation", "--preset", "smoke"]
    sweep += ["--seeds", "2", "--executor", "ray", "--address", f"127.0.0.1:{gcs}"]
    log = tmp_path / "driver.log"
    with log.open("w") as out:
        driver = subprocess.Popen(
            [*sweep, "--no-progress"], cwd=proj, env=env, stdout=out, stderr=subprocess.STDOUT
        )
    try:
        killed = _kill_node_b_at_first_checkpoint(lb, driver, node_b, gcs, proj, url, monkeypatch)
        driver.wait(timeout=900)
    finally:
        if driver.poll() is None:
            driver.kill()
    output = log.read_text()
    assert killed is not None, "no run logged a checkpoint while node B trained it"
    assert driver.returncode == 0, output[-4000:]
    assert "6 trained, 0 skipped, 0 failed" in output, output[-4000:]
    client = tracking.setup(proj)

    # Every run finished, tagged and evaluated in the server's store, once.
    done = tracking.find_runs(client, preset="smoke", status=None)
    assert sorted((r.data.tags["variant"], r.data.tags["seed"]) for r in done) == sorted(
        (v, s) for v in ("shared-0", "quaternion", "rot6d") for s in ("1", "2")
    )
    for run in done:
        assert run.info.status == "FINISHED", run.info.run_name
        assert runs.TEST_KEY in run.data.metrics and "test_icp/ads_auc" in run.data.metrics
        assert {"variant", "group", "preset", "seed", "data", "config"} <= set(run.data.tags)
        artifacts = {f.path for f in client.list_artifacts(run.info.run_id)}
        assert "model.pt" in artifacts and "checkpoint" not in artifacts
        assert "eval/test/instances.csv" in {
            f.path for f in client.list_artifacts(run.info.run_id, "eval/test")
        }
    # the group's report, rendered by the driver from the server's runs
    table = (proj / "reports" / "smoke" / "table4_rotation.md").read_text()
    assert "quaternion" in table and "rot6d" in table
    # the killed run continued on node C from its logged checkpoint, into the same run: its
    # first epoch was not trained again (logged once), and node B's disk was not needed
    resumed = client.get_run(killed)
    assert resumed.info.status == "FINISHED"
    steps = [m.step for m in client.get_metric_history(killed, "train/loss")]
    assert steps.count(1) == 1 and set(steps) == {1, 2}
    on_c = list((lb.root / "node-c-runs").glob("*/smoke/*/run.json"))
    assert killed in {runs.read_info(p.parent)["run_id"] for p in on_c}

    # ... and ended with the numbers of an uninterrupted run of the same seed (same threads)
    import torch

    from cloudpose.config import resolve
    from cloudpose.pipeline import train_and_evaluate

    tags = resumed.data.tags
    cfg = resolve(tags["variant"], "smoke", int(tags["seed"]))
    ref_proj = make_project(tmp_path / "ref", smoke_data, monkeypatch)  # its own SQLite store
    threads = torch.get_num_threads()
    torch.set_num_threads(max(1, int(RayOptions().cpus_per_run)))
    try:
        train_and_evaluate(cfg, project_dir=ref_proj, group="rotation", progress=False)
    finally:
        torch.set_num_threads(threads)
    (ref,) = tracking.find_runs(tracking.setup(ref_proj))
    assert _final_metrics(resumed) == _final_metrics(ref)
