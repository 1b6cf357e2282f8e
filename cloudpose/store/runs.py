"""Run identity: what makes two runs the same run, where a run lives, and how a user's name for a
run is resolved to one.

A run is one config (:meth:`cloudpose.config.Config.fingerprint`, which covers the variant,
preset values, seed and every override) trained on one dataset
(:func:`cloudpose.data.dataset.data_fingerprint`, a content hash). Both fingerprints name:

- the run folder ``runs/{variant}/{preset}/seed{S}-{data[:10]}-{config[:8]}`` (:func:`run_dir`),
  holding ``last.pt`` (and ``last.prev.pt`` while it trains), ``model.pt`` and ``run.json``
  (:func:`read_info` / :func:`write_info`: the MLflow run id, the group, the config, and once
  finished its final metrics); a checkpoint is read checked (:func:`read_checkpoint`: a torn
  or empty one is a :class:`CheckpointError` naming it);
- the MLflow run's tags ``config`` and ``data``; its name is ``variant/preset/seedS``
  (:func:`run_name`), plus ``+{config[:8]}`` for a config that is not its preset's own
  (:func:`display_name`), so runs of different configs never share a name.

A user names a run by its folder, its MLflow run id, or its name: ``variant/preset/seedS`` means
the one finished run of the preset's own config, ``variant/preset/seedS+CONFIG`` the one of
the config whose fingerprint starts with CONFIG (:func:`resolve_run_id`); an error lists the
candidates when there are none or several. The ablation runner takes a run as done when a
finished run of exactly the config on exactly the data has test metrics (:func:`finished_run`).

One process at a time trains a run folder: the others wait on its lock file ``.{folder}.lock``
beside it (:func:`run_lock`).

Run folders live under ``CLOUDPOSE_RUNS_DIR`` when it is set (a worker node's own disk), else
under the project folder's ``runs/``. A machine that lacks a run's folder rebuilds it from the
MLflow run's artifacts (:func:`restore_run_folder`): ``model.pt`` of a finished run, the last
checkpoint ``checkpoint/last.pt`` of an unfinished one (logged while training against a
tracking server).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from filelock import FileLock, Timeout

from cloudpose.data.keys import DataKey
from cloudpose.files import atomic_text
from cloudpose.registry import resolve
from cloudpose.store import tracking
from cloudpose.store.pretrained import is_pretrained, shipped

if TYPE_CHECKING:
    from cloudpose.config import Config

__all__ = [
    "TEST_KEY",
    "CheckpointError",
    "describe_run",
    "display_name",
    "drop_checkpoint_artifact",
    "fetch_artifact",
    "finished_run",
    "is_preset_config",
    "is_preset_fingerprint",
    "local_checkpoint",
    "lock_path",
    "open_training_run",
    "read_checkpoint",
    "read_info",
    "resolve_run",
    "resolve_run_id",
    "restore_run_folder",
    "run_dir",
    "run_folder",
    "run_has_config",
    "run_lock",
    "run_name",
    "write_info",
]

TEST_KEY = "test/ads_auc"
"""The metric a run has once its own test set is evaluated."""

INFO = "run.json"

CHECKPOINT_ARTIFACT_DIR = "checkpoint"
"""Artifact folder of an unfinished run's last checkpoint (``checkpoint/last.pt``)."""

RUNS_DIR_ENV = "CLOUDPOSE_RUNS_DIR"
"""Environment variable: where run folders live instead of ``{project}/runs``."""


def run_name(variant: str, preset: str, seed: int) -> str:
    """Deterministic run name, ``shared-3/cpu/seed1``."""
    return f"{variant}/{preset}/seed{seed}"


def display_name(cfg: Config) -> str:
    """The MLflow run name of ``cfg``: :func:`run_name`, plus ``+{config fingerprint}`` when
    ``cfg`` is not its preset's own config (overrides)."""
    name = run_name(cfg.variant, cfg.preset, cfg.seed)
    return (
        name
        if is_preset_fingerprint(
            cfg.variant, cfg.preset, cfg.seed, cfg.data.root, cfg.fingerprint()
        )
        else f"{name}+{cfg.fingerprint()[:8]}"
    )


def training_tags(cfg: Config, group: str, data_key: DataKey, run_dir: Path) -> dict[str, str]:
    """The MLflow tags of a training run: what the reports, the runner and ``--run`` look it up
    by (variant, group, preset, seed, data, config) and where it came from."""
    return {
        "variant": cfg.variant,
        "group": group,
        "preset": cfg.preset,
        "seed": str(cfg.seed),
        "data": data_key,
        "config": cfg.fingerprint(),
        "git_commit": tracking.git_commit(),
        "run_dir": str(run_dir),
    }


def baseline_name(method: str, preset: str, seed: int, split: str, config: str, own: str) -> str:
    """The MLflow run name of a classical baseline: ``baseline-{method}/{preset}/seed{S}``, plus
    ``+{split}-{config[:8]}`` when it is not the test split with the method's current settings
    (``own``), so runs of other settings or data never share a name."""
    name = run_name(f"baseline-{method}", preset, seed)
    if split != "test" or config != own:
        name += f"+{split}-{config[:8]}"
    return name


def baseline_tags(
    method: str,
    group: str,
    preset: str,
    seed: int,
    data_key: DataKey,
    config: str,
    *,
    limit: int | None,
    split: str,
) -> dict[str, str]:
    """The MLflow tags of a baseline run: those of a training run (variant ``baseline-METHOD``,
    ``config`` its settings' fingerprint) plus ``kind``, ``subsample`` and ``split``."""
    return {
        "variant": f"baseline-{method}",
        "group": group,
        "preset": preset,
        "seed": str(seed),
        "data": data_key,
        "config": config,
        "kind": "baseline",
        "subsample": str(limit or "all"),
        "split": split,
        "git_commit": tracking.git_commit(),
    }


def report_tags(
    group: str, preset: str, command: str, data: str, seeds, commits, note: str
) -> dict[str, str]:
    """The MLflow tags of a report run ``report/{group}/{preset}``: ``kind=report``, what it was
    made from, and its summary ``note`` (no ``variant``/``preset`` tags, so run look-ups by
    those never find it)."""
    return {
        "kind": "report",
        "report_group": group,
        "report_preset": preset,
        "command": command,
        "data": data,
        "seeds": ",".join(map(str, seeds)),
        "git_commit": ",".join(commits),
        "mlflow.note.content": note,
    }


PARAMS_PER_BATCH = 100
"""MLflow's limit of params in one ``log_batch`` request."""


def create_run_record(
    client,
    experiment_id: str,
    name: str,
    tags: dict[str, str],
    params: dict[str, Any] | None = None,
    config: dict[str, Any] | None = None,
) -> str:
    """Create the MLflow run of a record and return its id: its name and tags (as
    :func:`training_tags`, :func:`baseline_tags` or :func:`report_tags` make them), its params
    (flattened as MLflow stores them, :func:`cloudpose.store.tracking.flat_params`) and, for a trained
    network, its full config as the artifact ``config.json`` (what reports and ``--run``
    rebuild a run's config from)."""
    from mlflow.entities import Param

    run_id = client.create_run(experiment_id, tags=tags, run_name=name).info.run_id
    flat = [Param(k, v) for k, v in tracking.flat_params(params or {}).items()]
    for i in range(0, len(flat), PARAMS_PER_BATCH):
        client.log_batch(run_id, params=flat[i : i + PARAMS_PER_BATCH])
    if config is not None:
        client.log_text(run_id, json.dumps(config, indent=2), "config.json")
    return run_id


def open_training_run(
    client,
    cfg: Config,
    data_key: DataKey,
    folder: Path,
    *,
    group: str,
    params: dict[str, Any],
    project_dir: Path,
) -> dict[str, Any]:
    """The MLflow run of the run folder ``folder``, RUNNING: the one its ``run.json`` names
    (a resumed run, marked RUNNING again), else a new run of ``cfg`` on ``data_key`` in
    ``group``'s experiment (name :func:`display_name`, tags :func:`training_tags`, ``params``
    beside ``cfg``'s own, the config as ``config.json``), whose id the folder's new
    ``run.json`` records.

    Returns:
        The folder's ``run.json`` content: ``run_id``, ``group``, ``config`` (and a finished
        run's ``finished`` and ``metrics``).
    """
    info = read_info(folder)
    if info.get("run_id") is not None:
        _check_in_store(client, folder, info["run_id"])
        client.update_run(info["run_id"], status="RUNNING")
        return info
    exp = tracking.experiment_id(client, group, project_dir)
    tags = training_tags(cfg, group, data_key, folder)
    folder.mkdir(parents=True, exist_ok=True)
    run_id = create_run_record(
        client, exp, display_name(cfg), tags, cfg.flat() | params, cfg.to_dict()
    )
    info = {"run_id": run_id, "group": group, "config": cfg.to_dict()}
    write_info(folder, info)
    return info


def _check_in_store(client, folder: Path, run_id: str) -> None:
    """Raise :class:`~cloudpose.store.tracking.StoreError` when the MLflow run a run folder's
    ``run.json`` names is not in the store ``client`` opens: the folder was started against
    another store (another ``MLFLOW_TRACKING_URI``), whose run its checkpoints continue."""
    from mlflow.exceptions import MlflowException

    try:
        client.get_run(run_id)
    except MlflowException as exc:
        if exc.error_code != "RESOURCE_DOES_NOT_EXIST":
            raise
        raise tracking.StoreError(
            f"{folder / INFO}: its MLflow run {run_id} is not in the store at "
            f"{client.tracking_uri} (the folder was started against another store); continue it "
            "with MLFLOW_TRACKING_URI set to that store, or remove the folder to train the run "
            "anew in this one"
        ) from None


def is_preset_fingerprint(
    variant: str, preset: str, seed: int, root: str, fingerprint: str | None
) -> bool:
    """Whether ``fingerprint`` (a run's ``config`` tag) is the config that variant/preset/seed
    resolves to today on dataset root ``root`` ("": the preset's own): the preset's own config,
    no override. False for a name that no longer resolves. The rule of :func:`display_name`,
    :func:`is_preset_config` and the committed store's runs
    (:func:`cloudpose.report.committed.committed_pairs`)."""
    try:
        own = resolve(variant, preset, seed, {"data": {"root": root}} if root else None)
    except (KeyError, ValueError):
        return False
    return own.fingerprint() == fingerprint


def run_folder(
    variant: str, preset: str, seed: int, data_key: DataKey, settings_key: str, project_dir: Path
) -> Path:
    """``runs/{variant}/{preset}/seed{S}-{data[:10]}-{settings[:8]}`` under the project folder
    (under ``$CLOUDPOSE_RUNS_DIR`` instead of ``runs/`` when that is set): the folder of a
    training run (:func:`run_dir`) or of a baseline run (its settings' hash as the key)."""
    name = f"seed{seed}-{data_key[:10]}-{settings_key[:8]}"
    root = Path(os.environ.get(RUNS_DIR_ENV) or project_dir / "runs")
    return root / variant / preset / name


def run_dir(cfg: Config, data_key: DataKey, project_dir: Path) -> Path:
    """The run folder of ``cfg`` trained on data ``data_key`` (:func:`run_folder`)."""
    return run_folder(cfg.variant, cfg.preset, cfg.seed, data_key, cfg.fingerprint(), project_dir)


def lock_path(folder: Path) -> Path:
    """The lock file of a run folder: ``.{name}.lock`` beside it (:func:`run_lock`)."""
    folder = Path(folder)
    return folder.parent / f".{folder.name}.lock"


def folder_locked(folder: Path | None) -> bool:
    """Whether a process on this machine holds the lock of run folder ``folder`` (it trains);
    False for no folder, one that does not exist, or one without a lock file."""
    if folder is None or not Path(folder).is_dir():
        return False
    path = lock_path(folder)
    if not path.exists():
        return False
    lock = FileLock(str(path))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        return True
    lock.release()
    return False


@contextlib.contextmanager
def run_lock(folder: Path) -> Iterator[None]:
    """Hold the run folder's lock: one process at a time trains (or restores) a run on this
    machine. Another process of the same run waits, with a warning, until the first one ends
    (it then finds the run finished, or resumes it); a process that dies releases its lock.
    """
    path = lock_path(folder)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = FileLock(str(path))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        warnings.warn(
            f"{folder}: another process is training this run; waiting for it to end (lock {path})",
            stacklevel=3,
        )
        lock.acquire()
    try:
        yield
    finally:
        lock.release()


def read_info(folder: Path) -> dict[str, Any]:
    """The run folder's ``run.json`` ({} when there is none yet)."""
    path = Path(folder) / INFO
    return json.loads(path.read_text()) if path.exists() else {}


def write_info(folder: Path, info: dict[str, Any]) -> None:
    """Write the run folder's ``run.json`` atomically."""
    atomic_text(Path(folder) / INFO, json.dumps(info, indent=2))


def is_run_folder(path: str | Path) -> bool:
    return (Path(path) / INFO).exists()


def run_has_config(run, cfg: Config) -> bool:
    """Whether an MLflow ``run`` was made with exactly the config ``cfg``.

    By the ``config`` tag; a run from before that tag existed is compared on its logged params
    (every ``section.field`` of ``cfg`` must be there with the same value).
    """
    tag = run.data.tags.get("config")
    if tag is not None:
        return tag == cfg.fingerprint()
    params = run.data.params
    return all(params.get(k) == v for k, v in tracking.flat_params(cfg.flat()).items())


def is_preset_config(run) -> bool:
    """Whether an MLflow ``run`` was trained with its preset's own config (no override).

    Its tags name variant, preset and seed; the config those resolve to today (with the run's
    dataset root) must have the run's ``config`` fingerprint. A run made with ``--set`` or
    ``--epochs``, or under an edited preset, is another config and answers False.
    """
    tags = run.data.tags
    try:
        seed = int(tags["seed"])
        variant, preset = tags["variant"], tags["preset"]
    except (KeyError, ValueError):
        return False
    root = run.data.params.get("data.root", "")
    return is_preset_fingerprint(variant, preset, seed, root, tags.get("config"))


def describe_run(run) -> str:
    """One line naming a run: id, name, config and data fingerprints, start time."""
    t = run.data.tags
    start = datetime.datetime.fromtimestamp((run.info.start_time or 0) / 1000)
    return (
        f"{run.info.run_id} ({run.info.run_name}, config {t.get('config', '?')}, "
        f"data {t.get('data', '?')[:10]}, started {start:%Y-%m-%d %H:%M})"
    )


def finished_run(client, cfg: Config, data_key: DataKey):
    """The newest FINISHED run of exactly ``cfg`` on ``data_key`` with test metrics, or None.

    Matched on the tags (variant, preset, seed, data) and then on the whole config: after an
    edit of the preset or the variant, or a run with overrides, the runs of the old config are
    not taken for the new one.
    """
    for r in tracking.find_runs(
        client, variant=cfg.variant, preset=cfg.preset, seed=cfg.seed, data=data_key
    ):
        if TEST_KEY in r.data.metrics and run_has_config(r, cfg):
            return r
    return None


def restore_run_folder(client, cfg: Config, data_key: DataKey, folder: Path) -> dict[str, Any]:
    """Rebuild the run folder of ``cfg`` on ``data_key`` from MLflow, on a machine without it.

    The newest run of exactly this config and data is taken: a finished one with its
    ``model.pt``, else an unfinished one (a worker that died), with its last checkpoint
    ``checkpoint/last.pt`` when it logged one; training then continues into that MLflow run,
    from the checkpoint or from the start (a run dies before its first checkpoint only in its
    first epoch, before it logged any metric).

    Args:
        client: MLflow client of the store.
        cfg: the run's config; data_key: its data key.
        folder: the run folder to fill (:func:`run_dir`).

    Returns:
        The folder's new ``run.json`` content, or {} when MLflow has no run to continue.
    """
    candidates = tracking.find_runs(
        client,
        variant=cfg.variant,
        preset=cfg.preset,
        seed=cfg.seed,
        data=data_key,
        status=None,
    )
    for run in candidates:
        if not run_has_config(run, cfg):
            continue
        run_id = run.info.run_id
        info: dict[str, Any] = {
            "run_id": run_id,
            "group": run.data.tags.get("group"),
            "config": cfg.to_dict(),
        }
        if run.info.status == "FINISHED":
            if not fetch_artifact(client, run_id, "model.pt", folder / "model.pt"):
                continue
            metrics = {k: v for k, v in run.data.metrics.items() if k.split("/")[0] in _TRAINED}
            info.update({"finished": True, "metrics": metrics})
        else:
            fetch_artifact(client, run_id, f"{CHECKPOINT_ARTIFACT_DIR}/last.pt", folder / "last.pt")
        write_info(folder, info)
        return info
    return {}


_TRAINED = ("train", "val", "fit")
"""Metric prefixes training logs (a finished run's ``run.json`` metrics)."""

TRAINING_PREFIXES = (*_TRAINED, "time")
"""Every metric prefix training logs, per epoch: no evaluation may be named like one."""


def fetch_artifact(client, run_id: str, path: str, dest: Path) -> bool:
    """Download the run's artifact ``path`` to ``dest``; False when the run has none."""
    parent, _, name = path.rpartition("/")
    if name not in {Path(f.path).name for f in client.list_artifacts(run_id, parent or None)}:
        return False
    dest.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=dest.parent) as tmp:
        got = client.download_artifacts(run_id, path, tmp)
        os.replace(got, dest)
    return True


def drop_checkpoint_artifact(client, run_id: str) -> None:
    """Delete a finished run's ``checkpoint/`` artifacts (its ``model.pt`` stays); warns when
    the artifact store refuses."""
    from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository

    try:
        uri = tracking.artifact_address(
            client.get_run(run_id).info.artifact_uri, client.tracking_uri
        )
        repo = get_artifact_repository(uri, tracking_uri=client.tracking_uri)
        repo.delete_artifacts(CHECKPOINT_ARTIFACT_DIR)
    except Exception as exc:  # any store's refusal: the checkpoint only costs space
        warnings.warn(
            f"run {run_id}: could not delete its {CHECKPOINT_ARTIFACT_DIR}/ artifacts "
            f"({type(exc).__name__}: {exc})",
            stacklevel=2,
        )


def resolve_run_id(client, run: str) -> str:
    """MLflow run id of ``run`` (a run folder, an MLflow run id or a run name; see resolve_run)."""
    if is_run_folder(run):
        return read_info(Path(run))["run_id"]
    if run.count("/") == 2:
        return _resolve_name(client, run)
    try:
        return client.get_run(run).info.run_id
    except Exception as exc:
        raise ValueError(
            f"--run {run!r} is neither a run folder, a run name variant/preset/seedS[+CONFIG], "
            f"nor an MLflow run id in {tracking.tracking_uri()}"
        ) from exc


def _resolve_name(client, run: str) -> str:
    """MLflow run id of the one finished run named ``variant/preset/seedS`` (the preset's own
    config) or ``variant/preset/seedS+CONFIG`` (the config whose fingerprint starts with
    CONFIG, as :func:`display_name` prints it)."""
    name, plus, config = run.partition("+")
    variant, preset, seed = name.split("/")
    try:
        seed_n = int(seed.removeprefix("seed"))
    except ValueError:
        raise ValueError(f"--run {run!r}: expected variant/preset/seedN[+CONFIG]") from None
    if plus and not config:
        raise ValueError(f"--run {run!r}: expected a config fingerprint after '+'")
    found = tracking.find_runs(client, variant=variant, preset=preset, seed=seed_n)
    if not found:
        raise ValueError(f"no finished run named {run!r} in {tracking.tracking_uri()}")
    if plus:
        own = [r for r in found if r.data.tags.get("config", "").startswith(config)]
        what = f"of config {config}"
    else:
        own = [r for r in found if is_preset_config(r)]
        what = f"of preset {preset!r}'s own config"
    if len(own) == 1:
        return own[0].info.run_id
    listed = "; ".join(describe_run(r) for r in (own or found))
    if own:
        why = f"{len(own)} finished runs {what} are named {run!r}"
    elif plus:
        why = f"no finished run named {name!r} has a config starting with {config!r}"
    else:
        why = (
            f"no finished run named {run!r} has preset {preset!r}'s own config "
            "(the ones there were made with overrides or an older preset)"
        )
    raise ValueError(f"{why}: {listed}. Pass the run id or run folder")


CHECKPOINT_KEYS = ("model", "config")
"""What every checkpoint holds (``model.pt``); ``last.pt`` also ``optimizer``, ``epoch``,
``batch`` and ``sums``."""


class CheckpointError(ValueError):
    """A checkpoint that cannot be read (empty, truncated, not a checkpoint): the message names
    the file and why."""


def read_checkpoint(
    path: str | Path, map_location: Any = "cpu", keys: tuple[str, ...] = CHECKPOINT_KEYS
) -> dict[str, Any]:
    """The state saved in a checkpoint, checked: readable (tensors and plain data only) and
    holding ``keys``; else :class:`CheckpointError` naming the file and why (a zero-byte or
    torn file, a foreign pickle)."""
    import torch

    path = Path(path)
    if path.is_file() and path.stat().st_size == 0:
        raise CheckpointError(f"{path} is not a readable checkpoint (it is empty: 0 bytes)")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # a torn zip, an empty file (EOFError), an unsafe pickle, ...
        reason = " ".join(str(exc).split())[:120] or type(exc).__name__
        raise CheckpointError(
            f"{path} is not a readable checkpoint ({type(exc).__name__}: {reason})"
        ) from exc
    missing = [k for k in keys if not isinstance(state, dict) or k not in state]
    if missing:
        raise CheckpointError(
            f"{path} is not a readable checkpoint (it lacks {', '.join(map(repr, missing))})"
        )
    return state


def client_for(names: list[str], project_dir: Path | None = None):
    """The MLflow client that :func:`local_checkpoint` needs to resolve ``names``, on the store
    of ``project_dir`` (:func:`cloudpose.store.tracking.setup`); None when every name is a
    shipped network, so that no store is opened, nor created in the working folder."""
    if all(is_pretrained(n) for n in names):
        return None
    return tracking.setup(project_dir)


@contextlib.contextmanager
def local_checkpoint(client, run: str) -> Iterator[tuple[str, Path]]:
    """:func:`resolve_run` whose downloaded checkpoint (a run whose folder is not on this
    machine) lives in a temporary folder for the block only: read it inside the block.
    ``pretrained`` (:mod:`cloudpose.store.pretrained`) gives run id None and the shipped weights."""
    if is_pretrained(run):  # the network the package ships: no MLflow run
        yield None, shipped(run).path
        return
    with tempfile.TemporaryDirectory(prefix="cloudpose-checkpoint-") as tmp:
        yield resolve_run(client, run, download_to=Path(tmp))


def resolve_run(client, run: str, download_to: Path | None = None) -> tuple[str, Path]:
    """MLflow run id and local checkpoint of ``run``.

    ``run`` is a run folder (``runs/shared-0/cpu/seed1-...``), an MLflow run id, or a run name:
    ``variant/preset/seedS``, the one finished run of that name trained with the preset's own
    config, or ``variant/preset/seedS+CONFIG`` as :func:`display_name` prints a run made with
    overrides, the one finished run whose config fingerprint starts with CONFIG (an error
    listing the candidates when there are none or several). A checkpoint that
    is not on this machine is downloaded from the run's artifacts into ``download_to`` (a
    folder the caller removes: :func:`local_checkpoint`), else into a new temporary folder that
    stays.
    """
    run_id = resolve_run_id(client, run)
    if is_run_folder(run):
        return run_id, Path(run) / "model.pt"
    run_info = client.get_run(run_id)
    folder = run_info.data.tags.get("run_dir", "")
    local = tracking.store_path(folder, client.tracking_uri) / "model.pt" if folder else None
    if local is None or not local.exists():
        local = tracking.download_artifact(client, run_info, "model.pt", download_to)
    return run_id, local
