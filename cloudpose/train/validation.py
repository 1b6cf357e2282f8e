"""Validation during training: pose accuracy without ICP, and BatchNorm statistics.

:func:`validate` measures a network in eval mode on held-out (or training) segments: the loss,
ADS AUC, median errors and hit rates. Eval mode normalises with BatchNorm's running statistics:
:func:`recalibrate_bn` re-estimates them on training batches (``train.bn_recalibrate``), and
:func:`batch_stats_rotation_error` measures the same network with batch statistics for
comparison. :func:`cloudpose.train.loop.train` calls them at the end of every epoch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from cloudpose.config import Config
from cloudpose.geometry.symmetry import SymmetryTensors, rotation_errors_modulo_symmetry
from cloudpose.infer import forward_in_batches
from cloudpose.metrics import adds_distance, rotation_error_deg, voc_ap_auc
from cloudpose.train.losses import pose_loss

if TYPE_CHECKING:
    from cloudpose.data.batches import Batchable


@torch.no_grad()
def validate(
    model: torch.nn.Module,
    data: Batchable,
    models_by_class: dict[int, np.ndarray],
    cfg: Config,
    device: torch.device,
    batch_size: int = 512,
    class_names: list[str] | None = None,
    symmetry: SymmetryTensors | None = None,
    prefix: str = "val",
) -> dict[str, float]:
    """Loss and pose accuracy (no ICP) of ``model`` in eval mode on ``data``.

    Args:
        symmetry: the loss's symmetry table when the run trains modulo symmetry.
        class_names: names of class ids 1..k; adds the rotation error modulo symmetry.
        prefix: metric key prefix ("val", or "fit" for training segments).
    """
    if len(data) == 0:
        return {}
    Rs, ts, totals = [], [], []
    batches = forward_in_batches(
        model, data.points, data.cls_id, device, batch_size, data.trans_points
    )
    for sl, out in batches:
        cls_id = data.cls_id[sl].to(device)
        terms = pose_loss(
            out.R,
            out.t,
            data.R[sl].to(device),
            data.t[sl].to(device),
            rotation=cfg.loss.rotation,
            alpha=cfg.loss.alpha,
            rotvec_pred=out.rot_raw,
            symmetry=symmetry,
            cls_id=cls_id,
        )
        totals.append(float(terms.total) * out.R.shape[0])
        Rs.append(out.R.float().cpu())
        ts.append(out.t.float().cpu())
    R_est, t_est = torch.cat(Rs).numpy(), torch.cat(ts).numpy()
    R_gt, t_gt = data.R.numpy(), data.t.numpy()
    cls_id = data.cls_id.numpy()
    ads = np.empty(len(data))
    for c in np.unique(cls_id):
        m = cls_id == c
        poses = {"R_est": R_est[m], "t_est": t_est[m], "R_gt": R_gt[m], "t_gt": t_gt[m]}
        ads[m] = adds_distance(models_by_class[int(c)], **poses)
    rot = rotation_error_deg(R_gt, R_est)
    trans = np.linalg.norm(t_gt - t_est, axis=-1)
    out = {
        "loss": sum(totals) / len(data),
        "ads_auc": voc_ap_auc(ads),
        "rot_err_median_deg": float(np.median(rot)),
        "trans_err_median_mm": float(np.median(trans) * 1000),
        "rot_lt_10deg": float(np.mean(rot < 10)),
        "trans_lt_1cm": float(np.mean(trans < 0.01)),
    }
    if class_names is not None:
        sym = rotation_errors_modulo_symmetry(
            cls_id, R_gt, R_est, class_names, table=cfg.loss.symmetry_table
        )
        out.update(
            {
                "rot_sym_err_median_deg": float(np.median(sym)),
                "rot_sym_lt_10deg": float(np.mean(sym < 10)),
                "rot_sym_lt_20deg": float(np.mean(sym < 20)),
            }
        )
    return {f"{prefix}/{k}": v for k, v in out.items()}


def bn_modules(model: torch.nn.Module) -> list[torch.nn.BatchNorm1d]:
    """Every BatchNorm of ``model`` (fused layers keep theirs as ``.bn``)."""
    return [m for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]


@torch.no_grad()
def recalibrate_bn(
    model: torch.nn.Module,
    data: Batchable,
    batches: int,
    batch_size: int,
    seed: int,
    device: torch.device,
) -> None:
    """Re-estimate every BatchNorm's running statistics on training batches ("precise BN").

    Each running mean and variance becomes the plain average of its batch statistics over
    ``batches`` batches of ``batch_size`` segments (drawn by ``seed``), the distribution the
    layer sees in training (each branch on its own form of segments that have two,
    ``data.trans_points``). No parameter changes. Used before every evaluation in eval mode:
    an exponential average with momentum 0.01 started at variance 1 is still far from the
    real statistics after a few thousand steps.
    """
    bns = bn_modules(model)
    momenta = [bn.momentum for bn in bns]
    for bn in bns:
        bn.reset_running_stats()
        bn.momentum = None  # cumulative average
    was_training = model.training
    model.train()
    g = torch.Generator().manual_seed(seed)
    for _ in range(batches):
        idx = torch.randint(len(data), (batch_size,), generator=g)
        extra = () if data.trans_points is None else (data.trans_points[idx].to(device),)
        model(data.points[idx].to(device), data.cls_id[idx].to(device), *extra)
    for bn, m in zip(bns, momenta, strict=True):
        bn.momentum = m
    model.train(was_training)


@torch.no_grad()
def batch_stats_rotation_error(
    model: torch.nn.Module, data: Batchable, batch_size: int, device: torch.device
) -> float:
    """Median rotation error (degrees) of ``model`` in *train* mode (batch statistics).

    The same segments in eval mode give ``validate``'s number; the two agree when the running
    statistics match the training distribution. BatchNorm buffers are restored afterwards.
    """
    saved = [
        (bn, bn.running_mean.clone(), bn.running_var.clone(), bn.num_batches_tracked.clone())
        for bn in bn_modules(model)
    ]
    was_training = model.training
    model.train()
    errs = []
    for i in range(0, len(data) - batch_size + 1, batch_size):
        sl = slice(i, i + batch_size)
        out = model(data.points[sl].to(device), data.cls_id[sl].to(device))
        errs.append(rotation_error_deg(data.R[sl].numpy(), out.R.float().cpu().numpy()))
    for bn, mean, var, n in saved:
        bn.running_mean.copy_(mean)
        bn.running_var.copy_(var)
        bn.num_batches_tracked.copy_(n)
    model.train(was_training)
    return float(np.median(np.concatenate(errs))) if errs else float("nan")
