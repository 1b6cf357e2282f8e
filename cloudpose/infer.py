"""Inference: a trained network from its checkpoint, and its poses for many segments.

:func:`load_checkpoint` reads a ``model.pt`` / ``last.pt`` (tensors and plain data only: any
other pickle is refused) and returns the network folded for inference (every BatchNorm folded
into its layer; ``cloudpose.models.folded``). :func:`forward_in_batches` is the one batched
forward of the package, used by evaluation (:func:`estimate_poses`) and by training's
validation; :func:`cloudpose.refine.refine_poses` runs the paper's ICP on the estimates.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from cloudpose.config import Config
from cloudpose.models import build_model
from cloudpose.models.folded import fold_for_inference
from cloudpose.models.stored import FORM_KEY, decode
from cloudpose.refine import Estimates
from cloudpose.runtime import pick_device

__all__ = [
    "estimate_poses",
    "forward_in_batches",
    "load_checkpoint",
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


def load_checkpoint(
    path: str | Path, device: str | torch.device = "cpu"
) -> tuple[torch.nn.Module, Config]:
    """Inference model and config from a ``model.pt`` or ``last.pt`` checkpoint, or one stored
    in fewer bytes (``model.f24.pt``, ``model.fp16.pt``: :mod:`cloudpose.models.stored`).

    ``device``: where the model goes ("auto": CUDA when available, :func:`pick_device`).

    The model is the trained network folded for inference (no training from it).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    device = pick_device(device)
    try:
        # weights_only: a checkpoint holds tensors and plain data; any other pickle is refused
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a text file, a torn file, a foreign or unsafe pickle
        reason = " ".join(str(exc).split())[:160] or type(exc).__name__
        raise ValueError(f"{path} is not a cloudpose checkpoint ({reason})") from exc
    if not isinstance(state, dict) or "model" not in state or "config" not in state:
        raise ValueError(f"{path} is not a cloudpose checkpoint (expected keys 'model', 'config')")
    if FORM_KEY in state:
        try:
            state = decode(state)
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{path}: a damaged packed checkpoint ({exc})") from exc
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
