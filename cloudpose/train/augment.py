"""Augmentations of training batches: the camera rolled about its optical axis, and depth noise
along the viewing rays. Each draws from its own stream of the run
(:func:`cloudpose.train.seeds.seed_for`), indexed by epoch and batch, so a resumed run
augments as an uninterrupted one does."""

from __future__ import annotations

import math

import torch

from cloudpose.config import Config
from cloudpose.train import seeds


def augment(
    points: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    cfg: Config,
    epoch: int,
    batch: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A training batch augmented as ``cfg.train`` asks (``augment_roll_deg``, then
    ``augment_depth_noise_mm``; each 0 = off).

    Args:
        points: (B, n, 3) camera-frame points, metres; R (B, 3, 3), t (B, 3) their poses.
        cfg: the run's config (its seed and ``train`` settings).
        epoch, batch: the step's position (0-based epoch, batch within it): the streams' index.

    Returns:
        ``(points, R, t)`` augmented, the same shapes.
    """
    train = cfg.train
    if train.augment_roll_deg > 0:
        g = seeds.generator(cfg.seed, "roll", epoch, batch, streams=train.seed_streams)
        points, R, t = roll_about_optical_axis(points, R, t, train.augment_roll_deg, g)
    if train.augment_depth_noise_mm > 0:
        g = seeds.generator(cfg.seed, "depth_noise", epoch, batch, streams=train.seed_streams)
        points = jitter_along_rays(points, train.augment_depth_noise_mm / 1000, g)
    return points, R, t


def augment_forms(
    points: torch.Tensor,
    trans_points: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    cfg: Config,
    epoch: int,
    batch: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Segments in two forms augmented as a pair (``data.online_bleed_branch =
    "translation-paired"``): the rotation branch's form exactly as :func:`augment` augments a
    batch of one form (the same draws), the translation branch's rolled by the same angles,
    its depth noise drawn after the first form's.

    Args:
        points, trans_points: (B, n, 3) the two forms of the same segments; R, t their poses.

    Returns:
        ``(points, trans_points, R, t)`` augmented.
    """
    train = cfg.train
    if train.augment_roll_deg > 0:  # one stream drawn twice: the same angles for both forms
        g = seeds.generator(cfg.seed, "roll", epoch, batch, streams=train.seed_streams)
        rolled, R2, t2 = roll_about_optical_axis(points, R, t, train.augment_roll_deg, g)
        g = seeds.generator(cfg.seed, "roll", epoch, batch, streams=train.seed_streams)
        trans_points, _, _ = roll_about_optical_axis(trans_points, R, t, train.augment_roll_deg, g)
        points, R, t = rolled, R2, t2
    if train.augment_depth_noise_mm > 0:  # augment's draws, then the second form's
        g = seeds.generator(cfg.seed, "depth_noise", epoch, batch, streams=train.seed_streams)
        points = jitter_along_rays(points, train.augment_depth_noise_mm / 1000, g)
        trans_points = jitter_along_rays(trans_points, train.augment_depth_noise_mm / 1000, g)
    return points, trans_points, R, t


def roll_about_optical_axis(
    points: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    max_deg: float,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Segments and poses as seen by the camera rolled about its optical (z) axis.

    Exact for depth data: a camera rolled about its optical axis sees the same surface points.

    Args:
        points: (B, n, 3) camera-frame points, metres; R (B, 3, 3), t (B, 3) their poses.
        max_deg: roll angles are uniform in [-max_deg, max_deg] degrees, one per segment.

    Returns:
        ``(points @ Q^T, Q R, Q t)`` with Q (B, 3, 3) the rolls.
    """
    B = points.shape[0]
    a = (torch.rand(B, generator=generator) * 2 - 1) * math.radians(max_deg)  # (B,) radians
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
