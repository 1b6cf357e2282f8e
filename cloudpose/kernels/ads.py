"""ADS of many instances of one model, compiled and parallel over instances."""

from __future__ import annotations

import math

import numpy as np

from cloudpose.kernels.backend import configure_threads, njit, prange
from cloudpose.kernels.graph import NNIndex, _delaunay_walk, _nearest_from
from cloudpose.kernels.icp import _affine_apply, _affine_rows
from cloudpose.kernels.kdtree import _STACK, _d2

__all__ = ["adds_mean"]


@njit(cache=True, parallel=True)
def _adds_kernel(tree, adj_ptr, adj, adj_len, nbr, nbr_d2, W, n_walk):
    """ADS per instance: each mapped point's nearest model point over the Delaunay graph where
    the model has one (adj_ptr not empty), else over the neighbour lists."""
    P = tree.points
    graph = adj_ptr.shape[0] > 0
    M = W.shape[0]
    n = P.shape[0]
    out = np.empty(M)
    for m in prange(M):
        stack = np.empty(_STACK, np.int64)
        stack_d2 = np.empty(_STACK)
        A = _affine_rows(W[m])
        total = 0.0
        prev = 0
        for i in range(n):
            x, y, z = _affine_apply(A, P[i, 0], P[i, 1], P[i, 2])
            # Start from the point's own model point (the answer for a correct estimate) or
            # the previous point's neighbour (stored order is spatially local).
            best, c = _d2(P, i, x, y, z), i
            d2 = _d2(P, prev, x, y, z)
            if d2 < best:
                best, c = d2, prev
            if graph:
                best, prev, _ = _delaunay_walk(P, adj_ptr, adj, adj_len, x, y, z, c, best, False)
            else:
                best, prev = _nearest_from(
                    tree, nbr, nbr_d2, n_walk, x, y, z, c, np.inf, stack, stack_d2
                )
            total += math.sqrt(best)
        out[m] = total / n
    return out


def adds_mean(index: NNIndex, W: np.ndarray, n_walk: int = 8) -> np.ndarray:
    """ADS of M instances of one model: mean over model points y of min over model points x of
    ``|A y + b - x|``, with ``W[m] = [A | b]`` mapping the ground-truth model frame into the
    estimate's (metrics.adds_distance builds W).

    Each nearest neighbour is exact: a downhill walk over the Delaunay graph from the point's
    own model point or the previous point's neighbour (``_delaunay_walk``), or where the model
    has no graph, a walk over the neighbour lists, a certificate, and a bounded k-d tree search
    where the certificate fails (``_nearest_from``). Instances run in parallel on numba's
    threads.

    Args:
        index: ``build_nn_index`` of the model points, metres.
        W: (M, 3, 4) affine maps.
        n_walk: neighbours tried per step of the walk over the lists.

    Returns:
        (M,) ADS in metres.
    """
    configure_threads()
    W = np.ascontiguousarray(W, dtype=np.float64)
    return _adds_kernel(
        index.tree, index.adj_ptr, index.adj, index.adj_len, index.nbr, index.nbr_d2, W, int(n_walk)
    )
