"""Training of one variant from the segment cache, resumable and tracked in MLflow.

Resumability: the run folder ``runs/{variant}/{preset}/seed{S}-{data}-{config}`` (data and config
fingerprints: an edited preset or an override never resumes another config's run) holds ``last.pt`` (model,
optimiser, position in the epoch and the epoch's running loss sums), written atomically at the end
of every epoch and every ``checkpoint_every_s`` seconds within one, the one before it as
``last.prev.pt``, and ``run.json`` with the MLflow run id. Rerunning the same command after any
interruption (``kill -9``, SIGTERM, Ctrl-C, a full disk) continues from ``last.pt`` into the same
MLflow run; from ``last.prev.pt``, with a warning naming the bad file, when ``last.pt`` cannot be
read (torn, empty). An epoch's metrics are logged once: a resumed run that trains an epoch again
(from an earlier checkpoint) does not log it a second time. A full disk is one line naming the
file and the space it needs (:class:`cloudpose.failures.DiskFullError`), and the run is marked
FAILED; SIGTERM stops training as Ctrl-C does (the run is marked KILLED). The batch order of
epoch ``e`` depends only on ``(seed, e)`` and the model's initial weights only on ``seed``, so a
resumed run ends with the same numbers as an uninterrupted one (on CPU, with the same thread
count). Against a tracking server
(:func:`cloudpose.store.tracking.is_remote`) every checkpoint is also logged to the run as the artifact
``checkpoint/last.pt`` (removed once the run finishes), and a machine without the run folder
(a retried Ray task on another node) rebuilds it from MLflow (:func:`cloudpose.store.runs.restore_run_folder`):
the run continues into the same MLflow run from the last logged checkpoint.

Several processes (``torchrun``; :mod:`cloudpose.train.distributed`) train one run: each takes an equal
share of every global batch, DDP averages the gradients, BatchNorm uses the global batch's
statistics; rank 0 alone writes the run folder and talks to MLflow.

Validation: a fixed share of the training *frames* (not instances: instances of one frame share a
scene) is held out, chosen from the frame ids alone so every seed and variant sees the same split;
:mod:`cloudpose.train.validation` measures the network on it at the end of every epoch.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import math
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from cloudpose import runtime
from cloudpose.config import Config
from cloudpose.data.batches import Batchable
from cloudpose.data.dataset import Prepared
from cloudpose.data.synth.online import REUSE_SPACING, OnlineChunks, OnlineStream
from cloudpose.data.synth.store import STORE_DIR, code_digest
from cloudpose.failures import DiskFullError, disk_full, sigterm_as_interrupt
from cloudpose.files import atomic_write
from cloudpose.geometry.symmetry import SymmetryTensors, symmetries_for
from cloudpose.losses import pose_loss
from cloudpose.models import build_model, count_parameters
from cloudpose.models.fused import fuse_model
from cloudpose.registry import groups_of
from cloudpose.store import runs, tracking
from cloudpose.train.distributed import SINGLE, World, local_batch_stats, sync_batch_stats
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


def online_synth_kwargs(cfg: Config, class_names: list[str]) -> dict:
    """:class:`~cloudpose.data.synth.online.OnlineSynth` arguments of an on-line run: the
    generator version, noise and segment settings of ``cfg.data``, and the ids of its
    ``data.classes`` in ``class_names`` (the dataset's ``classes.txt``), every class when
    empty."""
    d = cfg.data
    if d.root:
        raise ValueError(
            f"data.train_source='online' synthesizes YCB-Video scenes from the packaged models; "
            f"it cannot be combined with data.root={d.root!r} (train on its frames instead)"
        )
    classes = None
    if d.classes:
        classes = tuple(sorted(class_names.index(c) + 1 for c in d.classes))
    return {
        "version": d.synth_version,
        "noise": d.noise,
        "n_points": cfg.train.n_points,
        "outlier_radius": d.outlier_radius,
        "class_ids": classes,
        "scenes": d.online_scenes,
        # version 1 leaves it out: its chunk store settings stay as they were
        **({"online_version": d.online_version} if d.online_version != 1 else {}),
    }


ONLINE_STORE_ENV = "CLOUDPOSE_ONLINE_STORE"
"""Environment variable: ``0`` keeps on-line runs from reading or writing the project's chunk
store (:mod:`cloudpose.data.synth.store`); a path puts the store there. Unset: the project's
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


def online_chunks(cfg: Config, class_names: list[str]) -> tuple[dict, int, int]:
    """``(synth_kwargs, chunk_size, n_chunks)`` of an on-line run: the chunks its
    :class:`~cloudpose.data.synth.online.OnlineStream` draws, the same for every variant that
    shares its ``data`` section, ``train.n_points``, ``train.batch_size`` and epochs."""
    reuse = cfg.data.online_reuse
    span = (reuse - 1) * REUSE_SPACING
    return (
        online_synth_kwargs(cfg, class_names),
        cfg.train.batch_size // reuse,
        cfg.train.epochs * online_epoch_steps(cfg) + span,
    )


def online_probe(
    synth_kwargs: dict, seed: int, n: int, store: str | Path | None = None
) -> Batchable:
    """``n`` segments drawn as the run's first step draws them (its first chunk is trained on):
    the ``fit/`` probe of an on-line run (read from, or kept in, the chunk store ``store``)."""
    return Batchable(*OnlineChunks(synth_kwargs, seed, n, 1, store)[0])


def epoch_order(fit: Batchable, sampler: str, seed: int, epoch: int, n: int) -> torch.Tensor:
    """(n,) training indices of one epoch, a function of ``(seed, epoch)`` only.

    ``shuffle``: a permutation of the segments (the first ``n``); ``class_balanced``: each
    draw picks a class uniformly among the classes present, then one of its segments.
    """
    g = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    if sampler == "shuffle":
        return torch.randperm(len(fit), generator=g)[:n]
    classes, inverse = torch.unique(fit.cls_id, return_inverse=True)
    members = [torch.nonzero(inverse == c).squeeze(1) for c in range(len(classes))]
    pick = torch.randint(len(classes), (n,), generator=g)
    out = torch.empty(n, dtype=torch.long)
    for c, idx in enumerate(members):
        sel = pick == c
        out[sel] = idx[torch.randint(len(idx), (int(sel.sum()),), generator=g)]
    return out


def roll_about_optical_axis(
    points: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    max_deg: float,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Segments and poses as seen by the camera rolled about its optical (z) axis.

    Args:
        points: (B, n, 3) camera-frame points, metres; R (B, 3, 3), t (B, 3) their poses.
        max_deg: roll angles are uniform in [-max_deg, max_deg] degrees, one per segment.

    Returns:
        ``(points @ Q^T, Q R, Q t)`` with Q (B, 3, 3) the rolls.
    """
    B = points.shape[0]
    a = (torch.rand(B, generator=generator) * 2 - 1) * math.radians(max_deg)
    c, s = torch.cos(a), torch.sin(a)
    Q = torch.zeros(B, 3, 3)
    Q[:, 0, 0], Q[:, 0, 1], Q[:, 1, 0], Q[:, 1, 1], Q[:, 2, 2] = c, -s, s, c, 1.0
    Q = Q.to(points.device, points.dtype)
    return points @ Q.mT, Q @ R, (Q @ t[..., None]).squeeze(-1)


def jitter_along_rays(
    points: torch.Tensor, max_sigma_m: float, generator: torch.Generator
) -> torch.Tensor:
    """Segments with depth noise of a randomized level: each point moves along its viewing ray
    by a normal draw whose standard deviation is uniform in ``[0, max_sigma_m]``, one level per
    segment. Real depth is noisier than a fitted sensor model (and a network trained on one
    noise level does worse on clean depth than on noisy): training over a range of levels
    covers both.

    Args:
        points: (B, n, 3) camera-frame points, metres.
        max_sigma_m: the largest per-segment standard deviation, metres.

    Returns:
        (B, n, 3) the moved points (the poses are unchanged: the surface is where it was).
    """
    B, n, _ = points.shape
    sigma = torch.rand(B, 1, generator=generator) * max_sigma_m  # (B, 1)
    step = torch.randn(B, n, generator=generator) * sigma  # (B, n) metres along each ray
    ray = points / points.norm(dim=-1, keepdim=True).clamp_min(1e-9)  # (B, n, 3)
    return points + step.to(points.device, points.dtype)[..., None] * ray


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
    """:func:`train` with the run folder's lock held (rank 0)."""
    device = world.device(runtime.pick_device(cfg.train.device))
    if not world.distributed:
        # the thread count changes the numbers (training BatchNorm and GEMM reductions split
        # across threads), so a run trains with its own, part of its identity
        runtime.configure_threads(cfg.train.threads)
    shard = world.shard(cfg.train.batch_size)
    train_set, data_key = data.train, data.data_key
    last, final = rdir / "last.pt", rdir / "model.pt"
    client, info = None, {}
    if world.is_main:
        info = runs.read_info(rdir)
        client = tracking.setup(project_dir)
        if checkpoint_artifacts is None:
            checkpoint_artifacts = tracking.is_remote(client.tracking_uri)
        if not info and checkpoint_artifacts:
            info = runs.restore_run_folder(client, cfg, data_key, rdir)
    info = world.broadcast(info)
    if info.get("finished") and world.broadcast(
        world.is_main and _final_model_ready(final, last, cfg, client, info["run_id"])
    ):
        return TrainOutcome(info["run_id"], rdir, final, info.get("metrics", {}))

    dataset = data.dataset
    class_names = list(dataset.classes)
    online = cfg.data.train_source == "online"
    if online:  # the rendered training frames validate; fitting draws fresh segments
        synth_kwargs = online_synth_kwargs(cfg, class_names)
        val = Batchable.from_segments(train_set, cfg.train.n_points)
        fit = online_probe(synth_kwargs, cfg.seed, 256, online_store_root(project_dir))
    else:
        held = split_frames(train_set.frame_id, cfg.train.val_fraction)
        fit = Batchable.from_segments(train_set.subset(~held), cfg.train.n_points)
        val = Batchable.from_segments(train_set.subset(held), cfg.train.n_points)
    if len(fit) < cfg.train.batch_size:
        raise ValueError(
            f"only {len(fit)} valid training segments, fewer than train.batch_size="
            f"{cfg.train.batch_size}; render more frames (data.train_frames)"
        )
    models_by_class = dataset.models()
    symmetry = None
    if cfg.loss.symmetric:
        symmetry = SymmetryTensors(symmetries_for(class_names, cfg.loss.symmetry_table)).to(device)
    # A fixed sample of training segments: eval- vs train-mode error on the same segments.
    probe = fit.subset(torch.randperm(len(fit), generator=torch.Generator().manual_seed(0))[:512])

    torch.manual_seed(cfg.seed)
    model = build_model(cfg.model).to(device)
    use_bf16 = cfg.train.precision == "bf16"
    if use_bf16:
        warn_if_slow_bf16(device)
    if fused_kernel(cfg, device):
        fuse_model(model, bf16=use_bf16)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.train.lr)
    epoch, batch, sums = 0, 0, {"loss": 0.0, "rot": 0.0, "trans": 0.0, "n": 0}
    state = None
    if world.is_main:
        where = "cpu" if world.distributed else device  # sent to the other processes first
        state = _read_resume_state(last, where)
    state = world.broadcast(state)  # rank 0's checkpoint, on every process
    if state is not None:
        if Config.from_dict(state["config"]).to_dict() != cfg.to_dict():
            raise ValueError(f"{last} was written by another config; delete {rdir} to restart")
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        epoch, batch, sums = state["epoch"], state["batch"], state["sums"]

    group = group or (groups_of(cfg.variant) or ["misc"])[0]
    run_id = info.get("run_id")
    if world.is_main and run_id is None:
        exp = tracking.experiment_id(client, group, project_dir)
        tags = runs.training_tags(cfg, group, data_key, rdir)
        rdir.mkdir(parents=True, exist_ok=True)
        params = cfg.flat() | {
            "model.parameters": count_parameters(model),
            "data.fingerprint": data_key,
            "data.train_segments": "online" if online else len(fit),
            # on line, the segments are made by code: runs of one seed are like for like only
            # when their synthesis code agrees (the chunk store's key holds it too)
            **({"data.online_code": code_digest()} if online else {}),
            "data.val_segments": len(val),
            "device": device,
        }
        run_id = runs.create_run_record(
            client, exp, runs.display_name(cfg), tags, params, cfg.to_dict()
        )
        info = {"run_id": run_id, "group": group, "config": cfg.to_dict()}
        runs.write_info(rdir, info)
    elif world.is_main:
        client.update_run(run_id, status="RUNNING")
    run_id = world.broadcast(run_id)
    # epochs already logged: trained again from an earlier checkpoint, not logged again
    logged = set()
    if world.is_main:
        logged = {m.step for m in client.get_metric_history(run_id, "train/loss")}

    def checkpoint() -> None:
        _checkpoint(last, model, opt, cfg, epoch, batch, sums)
        if checkpoint_artifacts:
            client.log_artifact(run_id, str(last), artifact_path=runs.CHECKPOINT_ARTIFACT_DIR)

    net = model
    if world.distributed:
        sync_batch_stats(model, world.stats_group)
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None
        )

    bs = cfg.train.batch_size
    if online:
        n_batches = online_epoch_steps(cfg)
    else:
        n_batches = len(fit) // bs  # drop the last partial batch: BatchNorm needs full batches
    steps_here, t_ckpt = 0, time.monotonic()
    model.train()
    bar = tqdm(
        total=cfg.train.epochs * n_batches,
        initial=epoch * n_batches + batch,
        disable=not progress or not world.is_main,
        desc=runs.display_name(cfg),
        unit="step",
        dynamic_ncols=True,
    )
    metrics: dict[str, float] = {}
    total_steps = cfg.train.epochs * n_batches
    stream = None
    if online and epoch < cfg.train.epochs:
        stream = OnlineStream(
            synth_kwargs,
            cfg.seed,
            bs,
            cfg.data.online_reuse,
            total_steps,
            start=epoch * n_batches + batch,
            workers=cfg.data.online_workers,
            store=online_store_root(project_dir),
        )
    while epoch < cfg.train.epochs:
        t_epoch = time.monotonic()
        if stream is None:
            perm = epoch_order(fit, cfg.train.sampler, cfg.seed, epoch, n_batches * bs)
        while batch < n_batches:
            for group_ in opt.param_groups:
                group_["lr"] = lr_at(cfg, epoch * n_batches + batch, total_steps)
            if stream is not None:
                pts, cls_id, R_gt, t_gt = (x.to(device) for x in stream.next())
            else:
                idx = perm[batch * bs : (batch + 1) * bs]
                pts, cls_id = fit.points[idx].to(device), fit.cls_id[idx].to(device)
                R_gt, t_gt = fit.R[idx].to(device), fit.t[idx].to(device)
            if cfg.train.augment_roll_deg > 0:
                g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + epoch * 100_003 + batch)
                pts, R_gt, t_gt = roll_about_optical_axis(
                    pts, R_gt, t_gt, cfg.train.augment_roll_deg, g
                )
            if cfg.train.augment_depth_noise_mm > 0:
                g = torch.Generator().manual_seed(cfg.seed * 7_000_003 + epoch * 100_003 + batch)
                pts = jitter_along_rays(pts, cfg.train.augment_depth_noise_mm / 1000, g)
            if world.distributed:  # this process's share of the global batch
                pts, cls_id, R_gt, t_gt = pts[shard], cls_id[shard], R_gt[shard], t_gt[shard]
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_bf16):
                out = net(pts, cls_id)
            terms = pose_loss(
                out.R.float(),
                out.t.float(),
                R_gt,
                t_gt,
                rotation=cfg.loss.rotation,
                alpha=cfg.loss.alpha,
                rotvec_pred=out.rot_raw.float(),
                symmetry=symmetry,
                cls_id=cls_id,
            )
            opt.zero_grad(set_to_none=True)
            terms.total.backward()
            opt.step()
            loss, l_rot, l_trans = (float(x.detach()) for x in terms)
            if world.distributed:  # the global batch's: the mean of the equal shares' means
                loss, l_rot, l_trans = world.mean([loss, l_rot, l_trans])
            if not math.isfinite(loss):
                raise FloatingPointError(f"loss became {loss} at epoch {epoch + 1}")
            sums["loss"] += loss
            sums["rot"] += l_rot
            sums["trans"] += l_trans
            sums["n"] += 1
            batch += 1
            steps_here += 1
            bar.update(1)
            bar.set_postfix(epoch=epoch + 1, loss=f"{sums['loss'] / sums['n']:.3f}")
            if world.is_main and time.monotonic() - t_ckpt > checkpoint_every_s:
                checkpoint()
                t_ckpt = time.monotonic()
            if max_steps is not None and steps_here >= max_steps:
                if world.is_main:
                    checkpoint()
                bar.close()
                if stream is not None:
                    stream.close()
                raise TrainingInterrupted(rdir)
        n = max(sums["n"], 1)
        metrics = {
            "train/loss": sums["loss"] / n,
            "train/loss_rot": sums["rot"] / n,
            "train/loss_trans": sums["trans"] / n,
            "time/epoch_s": time.monotonic() - t_epoch,
            "train/lr": opt.param_groups[0]["lr"],
        }
        # Rank 0 alone, on whole batches of its own; the other processes wait for it at their
        # next step, where DDP hands them its re-estimated BatchNorm buffers.
        if world.is_main:
            with local_batch_stats(model):
                metrics["fit/rot_err_median_deg_batchstats"] = batch_stats_rotation_error(
                    model, probe, bs, device
                )
                if cfg.train.bn_recalibrate:
                    recalibrate_bn(
                        model, fit, cfg.train.bn_recalibrate, bs, cfg.seed + epoch, device
                    )
                for data_, prefix in ((val, "val"), (probe, "fit")):
                    metrics.update(
                        validate(
                            model,
                            data_,
                            models_by_class,
                            cfg,
                            device,
                            class_names=class_names,
                            symmetry=symmetry,
                            prefix=prefix,
                        )
                    )
            if epoch + 1 not in logged:
                client.log_batch(run_id, metrics=tracking.metric_batch(metrics, epoch + 1))
        epoch, batch, sums = epoch + 1, 0, {"loss": 0.0, "rot": 0.0, "trans": 0.0, "n": 0}
        if world.is_main:
            checkpoint()
        t_ckpt = time.monotonic()
    bar.close()
    if stream is not None:
        stream.close()

    final_metrics = {k: v for k, v in metrics.items() if not k.startswith("time/")}
    if not metrics and world.is_main:  # stopped after its last checkpoint: as it logged them
        logged_metrics = client.get_run(run_id).data.metrics
        final_metrics = info.get("metrics") or {
            k: v
            for k, v in logged_metrics.items()
            if k.split("/")[0] in runs.TRAINING_PREFIXES and not k.startswith("time/")
        }
    if world.is_main:
        _save(final, {"model": model.state_dict(), "config": cfg.to_dict()})
        client.log_artifact(run_id, str(final))
        last.with_name(PREVIOUS_CHECKPOINT).unlink(missing_ok=True)
        info.update({"finished": True, "metrics": final_metrics})
        runs.write_info(rdir, info)
        if checkpoint_artifacts:
            runs.drop_checkpoint_artifact(client, run_id)
        client.set_terminated(run_id, "FINISHED")
    return TrainOutcome(run_id, rdir, final, world.broadcast(final_metrics))


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


def _checkpoint(path: Path, model, opt, cfg: Config, epoch: int, batch: int, sums: dict) -> None:
    state = {
        "model": model.state_dict(),
        "optimizer": opt.state_dict(),
        "config": cfg.to_dict(),
        "epoch": epoch,
        "batch": batch,
        "sums": dict(sums),
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
