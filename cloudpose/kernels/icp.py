"""The paper's ICP loop in the model frame, compiled (refine.py holds the numpy twin)."""

from __future__ import annotations

import math

import numpy as np

from cloudpose.kernels.backend import njit
from cloudpose.kernels.graph import NNIndex, _nearest_from
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
def _match(P, box, left, right, start, end, nbr, nbr_d2, x, y, z, prev, r2, stack, stack_d2):
    """Nearest model point within the radius (squared r2), with the neighbour lists: from last
    iteration's match where there was one (the points moved little), else a bounded k-d tree
    search."""
    if prev >= 0:
        return _nearest_from(
            P, box, left, right, start, end, nbr, nbr_d2, 8, x, y, z, prev, r2, stack, stack_d2
        )
    return _nearest(P, box, left, right, start, end, x, y, z, r2, -1, stack, stack_d2)


@njit(cache=True, inline="always")
def _delaunay_walk(P, adj_ptr, adj, adj_len, x, y, z, c):
    """Exact nearest point by a downhill walk over the Delaunay graph from c.

    Returns its squared distance, its stored index, and how far the query may move before it
    can leave the point's Voronoi cell: the distance to the nearest bisector plane with a
    Delaunay neighbour z, ``(|q - z|^2 - |q - c|^2) / (2 |z - c|)`` (metres).
    """
    best = _d2(P, c, x, y, z)
    while True:
        cc = c
        b0 = best
        slack = np.inf  # valid when this step finds nothing nearer (b0 is then c's distance)
        for j in range(adj_ptr[c], adj_ptr[c + 1]):
            q = adj[j]
            d2 = _d2(P, q, x, y, z)
            if adj_len[j] > 0:  # a duplicate of c is as near as c wherever the query goes
                slack = min(slack, (d2 - b0) / (2.0 * adj_len[j]))
            if d2 < best:
                best, cc = d2, q
        if cc == c:
            return best, c, slack
        c = cc


@njit(cache=True)
def _icp_graph_kernel(P, box, left, right, start, end, adj_ptr, adj, adj_len, cur, radii):
    """The ICP loop for a model with a Delaunay graph.

    ``nn[k]`` is point k's exact nearest model point (any distance) when last searched,
    ``slack[k]`` its distance then to the boundary of that point's Voronoi cell (the nearest
    bisector plane with a Delaunay neighbour), ``moved[k]`` how far it has moved since. While
    it has moved less than the slack its nearest point cannot have changed, so no search is
    needed (late ICP iterations move points by micrometres); otherwise a Delaunay walk from
    ``nn[k]``, or a bounded k-d tree search for a point with no neighbour yet. Written as one
    flat loop body: with the searches behind helper layers it ran 2x slower.
    """
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
            if j >= 0 and moved[k] < slack[k]:  # still in j's Voronoi cell: j is nearest
                d2 = _d2(P, j, x, y, z)
            else:
                if j < 0:
                    d2, j = _nearest(
                        P, box, left, right, start, end, x, y, z, r2, -1, stack, stack_d2
                    )
                    if j < 0:
                        continue
                d2, j, sl = _delaunay_walk(P, adj_ptr, adj, adj_len, x, y, z, j)
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
        for k in range(N):
            x, y, z = cur[k, 0], cur[k, 1], cur[k, 2]
            nx = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
            ny = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
            nz = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
            moved[k] += math.sqrt((nx - x) ** 2 + (ny - y) ** 2 + (nz - z) ** 2)
            cur[k, 0], cur[k, 1], cur[k, 2] = nx, ny, nz
        T_acc = T @ T_acc
    return T_acc, 0, 0.0  # not reached


@njit(cache=True)
def _icp_kernel(P, box, left, right, start, end, nbr, nbr_d2, cur, radii):
    """The ICP loop with the neighbour lists (models without a Delaunay graph): each point's
    correspondence searched from its previous match (``_match``)."""
    N = cur.shape[0]
    n_it = radii.shape[0]
    T_acc = np.eye(4)
    stack = np.empty(_STACK, np.int64)
    stack_d2 = np.empty(_STACK)
    S = np.empty((4, 4))
    match = np.full(N, -1, np.int64)
    for it in range(n_it + 1):  # the last pass only scores the final pose
        r2 = radii[min(it, n_it - 1)] ** 2
        S[:] = 0.0
        sum_d2 = 0.0
        for k in range(N):
            x, y, z = cur[k, 0], cur[k, 1], cur[k, 2]
            d2, j = _match(
                P,
                box,
                left,
                right,
                start,
                end,
                nbr,
                nbr_d2,
                x,
                y,
                z,
                match[k],
                r2,
                stack,
                stack_d2,
            )
            match[k] = j
            if j >= 0:
                m = (P[j, 0], P[j, 1], P[j, 2], 1.0)
                c = (x, y, z, 1.0)
                for a in range(4):
                    for b in range(4):
                        S[a, b] += m[a] * c[b]
                sum_d2 += d2
        if it == n_it:
            return T_acc, int(S[3, 3]), sum_d2
        if it == 0 and S[3, 3] == 0:
            return T_acc, -1, 0.0
        T = _umeyama_moments(S)
        for k in range(N):
            x, y, z = cur[k, 0], cur[k, 1], cur[k, 2]
            for a in range(3):
                cur[k, a] = T[a, 0] * x + T[a, 1] * y + T[a, 2] * z + T[a, 3]
        T_acc = T @ T_acc
    return T_acc, 0, 0.0  # not reached


def icp_model_frame(
    index: NNIndex, observed_model_frame: np.ndarray, radii: np.ndarray
) -> tuple[np.ndarray, int, float]:
    """The ICP loop of refine._icp_model_frame, compiled.

    Each correspondence is the exact nearest model point within the radius: a bounded k-d
    tree search for a point without one yet, then a Delaunay walk from its previous nearest
    point, skipped while the point has moved less than half the gap to its second nearest
    (``_match`` and ``_delaunay_walk``).

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
    t = index.tree
    if len(index.adj_ptr):
        return _icp_graph_kernel(
            t.points, *t[2:], index.adj_ptr, index.adj, index.adj_len, cur, radii
        )
    return _icp_kernel(t.points, *t[2:], index.nbr, index.nbr_d2, cur, radii)
