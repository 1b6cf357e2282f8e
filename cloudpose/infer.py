"""Inference: a trained network from its checkpoint, and its poses for many segments.

:func:`load_checkpoint` reads a ``model.pt`` / ``last.pt`` (tensors and plain data only: any
other pickle is refused) and returns the network folded for inference (every BatchNorm folded
into its layer; ``cloudpose.models.folded``). :func:`forward_in_batches` is the one batched
forward of the package, used by evaluation (:func:`estimate_poses`) and by training's
validation; :func:`refine_poses` runs the paper's ICP on the estimates.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from cloudpose.config import Config
from cloudpose.kernels.model_index import ModelIndex
from cloudpose.models import build_model
from cloudpose.models.folded import fold_for_inference
from cloudpose.refine import (
    SELECTIONS,
    ICPSettings,
    ICPStats,
    depth_agreement,
    depth_score,
    icp_refine,
)
from cloudpose.runtime import pick_device

__all__ = [
    "Estimates",
    "estimate_poses",
    "forward_in_batches",
    "load_checkpoint",
    "refine_ensemble",
    "refine_poses",
    "refinement_scores",
    "select_refinements",
]


@torch.no_grad()
def forward_in_batches(
    model: torch.nn.Module,
    points: torch.Tensor,
    cls_id: torch.Tensor,
    device,
    batch_size: int = 512,
    trans_points: torch.Tensor | None = None,
) -> Iterator[tuple[slice, object]]:
    """The network in eval mode over ``points`` in batches: yields (rows, output) per batch.

    Args:
        points: (M, n, 3) float32 segments, the first ``n`` FPS points of each.
        cls_id: (M,) int64 class ids.
        device: where the network runs.
        batch_size: segments per forward.
        trans_points: (M, n, 3) the translation branch's own form of the segments, or None.

    The model is left in the mode it was in.
    """
    was_training = model.training
    model.eval()
    try:
        for i in range(0, len(points), batch_size):
            sl = slice(i, i + batch_size)
            extra = () if trans_points is None else (trans_points[sl].to(device),)
            yield sl, model(points[sl].to(device), cls_id[sl].to(device), *extra)
    finally:
        model.train(was_training)


@dataclass(frozen=True)
class Estimates:
    """Poses of every row of a segment set; rows that are misses hold NaN."""

    R: np.ndarray  # (M, 3, 3)
    t: np.ndarray  # (M, 3) metres

    @classmethod
    def kept(cls, candidates: list[Estimates], pick: np.ndarray) -> Estimates:
        """Per row, the pose of ``candidates[pick[row]]`` (several estimates of the same rows,
        :func:`select_refinements`)."""
        return cls(
            _per_row([c.R for c in candidates], pick), _per_row([c.t for c in candidates], pick)
        )


def _per_row(candidates: list[np.ndarray], pick: np.ndarray) -> np.ndarray:
    """Row ``i`` of ``candidates[pick[i]]``, for arrays of the same rows."""
    return np.stack(candidates)[pick, np.arange(len(pick))]


def estimate_poses(model, segs, n_points: int, device="cpu", batch_size: int = 512) -> Estimates:
    """Run the pose network on every valid segment of ``segs`` (first ``n_points`` FPS points)."""
    m = len(segs)
    R = np.full((m, 3, 3), np.nan)
    t = np.full((m, 3), np.nan)
    idx = np.flatnonzero(segs.valid)
    pts = torch.from_numpy(np.ascontiguousarray(segs.points[idx, :n_points], np.float32))
    cls_id = torch.from_numpy(segs.cls_id[idx].astype(np.int64))
    for sl, out in forward_in_batches(model, pts, cls_id, device, batch_size):
        R[idx[sl]] = out.R.double().cpu().numpy()
        t[idx[sl]] = out.t.double().cpu().numpy()
    return Estimates(R, t)


def no_estimate(segs) -> Estimates:
    """The control of any method: the identity rotation at the mean of each segment's
    observed points (what ICP starts from when nothing estimated the pose)."""
    n = len(segs)
    t = np.zeros((n, 3))
    for i in np.flatnonzero(segs.valid):
        t[i] = segs.observed(i).mean(axis=0)
    return Estimates(np.tile(np.eye(3), (n, 1, 1)), t)


def refine_poses(
    segs,
    est: Estimates,
    models_by_class: dict[int, np.ndarray],
    settings: ICPSettings | None = None,
    progress: bool = False,
    views=None,
) -> tuple[Estimates, ICPStats]:
    """ICP-refine every valid row; returns the refined poses and, per row, Open3D's fitness and
    inlier RMSE and whether the guard kept the estimate (``settings.fallback``; NaN / False
    for rows that are misses).

    The observed cloud is the segment's cached FPS points without the fill-by-repeat copies
    (``points[:count]``). ``views``: per row, the frame's depth
    (:func:`cloudpose.refine.segment_views`), which ``settings.select == "depth"`` needs.
    """
    settings = settings or ICPSettings()
    R, t = est.R.copy(), est.t.copy()
    fitness = np.full(len(segs), np.nan)
    rmse = np.full(len(segs), np.nan)
    kept = np.zeros(len(segs), dtype=bool)
    index = {c: ModelIndex.of(m) for c, m in models_by_class.items()}  # shared with ADS
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for i in tqdm(np.flatnonzero(segs.valid), disable=not progress, desc="ICP", unit="obj"):
            sol = icp_refine(
                segs.observed(i).astype(np.float64),
                index[int(segs.cls_id[i])],
                est.R[i],
                est.t[i],
                settings,
                view=views[i] if views is not None else None,
            )
            R[i], t[i], fitness[i], rmse[i], kept[i] = sol
    if caught:
        # One line instead of one per object: far-off estimates leave ICP nothing to match.
        warnings.warn(
            f"ICP kept the network's pose for {len(caught)} of {int(np.sum(segs.valid))} "
            f"objects (e.g. {caught[0].message})",
            stacklevel=2,
        )
    return Estimates(R, t), ICPStats(fitness, rmse, kept)


def refinement_scores(
    segs,
    refined: Estimates,
    stats: ICPStats,
    models_by_class: dict[int, np.ndarray],
    select: str,
    views=None,
) -> np.ndarray:
    """(M,) score of each row's refinement (:func:`refine_poses`) under ``select``: ICP's
    fitness (``"fitness"``) or the depth score (``"depth"``,
    :func:`cloudpose.refine.depth_score`: coverage of the segment and free-space violations
    against ``views``, the rows' depth); -inf for a row not refined (a miss)."""
    if select not in SELECTIONS:
        raise ValueError(f"select: expected one of {', '.join(SELECTIONS)}, got {select!r}")
    if select == "depth" and views is None:
        raise ValueError('select "depth" needs the rows\' depth views (segment_views)')
    score = np.full(len(segs), -np.inf)
    index = {c: ModelIndex.of(m) for c, m in models_by_class.items()}
    for i in np.flatnonzero(segs.valid):
        fit = float(stats.fitness[i])
        if not np.isfinite(fit):
            continue
        if select == "fitness":
            score[i] = fit
            continue
        agree = depth_agreement(
            segs.observed(i).astype(np.float64),
            index[int(segs.cls_id[i])],
            refined.R[i],
            refined.t[i],
            views[i],
        )
        score[i] = depth_score(fit, agree)
    return score


def select_refinements(
    segs,
    refined: list[Estimates],
    stats: list[ICPStats],
    models_by_class: dict[int, np.ndarray],
    select: str,
    views=None,
) -> np.ndarray:
    """Per row of ``segs``, which of several refinements of it to keep (an ensemble: each
    network's estimate refined by ICP, :func:`refine_poses`): the highest
    :func:`refinement_scores` under ``select``.

    Returns:
        (M,) int indices into ``refined``; the first on a tie and for a miss.
    """
    if len(refined) != len(stats) or not refined:
        raise ValueError(
            f"refined and stats: one of each per network, got {len(refined)} and {len(stats)}"
        )
    scores = [
        refinement_scores(segs, r, st, models_by_class, select, views)
        for r, st in zip(refined, stats, strict=True)
    ]
    return np.argmax(np.stack(scores), axis=0)


def refine_ensemble(
    segs,
    estimates: list[Estimates],
    models_by_class: dict[int, np.ndarray],
    settings: ICPSettings,
    views=None,
    progress: bool = False,
    choose: str | None = None,
) -> tuple[Estimates, ICPStats, np.ndarray]:
    """Several networks' estimates of the same rows as one: each refined by ICP
    (:func:`refine_poses` with ``settings``), per row the refinement with the best score of
    ``choose`` kept (default ``settings.select``, the score of the starts too;
    :func:`select_refinements`; one network: its own, unscored).

    Returns:
        The kept refinements, their ICP figures, and (M,) the index of the network each row
        kept (0 for a miss).
    """
    refined = [
        refine_poses(segs, e, models_by_class, settings, progress, views=views) for e in estimates
    ]
    if len(refined) == 1:
        return *refined[0], np.zeros(len(segs), dtype=np.int64)
    poses, stats = [r for r, _ in refined], [st for _, st in refined]
    pick = select_refinements(segs, poses, stats, models_by_class, choose or settings.select, views)
    kept_stats = ICPStats(*(_per_row(list(field), pick) for field in zip(*stats, strict=True)))
    return Estimates.kept(poses, pick), kept_stats, pick


def load_checkpoint(
    path: str | Path, device: str | torch.device = "cpu"
) -> tuple[torch.nn.Module, Config]:
    """Inference model and config from a ``model.pt`` or ``last.pt`` checkpoint.

    ``device``: where the model goes ("auto": CUDA when available, :func:`pick_device`).

    The model is the trained network folded for inference (no training from it).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    device = pick_device(device)
    try:
        # weights_only: a checkpoint holds tensors and plain data; any other pickle is refused
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # a text file, a torn file, a foreign or unsafe pickle
        reason = " ".join(str(exc).split())[:160] or type(exc).__name__
        raise ValueError(f"{path} is not a cloudpose checkpoint ({reason})") from exc
    if not isinstance(state, dict) or "model" not in state or "config" not in state:
        raise ValueError(f"{path} is not a cloudpose checkpoint (expected keys 'model', 'config')")
    cfg = Config.from_dict(state["config"])
    model = build_model(cfg.model).to(device)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise ValueError(f"{path}: the weights do not fit its config's network ({exc})") from exc
    model.eval()
    # Inference only: every BatchNorm folded into its layer, both networks as one batched
    # product (same outputs as eval mode to ~1e-7 in float32; cloudpose.models.folded).
    return fold_for_inference(model), cfg
