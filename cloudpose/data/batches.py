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


def split_forms(points: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Segments in two forms side by side, ``(B, 2n, 3)`` (``data.online_bleed_branch =
    "translation"``), as the rotation branch's form (rows ``:n``, cut from the rendered masks)
    and the translation branch's (rows ``n:``, from the bleeding masks). :func:`join_forms`
    undoes it."""
    if points.shape[1] != 2 * n:
        raise ValueError(
            f"data.online_bleed_branch='translation' trains on segments of two forms "
            f"({2 * n} points each: 2 x train.n_points); this batch has {points.shape[1]} "
            f"(the on-line stream of data.online_version=3 makes them)"
        )
    return points[:, :n], points[:, n:]


def join_forms(points: torch.Tensor, trans_points: torch.Tensor) -> torch.Tensor:
    """The two forms side by side, as the on-line stream's batches hold them
    (:func:`split_forms`'s inverse)."""
    return torch.cat([points, trans_points], dim=1)
