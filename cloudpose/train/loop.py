"""Training of one variant from the segment cache, resumable and tracked in MLflow.

A run is a sequence of steps (:func:`_train`): open the run folder (:class:`TrainingRun`), build
the data (:class:`TrainingSets`) and the network, resume from the last checkpoint (a
:class:`Position`), open the MLflow run (:func:`cloudpose.store.runs.open_training_run`),
train the epochs (:class:`Trainer`; each optimiser step is
:func:`cloudpose.train.step.train_step`, on batches augmented by :mod:`cloudpose.train.augment`),
and finish. Every random stream is :func:`cloudpose.train.seeds.seed_for`'s.

Resumability: the run folder ``runs/{variant}/{preset}/seed{S}-{data}-{config}`` (data and
config fingerprints: an edited preset or an override never resumes another config's run) holds
``last.pt`` (model, optimiser, position in the epoch and the epoch's running loss sums), written
atomically at the end of every epoch and every ``checkpoint_every_s`` seconds within one, the
one before it as ``last.prev.pt``, and ``run.json`` with the MLflow run id. Rerunning the same
command after any interruption (``kill -9``, SIGTERM, Ctrl-C, a full disk) continues from
``last.pt`` into the same MLflow run; from ``last.prev.pt``, with a warning naming the bad file,
when ``last.pt`` cannot be read (torn, empty). An epoch's metrics are logged once: a resumed run
that trains an epoch again (from an earlier checkpoint) does not log it a second time. A full
disk is one line naming the file and the space it needs
(:class:`cloudpose.failures.DiskFullError`), and the run is marked FAILED; SIGTERM stops
training as Ctrl-C does (the run is marked KILLED). Every random stream of training depends only
on the seed, its purpose and its index (the batch order of epoch ``e`` on ``(seed, e)``, the
model's initial weights on ``seed``), so a resumed run ends with the same numbers as an
uninterrupted one (on CPU, with the same thread count). Against a tracking server
(:func:`cloudpose.store.tracking.is_remote`) every checkpoint is also logged to the run as the
artifact ``checkpoint/last.pt`` (removed once the run finishes), and a machine without the run
folder (a retried Ray task on another node) rebuilds it from MLflow
(:func:`cloudpose.store.runs.restore_run_folder`): the run continues into the same MLflow run
from the last logged checkpoint.

Several processes (``torchrun``; :mod:`cloudpose.models.sync_bn`) train one run: each takes
an equal share of every global batch, DDP averages the gradients, BatchNorm uses the global
batch's statistics; rank 0 alone writes the run folder and talks to MLflow.

Validation: a fixed share of the training *frames* (not instances: instances of one frame share
a scene) is held out, chosen from the frame ids alone so every seed and variant sees the same
split; :mod:`cloudpose.train.validation` measures the network on it at the end of every epoch.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import math
import os
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from cloudpose import runtime
from cloudpose.config import PAIRED_BRANCH, Config
from cloudpose.data.batches import Batchable, split_forms
from cloudpose.data.dataset import Prepared
from cloudpose.data.keys import DataKey
from cloudpose.data.synth.chunks import STORE_DIR, OnlineSettings, code_digest
from cloudpose.data.synth.online import REUSE_SPACING, OnlineChunks, OnlineStream
from cloudpose.failures import DiskFullError, disk_full, sigterm_as_interrupt
from cloudpose.files import atomic_write
from cloudpose.geometry.symmetry import SymmetryTensors, symmetries_for
from cloudpose.models import build_model, count_parameters
from cloudpose.models.fused import fuse_model
from cloudpose.models.sync_bn import local_batch_stats, sync_batch_stats
from cloudpose.registry import groups_of
from cloudpose.store import runs, tracking
from cloudpose.train import seeds
from cloudpose.train.augment import augment, augment_forms
from cloudpose.train.distributed import SINGLE, World
from cloudpose.train.step import Batch, StepLoss, train_step
from cloudpose.train.validation import batch_stats_rotation_error, recalibrate_bn, validate


@dataclass(frozen=True)
class TrainOutcome:
    """Where a finished training run lives and what it ended with."""

    run_id: str
    run_dir: Path
    checkpoint: Path
    metrics: dict[str, float]


def split_frames(frame_ids: np.ndarray, val_fraction: float) -> np.ndarray:
    """Boolean (M,) mask of instances whose frame is held out for validation.

    A frame is held out when the first 8 hex digits of its id's SHA-1 fall below
    ``val_fraction``: fixed by the data alone, independent of seed, variant and frame count.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"train.val_fraction must be in [0, 1), got {val_fraction}")
    held = {}
    for f in np.unique(frame_ids):
        h = int(hashlib.sha1(str(f).encode()).hexdigest()[:8], 16) / 0x1_0000_0000
        held[f] = h < val_fraction
    return np.array([held[f] for f in frame_ids], dtype=bool)


ONLINE_STORE_ENV = "CLOUDPOSE_ONLINE_STORE"
"""Environment variable: ``0`` keeps on-line runs from reading or writing the project's chunk
store (:mod:`cloudpose.data.synth.chunks`); a path puts the store there. Unset: the project's
``data/cache/online``."""


def online_store_root(project_dir: str | Path) -> Path | None:
    """Where on-line runs of ``project_dir`` keep their chunks (:data:`ONLINE_STORE_ENV`)."""
    value = os.environ.get(ONLINE_STORE_ENV, "").strip()
    if value == "0":
        return None
    return Path(value) if value else Path(project_dir).joinpath(*STORE_DIR)


def online_epoch_steps(cfg: Config) -> int:
    """Optimiser steps of an on-line run's epoch (``data.online_epoch_segments``)."""
    return max(cfg.data.online_epoch_segments // cfg.train.batch_size, 1)


def online_chunks(cfg: Config, class_names: list[str]) -> tuple[OnlineSettings, int, int]:
    """``(settings, chunk_size, n_chunks)`` of an on-line run: the chunks its
    :class:`~cloudpose.data.synth.online.OnlineStream` draws, the same for every variant that
    shares its ``data`` section, ``train.n_points``, ``train.batch_size`` and epochs."""
    reuse = cfg.data.online_reuse
    span = (reuse - 1) * REUSE_SPACING
    return (
        OnlineSettings.from_config(cfg, class_names),
        cfg.train.batch_size // reuse,
        cfg.train.epochs * online_epoch_steps(cfg) + span,
    )


def online_probe(
    settings: OnlineSettings, seed: int, n: int, store: str | Path | None = None
) -> Batchable:
    """``n`` segments drawn as the run's first step draws them (its first chunk is trained on):
    the ``fit/`` probe of an on-line run (read from, or kept in, the chunk store ``store``);
    segments in two forms (``data.online_bleed_branch``) keep both, each for its branch."""
    points, cls_id, R, t = OnlineChunks(settings, seed, n, 1, store)[0]
    if settings.forms == 1:
        return Batchable(points, cls_id, R, t)
    points, trans_points = split_forms(points, settings.n_points)
    return Batchable(points, cls_id, R, t, trans_points=trans_points)


def epoch_order(fit: Batchable, sampler: str, n: int, generator: torch.Generator) -> torch.Tensor:
    """(n,) training indices of one epoch, drawn from ``generator`` (the epoch's ``order``
    stream, :func:`cloudpose.train.seeds.seed_for`).

    ``shuffle``: a permutation of the segments (the first ``n``); ``class_balanced``: each
    draw picks a class uniformly among the classes present, then one of its segments.
    """
    if sampler == "shuffle":
        return torch.randperm(len(fit), generator=generator)[:n]
    classes, inverse = torch.unique(fit.cls_id, return_inverse=True)
    members = [torch.nonzero(inverse == c).squeeze(1) for c in range(len(classes))]
    pick = torch.randint(len(classes), (n,), generator=generator)
    out = torch.empty(n, dtype=torch.long)
    for c, idx in enumerate(members):
        sel = pick == c
        out[sel] = idx[torch.randint(len(idx), (int(sel.sum()),), generator=generator)]
    return out


def lr_at(cfg: Config, step: int, total: int) -> float:
    """Learning rate of optimiser step ``step`` (0-based) of ``total`` (``train.lr_schedule``)."""
    if cfg.train.lr_schedule == "cosine":
        return 0.5 * cfg.train.lr * (1.0 + math.cos(math.pi * min(step, total) / max(total, 1)))
    return cfg.train.lr


def train(
    cfg: Config,
    data: Prepared,
    *,
    project_dir: Path | None = None,
    group: str | None = None,
    progress: bool = True,
    checkpoint_every_s: float = 60.0,
    max_steps: int | None = None,
    world: World = SINGLE,
    checkpoint_artifacts: bool | None = None,
) -> TrainOutcome:
    """Train ``cfg`` on prepared data (resuming if its run folder has a checkpoint) and log it
    to MLflow. Making the data is the caller's step (:func:`cloudpose.suite.pipeline.train_run`).

    Args:
        cfg: the full resolved config (:func:`cloudpose.registry.resolve`).
        data: ``cfg.data`` prepared (:func:`cloudpose.data.dataset.prepare_data`); its
            training segments are fitted and validated on, its key names the run.
        project_dir: folder holding ``data/``, ``runs/`` and the default MLflow store (cwd).
        group: ablation group whose experiment receives a new run; default the variant's
            first group.
        progress: show progress bars.
        checkpoint_every_s: seconds between mid-epoch checkpoints.
        max_steps: stop (without finishing the run) after this many optimiser steps in this
            call; for tests that simulate an interruption.
        world: the processes training this run together (:func:`cloudpose.train.distributed.from_env`);
            default one.
        checkpoint_artifacts: also log every checkpoint to the MLflow run, and rebuild a
            missing run folder from MLflow; default: when the store is a tracking server.

    Returns:
        The run's id, folder, final checkpoint and final metrics. A finished run is returned
        as it is, without training again.

    A second process training the same run on this machine waits for the first
    (:func:`cloudpose.store.runs.run_lock`). A run that stops on an error is marked FAILED in
    MLflow (KILLED after Ctrl-C); the same command resumes it.
    """
    project_dir = (project_dir or Path.cwd()).resolve()
    if group is not None:
        tracking.check_name("group", group)
    rdir = runs.run_dir(cfg, data.data_key, project_dir)
    # One process at a time per run folder: a second identical command waits, then finds
    # the run finished (or resumes it), instead of training a twin into the same folder.
    lock = runs.run_lock(rdir) if world.is_main else contextlib.nullcontext()
    with sigterm_as_interrupt(), lock:
        try:
            return _train(
                cfg,
                data,
                rdir,
                project_dir=project_dir,
                group=group,
                progress=progress,
                checkpoint_every_s=checkpoint_every_s,
                max_steps=max_steps,
                world=world,
                checkpoint_artifacts=checkpoint_artifacts,
            )
        except TrainingInterrupted:
            raise
        except BaseException as exc:
            full = _disk_full(exc, project_dir, rdir)
            if world.is_main:
                _mark_ended(project_dir, rdir, exc)
            if full is not None:
                raise full from exc
            raise


RESUME_HINT = "rerun the same command: the run resumes from its last checkpoint"


def _disk_full(exc: BaseException, project_dir: Path, rdir: Path) -> DiskFullError | None:
    """The one-line :class:`DiskFullError` of a full disk while training, else None. The file
    is the one a write named (a checkpoint names itself and its size), else the MLflow store
    for SQLite's "database or disk is full", else the run folder."""
    if isinstance(exc, DiskFullError):
        return exc
    db = tracking.sqlite_path(tracking.tracking_uri(project_dir))
    where = db if db is not None and "database or disk is full" in str(exc) else rdir
    return disk_full(exc, where, then=RESUME_HINT)


def _mark_ended(project_dir: Path, rdir: Path, exc: BaseException) -> None:
    """Mark the MLflow run of ``rdir`` (if it has one) FAILED, or KILLED after Ctrl-C: a run
    that stopped on an error is not left RUNNING. Rerunning the command resumes it."""
    run_id = runs.read_info(rdir).get("run_id")
    if run_id is None:
        return
    status = "KILLED" if isinstance(exc, KeyboardInterrupt) else "FAILED"
    try:
        tracking.setup(project_dir).set_terminated(run_id, status)
    except Exception as e:  # the store's own failure must not hide the training error
        warnings.warn(f"run {run_id}: could not mark it {status} ({e})", stacklevel=3)


def _train(
    cfg: Config,
    data: Prepared,
    rdir: Path,
    *,
    project_dir: Path,
    group: str | None,
    progress: bool,
    checkpoint_every_s: float,
    max_steps: int | None,
    world: World,
    checkpoint_artifacts: bool | None,
) -> TrainOutcome:
    """:func:`train` with the run folder's lock held (rank 0): the run's folder and MLflow
    record, its data, its network resumed from the last checkpoint, the epochs, the end."""
    device = _training_device(cfg, world)
    run = _open_run(cfg, data.data_key, rdir, project_dir, world, checkpoint_artifacts)
    if run.finished(cfg, world):
        return TrainOutcome(run.info["run_id"], rdir, run.final, run.info.get("metrics", {}))
    sets = _training_sets(cfg, data, project_dir, device)
    model, opt = _network(cfg, device)
    position = _resume(run, model, opt, cfg, world, device)
    params = _run_params(cfg, data.data_key, model, sets, device)
    group = group or (groups_of(cfg.variant) or ["misc"])[0]
    run.open_mlflow_run(cfg, data.data_key, group, params, project_dir, world)
    trainer = Trainer(cfg, model, opt, device, world, sets, run)
    metrics = trainer.run(
        position, progress=progress, checkpoint_every_s=checkpoint_every_s, max_steps=max_steps
    )
    return run.finish(model, cfg, metrics, world)


def _training_device(cfg: Config, world: World) -> torch.device:
    """This process's device, with training's own thread count on one process."""
    device = world.device(runtime.pick_device(cfg.train.device))
    if not world.distributed:
        # the thread count changes the numbers (training BatchNorm and GEMM reductions split
        # across threads), so a run trains with its own, part of its identity
        runtime.configure_threads(cfg.train.threads)
    world.shard(cfg.train.batch_size)  # a batch that does not split fails here, not later
    return device


# ---------------------------------------------------------------------------- the run record


@dataclass
class TrainingRun:
    """A run's folder and MLflow run as this process sees them: rank 0 holds the MLflow
    client and writes; the other processes hold what rank 0 broadcast."""

    folder: Path
    info: dict[str, Any]
    client: Any = None
    artifacts: bool = False
    run_id: str | None = None
    logged: frozenset[int] = frozenset()

    @property
    def last(self) -> Path:
        """The resume checkpoint, ``last.pt``."""
        return self.folder / "last.pt"

    @property
    def final(self) -> Path:
        """The finished run's model, ``model.pt``."""
        return self.folder / "model.pt"

    def finished(self, cfg: Config, world: World) -> bool:
        """Whether the run is finished and its ``model.pt`` is there (rewritten if torn)."""
        if not self.info.get("finished"):
            return False
        ready = world.is_main and _final_model_ready(
            self.final, self.last, cfg, self.client, self.info["run_id"]
        )
        return world.broadcast(ready)

    def open_mlflow_run(
        self,
        cfg: Config,
        data_key: DataKey,
        group: str,
        params: dict[str, Any],
        project_dir: Path,
        world: World,
    ) -> None:
        """Resume the folder's MLflow run, or create it (:func:`runs.open_training_run`), and
        note the epochs it has logged already (trained again from an earlier checkpoint, they
        are not logged again)."""
        if world.is_main:
            self.info = runs.open_training_run(
                self.client,
                cfg,
                data_key,
                self.folder,
                group=group,
                params=params,
                project_dir=project_dir,
            )
            history = self.client.get_metric_history(self.info["run_id"], "train/loss")
            self.logged = frozenset(m.step for m in history)
        self.run_id = world.broadcast(self.info.get("run_id"))

    def checkpoint(self, model: torch.nn.Module, opt, cfg: Config, position: Position) -> None:
        """Write ``last.pt`` at ``position`` (and log it to the run with ``artifacts``)."""
        _checkpoint(self.last, model, opt, cfg, position)
        if self.artifacts:
            self.client.log_artifact(
                self.run_id, str(self.last), artifact_path=runs.CHECKPOINT_ARTIFACT_DIR
            )

    def log_epoch(self, epoch: int, metrics: dict[str, float]) -> None:
        """Log the metrics of ``epoch`` (1-based) unless the run logged that epoch already."""
        if epoch not in self.logged:
            self.client.log_batch(self.run_id, metrics=tracking.metric_batch(metrics, epoch))

    def finish(
        self, model: torch.nn.Module, cfg: Config, metrics: dict[str, float], world: World
    ) -> TrainOutcome:
        """Save ``model.pt``, record the final metrics and mark the run FINISHED (rank 0)."""
        final_metrics = {k: v for k, v in metrics.items() if not k.startswith("time/")}
        if world.is_main:
            if not metrics:  # stopped after its last checkpoint: as it logged them
                final_metrics = self.info.get("metrics") or self._logged_metrics()
            _save(self.final, {"model": model.state_dict(), "config": cfg.to_dict()})
            self.client.log_artifact(self.run_id, str(self.final))
            self.last.with_name(PREVIOUS_CHECKPOINT).unlink(missing_ok=True)
            self.info.update({"finished": True, "metrics": final_metrics})
            runs.write_info(self.folder, self.info)
            if self.artifacts:
                runs.drop_checkpoint_artifact(self.client, self.run_id)
            self.client.set_terminated(self.run_id, "FINISHED")
        return TrainOutcome(self.run_id, self.folder, self.final, world.broadcast(final_metrics))

    def _logged_metrics(self) -> dict[str, float]:
        logged = self.client.get_run(self.run_id).data.metrics
        return {
            k: v
            for k, v in logged.items()
            if k.split("/")[0] in runs.TRAINING_PREFIXES and not k.startswith("time/")
        }


def _open_run(
    cfg: Config,
    data_key: DataKey,
    rdir: Path,
    project_dir: Path,
    world: World,
    artifacts: bool | None,
) -> TrainingRun:
    """The run folder as it stands: its ``run.json`` (rebuilt from MLflow on a machine without
    it when checkpoints are logged there), on every process."""
    run = TrainingRun(rdir, {})
    if world.is_main:
        run.info = runs.read_info(rdir)
        run.client = tracking.setup(project_dir)
        if artifacts is None:
            artifacts = tracking.is_remote(run.client.tracking_uri)
        run.artifacts = artifacts
        if not run.info and artifacts:
            run.info = runs.restore_run_folder(run.client, cfg, data_key, rdir)
    run.info = world.broadcast(run.info)
    return run


def _run_params(
    cfg: Config, data_key: DataKey, model: torch.nn.Module, sets: TrainingSets, device
) -> dict[str, Any]:
    """The MLflow params of a new run besides its config's."""
    online = sets.online is not None
    return {
        "model.parameters": count_parameters(model),
        "data.fingerprint": data_key,
        "data.train_segments": "online" if online else len(sets.fit),
        # on line, the segments are made by code: runs of one seed are like for like only
        # when their synthesis code agrees (the chunk store's key holds it too)
        **({"data.online_code": code_digest()} if online else {}),
        "data.val_segments": len(sets.val),
        "device": device,
    }


# ---------------------------------------------------------------------------- data and network


@dataclass(frozen=True)
class TrainingSets:
    """What a run trains and validates on.

    Attributes:
        fit: the training segments (on line: the first step's segments, which re-estimate
            BatchNorm statistics).
        val: the validation segments (on line: every rendered training frame's).
        probe: a fixed sample of ``fit`` (eval- vs train-mode error on the same segments).
        online: the on-line synthesis settings; None when training on frames.
        online_store: where on-line chunks are kept (:func:`online_store_root`).
        class_names: the dataset's classes; models_by_class: their model points.
        symmetry: each class's symmetries on the device (``loss.symmetric``), else None.
    """

    fit: Batchable
    val: Batchable
    probe: Batchable
    online: OnlineSettings | None
    online_store: Path | None
    class_names: list[str]
    models_by_class: dict
    symmetry: SymmetryTensors | None


def _training_sets(
    cfg: Config, data: Prepared, project_dir: Path, device: torch.device
) -> TrainingSets:
    """The run's :class:`TrainingSets`: held-out frames validate (``train.val_fraction``), or
    on line, the rendered training frames do and fitting draws fresh segments."""
    class_names = list(data.dataset.classes)
    n_points, store = cfg.train.n_points, online_store_root(project_dir)
    models = data.dataset.models()
    if cfg.data.train_source == "online":
        val = Batchable.from_segments(data.train, n_points)
        return online_training_sets(cfg, class_names, val, models, store, device)
    held = split_frames(data.train.frame_id, cfg.train.val_fraction)
    fit = Batchable.from_segments(data.train.subset(~held), n_points)
    val = Batchable.from_segments(data.train.subset(held), n_points)
    return _assemble(cfg, fit, val, None, store, class_names, models, device)


def online_training_sets(
    cfg: Config,
    class_names: list[str],
    val: Batchable,
    models: dict,
    store: Path | None,
    device: torch.device,
) -> TrainingSets:
    """The :class:`TrainingSets` of an on-line run from its validation segments and model
    points: fitting draws fresh segments (the first step's, from the chunk store ``store``,
    re-estimate BatchNorm statistics); what a machine without the rendered frames needs
    (``benchmarks/gpu_run.py``)."""
    online = OnlineSettings.from_config(cfg, class_names)
    fit = online_probe(online, cfg.seed, 256, store)
    return _assemble(cfg, fit, val, online, store, class_names, models, device)


def _assemble(
    cfg: Config,
    fit: Batchable,
    val: Batchable,
    online: OnlineSettings | None,
    store: Path | None,
    class_names: list[str],
    models: dict,
    device: torch.device,
) -> TrainingSets:
    """:class:`TrainingSets` of ``fit`` and ``val``: the probe (the seed's ``probe`` stream)
    and the symmetry tensors on the device."""
    if len(fit) < cfg.train.batch_size:
        raise ValueError(
            f"only {len(fit)} valid training segments, fewer than train.batch_size="
            f"{cfg.train.batch_size}; render more frames (data.train_frames)"
        )
    symmetry = None
    if cfg.loss.symmetric:
        symmetry = SymmetryTensors(symmetries_for(class_names, cfg.loss.symmetry_table)).to(device)
    g = seeds.generator(cfg.seed, "probe", streams=cfg.train.seed_streams)
    probe = fit.subset(torch.randperm(len(fit), generator=g)[:512])
    return TrainingSets(fit, val, probe, online, store, class_names, models, symmetry)


def _network(cfg: Config, device: torch.device) -> tuple[torch.nn.Module, torch.optim.Optimizer]:
    """The network at its initial weights (the seed's ``init`` stream) and its Adam."""
    torch.manual_seed(seeds.seed_for(cfg.seed, "init", streams=cfg.train.seed_streams))
    model = build_model(cfg.model).to(device)
    bf16 = cfg.train.precision == "bf16"
    if bf16:
        warn_if_slow_bf16(device)
    if fused_kernel(cfg, device):
        fuse_model(model, bf16=bf16)
    return model, torch.optim.Adam(model.parameters(), lr=cfg.train.lr)


@dataclass
class Position:
    """Where a run stands: its epoch (0-based), the next batch within it, and the epoch's
    running loss sums (``loss``, ``rot``, ``trans`` and the step count ``n``); ``last.pt``
    keeps them beside the model and the optimiser."""

    epoch: int = 0
    batch: int = 0
    sums: dict[str, float] = field(
        default_factory=lambda: {"loss": 0.0, "rot": 0.0, "trans": 0.0, "n": 0}
    )

    def add(self, step: StepLoss) -> None:
        """Count one step's losses; on to the next batch."""
        self.sums["loss"] += step.loss
        self.sums["rot"] += step.rot
        self.sums["trans"] += step.trans
        self.sums["n"] += 1
        self.batch += 1

    def means(self) -> dict[str, float]:
        """The epoch's mean losses so far, as logged (``train/loss`` and its two terms)."""
        n = max(self.sums["n"], 1)
        return {
            "train/loss": self.sums["loss"] / n,
            "train/loss_rot": self.sums["rot"] / n,
            "train/loss_trans": self.sums["trans"] / n,
        }


def _resume(
    run: TrainingRun, model: torch.nn.Module, opt, cfg: Config, world: World, device: torch.device
) -> Position:
    """Load the run's last checkpoint (rank 0's, on every process) into ``model`` and ``opt``
    and return its position; the start when there is none."""
    state = None
    if world.is_main:
        where = "cpu" if world.distributed else device  # sent to the other processes first
        state = _read_resume_state(run.last, where)
    state = world.broadcast(state)
    if state is None:
        return Position()
    if Config.from_dict(state["config"]).to_dict() != cfg.to_dict():
        raise ValueError(
            f"{run.last} was written by another config; delete {run.folder} to restart"
        )
    model.load_state_dict(state["model"])
    opt.load_state_dict(state["optimizer"])
    return Position(state["epoch"], state["batch"], state["sums"])


# ---------------------------------------------------------------------------- the epochs


class Trainer:
    """The epochs of one run from a :class:`Position` on: batches, steps, checkpoints, and
    each epoch's validation and metrics."""

    def __init__(
        self,
        cfg: Config,
        model: torch.nn.Module,
        opt: torch.optim.Optimizer,
        device: torch.device,
        world: World,
        sets: TrainingSets,
        run: TrainingRun,
    ) -> None:
        self.cfg, self.model, self.opt, self.device = cfg, model, opt, device
        self.world, self.sets, self.run_record = world, sets, run
        self.net = model
        if world.distributed:
            sync_batch_stats(model, world.stats_group)
            self.net = torch.nn.parallel.DistributedDataParallel(
                model, device_ids=[device.index] if device.type == "cuda" else None
            )
        self.batch_size = cfg.train.batch_size
        if sets.online is not None:
            self.n_batches = online_epoch_steps(cfg)
        else:  # drop the last partial batch: BatchNorm needs full batches
            self.n_batches = len(sets.fit) // self.batch_size
        self.total_steps = cfg.train.epochs * self.n_batches

    def run(
        self,
        position: Position,
        *,
        progress: bool,
        checkpoint_every_s: float,
        max_steps: int | None,
    ) -> dict[str, float]:
        """Train from ``position`` to the last epoch; the last epoch's metrics ({} when none
        was trained here). ``max_steps`` steps in: a checkpoint, then
        :class:`TrainingInterrupted`."""
        epochs, world = self.cfg.train.epochs, self.world
        metrics: dict[str, float] = {}
        steps, t_ckpt = 0, time.monotonic()
        with contextlib.ExitStack() as stack:
            bar = stack.enter_context(self._progress_bar(position, progress))
            stream = None
            if self.sets.online is not None and position.epoch < epochs:
                stream = stack.enter_context(contextlib.closing(self._stream(position)))
            self.model.train()
            while position.epoch < epochs:
                t_epoch = time.monotonic()
                for batch in self._batches(position, stream):
                    position.add(self._step(batch, position))
                    steps += 1
                    bar.update(1)
                    mean = position.sums["loss"] / position.sums["n"]
                    bar.set_postfix(epoch=position.epoch + 1, loss=f"{mean:.3f}")
                    if world.is_main and time.monotonic() - t_ckpt > checkpoint_every_s:
                        self._checkpoint(position)
                        t_ckpt = time.monotonic()
                    if max_steps is not None and steps >= max_steps:
                        if world.is_main:
                            self._checkpoint(position)
                        raise TrainingInterrupted(self.run_record.folder)
                metrics = self._end_epoch(position, time.monotonic() - t_epoch)
                position = Position(position.epoch + 1)
                if world.is_main:
                    self._checkpoint(position)
                t_ckpt = time.monotonic()
        return metrics

    def _progress_bar(self, position: Position, progress: bool) -> tqdm:
        return tqdm(
            total=self.total_steps,
            initial=position.epoch * self.n_batches + position.batch,
            disable=not progress or not self.world.is_main,
            desc=runs.display_name(self.cfg),
            unit="step",
            dynamic_ncols=True,
        )

    def _stream(self, position: Position) -> OnlineStream:
        """The on-line batches from ``position`` on."""
        assert self.sets.online is not None
        return OnlineStream(
            self.sets.online,
            self.cfg.seed,
            self.batch_size,
            self.cfg.data.online_reuse,
            self.total_steps,
            start=position.epoch * self.n_batches + position.batch,
            workers=self.cfg.data.online_workers,
            store=self.sets.online_store,
        )

    def _batches(self, position: Position, stream: OnlineStream | None) -> Iterator[Batch]:
        """The global batches of ``position``'s epoch from its batch on, on the device: the
        on-line stream's, else the epoch's order of the training segments."""
        to = self.device
        if stream is not None:
            for _ in range(position.batch, self.n_batches):
                yield Batch(*(x.to(to) for x in stream.next()))
            return
        fit, bs, cfg = self.sets.fit, self.batch_size, self.cfg
        g = seeds.generator(cfg.seed, "order", position.epoch, streams=cfg.train.seed_streams)
        perm = epoch_order(fit, cfg.train.sampler, self.n_batches * bs, g)
        for b in range(position.batch, self.n_batches):
            idx = perm[b * bs : (b + 1) * bs]
            yield Batch(
                fit.points[idx].to(to), fit.cls_id[idx].to(to), fit.R[idx].to(to), fit.t[idx].to(to)
            )

    def _step(self, batch: Batch, position: Position) -> StepLoss:
        """One optimiser step on ``batch`` at ``position``: the learning rate of the step, the
        batch augmented (the whole global batch, then this process's share), :func:`train_step`."""
        cfg = self.cfg
        for group in self.opt.param_groups:
            group["lr"] = lr_at(
                cfg, position.epoch * self.n_batches + position.batch, self.total_steps
            )
        branch, at = cfg.data.online_bleed_branch, (position.epoch, position.batch)
        if branch == PAIRED_BRANCH:  # the first form augmented as a run of one form's batch
            points, trans_points = split_forms(batch.points, cfg.train.n_points)
            points, trans_points, R, t = augment_forms(  # contiguous, as a plain batch is
                points.contiguous(), trans_points.contiguous(), batch.R, batch.t, cfg, *at
            )
            batch = batch._replace(points=points, R=R, t=t, trans_points=trans_points)
        else:
            points, R, t = augment(batch.points, batch.R, batch.t, cfg, *at)
            batch = batch._replace(points=points, R=R, t=t)
        if branch == "translation":  # augmented together: one roll, one noise draw
            points, trans_points = split_forms(points, cfg.train.n_points)
            batch = batch._replace(points=points, trans_points=trans_points)
        if self.world.distributed:  # this process's share of the global batch
            shard = self.world.shard(self.batch_size)
            batch = Batch(*(None if x is None else x[shard] for x in batch))
        try:
            return train_step(
                self.net,
                self.opt,
                batch,
                cfg.loss,
                symmetry=self.sets.symmetry,
                bf16=cfg.train.precision == "bf16",
                world=self.world,
            )
        except FloatingPointError as exc:
            raise FloatingPointError(f"{exc} at epoch {position.epoch + 1}") from None

    def _checkpoint(self, position: Position) -> None:
        self.run_record.checkpoint(self.model, self.opt, self.cfg, position)

    def _end_epoch(self, position: Position, seconds: float) -> dict[str, float]:
        """The finished epoch's metrics: its losses, time and learning rate, and (rank 0)
        validation, logged once."""
        metrics = position.means() | {
            "time/epoch_s": seconds,
            "train/lr": self.opt.param_groups[0]["lr"],
        }
        # Rank 0 alone, on whole batches of its own; the other processes wait for it at their
        # next step, where DDP hands them its re-estimated BatchNorm buffers.
        if self.world.is_main:
            metrics |= self._validate(position.epoch)
            self.run_record.log_epoch(position.epoch + 1, metrics)
        return metrics

    def _validate(self, epoch: int) -> dict[str, float]:
        """Train-mode error on the probe; BatchNorm statistics re-estimated
        (``train.bn_recalibrate``); the eval-mode metrics of the validation set and the probe."""
        cfg, model, sets, device, bs = self.cfg, self.model, self.sets, self.device, self.batch_size
        with local_batch_stats(model):
            out = {
                "fit/rot_err_median_deg_batchstats": batch_stats_rotation_error(
                    model, sets.probe, bs, device
                )
            }
            if cfg.train.bn_recalibrate:
                seed = seeds.seed_for(
                    cfg.seed, "bn_recalibrate", epoch, streams=cfg.train.seed_streams
                )
                recalibrate_bn(model, sets.fit, cfg.train.bn_recalibrate, bs, seed, device)
            for data, prefix in ((sets.val, "val"), (sets.probe, "fit")):
                out |= validate(
                    model,
                    data,
                    sets.models_by_class,
                    cfg,
                    device,
                    class_names=sets.class_names,
                    symmetry=sets.symmetry,
                    prefix=prefix,
                )
        return out


def fused_kernel(cfg: Config, device: torch.device) -> bool:
    """Whether training runs the fused per-point kernel: ``train.kernel = "fused"`` on a CPU.

    The fused kernel is written for the CPU's memory traffic; on a GPU the plain modules are
    faster (1.5x a step at batch 32, 1.8x at 128 on an H100: ``reports/benchmarks.md``) and
    compute the same, so there they run whatever the setting.
    """
    return cfg.train.kernel == "fused" and device.type == "cpu"


def warn_if_slow_bf16(device: torch.device) -> None:
    """Warn when bfloat16 has no hardware path here (CPUs without AVX-512 BF16 or AMX)."""
    if device.type != "cpu":
        return
    cap = torch.backends.cpu.get_cpu_capability()
    if "AVX512" not in cap and "AMX" not in cap:
        warnings.warn(
            f"train.precision='bf16' on a CPU with {cap} only: bfloat16 matrix products are "
            "emulated and far slower than fp32 here",
            stacklevel=3,
        )


class TrainingInterrupted(RuntimeError):
    """Raised when ``max_steps`` stops a run before its end (its checkpoint is saved)."""


PREVIOUS_CHECKPOINT = "last.prev.pt"
"""The checkpoint before ``last.pt``, beside it: where a run resumes when ``last.pt`` is torn."""

RESUME_KEYS = ("model", "optimizer", "config", "epoch", "batch", "sums")
"""What a ``last.pt`` holds."""


def _save(path: Path, state: dict, keep: Path | None = None) -> None:
    """Write ``state`` to ``path`` atomically; with ``keep``, the file it replaces becomes
    ``keep``. Serialised in memory first: a full disk then fails in a plain write, as an
    ``OSError`` (``torch.save`` into a file raises a bare RuntimeError), and is
    :class:`DiskFullError` naming ``path`` and the bytes it needs."""
    buf = io.BytesIO()
    torch.save(state, buf)
    data = buf.getbuffer()

    def write(tmp: Path) -> None:
        tmp.write_bytes(data)
        if keep is not None and path.exists():
            os.replace(path, keep)

    try:
        atomic_write(path, write)
    except OSError as exc:
        full = disk_full(exc, path, len(data), then=RESUME_HINT)
        if full is None:
            raise
        raise full from exc


def _checkpoint(path: Path, model, opt, cfg: Config, position: Position) -> None:
    """Write ``last.pt`` (:data:`RESUME_KEYS`) at ``position``; the one it replaces becomes
    :data:`PREVIOUS_CHECKPOINT`."""
    state = {
        "model": model.state_dict(),
        "optimizer": opt.state_dict(),
        "config": cfg.to_dict(),
        "epoch": position.epoch,
        "batch": position.batch,
        "sums": dict(position.sums),
    }
    _save(path, state, keep=path.with_name(PREVIOUS_CHECKPOINT))


def _read_resume_state(last: Path, map_location) -> dict | None:
    """The state to resume from: ``last.pt``, else (torn, empty) ``last.prev.pt`` with a
    warning naming the bad file, which is removed (a later checkpoint must not keep it as the
    previous one); None when the run has no checkpoint yet. Neither readable: ``ValueError``
    naming the file and what to do."""
    prev = last.with_name(PREVIOUS_CHECKPOINT)
    bad: dict[Path, runs.CheckpointError] = {}
    for path in (last, prev):
        if not path.exists():
            continue
        try:
            state = runs.read_checkpoint(path, map_location, keys=RESUME_KEYS)
        except runs.CheckpointError as exc:
            bad[path] = exc
            continue
        if bad:
            last.unlink(missing_ok=True)
            warnings.warn(
                f"{bad[last]}; resuming from {path} (epoch {state['epoch'] + 1}, step "
                f"{state['batch']}), the one before it (the bad file is removed)",
                stacklevel=3,
            )
        return state
    if bad:
        raise ValueError(
            f"{'; '.join(map(str, bad.values()))}: the run cannot resume from it; delete it "
            f"(rm {' '.join(map(str, bad))}) to train the run from its start, into the same "
            "MLflow run"
        )
    return None


def _final_model_ready(final: Path, last: Path, cfg: Config, client, run_id: str) -> bool:
    """Whether a finished run's ``model.pt`` is there and readable; a torn or missing one is
    rewritten (with a warning) from ``last.pt`` of the last epoch, whose model it is, or from
    the run's MLflow artifact. False when neither can: the run is then trained to its end
    again, from its last checkpoint."""
    try:
        runs.read_checkpoint(final, "cpu")
        return True
    except (runs.CheckpointError, FileNotFoundError) as exc:
        why = str(exc) if final.exists() else f"{final} is missing"
    try:
        state = runs.read_checkpoint(last, "cpu", keys=RESUME_KEYS)
        same = Config.from_dict(state["config"]).to_dict() == cfg.to_dict()
        if state["epoch"] == cfg.train.epochs and same:
            _save(final, {"model": state["model"], "config": state["config"]})
            warnings.warn(f"{why}; rewritten from {last}", stacklevel=4)
            return True
    except (runs.CheckpointError, FileNotFoundError):
        pass
    if runs.fetch_artifact(client, run_id, "model.pt", final):
        try:
            runs.read_checkpoint(final, "cpu")
            warnings.warn(f"{why}; fetched again from the MLflow run {run_id}", stacklevel=4)
            return True
        except runs.CheckpointError:
            final.unlink(missing_ok=True)
    return False
