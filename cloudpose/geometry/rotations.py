"""Rotation representations and the geodesic distance, batched in torch.

Every function takes any leading batch shape ``...`` and works in float32 and float64. Names
follow RoMa (``<src>_to_<dst>``). Conventions, stated once:

- rotation matrices ``R`` act on column vectors, ``p_cam = R @ p_model + t`` (``conventions``);
- rotation vectors (axis-angle) ``r = angle * axis``, angle in radians;
- unit quaternions are **XYZW** (vector part first, scalar last), as in RoMa and
  ``scipy.spatial.transform.Rotation.as_quat``;
- the 6D representation is the first two **columns** of ``R``, ``x = [a1, a2]`` (Zhou et al.,
  "On the Continuity of Rotation Representations in Neural Networks", CVPR 2019). PyTorch3D uses
  rows instead; do not mix the two.

RoMa does the conversions it gets right at the edges (quaternions, the log map, Gram-Schmidt,
sampling). Two are written here: the exponential map (RoMa's switches to a first-order formula
below 1e-6 rad, whose gradient is off by O(angle), and uses ``1 - cos``, which loses float32
precision near 1e-3 rad) and the geodesic distance (RoMa's ``asin`` form has an infinite gradient
at pi and, in float32, a value error of about 1e-3 rad there).
"""

from __future__ import annotations

import roma
import torch

__all__ = [
    "normalize_quat",
    "random_rotmat",
    "rot6d_to_rotmat",
    "rotmat_geodesic_distance",
    "rotmat_to_rot6d",
    "rotmat_to_rotvec",
    "rotmat_to_unitquat",
    "rotvec_to_rotmat",
    "safe_norm",
    "skew",
    "unitquat_to_rotmat",
    "vee",
]


def safe_norm(x: torch.Tensor, dim: int = -1, keepdim: bool = False) -> torch.Tensor:
    """Euclidean norm whose value is exact and whose gradient is finite (zero) at ``x = 0``.

    ``torch.linalg.norm`` has an undefined derivative at the origin; here the square root is
    only taken where the squared norm is positive and the zero branch has a zero gradient.

    Args:
        x: (..., D, ...) tensor.
        dim: the dimension to reduce.
        keepdim: keep ``dim`` with size 1.

    Returns:
        (...) norms, same unit as ``x``.
    """
    sq = (x * x).sum(dim=dim, keepdim=keepdim)
    positive = sq > 0
    # sqrt only sees positive inputs, so neither branch produces a NaN gradient.
    return torch.where(positive, torch.sqrt(torch.where(positive, sq, torch.ones_like(sq))), 0.0)


def skew(r: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix ``[r]_x`` with ``[r]_x v = r x v``.

    Args:
        r: (..., 3) vectors.

    Returns:
        (..., 3, 3) skew-symmetric matrices.
    """
    x, y, z = r.unbind(-1)
    o = torch.zeros_like(x)
    # fmt: off
    return torch.stack([o, -z, y,
                        z, o, -x,
                        -y, x, o], dim=-1).unflatten(-1, (3, 3))
    # fmt: on


def vee(M: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`skew` on the skew part: ``vee(M) = (M32 - M23, M13 - M31, M21 - M12) / 2``.

    Args:
        M: (..., 3, 3) matrices.

    Returns:
        (..., 3) vectors; ``vee(skew(r)) == r``.
    """
    return 0.5 * torch.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]],
        dim=-1,
    )


def _series_threshold(dtype: torch.dtype) -> float:
    # Below this angle the Taylor series (truncated after theta^4) is exact to machine precision
    # in value and first derivative (RoMa's sinc threshold, 2 eps^(1/6): 0.14 f32, 5e-3 f64).
    return 2.0 * torch.finfo(dtype).eps ** (1.0 / 6.0)


def rotvec_to_rotmat(r: torch.Tensor) -> torch.Tensor:
    """Exponential map: rotation vector to rotation matrix (Rodrigues).

    ``R = I + a K + b K^2`` with ``K = [r]_x``, ``a = sin(t)/t``, ``b = (1 - cos t)/t^2``,
    ``t = |r|``. Below a dtype-dependent angle ``a`` and ``b`` are their Taylor series in ``t^2``
    (``1 - t^2/6 + t^4/120`` and ``1/2 - t^2/24 + t^4/720``), so value and gradient are finite
    and accurate at ``r = 0``; above it ``b = sinc(t/2)^2 / 2`` avoids the cancellation in
    ``1 - cos t``.

    Args:
        r: (..., 3) rotation vectors, angle ``|r|`` in radians (any magnitude).

    Returns:
        (..., 3, 3) rotation matrices.
    """
    if r.shape[-1:] != (3,):
        raise ValueError(f"rotvec_to_rotmat: expected r of shape (..., 3), got {tuple(r.shape)}")
    t2 = (r * r).sum(-1)  # (...)
    small = t2 < _series_threshold(r.dtype) ** 2
    t = torch.sqrt(torch.where(small, torch.ones_like(t2), t2))  # 1 where unused: no NaN grads
    half = 0.5 * t
    a = torch.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, 0.5 * (torch.sin(half) / half) ** 2)
    K = skew(r)  # (..., 3, 3)
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def rotmat_to_rotvec(R: torch.Tensor) -> torch.Tensor:
    """Logarithm map: rotation matrix to rotation vector with angle in [0, pi].

    Goes through the unit quaternion (Markley's method, then ``2 atan2(|v|, w) v/|v|`` with a
    series near 0), which stays accurate near 0 and near pi (``roma.rotmat_to_rotvec``). At
    exactly pi, ``r`` and ``-r`` are the same rotation and either may be returned.

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) rotation vectors, ``|r|`` in [0, pi] radians.
    """
    _check_rotmat(R, "rotmat_to_rotvec")
    return roma.rotmat_to_rotvec(R)


def normalize_quat(q: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Scale quaternions to unit norm: ``q / max(|q|, eps)``.

    Args:
        q: (..., 4) quaternions (any order; the norm does not care).
        eps: lower bound on the divisor, so a zero input gives a zero output, not NaN.

    Returns:
        (..., 4) unit quaternions (zero where ``|q| < eps``).
    """
    if q.shape[-1:] != (4,):
        raise ValueError(f"normalize_quat: expected q of shape (..., 4), got {tuple(q.shape)}")
    return q / torch.clamp_min(safe_norm(q, dim=-1, keepdim=True), eps)


def unitquat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion (XYZW) to rotation matrix.

    Args:
        q: (..., 4) unit quaternions ``(x, y, z, w)``, scalar last; ``q`` and ``-q`` give the
            same rotation. Not normalised here: call :func:`normalize_quat` on network outputs.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    if q.shape[-1:] != (4,):
        raise ValueError(f"unitquat_to_rotmat: expected q of shape (..., 4), got {tuple(q.shape)}")
    return roma.unitquat_to_rotmat(q)


def rotmat_to_unitquat(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrix to unit quaternion (XYZW), sign chosen so that ``w >= 0``.

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 4) unit quaternions ``(x, y, z, w)`` with ``w >= 0``.
    """
    _check_rotmat(R, "rotmat_to_unitquat")
    q = roma.rotmat_to_unitquat(R)
    sign = torch.where(q[..., 3:] < 0, -1.0, 1.0).to(q.dtype)
    return q * sign


def rot6d_to_rotmat(x: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Continuous 6D representation to rotation matrix (Zhou et al., CVPR 2019).

    ``x = [a1, a2]`` are two 3-vectors; Gram-Schmidt gives ``b1 = a1/|a1|``,
    ``b2 = normalise(a2 - (b1.a2) b1)``, ``b3 = b1 x b2``, and ``R = [b1 b2 b3]`` as
    **columns**.

    Args:
        x: (..., 6) with ``x[..., :3] = a1`` and ``x[..., 3:] = a2``.
        eps: lower bound on the norms divided by (collinear or zero input then gives a finite,
            non-rotation output instead of NaN).

    Returns:
        (..., 3, 3) rotation matrices.
    """
    if x.shape[-1:] != (6,):
        raise ValueError(f"rot6d_to_rotmat: expected x of shape (..., 6), got {tuple(x.shape)}")
    M = torch.stack([x[..., :3], x[..., 3:]], dim=-1)  # (..., 3, 2): a1, a2 as columns
    return roma.special_gramschmidt(M, epsilon=eps)


def rotmat_to_rot6d(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrix to the 6D representation: its first two columns, concatenated.

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 6) ``[R[:, 0], R[:, 1]]``; :func:`rot6d_to_rotmat` inverts it exactly.
    """
    _check_rotmat(R, "rotmat_to_rot6d")
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


def rotmat_geodesic_distance(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Angle of the rotation taking ``R2`` to ``R1``, in radians, in [0, pi].

    docs/design.md defines ``geodesic(R1, R2) = arccos((trace(R1 R2^T) - 1) / 2)``. With
    ``M = R1 R2^T`` of angle ``theta``, ``|vee(M - M^T)| = 2 sin(theta)`` (``vee`` of the skew
    part, doubled) and ``trace(M) - 1 = 2 cos(theta)``, so here

        theta = atan2(|vee(M - M^T)|, trace(M) - 1),

    which equals the arccos form but keeps value and gradient finite and accurate at 0 and pi
    (arccos has an infinite slope at +-1). The norm is :func:`safe_norm`, whose gradient at
    zero (theta exactly 0 or pi) is zero instead of NaN.

    Args:
        R1: (..., 3, 3) rotation matrices.
        R2: (..., 3, 3) rotation matrices (broadcast against ``R1``).

    Returns:
        (...) angles in radians.
    """
    _check_rotmat(R1, "rotmat_geodesic_distance (R1)")
    _check_rotmat(R2, "rotmat_geodesic_distance (R2)")
    M = R1 @ R2.mT  # (..., 3, 3)
    sin2 = safe_norm(2.0 * vee(M), dim=-1)  # 2 sin(theta) >= 0
    cos2 = M.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0  # 2 cos(theta)
    return torch.atan2(sin2, cos2)


def random_rotmat(
    n: int | tuple[int, ...],
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Rotations drawn uniformly (Haar measure) on SO(3), via Shoemake's unit quaternions.

    Args:
        n: batch size, or a batch shape tuple.
        generator: torch random generator for reproducible draws.
        dtype: floating point type of the result.
        device: device of the result.

    Returns:
        (n, 3, 3) (or ``(*n, 3, 3)``) rotation matrices.
    """
    return roma.random_rotmat(n, dtype=dtype, device=device, generator=generator)


def _check_rotmat(R: torch.Tensor, where: str) -> None:
    if R.shape[-2:] != (3, 3):
        raise ValueError(
            f"{where}: expected rotation matrices of shape (..., 3, 3), got {tuple(R.shape)}"
        )
