"""MLflow tracking: where runs live, how they are named, tagged and found again.

- Store: an embedded SQLite database ``mlflow.db`` in the project folder (the current directory),
  artifacts under ``mlartifacts/``; ``MLFLOW_TRACKING_URI`` points it anywhere else, e.g. a shared
  tracking server (:func:`server_command`, ``make mlflow-server``), through which the artifacts
  then go too.
- Artifact addresses: MLflow writes absolute ``file://`` ones; a store as ``store-pack`` and
  ``store-unpack`` write it keeps them relative to its folder (``mlartifacts/GROUP/RUN/artifacts``),
  so the folder can move. MLflow would read a relative address against the process's current
  directory; every artifact this project reads or writes is found against the SQLite store's
  folder instead (:func:`artifact_address`, :func:`local_artifact`, and the client
  :func:`setup` returns), and so is a relative ``run_dir`` tag (:func:`store_path`).
- One experiment per ablation group (``cloudpose-shared``, ``cloudpose-rotation``, ...). A run
  lives in the experiment of the group it was trained for; a variant listed in several groups
  (``shared-0``) is trained once and found by tags from every group's report.
- Tags ``variant``, ``group``, ``preset``, ``seed``, ``data`` (the data fingerprint), ``config``
  (:meth:`Config.fingerprint`), ``git_commit``; names and identity in :mod:`cloudpose.store.runs`.
  Metric keys are split-prefixed (``train/loss``, ``val/ads_auc``, ``test/ads_auc``,
  ``test_icp/ads_auc``).
"""

from __future__ import annotations

import errno
import functools
import logging
import math
import os
import re
import shlex
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any, NamedTuple
from urllib.parse import unquote, urlparse

from filelock import FileLock

from cloudpose.data.keys import same_data_keys

EXPERIMENT_PREFIX = "cloudpose-"
_KEY_BAD = re.compile(r"[^A-Za-z0-9_\-./ ]")
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,99}")


def check_name(what: str, name: str) -> str:
    """``name`` if it is safe as one path component, an experiment name and a metric prefix:
    1-100 letters, digits, ``_ - .``, starting with a letter or digit (so never ``.``, ``..``,
    a path separator or an absolute path). Else ``ValueError`` naming ``what`` (``--group``).
    """
    if not isinstance(name, str) or _NAME.fullmatch(name) is None:
        raise ValueError(
            f"{what} {name!r}: expected 1-100 letters, digits, '_', '-' or '.', starting with "
            "a letter or digit (it names a folder and an MLflow experiment or metric prefix)"
        )
    return name


STORE_DB = "mlflow.db"
"""A project's SQLite store of runs, in the project folder."""

ARTIFACT_DIR = "mlartifacts"
"""A project's artifact folder, beside :data:`STORE_DB` (one subfolder per group)."""


def tracking_uri(project_dir: Path | None = None) -> str:
    """``MLFLOW_TRACKING_URI`` if set, else SQLite ``mlflow.db`` in ``project_dir`` (cwd)."""
    env = os.environ.get("MLFLOW_TRACKING_URI")
    if env:
        return env
    root = (project_dir or Path.cwd()).resolve()
    return f"sqlite:///{root / STORE_DB}"


SERVER_FOLDER = "mlflow-server"
"""The folder (in the working directory) of a tracking server's default SQLite store and
artifacts."""


class ServerCommand(NamedTuple):
    """An ``mlflow server`` invocation: argv, environment variables to add, and its store."""

    argv: list[str]
    env: dict[str, str]
    backend: str


def check_port_free(host: str, port: int) -> None:
    """Raise ValueError unless a server can listen on ``host:port`` (the tracking server's port,
    checked before it is announced: the MLflow server itself ends quietly when it is taken).

    The test binds as the server does (``SO_REUSEADDR``: a port left in TIME_WAIT is free).
    """
    try:
        family, kind, proto, _, addr = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
    except socket.gaierror:
        raise ValueError(f"--host {host!r}: not an address or a known host name") from None
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
            s.listen()
        except OSError as exc:
            why = (
                "it is in use (an MLflow server started before?): stop that server or"
                if exc.errno == errno.EADDRINUSE
                else f"{exc.strerror or exc}:"
            )
            raise ValueError(
                f"cannot listen on {host}:{port}; {why} choose another port "
                "(--port, or MLFLOW_PORT=... with make)"
            ) from None


def server_command(
    backend: str | None = None,
    artifacts: str | Path | None = None,
    host: str = "127.0.0.1",
    port: int = 5000,
    workers: int = 2,
    root: Path | None = None,
) -> ServerCommand:
    """The ``mlflow server`` command line of a tracking server for several machines.

    Args:
        backend: where runs, params and metrics are kept: any SQLAlchemy URI
            (``sqlite:///abs/path.db``, ``postgresql://user:pw@host/db``); default SQLite
            ``ROOT/mlflow-server/mlflow.db`` (the folder is made).
        artifacts: where artifacts are kept (a folder, or an object-store URI such as
            ``s3://bucket/prefix``); the server serves them (``--serve-artifacts``), so clients
            need no access to it. Default ``ROOT/mlflow-server/artifacts``.
        host: interface to bind (127.0.0.1: this machine only; 0.0.0.0: every interface).
        port: TCP port.
        workers: server processes.
        root: where the default store lies; default the working directory.

    Returns:
        argv (this interpreter's MLflow), the environment variables to add to the server's
        (MLflow's GenAI job runner off: it starts 8 processes that tracking never uses) and
        the backend. Clients then set ``MLFLOW_TRACKING_URI=http://HOST:PORT``.
    """
    folder = (root or Path.cwd()) / SERVER_FOLDER
    if backend is None:
        folder.mkdir(parents=True, exist_ok=True)
        backend = f"sqlite:///{folder / STORE_DB}"
    if artifacts is None:
        artifacts = folder / "artifacts"
    if "://" not in backend:
        raise ValueError(
            f"--backend {backend!r}: expected an SQLAlchemy URI such as sqlite:///abs/path.db "
            "or postgresql://user:password@host/db"
        )
    argv = [
        sys.executable,
        "-m",
        "mlflow",
        "server",
        "--backend-store-uri",
        backend,
        "--artifacts-destination",
        str(artifacts),
        "--serve-artifacts",
        "--host",
        host,
        "--port",
        str(port),
        "--workers",
        str(workers),
    ]
    return ServerCommand(argv, {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}, backend)


def is_remote(uri: str) -> bool:
    """Whether ``uri`` is a tracking server (``http://``, ``https://``, ``databricks``), whose
    runs and artifacts other machines reach without this machine's disk."""
    return uri.split(":", 1)[0] in ("http", "https", "databricks")


def setup(project_dir: Path | None = None):
    """An ``MlflowClient`` on the store of :func:`tracking_uri`.

    The process-wide ``mlflow.set_tracking_uri`` is never called: it also writes
    ``MLFLOW_TRACKING_URI`` into the environment, which would then pin every later project
    folder of the same process to this one's store.
    """
    import mlflow

    # Alembic prints every schema migration of a new SQLite store at INFO.
    for name in ("alembic", "mlflow.store.db.utils"):
        logging.getLogger(name).setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", module="mlflow")
    uri = tracking_uri(project_dir)
    db = sqlite_path(uri)
    if db is None:
        return mlflow.MlflowClient(tracking_uri=uri)
    make = _store_client()
    # The first client of a new SQLite store creates its tables and runs every schema
    # migration; two processes doing that at once leave a store that no command can open again
    # (alembic's `_alembic_tmp_* already exists`). One process at a time, then every later one
    # finds the schema current and only reads it.
    db.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(str(db) + ".lock"):
        try:
            client = make(uri)
            client.search_experiments(max_results=1)
        except Exception as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise StoreError(
                f"the MLflow store {db} cannot be opened ({type(e).__name__}: {first}); "
                f"if it is broken, move it aside (mv {db} {db}.broken) and rerun, or set "
                "MLFLOW_TRACKING_URI to another store"
            ) from e
    return client


@functools.cache
def _store_client():
    """The client class of a SQLite store: an ``MlflowClient`` whose artifact repository of a run
    with a relative address is the folder under the store's folder (:func:`artifact_address`),
    for every read and write (``log_artifact``, ``log_text``, ``list_artifacts``,
    ``download_artifacts``); a plain ``MlflowClient`` with an MLflow that lacks the hook."""
    import mlflow
    from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository
    from mlflow.tracking._tracking_service.client import TrackingServiceClient

    if not hasattr(TrackingServiceClient, "_get_artifact_repo"):
        return lambda uri: mlflow.MlflowClient(tracking_uri=uri)

    class _Service(TrackingServiceClient):
        def _get_artifact_repo(self, resource_id, *args, **kwargs):
            if not args and kwargs.get("resource", "run") == "run":
                address = self.get_run(resource_id).info.artifact_uri or ""
                resolved = artifact_address(address, self.tracking_uri)
                if resolved != address:  # MLflow caches repositories by run id: not this one
                    return get_artifact_repository(resolved, tracking_uri=self.tracking_uri)
            return super()._get_artifact_repo(resource_id, *args, **kwargs)

    class StoreClient(mlflow.MlflowClient):
        def __init__(self, tracking_uri: str):
            super().__init__(tracking_uri=tracking_uri)
            self._tracking_client = _Service(self._tracking_client.tracking_uri)

        # MLflow's own download and listing go through a runs:/ address, which reads the
        # run's address as it is (a relative one against the current directory)
        def download_artifacts(self, run_id: str, path: str, dst_path: str | None = None):
            repo = self._tracking_client._get_artifact_repo(run_id)
            return repo.download_artifacts(path, dst_path)

        def list_artifacts(self, run_id: str, path: str | None = None):
            return self._tracking_client._get_artifact_repo(run_id).list_artifacts(path)

    return StoreClient


class StoreError(RuntimeError):
    """The MLflow store exists but cannot be opened (the message says how to recover)."""


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` tracking URI, else None."""
    prefix = "sqlite:///"
    return Path(uri[len(prefix) :]) if uri.startswith(prefix) else None


def experiment_id(client, group: str, project_dir: Path | None = None) -> str:
    """Id of the group's experiment, created (with a local artifact folder) if missing.

    Several processes may ask at once (the tasks of a sweep): when another one created it
    first, that experiment is the answer.
    """
    from mlflow.exceptions import MlflowException

    name = EXPERIMENT_PREFIX + check_name("group", group)
    exp = client.get_experiment_by_name(name)
    if exp is not None:
        return exp.experiment_id
    location = None
    if not os.environ.get("MLFLOW_TRACKING_URI"):
        location = ((project_dir or Path.cwd()).resolve() / ARTIFACT_DIR / group).as_uri()
    try:
        return client.create_experiment(name, artifact_location=location, tags={"group": group})
    except MlflowException:
        exp = client.get_experiment_by_name(name)
        if exp is None:
            raise
        return exp.experiment_id


def metric_key(*parts: str) -> str:
    """Join parts with ``/`` and replace characters MLflow keys do not allow."""
    return _KEY_BAD.sub("_", "/".join(parts))


def command_line() -> str:
    """The command line of this process, as a user would type it (``cloudpose report ...``), with
    absolute paths inside the working folder written relative to it (:func:`shown_path`)."""
    argv = list(sys.argv)
    prog = Path(argv[0]).name if argv else "python"
    return shlex.join([prog, *map(_shown_arg, argv[1:])])


def _shown_arg(arg: str) -> str:
    """One argument as :func:`command_line` writes it: ``/abs/x`` and ``--opt=/abs/x`` inside
    the working folder become relative; anything else is kept."""
    head, sep, value = arg.partition("=") if arg.startswith("--") else ("", "", arg)
    if not value.startswith("/"):
        return arg
    return f"{head}{sep}{shown_path(value)}"


def shown_path(path: str | Path) -> str:
    """A path as a provenance line writes it: relative to the working folder when inside it, so a
    committed report names the project's files, not one machine's folders; as given otherwise."""
    path = Path(path)
    if path.is_absolute():
        try:
            return str(path.relative_to(Path.cwd()))
        except ValueError:
            pass
    return str(path)


@functools.cache
def git_commit(repo: Path | None = None) -> str:
    """Short commit of the code, ``+dirty`` when the tree has changes; "unknown" outside git.

    Asked once per process: a process runs the code it imported when it started, so a long
    sweep process stamps every run with the tree as it was then, not with later commits or
    edits of the checkout that it never loads."""
    cwd = repo or Path(__file__).resolve().parent
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "--short=10", "HEAD"], cwd=cwd, capture_output=True, text=True
        ).stdout.strip()
        dirty = subprocess.run(
            # Code only: rendered reports and data under the repository are not the code.
            [
                "git",
                "status",
                "--porcelain",
                "--untracked-files=no",
                "--",
                ":/cloudpose",
                ":/ablations",
                ":/pyproject.toml",
            ],
            cwd=cwd,
            capture_output=True,
            text=True,
        ).stdout.strip()
    except OSError:
        return "unknown"
    return (sha + ("+dirty" if dirty else "")) if sha else "unknown"


def find_runs(
    client,
    *,
    variant: str | None = None,
    preset: str | None = None,
    seed: int | None = None,
    data: str | None = None,
    status: str | None = "FINISHED",
    extra_filter: str = "",
) -> list[Any]:
    """Runs of every cloudpose experiment matching the given tags, newest first; ``data``
    matches every key of the same data (:func:`cloudpose.data.keys.same_data_keys`)."""
    exps = [
        e.experiment_id for e in client.search_experiments() if e.name.startswith(EXPERIMENT_PREFIX)
    ]
    if not exps:
        return []
    clauses = []
    for tag, value in (("variant", variant), ("preset", preset), ("seed", seed)):
        if value is not None:
            clauses.append(f"tags.{tag} = '{value}'")
    if status:
        clauses.append(f"attributes.status = '{status}'")
    if extra_filter:
        clauses.append(extra_filter)
    keys = [None] if data is None else same_data_keys(data)
    found: dict[str, Any] = {}
    for key in keys:  # MLflow's filter has no "or": one search per key
        where = " and ".join(clauses + ([] if key is None else [f"tags.data = '{key}'"]))
        for r in client.search_runs(exps, where, order_by=["attributes.start_time DESC"]):
            found.setdefault(r.info.run_id, r)
    return sorted(found.values(), key=lambda r: r.info.start_time or 0, reverse=True)


def newest_run_named(client, name: str) -> Any | None:
    """The newest finished run whose MLflow run name is ``name`` (e.g.
    ``shared-0/cpu-online/seed1``), or None."""
    runs = [r for r in find_runs(client) if r.data.tags.get("mlflow.runName") == name]
    return runs[0] if runs else None  # find_runs: newest first


def store_folder(uri: str | None = None) -> Path | None:
    """The folder of the SQLite store that the tracking URI ``uri`` names (default
    :func:`tracking_uri`), against which its relative artifact addresses and ``run_dir`` tags
    are read; None for a store that is not a local SQLite file (a tracking server)."""
    db = sqlite_path(tracking_uri() if uri is None else uri)
    return None if db is None else db.resolve().parent


def is_relative_address(uri: str) -> bool:
    """Whether an artifact address is a relative path (no scheme, not absolute), such as
    ``mlartifacts/GROUP/RUN/artifacts`` of a packed or unpacked store."""
    return bool(uri) and not urlparse(uri).scheme and not Path(uri).is_absolute()


def artifact_address(uri: str, tracking: str | None = None) -> str:
    """An artifact address as an artifact repository is to read it: a relative one as the
    ``file:`` URI of that folder under the folder of the SQLite store ``tracking`` names
    (default :func:`tracking_uri`; the current directory without a SQLite store, as MLflow
    reads it); any other address as it is."""
    if not is_relative_address(uri):
        return uri
    folder = store_folder(tracking) or Path.cwd()
    return (folder / uri).resolve().as_uri()


def local_artifact(uri: str, rel: str, tracking: str | None = None) -> Path | None:
    """The file ``rel`` of the artifact folder at address ``uri`` (a run's ``artifact_uri``, an
    experiment's ``artifact_location``) on this machine: a ``file:`` URI or an absolute path as
    it is, a relative address under the folder of the SQLite store ``tracking`` names (default
    :func:`tracking_uri`: :func:`artifact_address`); None for a remote one (``s3://``,
    ``mlflow-artifacts:``)."""
    uri = artifact_address(uri, tracking)
    if uri.startswith("file:"):
        return Path(unquote(urlparse(uri).path)) / rel
    if uri and "://" not in uri and ":" not in uri.split("/")[0]:
        return Path(uri) / rel
    return None


def run_artifact(client, run, rel: str) -> Path | None:
    """The local file ``rel`` of an MLflow ``run``'s artifacts in ``client``'s store
    (:func:`local_artifact`; it may not exist), or None when they are remote. ``client`` may be
    None for a run whose artifact address is absolute."""
    store = getattr(client, "tracking_uri", None)  # None: an absolute address needs none
    return local_artifact(run.info.artifact_uri or "", rel, store)


def download_artifact(client, run, rel: str, dst: str | Path | None = None) -> Path:
    """The file (or folder) ``rel`` of ``run``'s artifacts as a local path: read in place from a
    local store, else downloaded into ``dst`` (a new temporary folder when None).

    Raises:
        FileNotFoundError: a local store's run has no such artifact.
        MlflowException, OSError: a remote store's download failed (no such artifact).
    """
    local = run_artifact(client, run, rel)
    if local is not None:
        if not local.exists():
            raise FileNotFoundError(f"{local}: run {run.info.run_id} has no artifact {rel}")
        return local
    return Path(client.download_artifacts(run.info.run_id, rel, None if dst is None else str(dst)))


def store_path(value: str, tracking: str | None = None) -> Path:
    """A path a run records (its ``run_dir`` tag): an absolute one as it is, a relative one
    (as ``store-unpack`` writes it) under the SQLite store's folder (:func:`store_folder`), else
    the current directory."""
    path = Path(value)
    if path.is_absolute():
        return path
    return (store_folder(tracking) or Path.cwd()) / path


def metric_batch(metrics: dict[str, float], step: int = 0, finite_only: bool = False) -> list:
    """MLflow ``Metric`` entities of ``metrics`` at ``step``, stamped now (for ``log_batch``);
    ``finite_only`` leaves out NaN and infinite values."""
    from mlflow.entities import Metric

    now = int(time.time() * 1000)
    return [
        Metric(k, float(v), now, step)
        for k, v in metrics.items()
        if not finite_only or math.isfinite(v)
    ]


def flat_params(d: dict[str, Any]) -> dict[str, str]:
    """MLflow params from a flat config dict: values as strings, keys sanitised."""
    return {metric_key(k): str(v) for k, v in d.items()}
