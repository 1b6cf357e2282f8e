"""BatchNorm over the global batch of several processes: plain ``BatchNorm1d`` layers become
:class:`SyncBatchNorm1d` (:func:`sync_batch_stats`), and the fused last layer
(:mod:`cloudpose.models.fused`), which computes its BatchNorm itself, all-reduces its own
statistics and their gradients with :func:`all_reduce_sum` and :func:`global_mean`.
``torch.nn.SyncBatchNorm`` is not used: it refuses CPU tensors. The process group comes from
:mod:`cloudpose.train.distributed`; alone (group None) every layer is plain BatchNorm.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import torch
import torch.distributed as dist
from torch import nn

__all__ = [
    "GroupBatchStats",
    "SyncBatchNorm1d",
    "all_reduce_sum",
    "global_mean",
    "local_batch_stats",
    "sync_batch_stats",
]


def all_reduce_sum(t: torch.Tensor, group: Any) -> torch.Tensor:
    """Sum ``t`` over the processes of ``group``, in place; returns ``t``."""
    dist.all_reduce(t, group=group)
    return t


def global_mean(x: torch.Tensor, group: Any) -> tuple[torch.Tensor, int]:
    """Mean over the rows of every process's ``x`` and the total row count.

    Args:
        x: (N_r, C) this process's rows.
        group: the process group.

    Returns:
        mean (C,) over all sum_r N_r rows, and that count.
    """
    s = torch.cat([x.sum(dim=0), x.new_tensor([x.shape[0]])])  # (C + 1,)
    all_reduce_sum(s, group)
    n = round(float(s[-1]))
    return s[:-1] / n, n


class GroupBatchStats:
    """A module that computes its own training BatchNorm statistics and all-reduces them over
    ``process_group``, the processes that each hold a share of the batch (None: this process's
    batch alone). :class:`SyncBatchNorm1d` is one, and so is the fused last layer
    (:class:`cloudpose.models.fused.FusedPointLayerMaxPool`); :func:`sync_batch_stats` and
    :func:`local_batch_stats` set the group of every such module of a model."""

    process_group: Any = None


class _SyncBatchNormFn(torch.autograd.Function):
    """BatchNorm over the rows of every process: statistics and their gradient all-reduced."""

    @staticmethod
    def forward(ctx: Any, x, weight, bias, eps: float, group: Any):
        """x (N_r, C); returns y (N_r, C), the global mean (C,), biased variance (C,) and
        row count (a 0-d tensor)."""
        mean, n = global_mean(x, group)
        xc = x - mean  # (N_r, C)
        var = all_reduce_sum((xc * xc).sum(dim=0), group) / n  # (C,) biased
        inv_std = torch.rsqrt(var + eps)
        xhat = xc * inv_std  # (N_r, C)
        y = xhat * weight + bias
        ctx.save_for_backward(xhat, weight, inv_std)
        ctx.n, ctx.group = n, group
        count = torch.tensor(n)
        ctx.mark_non_differentiable(mean, var, count)
        return y, mean, var, count

    @staticmethod
    def backward(ctx: Any, gy, *_):
        """The input gradient of the global objective from the all-reduced sums of ``gy`` and
        ``gy * xhat``; the weight and bias gradients of this process's rows (DDP sums them)."""
        xhat, weight, inv_std = ctx.saved_tensors
        dbeta = gy.sum(dim=0)  # (C,)
        dgamma = (gy * xhat).sum(dim=0)  # (C,)
        sums = all_reduce_sum(torch.stack([dbeta, dgamma]), ctx.group) / ctx.n  # (2, C)
        dx = (weight * inv_std) * (gy - sums[0] - xhat * sums[1])  # (N_r, C)
        return dx, dgamma, dbeta, None, None


class SyncBatchNorm1d(GroupBatchStats, nn.BatchNorm1d):
    """``nn.BatchNorm1d`` whose training statistics are those of every process's rows.

    With ``process_group`` None (the default) or in eval mode it is ``nn.BatchNorm1d``
    exactly. Running statistics follow ``nn.BatchNorm1d`` (momentum or cumulative average;
    unbiased variance over the global count). Input (N_r, C) only: the layers here normalise
    (B*n, C) point features or (B, C) pooled ones.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (self.training and self.process_group is not None):
            return super().forward(x)
        if x.ndim != 2:
            raise ValueError(f"SyncBatchNorm1d expects (N, C) input, got {tuple(x.shape)}")
        y, mean, var, count = _SyncBatchNormFn.apply(
            x, self.weight, self.bias, self.eps, self.process_group
        )
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)
                f = (
                    1.0 / float(self.num_batches_tracked)
                    if self.momentum is None
                    else self.momentum
                )
                n = int(count)
                self.running_mean.lerp_(mean, f)
                self.running_var.lerp_(var * (n / (n - 1)), f)
        return y


def sync_batch_stats(model: nn.Module, group: Any) -> nn.Module:
    """Make every BatchNorm of ``model`` normalise with the statistics of ``group``'s batch.

    Each plain ``nn.BatchNorm1d`` becomes a :class:`SyncBatchNorm1d` in place (its class is
    switched: same parameters, buffers, state_dict and module identity, so a module two
    branches share stays shared); every :class:`GroupBatchStats` module gets the group.
    ``group`` None turns the synchronisation off again.

    Returns:
        ``model``.
    """
    for m in model.modules():
        if type(m) is nn.BatchNorm1d:
            m.__class__ = SyncBatchNorm1d
        if isinstance(m, GroupBatchStats):
            m.process_group = group
    return model


@contextlib.contextmanager
def local_batch_stats(model: nn.Module) -> Iterator[nn.Module]:
    """Within the block, ``model``'s BatchNorms use this process's own batch statistics (one
    process validating or re-estimating running statistics on whole batches of its own)."""
    mods = [m for m in model.modules() if isinstance(m, GroupBatchStats)]
    groups = [m.process_group for m in mods]
    for m in mods:
        m.process_group = None
    try:
        yield model
    finally:
        for m, g in zip(mods, groups, strict=True):
            m.process_group = g
