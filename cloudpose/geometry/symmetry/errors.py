"""Rotation error modulo symmetry: numpy (the metrics) and torch (the losses)."""

from __future__ import annotations

import numpy as np
import torch

from cloudpose.geometry.rigid import rotation_error_deg
from cloudpose.geometry.rotations import rotmat_geodesic_distance, safe_norm
from cloudpose.geometry.symmetry.table import ClassSymmetry, rotvec_deg_to_rotmat, symmetries_for


def _sampled(s: ClassSymmetry, steps: int) -> ClassSymmetry:
    """``s`` with a continuous symmetry also listed as ``steps`` discrete turns (x2 with flip)."""
    if s.axis is None:
        return s
    turns = [rotvec_deg_to_rotmat(s.axis * deg) for deg in np.arange(steps) * 360.0 / steps]
    if s.flip:
        F = flip_rotation(s.axis)
        turns += [T @ F for T in turns]
    return ClassSymmetry(np.stack(turns), s.axis, s.flip, s.centre)


def flip_rotation(axis: np.ndarray) -> np.ndarray:
    """(3, 3) the 180 degree turn that reverses ``axis`` (about a perpendicular model axis)."""
    axis = np.asarray(axis, dtype=np.float64)
    perp = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    return rotvec_deg_to_rotmat(perp / np.linalg.norm(perp) * 180.0)


def _line_angle(u: np.ndarray, v: np.ndarray, flip: bool) -> np.ndarray:
    cos = np.sum(u * v, axis=-1)
    if flip:
        cos = np.abs(cos)
    sin = np.linalg.norm(np.cross(u, v), axis=-1)
    return np.degrees(np.arctan2(sin, cos))


def symmetric_rotation_error_deg(
    R_gt: np.ndarray, R_est: np.ndarray, sym: ClassSymmetry
) -> np.ndarray:
    """Rotation error modulo the symmetries of one class, degrees.

    Args:
        R_gt, R_est: (M, 3, 3) rotations, model -> camera.
        sym: the class's symmetries.

    Returns:
        (M,) ``min over equivalent ground truths`` of the geodesic angle, in [0, 180].
    """
    R_gt = np.asarray(R_gt, dtype=np.float64)
    R_est = np.asarray(R_est, dtype=np.float64)
    if sym.axis is not None:
        return _line_angle(R_est @ sym.axis, R_gt @ sym.axis, sym.flip)
    errs = [rotation_error_deg(R_gt @ S, R_est) for S in sym.discrete]
    return np.min(errs, axis=0)


def rotation_errors_modulo_symmetry(
    cls_id: np.ndarray,
    R_gt: np.ndarray,
    R_est: np.ndarray,
    class_names: list[str],
    miss: np.ndarray | None = None,
    table: int = 1,
) -> np.ndarray:
    """(M,) rotation errors modulo each class's symmetries, degrees; ``inf`` for misses.

    Args:
        cls_id: (M,) 1-based class ids; ``class_names[id - 1]`` names the class whose entry of
            the symmetry table applies.
        R_gt, R_est: (M, 3, 3) rotations.
        miss: (M,) instances without an estimate.
        table: the symmetry table version (``loss.symmetry_table`` of the run).
    """
    cls_id = np.asarray(cls_id).astype(int)
    syms = symmetries_for(list(class_names), table)
    out = np.full(len(cls_id), np.inf)
    hit = np.ones(len(cls_id), bool) if miss is None else ~np.asarray(miss, bool)
    for c in np.unique(cls_id[hit]):
        sel = hit & (cls_id == c)
        out[sel] = symmetric_rotation_error_deg(R_gt[sel], R_est[sel], syms[int(c) - 1])
    return out


class SymmetryTensors(torch.nn.Module):
    """A table's symmetries as padded tensors indexed by 1-based class id, for losses.

    Buffers (index 0 = no class):
        groups: (k + 1, G, 3, 3) discrete rotations, each class padded with its identity; a
            continuous symmetry is sampled every ``360 / continuous_steps`` degrees (and
            flipped), for :meth:`closest_ground_truth`.
        axes: (k + 1, 3) continuous axes, zero where there is none.
        flips: (k + 1,) bool.
        continuous: (k + 1,) bool.
    """

    def __init__(self, syms: list[ClassSymmetry], continuous_steps: int = 72) -> None:
        super().__init__()
        syms = [_sampled(s, continuous_steps) for s in syms]
        G = max(len(s.discrete) for s in syms)
        groups = np.tile(np.eye(3), (len(syms) + 1, G, 1, 1))
        axes = np.zeros((len(syms) + 1, 3))
        flips = np.zeros(len(syms) + 1, dtype=bool)
        for i, s in enumerate(syms, start=1):
            groups[i, : len(s.discrete)] = s.discrete
            if s.axis is not None:
                axes[i], flips[i] = s.axis, s.flip
        self.register_buffer("groups", torch.from_numpy(groups).float())
        self.register_buffer("axes", torch.from_numpy(axes).float())
        self.register_buffer("flips", torch.from_numpy(flips))
        self.register_buffer("continuous", torch.from_numpy(axes.any(axis=1)))

    def distance(
        self, R_pred: torch.Tensor, R_gt: torch.Tensor, cls_id: torch.Tensor
    ) -> torch.Tensor:
        """Geodesic rotation distance modulo each sample's class symmetries, radians.

        Args:
            R_pred, R_gt: (B, 3, 3) rotations.
            cls_id: (B,) 1-based class ids.

        Returns:
            (B,) angles in [0, pi]; finite gradients (the stable atan2 forms).
        """
        dtype = R_pred.dtype
        G = self.groups[cls_id].to(dtype)  # (B, G, 3, 3)
        disc = rotmat_geodesic_distance(R_pred[:, None], R_gt[:, None] @ G).amin(dim=1)  # (B,)
        a = self.axes[cls_id].to(dtype)  # (B, 3)
        u = (R_pred @ a[..., None]).squeeze(-1)  # (B, 3)
        v = (R_gt @ a[..., None]).squeeze(-1)  # (B, 3)
        cos = (u * v).sum(-1)
        cos = torch.where(self.flips[cls_id], cos.abs(), cos)
        cont = torch.atan2(safe_norm(torch.linalg.cross(u, v), dim=-1), cos)
        return torch.where(self.continuous[cls_id], cont, disc)

    @torch.no_grad()
    def closest_ground_truth(
        self, R_pred: torch.Tensor, R_gt: torch.Tensor, cls_id: torch.Tensor
    ) -> torch.Tensor:
        """(B, 3, 3) the equivalent ground truth ``R_gt S`` nearest to ``R_pred`` (no gradient).

        For losses that compare representations (the axis-angle L2 loss) rather than rotations;
        a continuous symmetry is resolved to its sampled rotations.
        """
        cand = R_gt[:, None] @ self.groups[cls_id].to(R_gt.dtype)  # (B, G, 3, 3)
        best = rotmat_geodesic_distance(R_pred[:, None], cand).argmin(dim=1)  # (B,)
        return cand[torch.arange(len(cand), device=cand.device), best]
