"""A model's k-d tree with its neighbour graph, and the exact nearest-neighbour search that
starts from a given point (for the ADS and ICP kernels).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from pykdtree.kdtree import KDTree as _PyKDTree

from cloudpose.kernels.backend import njit
from cloudpose.kernels.kdtree import KDTree, _d2, _nearest_call, build_kdtree

__all__ = ["NNIndex", "build_nn_index"]


class NNIndex(NamedTuple):
    """A point set's k-d tree and neighbour graph (for ``adds_mean`` and ``icp_model_frame``).

    The graph is the Delaunay triangulation's where it exists (any 3-D set of 5 or more points
    not all on a plane): q's nearest point is the point none of whose Delaunay neighbours is
    nearer (its Voronoi cell holds q), so a downhill walk ends at the exact answer. Otherwise
    (flat or tiny sets) each point's L nearest points, with a certificate and a k-d tree
    fallback (see ``_nearest_from``).

    Attributes:
        tree: float64 ``build_kdtree`` of the points.
        adj_ptr, adj: the Delaunay graph in CSR form over stored positions: the neighbours of
            stored point p are ``adj[adj_ptr[p]:adj_ptr[p + 1]]`` (int64, int32); empty arrays
            when there is no triangulation.
        adj_len: (E,) float64 length of each graph edge, metres.
        nbr: (P, L) int32 stored positions of each stored point's L nearest other points,
            nearest first ((P, 0) when the Delaunay graph is used).
        nbr_d2: (P, L) float32 their squared distances rounded down, ascending (the last one
            inf when the list holds every other point). Compact, so the lists stay in cache.
    """

    tree: KDTree
    adj_ptr: np.ndarray
    adj: np.ndarray
    adj_len: np.ndarray
    nbr: np.ndarray
    nbr_d2: np.ndarray


def _delaunay_graph(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Delaunay neighbours of every point (CSR) and the edge lengths, or None where Qhull
    cannot triangulate.

    Qhull leaves out points that coincide (to its precision) with a vertex; such a point gets
    its vertex's neighbours and the vertex, and is added to the vertex's neighbours, so a walk
    reaches it and can leave it.
    """
    if len(P) < 5:
        return None
    try:
        from scipy.spatial import Delaunay, QhullError

        tri = Delaunay(P)
    except (QhullError, ValueError):
        return None
    ptr, ind = tri.vertex_neighbor_vertices
    nbrs = [ind[ptr[i] : ptr[i + 1]] for i in range(len(P))]
    if len(tri.coplanar):
        extra: dict[int, list[int]] = {}
        for point, _facet, vertex in tri.coplanar.tolist():
            extra.setdefault(vertex, []).append(point)
            nbrs[point] = np.append(nbrs[vertex], vertex)
        for vertex, pts in extra.items():
            nbrs[vertex] = np.append(nbrs[vertex], pts)
        nbrs = [np.unique(a) for a in nbrs]
    if any(len(a) == 0 for a in nbrs):
        return None
    adj_ptr = np.zeros(len(P) + 1, np.int64)
    adj_ptr[1:] = np.cumsum([len(a) for a in nbrs])
    adj = np.concatenate(nbrs).astype(np.int32)
    rows = np.repeat(np.arange(len(P)), np.diff(adj_ptr))
    return adj_ptr, adj, np.linalg.norm(P[adj] - P[rows], axis=1)


def build_nn_index(points: np.ndarray, n_neighbours: int = 32, leaf_size: int = 16) -> NNIndex:
    """The k-d tree and neighbour graph of a point set (a model), see :class:`NNIndex`.

    Args:
        points: (P, 3) points, metres.
        n_neighbours: neighbours listed per point where there is no Delaunay graph.
        leaf_size: most points per k-d tree leaf.
    """
    tree = build_kdtree(points, leaf_size)
    P = len(tree.points)
    graph = _delaunay_graph(tree.points)
    if graph is not None:
        return NNIndex(tree, *graph, np.zeros((P, 0), np.int32), np.zeros((P, 0), np.float32))
    no_graph = (np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0))
    if P == 1:
        return NNIndex(
            tree, *no_graph, np.zeros((1, 1), np.int32), np.full((1, 1), np.inf, np.float32)
        )
    L = max(1, min(int(n_neighbours), P - 1))
    d, i = _PyKDTree(tree.points).query(tree.points, k=L + 1)
    d, i = d.reshape(P, L + 1), i.reshape(P, L + 1).astype(np.int64)
    # Row p lists p itself (distance 0), first unless duplicates tie with it: drop that entry,
    # or the last one if p is not listed (several duplicates).
    keep = i != np.arange(P)[:, None]
    keep[keep.all(axis=1), -1] = False
    nbr = i[keep].reshape(P, L).astype(np.int32)
    # float32, rounded down: a list then never claims more coverage than it has (the kernel
    # scans a little more, and falls back to the tree a little sooner, than exact values would)
    d2 = d[keep].reshape(P, L).astype(np.float64) ** 2
    nbr_d2 = d2.astype(np.float32)
    up = nbr_d2.astype(np.float64) > d2
    nbr_d2[up] = np.nextafter(nbr_d2[up], np.float32(0))
    if L == P - 1:  # every other point is listed: a list scan is always conclusive
        nbr_d2[:, -1] = np.inf
    return NNIndex(tree, *no_graph, np.ascontiguousarray(nbr), np.ascontiguousarray(nbr_d2))


@njit(cache=True, inline="always")
def _nearest_from(tree, nbr, nbr_d2, n_walk, x, y, z, c, bound_d2, stack, stack_d2):
    """Nearest stored point of ``tree`` with squared distance < bound_d2, searched from stored
    point c, with the neighbour lists ``nbr``, ``nbr_d2`` (models without a Delaunay graph):

    1. Walk downhill: move to the nearest of the current point's first ``n_walk`` neighbours
       while one is nearer to the query.
    2. Certificate: with c the end of the walk and d0 = |q - y_c|, any point nearer than
       d = sqrt(best) satisfies |z - y_c| < d0 + d, and c's list holds every point nearer to
       y_c than its last entry; scan the list up to that distance.
    3. Only where the list is too short, a k-d tree search bounded by the best so far.

    Returns (squared distance, stored index) or (bound_d2, -1) when none is that near.
    """
    P = tree.points
    best = _d2(P, c, x, y, z)
    n_walk = min(n_walk, nbr.shape[1])
    L = nbr.shape[1]
    for _ in range(P.shape[0]):
        cc = c
        for j in range(n_walk):
            q = nbr[c, j]
            d2 = _d2(P, q, x, y, z)
            if d2 < best:
                best, cc = d2, q
        if cc == c:
            break
        c = cc
    d0 = math.sqrt(best)
    if best < bound_d2:
        target, bi = best, c
    else:
        target, bi = bound_d2, -1
    s = d0 + math.sqrt(target)
    lim = s * s * (1.0 + 1e-9)
    j = n_walk  # the walk's last step tried the first n_walk neighbours of c: none nearer
    while j < L and nbr_d2[c, j] <= lim:
        q = nbr[c, j]
        d2 = _d2(P, q, x, y, z)
        if d2 < target:
            target, bi = d2, q
            s = d0 + math.sqrt(target)
            lim = s * s * (1.0 + 1e-9)
        j += 1
    if j == L and lim >= nbr_d2[c, L - 1]:
        target, bi = _nearest_call(tree, x, y, z, target, bi, stack, stack_d2)
    return target, bi


@njit(cache=True, inline="always")
def _delaunay_walk(P, adj_ptr, adj, adj_len, x, y, z, c, best, with_slack):
    """Exact nearest point by a downhill walk over the Delaunay graph from stored point c,
    whose squared distance to the query is ``best``.

    Returns its squared distance, its stored index, and (``with_slack``; else inf) how far the
    query may move before it can leave the point's Voronoi cell: the distance to the nearest
    bisector plane with a Delaunay neighbour z, ``(|q - z|^2 - |q - c|^2) / (2 |z - c|)``
    (metres). ``with_slack`` is a constant at each call site, so the compiler drops the unused
    branch.
    """
    while True:
        cc = c
        b0 = best
        slack = np.inf  # valid when this step finds nothing nearer (b0 is then c's distance)
        for j in range(adj_ptr[c], adj_ptr[c + 1]):
            q = adj[j]
            d2 = _d2(P, q, x, y, z)
            # a duplicate of c (edge length 0) is as near as c wherever the query goes
            if with_slack and adj_len[j] > 0:
                slack = min(slack, (d2 - b0) / (2.0 * adj_len[j]))
            if d2 < best:
                best, cc = d2, q
        if cc == c:
            return best, c, slack
        c = cc
