"""One training run across processes: the process group and the batch split (BatchNorm over the
global batch: :mod:`cloudpose.models.sync_bn`).

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
  one GPU does (:func:`cloudpose.models.sync_bn.sync_batch_stats`).

So N processes with a batch split N ways follow the loss curve of one process with the whole
batch, to float rounding (tests/train/test_distributed.py, gloo on CPU). Only rank 0 writes files
and talks to MLflow.
"""

from __future__ import annotations

import contextlib
import datetime
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, TypeVar

import torch
import torch.distributed as dist

__all__ = ["SINGLE", "World", "from_env", "relaunch_under_torchrun"]

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

        t = torch.tensor(values, dtype=torch.float64)
        dist.all_reduce(t, group=self.stats_group)
        return (t / self.size).tolist()

    def broadcast(self, obj: T) -> T:
        """Rank 0's ``obj`` on every process (pickled); ``obj`` itself for one process."""
        if not self.distributed:
            return obj

        box = [obj]
        dist.broadcast_object_list(box, src=0)
        return box[0]

    def main_first(self, fn: Callable[[], T]) -> T:
        """``fn()`` on rank 0 first, then on the others (e.g. data made once, then read)."""
        if not self.distributed:
            return fn()

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
    args = list(args)
    if "--nproc" in args:
        i = args.index("--nproc")
        del args[i : i + 2]
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    cmd += ["--nproc_per_node", str(nproc), "-m", "cloudpose.cli", *args]
    return subprocess.run(cmd, check=False).returncode
