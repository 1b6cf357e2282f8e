"""The random streams of training: one seed per purpose and index, from the run's seed.

Training draws from six streams: the network's initial weights (``init``), the fixed probe
sample of training segments (``probe``), the batch order of each epoch (``order``, by epoch),
the roll and depth-noise augmentations of each step (``roll``, ``depth_noise``, by epoch and
the step's batch within it) and the batches that re-estimate BatchNorm statistics before each
validation (``bn_recalibrate``, by epoch). :func:`seed_for` gives each its seed; a stream depends on the
run's seed, its purpose and its index only, so a resumed run draws what an uninterrupted one
draws.

How a seed is made is the setting ``train.seed_streams``
(:data:`~cloudpose.config.SEED_STREAMS`):

- ``"purpose"``: a hash of ``(seed, purpose, *index)``: no two purposes, indices or seeds share
  a stream.
- ``"arithmetic"``: the seed arithmetic every run stored before the setting existed used, kept
  so that those runs and their presets train to the same bits. Its streams overlap: the batch
  order of epoch ``e`` (``seed * 1_000_003 + e``) is the roll augmentation's stream of epoch 0,
  batch ``e``; the BatchNorm batches of epoch 0 (``seed``) are the initial weights' stream; the
  probe is the same sample for every seed (``0``).
"""

from __future__ import annotations

import hashlib
import json

import torch

from cloudpose.config import SEED_STREAMS

PURPOSES: dict[str, tuple[str, ...]] = {
    "init": (),
    "probe": (),
    "order": ("epoch",),
    "roll": ("epoch", "batch"),
    "depth_noise": ("epoch", "batch"),
    "bn_recalibrate": ("epoch",),
}
"""Every random stream of training and the indices that pick one of its members."""

_ARITHMETIC = {
    "init": lambda seed: seed,
    "probe": lambda seed: 0,
    "order": lambda seed, epoch: seed * 1_000_003 + epoch,
    "roll": lambda seed, epoch, batch: seed * 1_000_003 + epoch * 100_003 + batch,
    "depth_noise": lambda seed, epoch, batch: seed * 7_000_003 + epoch * 100_003 + batch,
    "bn_recalibrate": lambda seed, epoch: seed + epoch,
}
"""``train.seed_streams = "arithmetic"``: the seeds of every run stored before the setting."""


def seed_for(seed: int, purpose: str, *index: int, streams: str = "purpose") -> int:
    """The seed of stream ``purpose`` at ``index`` in a run of seed ``seed``.

    Args:
        seed: the run's seed (``cfg.seed``).
        purpose: one of :data:`PURPOSES`.
        index: the purpose's indices (:data:`PURPOSES` names them), e.g. epoch and batch.
        streams: how seeds are made (``train.seed_streams``, module doc).

    Returns:
        A seed for ``torch.Generator.manual_seed`` (``"purpose"``: in [0, 2**63)).
    """
    if purpose not in PURPOSES:
        raise ValueError(f"random stream {purpose!r}: expected one of {sorted(PURPOSES)}")
    names = PURPOSES[purpose]
    if len(index) != len(names):
        raise ValueError(f"random stream {purpose!r} takes {names} as its index, got {index}")
    if streams == "arithmetic":
        return _ARITHMETIC[purpose](int(seed), *(int(i) for i in index))
    if streams != "purpose":
        raise ValueError(f"train.seed_streams={streams!r}: expected one of {SEED_STREAMS}")
    text = json.dumps([int(seed), purpose, *(int(i) for i in index)])
    digest = hashlib.blake2b(text.encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") >> 1


def generator(seed: int, purpose: str, *index: int, streams: str = "purpose") -> torch.Generator:
    """A CPU ``torch.Generator`` seeded with :func:`seed_for` of the same arguments."""
    return torch.Generator().manual_seed(seed_for(seed, purpose, *index, streams=streams))
