"""One optimiser step: the network on a batch, the pose loss (paper eq. 6), its gradient, Adam.

:func:`train_step` is the whole of what a training step does to the network and the optimiser;
the loop (:mod:`cloudpose.train.loop`) chooses the batch, the learning rate and what to log.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from cloudpose.config import LossConfig
from cloudpose.geometry.symmetry import SymmetryTensors
from cloudpose.train.distributed import SINGLE, World
from cloudpose.train.losses import pose_loss


class Batch(NamedTuple):
    """Network inputs and targets of one step.

    Attributes:
        points: (B, n, 3) camera-frame points, metres.
        cls_id: (B,) int64 1-based class ids.
        R: (B, 3, 3) rotations model->camera.
        t: (B, 3) translations, metres.
        trans_points: (B, m, 3) the translation branch's own form of the segments
            (``data.online_bleed_branch = "translation"``: cut from bleeding masks), or None:
            both branches see ``points``.
    """

    points: torch.Tensor
    cls_id: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor
    trans_points: torch.Tensor | None = None


class StepLoss(NamedTuple):
    """The step's loss terms (before the step), as floats: ``loss = alpha * trans + rot``."""

    loss: float
    rot: float
    trans: float


def train_step(
    net: torch.nn.Module,
    opt: torch.optim.Optimizer,
    batch: Batch,
    loss: LossConfig,
    *,
    symmetry: SymmetryTensors | None = None,
    bf16: bool = False,
    world: World = SINGLE,
) -> StepLoss:
    """One optimiser step of ``net`` on ``batch``: forward (under bfloat16 autocast with
    ``bf16``), the pose loss, its gradient, ``opt.step()``.

    Args:
        net: the pose network (in training mode), or its ``DistributedDataParallel`` wrapper.
        opt: the optimiser of its parameters (at the step's learning rate).
        batch: this process's share of the step's batch, on the network's device.
        loss: the loss settings (``cfg.loss``).
        symmetry: each class's symmetries for a loss modulo symmetry (``loss.symmetric``).
        bf16: run the network under bfloat16 autocast (the loss in float32).
        world: the processes sharing the batch: the returned terms are the global batch's.

    Returns:
        The loss terms of the batch at the parameters before the step.

    Raises:
        FloatingPointError: the loss is not finite (the step has been taken).
    """
    device_type = batch.points.device.type
    with torch.autocast(device_type, dtype=torch.bfloat16, enabled=bf16):
        out = net(batch.points, batch.cls_id, batch.trans_points)
    terms = pose_loss(
        out.R.float(),
        out.t.float(),
        batch.R,
        batch.t,
        rotation=loss.rotation,
        alpha=loss.alpha,
        rotvec_pred=out.rot_raw.float(),
        symmetry=symmetry,
        cls_id=batch.cls_id,
    )
    opt.zero_grad(set_to_none=True)
    terms.total.backward()
    opt.step()
    values = [float(x.detach()) for x in terms]
    if world.distributed:  # the global batch's: the mean of the equal shares' means
        values = world.mean(values)
    step_loss = StepLoss(*values)
    if not math.isfinite(step_loss.loss):
        raise FloatingPointError(f"loss became {step_loss.loss}")
    return step_loss
