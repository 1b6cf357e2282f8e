"""ADS of many instances of one model, compiled and parallel over instances."""

from __future__ import annotations

import math

import numpy as np

from cloudpose.kernels.backend import configure_threads, njit, prange
from cloudpose.kernels.graph import NNIndex, _nearest_from
from cloudpose.kernels.kdtree import _STACK, _d2

__all__ = ["adds_mean"]


@njit(cache=True, parallel=True)
def _adds_kernel(P, box, left, right, start, end, nbr, nbr_d2, W, n_walk):
    """ADS per instance with the neighbour lists (models without a Delaunay graph)."""
    M = W.shape[0]
    n = P.shape[0]
    out = np.empty(M)
    for m in prange(M):
        stack = np.empty(_STACK, np.int64)
        stack_d2 = np.empty(_STACK)
        a00, a01, a02, b0 = W[m, 0, 0], W[m, 0, 1], W[m, 0, 2], W[m, 0, 3]
        a10, a11, a12, b1 = W[m, 1, 0], W[m, 1, 1], W[m, 1, 2], W[m, 1, 3]
        a20, a21, a22, b2 = W[m, 2, 0], W[m, 2, 1], W[m, 2, 2], W[m, 2, 3]
        total = 0.0
        prev = 0
        for i in range(n):
            px, py, pz = P[i, 0], P[i, 1], P[i, 2]
            x = a00 * px + a01 * py + a02 * pz + b0
            y = a10 * px + a11 * py + a12 * pz + b1
            z = a20 * px + a21 * py + a22 * pz + b2
            # Start from the point's own model point (the answer for a correct estimate) or
            # the previous point's neighbour (stored order is spatially local).
            c = i if _d2(P, i, x, y, z) <= _d2(P, prev, x, y, z) else prev
            best, prev = _nearest_from(
                P,
                box,
                left,
                right,
                start,
                end,
                nbr,
                nbr_d2,
                n_walk,
                x,
                y,
                z,
                c,
                np.inf,
                stack,
                stack_d2,
            )
            total += math.sqrt(best)
        out[m] = total / n
    return out


@njit(cache=True, parallel=True)
def _adds_graph_kernel(P, adj_ptr, adj, W):
    """``_adds_kernel`` for a model with a Delaunay graph, written out flat."""
    M = W.shape[0]
    n = P.shape[0]
    out = np.empty(M)
    for m in prange(M):
        a00, a01, a02, b0 = W[m, 0, 0], W[m, 0, 1], W[m, 0, 2], W[m, 0, 3]
        a10, a11, a12, b1 = W[m, 1, 0], W[m, 1, 1], W[m, 1, 2], W[m, 1, 3]
        a20, a21, a22, b2 = W[m, 2, 0], W[m, 2, 1], W[m, 2, 2], W[m, 2, 3]
        total = 0.0
        prev = 0
        for i in range(n):
            px, py, pz = P[i, 0], P[i, 1], P[i, 2]
            x = a00 * px + a01 * py + a02 * pz + b0
            y = a10 * px + a11 * py + a12 * pz + b1
            z = a20 * px + a21 * py + a22 * pz + b2
            c = i
            best = _d2(P, i, x, y, z)
            d2 = _d2(P, prev, x, y, z)
            if d2 < best:
                best, c = d2, prev
            while True:  # downhill over the Delaunay graph: ends in q's Voronoi cell
                cc = c
                for j in range(adj_ptr[c], adj_ptr[c + 1]):
                    q = adj[j]
                    d2 = _d2(P, q, x, y, z)
                    if d2 < best:
                        best, cc = d2, q
                if cc == c:
                    break
                c = cc
            total += math.sqrt(best)
            prev = c
        out[m] = total / n
    return out


def adds_mean(index: NNIndex, W: np.ndarray, n_walk: int = 8) -> np.ndarray:
    """ADS of M instances of one model: mean over model points y of min over model points x of
    ``|A y + b - x|``, with ``W[m] = [A | b]`` mapping the ground-truth model frame into the
    estimate's (metrics.adds_distance builds W).

    Each nearest neighbour is exact (``_nearest_from``: a walk over the neighbour lists, a
    certificate, a bounded k-d tree search where the certificate fails). Instances run in
    parallel on numba's threads.

    Args:
        index: ``build_nn_index`` of the model points, metres.
        W: (M, 3, 4) affine maps.
        n_walk: neighbours tried per step of the walk.

    Returns:
        (M,) ADS in metres.
    """
    configure_threads()
    W = np.ascontiguousarray(W, dtype=np.float64)
    t = index.tree
    if len(index.adj_ptr):
        return _adds_graph_kernel(t.points, index.adj_ptr, index.adj, W)
    return _adds_kernel(t.points, *t[2:], index.nbr, index.nbr_d2, W, int(n_walk))
