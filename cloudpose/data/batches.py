"""The network's view of a segment set: the n-point prefix of each valid segment and its
targets, as tensors (training, validation and the ``fit/`` probe take it)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class Batchable:
    """Training tensors of valid segments: the network's n-point prefix and the targets (and,
    for on-line segments in two forms, ``data.online_bleed_branch``, the translation branch's
    own points)."""

    points: torch.Tensor  # (M, n, 3) float32, metres
    cls_id: torch.Tensor  # (M,) int64, 1-based
    R: torch.Tensor  # (M, 3, 3)
    t: torch.Tensor  # (M, 3)
    trans_points: torch.Tensor | None = None  # (M, n, 3): the translation branch's own form

    @classmethod
    def from_segments(cls, segs, n_points: int) -> Batchable:
        if n_points > segs.points.shape[1]:
            raise ValueError(
                f"train.n_points={n_points} exceeds the {segs.points.shape[1]} cached FPS points"
            )
        keep = np.asarray(segs.valid, dtype=bool)
        return cls(
            points=torch.from_numpy(np.ascontiguousarray(segs.points[keep, :n_points], np.float32)),
            cls_id=torch.from_numpy(segs.cls_id[keep].astype(np.int64)),
            R=torch.from_numpy(segs.R[keep].astype(np.float32)),
            t=torch.from_numpy(segs.t[keep].astype(np.float32)),
        )

    def __len__(self) -> int:
        return self.points.shape[0]

    def subset(self, index: torch.Tensor) -> Batchable:
        """The segments at ``index`` (an index tensor or bool mask)."""
        trans = None if self.trans_points is None else self.trans_points[index]
        return Batchable(
            self.points[index], self.cls_id[index], self.R[index], self.t[index], trans
        )
