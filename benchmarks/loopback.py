"""A Ray cluster and an MLflow tracking server on this machine's loopback, for the cluster test
(tests/suite/test_cluster.py) and the Ray executor's benchmark (benchmarks/bench_cluster.py).

Every process is started in a process group of its own (``ray start`` leaves its daemons in
it; Ray's workers, which put themselves in groups of their own, are the raylet's children), so
:meth:`Loopback.close` ends exactly what was started here, and one node can be killed alone. Ports are taken from 18000-18999 (every one Ray opens is pinned, none left to Ray's
defaults), and Ray's temporary folder is short: its socket paths must stay under 108
characters.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

from cloudpose.store import tracking

VENV_BIN = Path(sys.executable).parent
PORTS = (18000, 19000)
"""The range every port is taken from."""


def free_ports(n: int, contiguous: bool = False, start: int = PORTS[0]) -> list[int]:
    """``n`` free TCP ports of 127.0.0.1 from ``start`` up, consecutive if asked."""
    found: list[int] = []
    for port in range(start, PORTS[1]):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
                ok = True
            except OSError:
                ok = False
        if ok:
            found.append(port)
            if len(found) == n:
                return found
        elif contiguous:
            found = []
    raise RuntimeError(f"no {n} free ports in [{start}, {PORTS[1]})")


def _group_and_descendants(group: int) -> list[int]:
    """PIDs of the live processes in process group ``group`` and of all their descendants."""
    parent, pgrp = {}, {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z":  # zombies are already gone
            parent[int(entry.name)], pgrp[int(entry.name)] = int(fields[1]), int(fields[2])
    found = {pid for pid, g in pgrp.items() if g == group}
    grew = True
    while grew:
        more = {pid for pid, ppid in parent.items() if ppid in found} - found
        found |= more
        grew = bool(more)
    return sorted(found)


class Loopback:
    """Ray nodes and an MLflow server started here, each a process group, ended by close().

    Attributes:
        root: a short temporary folder (Ray's, the server's store, the processes' logs).
        groups: the process group ids started, in order.
    """

    def __init__(self) -> None:
        self.root = Path(tempfile.mkdtemp(prefix="cp-ray-", dir="/tmp"))
        self.groups: list[int] = []
        self._next_port = PORTS[0]

    def __enter__(self) -> Loopback:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def ports(self, n: int, contiguous: bool = False) -> list[int]:
        got = free_ports(n, contiguous, self._next_port)
        self._next_port = got[-1] + 1
        return got

    def start(self, cmd: list[str], env: dict | None = None, wait: bool = True) -> subprocess.Popen:
        """Run ``cmd`` in a new process group (its id is the process's pid); ``wait``: until
        it exits (``ray start``, whose daemons stay in the group). Its output goes to
        ``root/NAME-K.log``."""
        log = self.log_path(len(self.groups), cmd)
        with log.open("w") as out:
            proc = subprocess.Popen(
                cmd,
                env={**os.environ, **(env or {})},
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        self.groups.append(proc.pid)
        if wait and proc.wait(timeout=300) != 0:
            raise RuntimeError(f"{' '.join(cmd[:3])} failed: {log.read_text()[-3000:]}")
        return proc

    def log_path(self, k: int, cmd: list[str]) -> Path:
        return self.root / f"{Path(cmd[0]).name}-{k}.log"

    @staticmethod
    def kill(group: int, sig: int = signal.SIGKILL) -> None:
        """Send ``sig`` to every process of ``group`` and to their descendants (a node's
        raylet, its agents and its workers)."""
        for pid in _group_and_descendants(group):
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, sig)

    def ray_node(
        self, runs_dir: Path | None = None, head: int | None = None, cpus: int = 2
    ) -> tuple[int, int]:
        """Start a Ray node: the head (no CPUs for tasks) when ``head`` is None, else one with
        ``cpus`` CPUs joining the head's GCS port ``head``.

        Args:
            runs_dir: the node's own run folders (``CLOUDPOSE_RUNS_DIR`` of its workers).

        Returns:
            (the node's process group, the cluster's GCS port).
        """
        p_nm, p_om, p_agent, p_grpc, p_env, p_metrics, p_dash, p_gcs = self.ports(8)
        workers = self.ports(24, contiguous=True)
        cmd = [str(VENV_BIN / "ray"), "start", "--disable-usage-stats"]
        cmd += ["--node-ip-address=127.0.0.1", "--object-store-memory=100000000"]
        cmd += [f"--node-manager-port={p_nm}", f"--object-manager-port={p_om}"]
        cmd += [f"--dashboard-agent-listen-port={p_agent}", f"--dashboard-agent-grpc-port={p_grpc}"]
        cmd += [f"--runtime-env-agent-port={p_env}", f"--metrics-export-port={p_metrics}"]
        cmd += [f"--min-worker-port={workers[0]}", f"--max-worker-port={workers[-1]}"]
        # workers at this process's niceness (Ray's default adds 15 to it)
        env = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_worker_niceness": "0"}
        if runs_dir is not None:
            env["CLOUDPOSE_RUNS_DIR"] = str(runs_dir)
        if head is None:
            cmd += ["--head", "--num-cpus=0", f"--port={p_gcs}", f"--dashboard-port={p_dash}"]
            cmd += ["--include-dashboard=false", f"--temp-dir={self.root / 'ray'}"]
            # a lost node is declared dead after ~3 s instead of ~30 s
            env.update(RAY_health_check_period_ms="1000", RAY_health_check_failure_threshold="3")
            head = p_gcs
        else:
            cmd += [f"--address=127.0.0.1:{head}", f"--num-cpus={cpus}"]
        return self.start(cmd, env).pid, head

    def mlflow_server(self, timeout_s: float = 300.0) -> str:
        """Start an MLflow server (SQLite store, served artifacts) here; returns its URL once it
        answers."""
        (port,) = self.ports(1)
        backend = f"sqlite:///{self.root / 'mlflow.db'}"
        server = tracking.server_command(backend, self.root / "artifacts", port=port)
        k = len(self.groups)
        proc = self.start(server.argv, server.env, wait=False)
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and proc.poll() is None:
            with contextlib.suppress(OSError):
                if urllib.request.urlopen(f"{url}/health", timeout=2).status == 200:
                    return url
            time.sleep(0.5)
        log = self.log_path(k, server.argv).read_text()[-3000:]
        raise RuntimeError(f"the MLflow server did not answer on {url}: {log}")

    def close(self) -> None:
        """End every process group started here (TERM, then KILL), remove the folder."""
        for sig in (signal.SIGTERM, signal.SIGKILL):
            for group in reversed(self.groups):
                self.kill(group, sig)
            time.sleep(1.0)
        shutil.rmtree(self.root, ignore_errors=True)
