"""The ablation sweep on a Ray cluster: every (variant, seed) one Ray task.

``cloudpose ablate --executor ray [--address ADDR]`` (:func:`cloudpose.suite.ablate.ensure_runs`):

- The driver (the machine running the command) prepares each data config once, under the
  project folder, which every node reads at the same path (a shared filesystem), and skips the
  runs MLflow already holds finished and evaluated, as the local executor does.
- Each remaining run is a task with ``num_cpus`` / ``num_gpus`` (:class:`RayOptions`) that
  trains and evaluates it (:func:`cloudpose.suite.pipeline.train_and_evaluate`) into the driver's
  MLflow store: the tasks receive its tracking URI (with a tracking server, the artifacts go
  through the server and no node needs another's disk).
- A task whose worker or node dies is retried by Ray (``max_retries``) and resumes from the
  run's last checkpoint into the same MLflow run: from the run folder when the node sees it,
  else from the checkpoint logged to the run (:func:`cloudpose.store.runs.restore_run_folder`). A
  task that fails by itself (a bad config, a NaN loss) is not retried.

Ray is an optional dependency (``pip install -e '.[cluster]'``). ``address`` None connects to
the cluster named by ``RAY_ADDRESS``, else starts Ray on this machine for the sweep. A cluster
address is checked before any data is made (:func:`check_cluster`): nothing answering there
within ``connect_timeout_s``, or a cluster refusing this machine's authentication token, is one
line naming the address and what to do.
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cloudpose import runtime
from cloudpose.store import tracking
from cloudpose.store.runs import TEST_KEY
from cloudpose.suite import pipeline

if TYPE_CHECKING:
    from cloudpose.config import Config

__all__ = [
    "EXECUTORS",
    "RayOptions",
    "RaySweep",
    "check_cluster",
    "cluster_address",
    "import_ray",
]

EXECUTORS = ("local", "ray")
"""Where the ablation runner trains: in this process, one run after another, or on Ray."""

INSTALL_HINT = "pip install -e '.[cluster]' (or pip install ray)"

CONNECT_TIMEOUT_S = 30.0
"""How long the driver waits for a cluster's address to accept a connection."""

TOKEN_HINT = (
    "a cluster started with token authentication needs RAY_AUTH_MODE=token on every machine "
    "and its token (`ray get-auth-token` on the head prints it) in RAY_AUTH_TOKEN, "
    "RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token; else start the cluster with RAY_AUTH_MODE=disabled"
)


def import_ray():
    """The ``ray`` module; a ValueError saying how to install it when it is missing."""
    try:
        import ray
    except ImportError:
        raise ValueError(
            f"--executor ray needs Ray, which is not installed: {INSTALL_HINT}"
        ) from None
    return ray


@dataclass(frozen=True)
class RayOptions:
    """How the sweep uses the cluster.

    Attributes:
        address: the cluster (``ray start --head`` prints it, e.g. ``10.0.0.1:6379``); None =
            ``RAY_ADDRESS``, else a Ray started on this machine for the sweep.
        cpus_per_run: ``num_cpus`` of each task; also its intra-op thread count.
        gpus_per_run: ``num_gpus`` of each task (0 = CPU; the task's device is then CPU).
        max_retries: how often Ray reruns a task whose worker died.
        connect_timeout_s: how long the cluster's address may take to accept a connection.
    """

    address: str | None = None
    cpus_per_run: float = 1.0
    gpus_per_run: float = 0.0
    max_retries: int = 3
    connect_timeout_s: float = CONNECT_TIMEOUT_S

    def __post_init__(self) -> None:
        if self.cpus_per_run <= 0 or self.gpus_per_run < 0 or self.max_retries < 0:
            raise ValueError(
                f"Ray resources: cpus_per_run must be > 0, gpus_per_run and max_retries >= 0; "
                f"got {self.cpus_per_run}, {self.gpus_per_run}, {self.max_retries}"
            )
        if not self.connect_timeout_s > 0:
            raise ValueError(f"Ray connect timeout must be > 0 s; got {self.connect_timeout_s}")


def cluster_address(address: str | None) -> str | None:
    """The cluster a sweep connects to: ``address``, else ``RAY_ADDRESS``; None = a Ray
    started on this machine."""
    return address or os.environ.get("RAY_ADDRESS") or None


def _host_port(address: str) -> tuple[str, int] | None:
    """(host, port) of a cluster address (``HOST:PORT``, ``ray://HOST:PORT``, ``[v6]:PORT``);
    None for ``auto`` and ``local``, which Ray resolves on this machine."""
    if address in ("auto", "local"):
        return None
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    host = host.strip("[]")
    if not (sep and host and port.isdigit() and 0 < int(port) < 65536):
        raise ValueError(
            f"Ray address {address!r}: expected HOST:PORT (`ray start --head` prints it, "
            "e.g. 10.0.0.1:6379), ray://HOST:PORT or auto"
        )
    return host, int(port)


def check_cluster(options: RayOptions) -> None:
    """Raise ValueError naming the address unless the cluster's address accepts a TCP connection
    within ``options.connect_timeout_s`` (tried each second: a head may still be starting).

    Ray's own connect retries for many minutes without a word when nothing listens; this check
    bounds that. No address (a Ray started here), ``auto`` and ``local``: nothing to check.
    """
    address = cluster_address(options.address)
    target = _host_port(address) if address else None
    if target is None:
        return
    timeout = options.connect_timeout_s
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection(target, timeout=max(0.1, min(5.0, timeout))).close()
            return
        except socket.gaierror:
            raise ValueError(
                f"Ray address {address}: unknown host {target[0]!r}; check --address / RAY_ADDRESS"
            ) from None
        except OSError as exc:
            if time.monotonic() + 1.0 > deadline:
                reason = exc.strerror or type(exc).__name__
                raise ValueError(
                    f"no Ray cluster answers at {address} ({reason}; waited {timeout:g} s): "
                    f"start one there with `ray start --head --port {target[1]}`, or check "
                    "--executor ray,address= / RAY_ADDRESS (connect-timeout= waits longer)"
                ) from None
            time.sleep(1.0)


def _connect_error(ray, address: str | None, exc: BaseException) -> str:
    """One line on why ``ray.init`` failed: a refused authentication token, else its cause."""
    chain: list[BaseException] = []
    e: BaseException | None = exc
    while e is not None and len(chain) < 8:
        chain.append(e)
        e = e.__cause__ or e.__context__
    if any(
        isinstance(e, ray.exceptions.AuthenticationError)
        or "InvalidAuthToken" in str(e)
        or "AuthenticationError" in str(e)
        for e in chain
    ):
        mode = os.environ.get("RAY_AUTH_MODE", "disabled")
        return (
            f"the Ray cluster at {address} refused this machine's authentication "
            f"(RAY_AUTH_MODE here: {mode}): {TOKEN_HINT}"
        )
    first = next((line for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
    if address is None:
        return f"Ray did not start on this machine: {first}"
    return f"could not connect to the Ray cluster at {address}: {first}"


def _train_and_evaluate(cfg: Config, project_dir: str, group: str, threads: int) -> dict:
    """A task's body, on a worker: train and evaluate ``cfg`` (resuming what there is)."""
    runtime.configure_threads(threads)
    t0 = time.monotonic()
    result = pipeline.train_and_evaluate(
        cfg, project_dir=Path(project_dir), group=group, progress=False
    )
    return {
        "run_id": result.train.run_id,
        "test_ads_auc": result.evaluation.metrics.get(TEST_KEY),
        "seconds": time.monotonic() - t0,
    }


class RaySweep:
    """Runs of one sweep submitted as Ray tasks; their outcomes as they finish.

    Args:
        options: cluster and resources.
        project_dir: the project folder (data, the default MLflow store), at the same path on
            every node.
        group: the experiment new runs go to.
    """

    def __init__(self, options: RayOptions, project_dir: Path, group: str) -> None:
        ray = import_ray()
        self._ray = ray
        self.options = options
        self.project_dir = Path(project_dir).resolve()
        self.group = group
        env = {"MLFLOW_TRACKING_URI": tracking.tracking_uri(self.project_dir)}
        check_cluster(options)
        try:
            ray.init(
                address=options.address,
                runtime_env={"env_vars": env},
                logging_level="WARNING",
                configure_logging=True,
            )
        except (ConnectionError, RuntimeError, ray.exceptions.RayError) as exc:
            raise ValueError(_connect_error(ray, cluster_address(options.address), exc)) from None
        self._task = ray.remote(_train_and_evaluate).options(
            num_cpus=options.cpus_per_run,
            num_gpus=options.gpus_per_run,
            max_retries=options.max_retries,
            retry_exceptions=False,
        )
        self._pending: dict[Any, tuple[int, Config]] = {}

    def submit(self, k: int, cfg: Config) -> None:
        """Queue run number ``k`` (``cfg``) as a task."""
        threads = max(1, int(self.options.cpus_per_run))
        ref = self._task.remote(cfg, str(self.project_dir), self.group, threads)
        self._pending[ref] = (k, cfg)

    def results(self) -> Iterator[tuple[int, Config, dict | None, BaseException | None]]:
        """``(k, cfg, outcome, error)`` of each submitted run as it finishes: the task's
        result dict (``run_id``, ``test_ads_auc``, ``seconds``) or the exception it raised."""
        ray = self._ray
        while self._pending:
            (ref,), _ = ray.wait(list(self._pending), num_returns=1)
            k, cfg = self._pending.pop(ref)
            try:
                yield k, cfg, ray.get(ref), None
            except ray.exceptions.RayTaskError as exc:  # the task's own error, as its type
                yield k, cfg, None, exc.as_instanceof_cause()
            except ray.exceptions.RayError as exc:  # retries used up, node lost, cancelled
                yield k, cfg, None, exc

    def close(self) -> None:
        """Cancel what has not finished and disconnect (a Ray started here stops)."""
        for ref in list(self._pending):
            self._ray.cancel(ref, force=True)
        self._pending.clear()
        self._ray.shutdown()
