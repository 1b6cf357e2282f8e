"""Rigid-motion math in numpy: Umeyama's least-squares alignment (no scale), and the angle
between two rotations.

One numpy implementation, written on the correspondences' homogeneous moment matrix so that
ICP can accumulate the moments in one pass; ``umeyama_rigid`` forms the moments of two point
lists and calls it. The compiled ICP loop has its twin in numba
(``cloudpose.kernels.icp._umeyama_moments``, kept apart: the numpy ICP twin in refine.py and
the compiled loop each keep their own rounding); tests compare both with scipy's
``Rotation.align_vectors`` and with each other on every branch (tests/test_refine.py).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "correspondence_moments",
    "rotation_error_deg",
    "umeyama_from_moments",
    "umeyama_rigid",
]


def correspondence_moments(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(4, 4) moment matrix ``sum [d, 1]^T [s, 1]`` of corresponding points (see
    :func:`umeyama_from_moments`).

    Args:
        src, dst: (n, 3) corresponding points.
    """
    n = len(src)
    return np.c_[dst, np.ones(n)].T @ np.c_[src, np.ones(n)]


def umeyama_from_moments(S: np.ndarray) -> np.ndarray:
    """Umeyama (1991, no scale) from the homogeneous moment matrix of the correspondences.

    Eigen's ``umeyama(src, dst, false)``, which Open3D's point-to-point estimation calls: the
    SVD of the cross-covariance, with the weakest singular direction flipped when
    det(U) det(V) < 0 so the result is a rotation.

    Args:
        S: (4, 4) sum over pairs of [d, 1]^T [s, 1]: S[:3, :3] = sum d s^T, S[:3, 3] = sum d,
            S[3, :3] = sum s, S[3, 3] = n.

    Returns:
        (4, 4) rigid transform taking s onto d; the identity when n = 0 (Open3D's behaviour)
        and a pure translation when n < 3 (one or two pairs fix no rotation).
    """
    T = np.eye(4)
    n = S[3, 3]
    if n == 0:
        return T
    mu_d = S[:3, 3] / n
    mu_s = S[3, :3] / n
    if n < 3:
        T[:3, 3] = mu_d - mu_s
        return T
    # sum (d - mu_d)(s - mu_s)^T from raw moments: coordinates centred near the origin (ICP's
    # model frame) lose no accuracy that matters (agrees with Eigen to ~1e-15)
    sigma = S[:3, :3] - n * np.outer(mu_d, mu_s)
    U, _, Vt = np.linalg.svd(sigma)
    R = U @ Vt
    if np.linalg.det(R) < 0:  # det(U) det(V) < 0: flip the weakest direction (Eigen's umeyama)
        R -= 2.0 * np.outer(U[:, 2], Vt[2])
    T[:3, :3] = R
    T[:3, 3] = mu_d - R @ mu_s
    return T


def umeyama_rigid(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid motion taking ``src`` onto ``dst`` (:func:`umeyama_from_moments`).

    Args:
        src: (n, 3) points, n >= 3.
        dst: (n, 3) corresponding points.

    Returns:
        R (3, 3) and t (3,) with ``dst ~ src @ R.T + t``.
    """
    src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
    # centre first: the moment form is exact for centred coordinates, whatever the offset
    c_s, c_d = src.mean(axis=0), dst.mean(axis=0)
    T = umeyama_from_moments(correspondence_moments(src - c_s, dst - c_d))
    R = T[:3, :3]
    return R, c_d + T[:3, 3] - R @ c_s


def rotation_error_deg(R_gt: np.ndarray, R_est: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotations, degrees.

    Computed as atan2(|skew part|, (trace - 1) / 2) of R_gt^T R_est, accurate at 0 and at 180
    degrees where arccos of the trace is not.

    Args:
        R_gt: (..., 3, 3) rotations.
        R_est: (..., 3, 3) rotations.

    Returns:
        (...) angles in [0, 180] degrees.
    """
    R_gt = np.asarray(R_gt, dtype=np.float64)
    R_est = np.asarray(R_est, dtype=np.float64)
    if R_gt.shape[-2:] != (3, 3) or R_est.shape[-2:] != (3, 3):
        raise ValueError(
            f"R_gt, R_est: expected shape (..., 3, 3), got {R_gt.shape}, {R_est.shape}"
        )
    Rr = np.swapaxes(R_gt, -1, -2) @ R_est  # (..., 3, 3)
    v = np.stack(
        [
            Rr[..., 2, 1] - Rr[..., 1, 2],
            Rr[..., 0, 2] - Rr[..., 2, 0],
            Rr[..., 1, 0] - Rr[..., 0, 1],
        ],
        axis=-1,
    )  # 2 sin(theta) * axis
    sin = 0.5 * np.linalg.norm(v, axis=-1)
    cos = 0.5 * (np.trace(Rr, axis1=-2, axis2=-1) - 1.0)
    return np.degrees(np.arctan2(sin, cos))
