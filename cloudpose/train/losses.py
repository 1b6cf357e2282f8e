"""Training losses: ``alpha * l_t + l_r`` (Gao et al. ICRA 2020, eq. 6; docs/design.md "The pose
networks").

Per-sample terms return ``(B,)`` tensors so callers can log or weight them; :func:`pose_loss`
reduces them to batch means. Rotation losses are in radians (geodesic) or in axis-angle units
(radians, l2); the translation loss is in metres, so ``alpha`` (default 10) has units rad/m.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import torch

from cloudpose.config import ROTATION_LOSSES
from cloudpose.conventions import packaged_classes
from cloudpose.geometry.rotations import rotmat_geodesic_distance, rotmat_to_rotvec, safe_norm
from cloudpose.geometry.symmetry import SymmetryTensors, symmetries_for

__all__ = ["LossTerms", "geodesic_loss", "pose_loss", "rotvec_l2_loss", "translation_loss"]


class LossTerms(NamedTuple):
    """Scalar losses of one batch (batch means).

    Attributes:
        total: ``alpha * translation + rotation``, the quantity to minimise.
        rotation: mean rotation loss, radians.
        translation: mean translation loss, metres.
    """

    total: torch.Tensor
    rotation: torch.Tensor
    translation: torch.Tensor


def geodesic_loss(R_pred: torch.Tensor, R_gt: torch.Tensor) -> torch.Tensor:
    """Geodesic rotation loss ``l_r = arccos((trace(R_pred R_gt^T) - 1) / 2)``.

    Computed in the stable atan2 form of
    :func:`cloudpose.geometry.rotations.rotmat_geodesic_distance` (finite gradients at 0 and pi).

    Args:
        R_pred: (B, 3, 3) predicted rotations.
        R_gt: (B, 3, 3) ground-truth rotations.

    Returns:
        (B,) angles in radians, in [0, pi].
    """
    return rotmat_geodesic_distance(R_pred, R_gt)


def rotvec_l2_loss(r_pred: torch.Tensor, r_gt: torch.Tensor) -> torch.Tensor:
    """Axis-angle l2 loss ``l_r = |r_pred - r_gt|_2`` (the paper's "l2" ablation).

    This compares vectors, not rotations: ``r`` and ``r - 2 pi r/|r|`` are the same rotation, so
    near an angle of pi two nearly equal rotations (``r_gt`` with ``|r_gt|`` just below pi and a
    prediction just past pi) can be almost ``2 pi`` apart. Ground truth should come from
    :func:`~cloudpose.geometry.rotations.rotmat_to_rotvec` (angle in [0, pi]).

    Args:
        r_pred: (B, 3) predicted rotation vectors, radians.
        r_gt: (B, 3) ground-truth rotation vectors, radians.

    Returns:
        (B,) Euclidean distances, radians (axis-angle units).
    """
    return safe_norm(r_pred - r_gt, dim=-1)


def translation_loss(t_pred: torch.Tensor, t_gt: torch.Tensor) -> torch.Tensor:
    """Translation loss ``l_t = |t_pred - t_gt|_2`` (Euclidean distance, not squared).

    Args:
        t_pred: (B, 3) predicted translations, metres.
        t_gt: (B, 3) ground-truth translations, metres.

    Returns:
        (B,) distances in metres.
    """
    return safe_norm(t_pred - t_gt, dim=-1)


def pose_loss(
    R_pred: torch.Tensor,
    t_pred: torch.Tensor,
    R_gt: torch.Tensor,
    t_gt: torch.Tensor,
    rotation: str = "geodesic",
    alpha: float = 10.0,
    rotvec_pred: torch.Tensor | None = None,
    symmetry: SymmetryTensors | None = None,
    cls_id: torch.Tensor | None = None,
    symmetric: bool = False,
    symmetry_table: int = 1,
) -> LossTerms:
    """The training loss ``alpha * mean(l_t) + mean(l_r)``.

    Args:
        R_pred: (B, 3, 3) predicted rotations.
        t_pred: (B, 3) predicted translations, metres.
        R_gt: (B, 3, 3) ground-truth rotations.
        t_gt: (B, 3) ground-truth translations, metres.
        rotation: ``"geodesic"`` (:func:`geodesic_loss` on ``R_pred``) or ``"l2"``
            (:func:`rotvec_l2_loss` of ``rotvec_pred`` against ``rotmat_to_rotvec(R_gt)``);
            ``cloudpose.config.LossConfig.rotation``.
        alpha: weight of the translation term, rad/m (``LossConfig.alpha``).
        rotvec_pred: (B, 3) the network's raw axis-angle output; required for ``"l2"``.
        symmetry: take the loss modulo each sample's class symmetries; needs ``cls_id``.
            ``"geodesic"``: the smallest distance to any ground truth that looks the same in
            depth (:meth:`SymmetryTensors.distance`, exact); ``"l2"``: the L2 distance to the
            rotation vector of the equivalent ground truth nearest to the prediction
            (:meth:`SymmetryTensors.closest_ground_truth`).
        cls_id: (B,) 1-based class ids, for ``symmetry``.
        symmetric: ``LossConfig.symmetric``; without ``symmetry``, the packaged table
            ``symmetry_table`` of the 21 YCB-Video classes (ids in ``classes.txt`` order).
        symmetry_table: ``LossConfig.symmetry_table``, the packaged table's version.

    Returns:
        :class:`LossTerms` of scalars: total, rotation (rad), translation (m).

    Raises:
        ValueError: unknown ``rotation``, missing ``rotvec_pred`` for ``"l2"``, or bad shapes.
    """
    if rotation not in ROTATION_LOSSES:
        raise ValueError(f"pose_loss: rotation must be one of {ROTATION_LOSSES}, got {rotation!r}")
    if symmetric and symmetry is None:
        symmetry = ycb_symmetry_tensors(symmetry_table).to(R_pred.device)
    _check_shape("R_pred", R_pred, (3, 3))
    _check_shape("R_gt", R_gt, (3, 3))
    _check_shape("t_pred", t_pred, (3,))
    _check_shape("t_gt", t_gt, (3,))
    batch = R_pred.shape[:-2]
    for name, x, tail in (("R_gt", R_gt, 2), ("t_pred", t_pred, 1), ("t_gt", t_gt, 1)):
        if x.shape[:-tail] != batch:
            raise ValueError(
                f"pose_loss: {name} has batch shape {tuple(x.shape[:-tail])}, "
                f"expected {tuple(batch)} like R_pred"
            )

    if rotation == "geodesic" and symmetry is not None:
        if cls_id is None or cls_id.shape != batch:
            raise ValueError(f"pose_loss: symmetry needs cls_id of shape {tuple(batch)}")
        l_r = symmetry.distance(R_pred, R_gt, cls_id)
    elif rotation == "geodesic":
        l_r = geodesic_loss(R_pred, R_gt)
    else:
        if rotvec_pred is None:
            raise ValueError(
                "pose_loss: rotation='l2' needs rotvec_pred, the (B, 3) axis-angle output"
            )
        _check_shape("rotvec_pred", rotvec_pred, (3,))
        if rotvec_pred.shape[:-1] != batch:
            raise ValueError(
                f"pose_loss: rotvec_pred has batch shape {tuple(rotvec_pred.shape[:-1])}, "
                f"expected {tuple(batch)} like R_pred"
            )
        if symmetry is not None:
            if cls_id is None or cls_id.shape != batch:
                raise ValueError(f"pose_loss: symmetry needs cls_id of shape {tuple(batch)}")
            R_gt = symmetry.closest_ground_truth(R_pred.detach(), R_gt, cls_id)
        l_r = rotvec_l2_loss(rotvec_pred, rotmat_to_rotvec(R_gt))
    l_t = translation_loss(t_pred, t_gt)
    rot, trans = l_r.mean(), l_t.mean()
    return LossTerms(total=alpha * trans + rot, rotation=rot, translation=trans)


@functools.cache
def ycb_symmetry_tensors(table: int = 1) -> SymmetryTensors:
    """The packaged symmetry table ``table`` for the 21 YCB-Video class ids, as loss tensors."""
    return SymmetryTensors(symmetries_for(packaged_classes(), table))


def _check_shape(name: str, x: torch.Tensor, tail: tuple[int, ...]) -> None:
    if x.shape[-len(tail) :] != tail or x.dim() < len(tail) + 1:
        raise ValueError(
            f"pose_loss: {name} must have shape (B, {', '.join(map(str, tail))}), got {tuple(x.shape)}"
        )
