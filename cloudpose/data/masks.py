"""Degraded segmentation masks: the errors of a segmentation network, imitated on ground truth.

The paper evaluates with PoseCNN's predicted masks, not ground truth. Without a download, the
suite imitates what such a network gets wrong, at three strengths, as mask sources next to
``gt`` (``DataConfig.segmentation = "degraded-mild" | "degraded-medium" | "degraded-strong"``):

- boundary error: the ground-truth mask eroded or dilated (one or the other, half the
  instances each) by up to ``boundary_px`` pixels, with a square element;
- bleeding: the mask grown by ``bleed_px`` pixels into the pixels of touching objects (where
  two objects meet, a network's labels spill across the edge; the background stays clean, as
  depth-only evaluation drops it anyway by the outlier filter);
- missed detections: with probability ``miss_rate`` an instance gets no mask at all (a miss in
  every metric).

Every draw is a pure function of the frame id and the class id (crc32-seeded), so a frame gives
the same degraded masks on every machine and in every process, and segment caches stay valid.
The occlusion factor still uses the ground-truth labels.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

if TYPE_CHECKING:
    from cloudpose.data.ycb import Frame

__all__ = ["DEGRADATIONS", "Degradation", "degraded_mask"]


@dataclass(frozen=True)
class Degradation:
    """How far a degraded mask departs from ground truth (see the module docstring)."""

    boundary_px: int
    bleed_px: int
    miss_rate: float


DEGRADATIONS = {
    "degraded-mild": Degradation(boundary_px=2, bleed_px=2, miss_rate=0.02),
    "degraded-medium": Degradation(boundary_px=4, bleed_px=4, miss_rate=0.05),
    "degraded-strong": Degradation(boundary_px=8, bleed_px=8, miss_rate=0.10),
}
"""The strengths, by mask-source name. Mild is near a good network's boundary error on
YCB-Video (a few pixels); strong is a poor one's."""


def degraded_mask(frame: Frame, cls_id: int, how: Degradation) -> np.ndarray:
    """(H, W) bool mask of instance ``cls_id`` of ``frame``, degraded as ``how`` says."""
    rng = np.random.default_rng([zlib.crc32(frame.frame_id.encode()), int(cls_id)])
    gt = frame.label == cls_id
    if rng.random() < how.miss_rate or not gt.any():
        return np.zeros_like(gt)
    k = int(rng.integers(0, how.boundary_px + 1))
    if k:
        element = np.ones((2 * k + 1, 2 * k + 1), bool)
        grow = rng.random() < 0.5
        op = ndimage.binary_dilation if grow else ndimage.binary_erosion
        mask = op(gt, structure=element)
        if not mask.any():  # a thin object eroded away: keep its ground truth
            mask = gt
    else:
        mask = gt.copy()
    if how.bleed_px:
        others = (frame.label != 0) & ~gt
        near = ndimage.binary_dilation(gt, iterations=how.bleed_px)
        mask |= near & others
    return mask
