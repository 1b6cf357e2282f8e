"""One training run across processes: the process group, the batch split, and BatchNorm
statistics over the global batch.

``torchrun --nproc_per_node N -m cloudpose.cli train ...`` (or ``cloudpose train --nproc N``)
starts N processes; :func:`from_env` joins them (gloo on CPU, NCCL for CUDA tensors) and
:func:`cloudpose.train.loop.train` then runs them as one run:

- Every global batch is the one a single process would draw (:func:`cloudpose.train.loop.epoch_order`
  over ``train.batch_size``); process r takes the r-th of N equal contiguous shares of it
  (:meth:`World.shard`). A ``DistributedSampler`` would instead deal whole permutations out to
  the processes, so which segments meet in a batch, and the loss curve, would change with N.
- The model is wrapped in ``DistributedDataParallel``, which averages the gradients of the N
  shares' mean losses: the gradient of the global batch's mean loss.
- BatchNorm normalises with the statistics of the global batch, as the paper's batch of 128 on
  one GPU does (:func:`sync_batch_stats`): plain ``BatchNorm1d`` layers become
  :class:`SyncBatchNorm1d`, and the fused last layer (:mod:`cloudpose.models.fused`), which
  computes its BatchNorm itself, all-reduces its own statistics and their gradients.
  ``torch.nn.SyncBatchNorm`` is not used: it refuses CPU tensors.

So N processes with a batch split N ways follow the loss curve of one process with the whole
batch, to float rounding (tests/train/test_distributed.py, gloo on CPU). Only rank 0 writes files
and talks to MLflow.
"""

from __future__ import annotations

import contextlib
import datetime
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, TypeVar

import torch
from torch import nn

__all__ = [
    "SINGLE",
    "GroupBatchStats",
    "SyncBatchNorm1d",
    "World",
    "all_reduce_sum",
    "from_env",
    "global_mean",
    "local_batch_stats",
    "relaunch_under_torchrun",
    "sync_batch_stats",
]

T = TypeVar("T")


@dataclass(frozen=True)
class World:
    """The processes of one run and this process's place among them.

    Attributes:
        rank: this process, 0..size-1 (torchrun's ``RANK``).
        size: number of processes (``WORLD_SIZE``).
        local_rank: this process on its node (``LOCAL_RANK``): its CUDA device index.
        stats_group: the process group BatchNorm statistics are all-reduced in (a group of its
            own, so they never queue behind DDP's gradient buckets); None for one process.
    """

    rank: int = 0
    size: int = 1
    local_rank: int = 0
    stats_group: Any = None

    @property
    def is_main(self) -> bool:
        """Whether this process writes files and logs to MLflow (rank 0)."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.size > 1

    def shard(self, batch_size: int) -> slice:
        """This process's share of a global batch of ``batch_size`` rows.

        Raises:
            ValueError: ``batch_size`` not divisible by the number of processes.
        """
        if batch_size % self.size:
            raise ValueError(
                f"train.batch_size={batch_size} does not split into {self.size} equal shares; "
                f"use a multiple of {self.size} (the global batch is split across processes)"
            )
        k = batch_size // self.size
        return slice(self.rank * k, (self.rank + 1) * k)

    def mean(self, values: list[float]) -> list[float]:
        """The mean over processes of each of ``values`` (one all-reduce); as is for one."""
        if not self.distributed:
            return values
        import torch.distributed as dist

        t = torch.tensor(values, dtype=torch.float64)
        dist.all_reduce(t, group=self.stats_group)
        return (t / self.size).tolist()

    def broadcast(self, obj: T) -> T:
        """Rank 0's ``obj`` on every process (pickled); ``obj`` itself for one process."""
        if not self.distributed:
            return obj
        import torch.distributed as dist

        box = [obj]
        dist.broadcast_object_list(box, src=0)
        return box[0]

    def main_first(self, fn: Callable[[], T]) -> T:
        """``fn()`` on rank 0 first, then on the others (e.g. data made once, then read)."""
        if not self.distributed:
            return fn()
        import torch.distributed as dist

        if self.is_main:
            out = fn()
            dist.barrier()
            return out
        dist.barrier()
        return fn()

    def device(self, device: torch.device) -> torch.device:
        """This process's device: its own GPU (``cuda:LOCAL_RANK``) when ``device`` is CUDA."""
        if device.type == "cuda" and self.distributed:
            torch.cuda.set_device(self.local_rank)
            return torch.device("cuda", self.local_rank)
        return device


SINGLE = World()
"""One process: nothing is split or all-reduced."""


@contextlib.contextmanager
def from_env(timeout_min: float = 60.0) -> Iterator[World]:
    """Join the process group torchrun describes in the environment for the block (left at
    its end); :data:`SINGLE` outside torchrun.

    Reads ``WORLD_SIZE``, ``RANK`` and ``LOCAL_RANK`` (with ``MASTER_ADDR``/``MASTER_PORT``,
    torchrun's rendezvous). The default group serves gloo for CPU tensors and NCCL for CUDA
    ones where CUDA is available.

    Args:
        timeout_min: how long a collective waits for the other processes (rank 0's epoch-end
            validation runs while the others wait).
    """
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        yield SINGLE
        return
    import torch.distributed as dist

    backend = "cpu:gloo,cuda:nccl" if torch.cuda.is_available() else "gloo"
    dist.init_process_group(backend, timeout=datetime.timedelta(minutes=timeout_min))
    try:
        yield World(
            rank=dist.get_rank(),
            size=dist.get_world_size(),
            local_rank=int(os.environ.get("LOCAL_RANK", "0")),
            stats_group=dist.new_group(),
        )
    finally:
        dist.destroy_process_group()


def relaunch_under_torchrun(args: list[str], nproc: int) -> int:
    """Run ``cloudpose ARGS`` again as ``nproc`` processes of one torchrun (standalone, this
    machine) and return its exit code; the ``--nproc N`` pair is dropped from ``args``.

    Args:
        args: the command's arguments after ``cloudpose`` (e.g. ``["train", "--nproc", "2",
            "--preset", "smoke"]``).
        nproc: processes to start.
    """
    import subprocess
    import sys

    args = list(args)
    if "--nproc" in args:
        i = args.index("--nproc")
        del args[i : i + 2]
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    cmd += ["--nproc_per_node", str(nproc), "-m", "cloudpose.cli", *args]
    return subprocess.run(cmd, check=False).returncode


def all_reduce_sum(t: torch.Tensor, group: Any) -> torch.Tensor:
    """Sum ``t`` over the processes of ``group``, in place; returns ``t``."""
    import torch.distributed as dist

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
