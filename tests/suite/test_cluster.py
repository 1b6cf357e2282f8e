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
import pwd
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from benchmarks.loopback import VENV_BIN, Loopback, free_ports
from cloudpose.store import runs, tracking
from cloudpose.suite.cluster import TOKEN_HINT, RayOptions, RaySweep, check_cluster, import_ray
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
    assert "pip install -e '.[cluster]'" in res.stderr and len(res.stderr.splitlines()) == 1
    res = CliRunner().invoke(app, [*cmd, "slurm"])
    assert res.exit_code == 2 and "expected one of local, ray" in res.output
    assert not Path("data").exists()  # refused before any data was made


def _listening() -> socket.socket:
    """A socket listening on a free port of 127.0.0.1 (close it when done)."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen()
    return s


def test_the_suite_reads_no_users_ray_mlflow_or_torch_state():
    home = Path.home()  # where Ray looks for ~/.ray/auth_token, MLflow and torch for theirs
    assert home != Path(pwd.getpwuid(os.getuid()).pw_dir)
    assert home.name.startswith("cloudpose-tests-home-")
    assert not {"RAY_ADDRESS", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH"} & set(os.environ)
    assert not [k for k in os.environ if k.startswith("MLFLOW_")]
    assert os.environ["RAY_AUTH_MODE"] == "disabled"
    assert Path(os.environ["TORCH_HOME"]).is_relative_to(home)


def test_ray_executor_says_when_nothing_answers_at_the_address():
    from typer.testing import CliRunner

    from cloudpose.cli import app

    (port,) = free_ports(1)
    cmd = ["ablate", "--group", "rotation", "--preset", "smoke", "--seeds", "1"]
    cmd += ["--executor", f"ray,address=127.0.0.1:{port},connect-timeout=1"]
    t0 = time.monotonic()
    res = CliRunner().invoke(app, cmd)
    assert res.exit_code == 2, res.output
    assert res.stderr.splitlines() == [
        f"error: no Ray cluster answers at 127.0.0.1:{port} (Connection refused; waited 1 s): "
        f"start one there with `ray start --head --port {port}`, or check --executor ray,address= / "
        "RAY_ADDRESS (connect-timeout= waits longer)"
    ]
    assert time.monotonic() - t0 < 15
    assert not Path("data").exists()  # refused before any data was made


@pytest.mark.parametrize(
    ("address", "message"),
    [
        ("10.0.0.1", "expected HOST:PORT"),
        ("10.0.0.1:http", "expected HOST:PORT"),
        ("nohost.invalid:6379", "unknown host 'nohost.invalid'"),
    ],
)
def test_ray_address_that_cannot_be_a_cluster_is_refused(address, message):
    with pytest.raises(ValueError, match=message):
        check_cluster(RayOptions(address))


def test_ray_address_from_the_environment_is_checked(monkeypatch):
    (port,) = free_ports(1)
    monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{port}")
    with pytest.raises(ValueError, match=f"no Ray cluster answers at 127.0.0.1:{port}"):
        check_cluster(RayOptions(connect_timeout_s=0.5))
    with _listening() as s:  # something listens: the check passes at once
        check_cluster(RayOptions(f"127.0.0.1:{s.getsockname()[1]}"))
    with pytest.raises(ValueError, match="connect timeout must be > 0"):
        RayOptions(connect_timeout_s=0)


def test_ray_executor_explains_a_refused_authentication_token(monkeypatch, tmp_path):
    ray = import_ray()

    def refused(**kwargs):  # what ray.init raises when the cluster wants another token
        cause = RuntimeError(
            "Failed to connect to GCS. Last connection error: Traceback ...\n"
            "ray.exceptions.AuthenticationError: RPC error: InvalidAuthToken: Authentication "
            "token is missing or incorrect."
        )
        raise ConnectionError(f"Failed to connect to Ray cluster at {kwargs['address']}") from cause

    monkeypatch.setattr(ray, "init", refused)
    with _listening() as s:
        address = f"127.0.0.1:{s.getsockname()[1]}"
        with pytest.raises(ValueError) as err:
            RaySweep(RayOptions(address), tmp_path, "rotation")
    message = str(err.value)
    assert message.startswith(f"the Ray cluster at {address} refused this machine's authentication")
    assert "RAY_AUTH_MODE here: disabled" in message and "RAY_AUTH_MODE=token" in message
    assert "\n" not in message


def test_ray_executor_says_why_ray_did_not_start(monkeypatch, tmp_path):
    ray = import_ray()

    def broken(**kwargs):
        raise RuntimeError(
            "Failed to start the GCS server.\nTraceback (most recent call last): ..."
        )

    monkeypatch.setattr(ray, "init", broken)
    with pytest.raises(
        ValueError, match=r"^Ray did not start on this machine: Failed to start the GCS server\.$"
    ):
        RaySweep(RayOptions(), tmp_path, "rotation")


@pytest.mark.slow
def test_ray_executor_explains_a_cluster_with_token_authentication(loopback, monkeypatch, tmp_path):
    import_ray()
    monkeypatch.setenv("RAY_AUTH_MODE", "token")  # the head (and only it) runs with a token
    monkeypatch.setenv("RAY_AUTH_TOKEN", "0123456789abcdef0123456789abcdef")
    _, gcs = loopback.ray_node()
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    monkeypatch.delenv("RAY_AUTH_TOKEN")
    sweep = f"RaySweep(RayOptions('127.0.0.1:{gcs}'), sys.argv[1], 'rotation')"
    code = f"import sys; from cloudpose.suite.cluster import RaySweep, RayOptions; {sweep}"
    res = subprocess.run(  # a driver of its own: a failed ray.init leaves Ray's state behind
        [sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=300
    )
    error = res.stderr.strip().splitlines()[-1]
    assert error.startswith(
        f"ValueError: the Ray cluster at 127.0.0.1:{gcs} refused this machine's authentication"
    ), res.stderr[-3000:]
    assert error.endswith(TOKEN_HINT)


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
    sweep += ["--seeds", "2", "--executor", f"ray,address=127.0.0.1:{gcs}"]
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
        assert "eval/test/instances.parquet" in {
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

    from cloudpose.registry import resolve
    from cloudpose.suite.pipeline import train_and_evaluate

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


def test_mlflow_server_refuses_a_port_in_use_before_announcing_it(monkeypatch):
    from typer.testing import CliRunner

    from cloudpose.cli import app

    def never(*args, **kwargs):
        raise AssertionError("the server was started")

    monkeypatch.setattr(subprocess, "Popen", never)
    with _listening() as s:
        port = s.getsockname()[1]
        res = CliRunner().invoke(app, ["mlflow-server", "--port", str(port)])
    assert res.exit_code == 2, res.output
    assert res.stdout == ""  # no URL announced
    assert res.stderr.splitlines() == [
        f"error: cannot listen on 127.0.0.1:{port}; it is in use (an MLflow server started "
        "before?): stop that server or choose another port (--port, or MLFLOW_PORT=... with make)"
    ]
    assert not Path("mlflow-server").exists()


def test_mlflow_server_that_stops_by_itself_is_a_failure(monkeypatch):
    from typer.testing import CliRunner

    from cloudpose.cli import app

    # MLflow's server exits 0 when it cannot bind (a port taken after the check)
    class Exited:  # the server process, gone by itself with exit code 0
        def __init__(self, cmd, **kw):
            self.pid = -1

        def wait(self, timeout=None):
            return 0

    monkeypatch.setattr(subprocess, "Popen", Exited)
    (port,) = free_ports(1)
    res = CliRunner().invoke(app, ["mlflow-server", "--port", str(port)])
    assert res.exit_code == 1
    assert res.stdout.startswith(f"MLflow server on http://127.0.0.1:{port}")
    assert res.stderr.splitlines() == [
        f"error: the MLflow server on 127.0.0.1:{port} stopped (exit code 0); its output above "
        "says why"
    ]
