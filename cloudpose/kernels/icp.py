"""The paper's ICP loop in the model frame, compiled (refine.py holds the numpy twin)."""

from __future__ import annotations

import math

import numpy as np

from cloudpose.kernels.backend import njit
from cloudpose.kernels.graph import NNIndex, _delaunay_walk, _nearest_from
from cloudpose.kernels.kdtree import _STACK, _d2, _nearest

__all__ = ["icp_model_frame"]


@njit(cache=True)
def _umeyama_moments(S):
    """Rigid transform from correspondence moments: geometry.rigid.umeyama_from_moments compiled."""
    T = np.eye(4)
    n = S[3, 3]
    if n == 0:
        return T
    mu_d = S[:3, 3] / n
    mu_s = S[3, :3] / n
    if n < 3:
        T[:3, 3] = mu_d - mu_s
        return T
    sigma = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            sigma[i, j] = S[i, j] - n * mu_d[i] * mu_s[j]
    U, _, Vt = np.linalg.svd(sigma)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        for i in range(3):
            for j in range(3):
                R[i, j] -= 2.0 * U[i, 2] * Vt[2, j]
    T[:3, :3] = R
    for i in range(3):
        T[i, 3] = mu_d[i] - (R[i, 0] * mu_s[0] + R[i, 1] * mu_s[1] + R[i, 2] * mu_s[2])
    return T


@njit(cache=True, inline="always")
def _affine_rows(T):
    """The first three rows of an affine map T, (3, 4) or (4, 4), as twelve scalars, row by
    row (held in registers through a loop over points)."""
    return (
        T[0, 0], T[0, 1], T[0, 2], T[0, 3],
        T[1, 0], T[1, 1], T[1, 2], T[1, 3],
        T[2, 0], T[2, 1], T[2, 2], T[2, 3],
    )  # fmt: skip


@njit(cache=True, inline="always")
def _affine_apply(A, x, y, z):
    """``T @ (x, y, z, 1)`` for ``A = _affine_rows(T)``."""
    a00, a01, a02, b0, a10, a11, a12, b1, a20, a21, a22, b2 = A
    return (
        a00 * x + a01 * y + a02 * z + b0,
        a10 * x + a11 * y + a12 * z + b1,
        a20 * x + a21 * y + a22 * z + b2,
    )


@njit(cache=True)
def _icp_kernel(tree, adj_ptr, adj, adj_len, nbr, nbr_d2, cur, radii):
    """The ICP loop.

    ``nn[k]`` is point k's nearest model point when last searched (-1: none yet, or none
    within the radius on the lists); a point without one gets a bounded k-d tree search.
    Where the model has a Delaunay graph (adj_ptr not empty), ``nn[k]`` is exact at any
    distance, ``slack[k]`` its distance then to the boundary of that point's Voronoi cell (the
    nearest bisector plane with a Delaunay neighbour), ``moved[k]`` how far it has moved since:
    while it has moved less than the slack its nearest point cannot have changed, so no search
    is needed (late ICP iterations move points by micrometres); otherwise a Delaunay walk from
    ``nn[k]``. Without a graph, a search over the neighbour lists from ``nn[k]``. The moments
    are sixteen scalars, so they stay in registers through the loop over points.
    """
    P = tree.points
    graph = adj_ptr.shape[0] > 0
    N = cur.shape[0]
    n_it = radii.shape[0]
    T_acc = np.eye(4)
    stack = np.empty(_STACK, np.int64)
    stack_d2 = np.empty(_STACK)
    S = np.empty((4, 4))
    nn = np.full(N, -1, np.int64)
    slack = np.zeros(N)
    moved = np.zeros(N)
    for it in range(n_it + 1):  # the last pass only scores the final pose
        r2 = radii[min(it, n_it - 1)] ** 2
        s00 = s01 = s02 = s03 = s10 = s11 = s12 = s13 = 0.0
        s20 = s21 = s22 = s23 = s30 = s31 = s32 = s33 = 0.0
        sum_d2 = 0.0
        for k in range(N):
            x, y, z = cur[k, 0], cur[k, 1], cur[k, 2]
            j = nn[k]
            if j < 0:  # none yet: a bounded k-d tree search
                d2, j = _nearest(tree, x, y, z, r2, -1, stack, stack_d2)
                if j < 0:
                    continue
                nn[k] = j
            elif not graph:  # the lists, from the last match (the points moved little)
                d2, j = _nearest_from(tree, nbr, nbr_d2, 8, x, y, z, j, r2, stack, stack_d2)
                nn[k] = j
            if graph:
                d2 = _d2(P, j, x, y, z)
                if moved[k] >= slack[k]:  # it may have left j's Voronoi cell
                    d2, j, sl = _delaunay_walk(P, adj_ptr, adj, adj_len, x, y, z, j, d2, True)
                    nn[k] = j
                    moved[k] = 0.0
                    slack[k] = sl * (1.0 - 1e-9) - 1e-13 if sl < np.inf else 0.0
            if d2 < r2:
                mx, my, mz = P[j, 0], P[j, 1], P[j, 2]
                s00 += mx * x
                s01 += mx * y
                s02 += mx * z
                s03 += mx
                s10 += my * x
                s11 += my * y
                s12 += my * z
                s13 += my
                s20 += mz * x
                s21 += mz * y
                s22 += mz * z
                s23 += mz
                s30 += x
                s31 += y
                s32 += z
                s33 += 1.0
                sum_d2 += d2
        if it == n_it:
            return T_acc, int(s33), sum_d2
        if it == 0 and s33 == 0:
            return T_acc, -1, 0.0
        S[0, 0], S[0, 1], S[0, 2], S[0, 3] = s00, s01, s02, s03
        S[1, 0], S[1, 1], S[1, 2], S[1, 3] = s10, s11, s12, s13
        S[2, 0], S[2, 1], S[2, 2], S[2, 3] = s20, s21, s22, s23
        S[3, 0], S[3, 1], S[3, 2], S[3, 3] = s30, s31, s32, s33
        T = _umeyama_moments(S)
        A = _affine_rows(T)
        for k in range(N):
            x, y, z = cur[k, 0], cur[k, 1], cur[k, 2]
            nx, ny, nz = _affine_apply(A, x, y, z)
            if graph:
                moved[k] += math.sqrt((nx - x) ** 2 + (ny - y) ** 2 + (nz - z) ** 2)
            cur[k, 0], cur[k, 1], cur[k, 2] = nx, ny, nz
        T_acc = T @ T_acc
    return T_acc, 0, 0.0  # not reached


def icp_model_frame(
    index: NNIndex, observed_model_frame: np.ndarray, radii: np.ndarray
) -> tuple[np.ndarray, int, float]:
    """The ICP loop of refine._icp_model_frame, compiled.

    Each correspondence is the exact nearest model point within the radius: a bounded k-d
    tree search for a point without one yet, then a walk from its previous nearest point:
    over the Delaunay graph, skipped while the point cannot have left that point's Voronoi
    cell (``_delaunay_walk``), or over the neighbour lists where the model has no graph
    (``_nearest_from``).

    Args:
        index: ``build_nn_index`` of the model points, metres.
        observed_model_frame: (N, 3) observed points mapped by the inverse estimate, metres.
        radii: (I,) correspondence radius of each iteration, metres.

    Returns:
        T_acc (4, 4), the accumulated correction (model-frame observed -> model); the inlier
        count after the last update within the last radius (-1: no correspondence in the first
        iteration, nothing done); and the sum of those inliers' squared distances (m^2).
    """
    cur = np.array(observed_model_frame, dtype=np.float64, order="C", copy=True)
    radii = np.ascontiguousarray(radii, dtype=np.float64)
    return _icp_kernel(
        index.tree, index.adj_ptr, index.adj, index.adj_len, index.nbr, index.nbr_d2, cur, radii
    )
