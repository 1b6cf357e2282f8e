"""The commands that serve MLflow stop their server, workers included, when they are stopped."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie is gone for our purpose (no init reaps it in some containers)
    with open(f"/proc/{pid}/stat") as f:
        return f.read().split()[2] != "Z"


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_stopped_serve_command_stops_its_server_and_the_servers_workers(tmp_path, sig):
    """A stand-in server: a shell that starts a worker and waits, as ``mlflow server`` starts
    its gunicorn or uvicorn workers."""
    pidfile = tmp_path / "worker.pid"
    server = ["sh", "-c", f"sleep 300 & echo $! > {pidfile}; wait"]
    code = (
        "from cloudpose.cli.serve import _serve_until_interrupted\n"
        f"_serve_until_interrupted({server!r}, {{}}, 'stand-in server')\n"
    )
    # As from a terminal: a command started in the background of a non-interactive shell (as CI
    # may start the suite) inherits SIGINT ignored, and Python then installs no handler for it.
    cmd = subprocess.Popen(
        [sys.executable, "-c", code],
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        deadline = time.monotonic() + 60
        while not (pidfile.is_file() and pidfile.read_text().strip()):
            assert time.monotonic() < deadline and cmd.poll() is None, cmd.stderr
            time.sleep(0.1)
        worker = int(pidfile.read_text())
        assert _alive(worker)
        cmd.send_signal(sig)
        cmd.wait(timeout=30)
        deadline = time.monotonic() + 15
        while _alive(worker) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(worker), "the server's worker outlived the command"
    finally:
        if cmd.poll() is None:
            cmd.kill()
        if pidfile.is_file() and pidfile.read_text().strip():
            try:
                os.kill(int(pidfile.read_text()), signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_a_served_store_is_served_from_its_folder(tmp_path, monkeypatch):
    """The UI server runs in a SQLite store's folder (relative artifact addresses, as a packed
    store holds them, resolve there) with the store's absolute address."""
    from typer.testing import CliRunner

    from cloudpose.cli import app, serve
    from cloudpose.store import tracking

    calls = []
    monkeypatch.setattr(serve, "_serve_until_interrupted", lambda *a: calls.append(a))
    monkeypatch.setattr(tracking, "check_port_free", lambda host, port: None)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "sqlite:///store/mlflow.db")  # relative
    store = tmp_path / "store"
    store.mkdir()
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, ["mlflow-ui"])
    assert res.exit_code == 0, res.output
    assert "no cloudpose run" in res.output
    (cmd, env, _what, cwd) = calls[0]
    assert cwd == store.resolve()
    assert cmd[cmd.index("--backend-store-uri") + 1] == f"sqlite:///{store.resolve()}/mlflow.db"
    assert env == {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
