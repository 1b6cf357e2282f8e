"""Compiled (numba) kernels for the point-cloud hot loops: exact FPS, bounded nearest neighbours,
the ICP loop and ADS (issue 6).

Three hot loops of the pipeline do per-point work that numpy can only express as many small
calls, so they run here as compiled loops:

- ``fps_order``: exact farthest point sampling (data/segments.py). A k-d tree groups the points
  into buckets; after each pick, a subtree is skipped when no point in it can get closer to the
  new sample than it already is to an earlier one (its box is farther than the largest
  nearest-sample distance inside it). The distances are the same float32 expressions as the
  numpy loop and ties go to the lowest index, so the order is the same, index for index.
- ``icp_model_frame``: the paper's ICP schedule in the model frame (refine.py): per iteration,
  each observed point's nearest model point within the radius, the correspondence moments, and
  Umeyama's rotation. A point's first neighbour comes from a bounded k-d tree search; later
  ones from a walk over the model's Delaunay graph from its previous neighbour, skipped while
  the point cannot have left that neighbour's Voronoi cell.
- ``adds_mean``: ADS of many instances of one model (metrics.py): each ground-truth-posed point
  in the estimate's model frame, its nearest model point, by a downhill walk over the Delaunay
  graph from the point's own model point or the previous point's neighbour. A point whose
  Delaunay neighbours are all farther from the query than itself has the query in its Voronoi
  cell: the walk's end is the exact nearest point.

Every kernel has a slow twin elsewhere (numpy loop FPS, ten Open3D calls, per-instance KD-tree
ADS) with tests that they agree; callers fall back to their numpy/pykdtree paths where numba is
not installed (``HAVE_NUMBA``). Compiled code is cached on disk (``cache=True``), so only the
first run on a machine pays the compilation (a few seconds).

The k-d tree (``KDTree``): boxes split at the middle of their widest side (never empty sides),
leaves of at most ``leaf_size`` points, points stored in leaf order; each node keeps the
bounding box of its points, which a search uses as its lower bound. Where a model has no 3-D
Delaunay triangulation (flat or under 5 points), ``NNIndex`` holds each point's nearest points
instead and searches use a certificate with a k-d tree fallback (``_nearest_from``).
"""

from __future__ import annotations

import math
import os
from typing import NamedTuple

import numpy as np

try:  # numba is optional: callers keep their numpy / pykdtree paths without it
    import numba
    from numba import njit, prange

    # workqueue first: its idle threads sleep (OpenMP's spin), so a parallel kernel does not
    # slow down 10x when another process holds a core; and no warning about an old TBB
    numba.config.THREADING_LAYER_PRIORITY = ["workqueue", "omp", "tbb"]
    HAVE_NUMBA = not os.environ.get("CLOUDPOSE_NO_NUMBA")
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None
    HAVE_NUMBA = False

    def njit(*args, **kwargs):  # type: ignore[no-redef]
        if args and callable(args[0]):
            return args[0]
        return lambda f: f

    prange = range  # type: ignore[assignment]

__all__ = [
    "HAVE_NUMBA",
    "KDTree",
    "NNIndex",
    "adds_mean",
    "build_kdtree",
    "build_nn_index",
    "fps_order",
    "icp_model_frame",
    "nearest_bounded",
]

_MAX_DEPTH = 96  # deeper boxes become leaves (only for pathological, near-duplicate clusters)
_STACK = 2 * _MAX_DEPTH + 8


class KDTree(NamedTuple):
    """A k-d tree over P points (arrays only, so compiled code can take it apart).

    Attributes:
        points: (P, 3) the points in leaf order (float64 for searches, float32 for FPS).
        index: (P,) int64 original index of each stored point.
        box: (K, 6) float64 bounding box of each node's points, (lo xyz, hi xyz).
        left, right: (K,) int64 children (-1 for a leaf).
        start, end: (K,) int64 the node's points are ``points[start:end]``.
    """

    points: np.ndarray
    index: np.ndarray
    box: np.ndarray
    left: np.ndarray
    right: np.ndarray
    start: np.ndarray
    end: np.ndarray


@njit(cache=True)
def _build(X, leaf_size):
    """Builds in place: rows of X (N, 3) are reordered into leaf order; returns the node arrays
    and the original index of each row."""
    N = X.shape[0]
    order = np.arange(N)
    cap = 2 * N + 1
    box = np.empty((cap, 6))
    left = np.full(cap, -1, np.int64)
    right = np.full(cap, -1, np.int64)
    start = np.empty(cap, np.int64)
    end = np.empty(cap, np.int64)
    depth = np.empty(cap, np.int64)
    stack = np.empty(cap, np.int64)
    start[0], end[0], depth[0] = 0, N, 0
    n_nodes = 1
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        s, e = start[node], end[node]
        l0 = l1 = l2 = np.inf
        h0 = h1 = h2 = -np.inf
        for i in range(s, e):
            v0, v1, v2 = np.float64(X[i, 0]), np.float64(X[i, 1]), np.float64(X[i, 2])
            l0, h0 = min(l0, v0), max(h0, v0)
            l1, h1 = min(l1, v1), max(h1, v1)
            l2, h2 = min(l2, v2), max(h2, v2)
        box[node, 0], box[node, 1], box[node, 2] = l0, l1, l2
        box[node, 3], box[node, 4], box[node, 5] = h0, h1, h2
        if e - s <= leaf_size or depth[node] >= _MAX_DEPTH:
            continue
        dim, span = 0, h0 - l0
        if h1 - l1 > span:
            dim, span = 1, h1 - l1
        if h2 - l2 > span:
            dim, span = 2, h2 - l2
        if not span > 0:
            continue  # all points equal (or NaN): one leaf
        split = 0.5 * (box[node, dim] + box[node, dim + 3])
        i, j = s, e - 1
        while i <= j:
            if np.float64(X[i, dim]) < split:
                i += 1
            else:
                for d in range(3):
                    X[i, d], X[j, d] = X[j, d], X[i, d]
                order[i], order[j] = order[j], order[i]
                j -= 1
        if i == s or i == e:  # the midpoint rounded onto an end: split by count
            i = (s + e) // 2
        a, b = n_nodes, n_nodes + 1
        start[a], end[a], depth[a] = s, i, depth[node] + 1
        start[b], end[b], depth[b] = i, e, depth[node] + 1
        stack[sp], stack[sp + 1] = a, b
        sp += 2
        left[node], right[node] = a, b
        n_nodes += 2
    K = n_nodes
    return order, box[:K], left[:K], right[:K], start[:K], end[:K]


def build_kdtree(points: np.ndarray, leaf_size: int = 8, dtype=np.float64) -> KDTree:
    """A k-d tree over ``points`` (see the module docstring).

    Args:
        points: (P, 3) points, P >= 1.
        leaf_size: most points per leaf.
        dtype: dtype of the stored ``points`` (the boxes are float64 either way).

    Returns:
        The tree; ``tree.points[i] == points[tree.index[i]]``.
    """
    pts = np.array(points, dtype=dtype, order="C", copy=True)  # reordered in place
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"points: expected shape (P, 3) with P >= 1, got {pts.shape}")
    order, box, left, right, start, end = _build(pts, int(leaf_size))
    return KDTree(pts, order, box, left, right, start, end)


# ---------------------------------------------------------------------------------------------
# Bounded nearest neighbour


@njit(cache=True, inline="always")
def _box_d2(box, node, x, y, z):
    """Squared distance from (x, y, z) to a node's box (0 inside); branch-free."""
    vx = max(box[node, 0] - x, x - box[node, 3], 0.0)
    vy = max(box[node, 1] - y, y - box[node, 4], 0.0)
    vz = max(box[node, 2] - z, z - box[node, 5], 0.0)
    return vx * vx + vy * vy + vz * vz


@njit(cache=True, inline="always")
def _nearest(P, box, left, right, start, end, x, y, z, best_d2, best_i, stack, stack_d2):
    """Nearest stored point with squared distance < best_d2; else (best_d2, best_i) unchanged."""
    sp = 0
    stack[0] = 0
    stack_d2[0] = _box_d2(box, 0, x, y, z)
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if stack_d2[sp] >= best_d2:
            continue
        while left[node] >= 0:
            a = left[node]  # the right child is always a + 1
            da = _box_d2(box, a, x, y, z)
            db = _box_d2(box, a + 1, x, y, z)
            # nearer child next, farther one pushed if it may still hold a closer point;
            # written as selects so the compiler can avoid unpredictable branches
            swap = db < da
            near = a + 1 if swap else a
            far = a if swap else a + 1
            dn = db if swap else da
            df = da if swap else db
            stack[sp] = far
            stack_d2[sp] = df
            sp += 1 if df < best_d2 else 0
            if dn >= best_d2:
                node = -1
                break
            node = near
        if node < 0:
            continue
        for i in range(start[node], end[node]):
            dx = P[i, 0] - x
            dy = P[i, 1] - y
            dz = P[i, 2] - z
            d2 = dx * dx + dy * dy + dz * dz
            if d2 < best_d2:
                best_d2 = d2
                best_i = i
    return best_d2, best_i


@njit(cache=True)
def _nearest_call(P, box, left, right, start, end, x, y, z, best_d2, best_i, stack, stack_d2):
    """``_nearest`` as a real call: for rare fallbacks, where inlining its loops into a hot
    loop only costs registers."""
    return _nearest(P, box, left, right, start, end, x, y, z, best_d2, best_i, stack, stack_d2)


@njit(cache=True)
def _nearest_many(P, box, left, right, start, end, Q, bound_d2):
    n = Q.shape[0]
    d2 = np.empty(n)
    idx = np.empty(n, np.int64)
    stack = np.empty(_STACK, np.int64)
    stack_d2 = np.empty(_STACK)
    for k in range(n):
        d2[k], idx[k] = _nearest(
            P, box, left, right, start, end, Q[k, 0], Q[k, 1], Q[k, 2], bound_d2, -1,
            stack, stack_d2,
        )  # fmt: skip
    return d2, idx


def nearest_bounded(
    tree: KDTree, queries: np.ndarray, bound: float = math.inf
) -> tuple[np.ndarray, np.ndarray]:
    """Each query's nearest tree point closer than ``bound`` (the twin of pykdtree's query).

    Args:
        tree: a float64 ``build_kdtree``.
        queries: (Q, 3) points.
        bound: only points with distance < bound count, same unit as the points.

    Returns:
        Squared distances (Q,) (``bound**2`` where none) and original indices (Q,) (-1 where
        none).
    """
    Q = np.ascontiguousarray(queries, dtype=np.float64)
    d2, i = _nearest_many(*tree[0:1], *tree[2:], Q, float(bound) ** 2)
    found = i >= 0
    return d2, np.where(found, tree.index[np.maximum(i, 0)], -1)


# ---------------------------------------------------------------------------------------------
# Nearest neighbour from a starting point (neighbour lists + certificate)


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
    from pykdtree.kdtree import KDTree as _PyKDTree

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
def _d2(P, j, x, y, z):
    dx = P[j, 0] - x
    dy = P[j, 1] - y
    dz = P[j, 2] - z
    return dx * dx + dy * dy + dz * dz


@njit(cache=True, inline="always")
def _nearest_from(
    P, box, left, right, start, end, nbr, nbr_d2, n_walk, x, y, z, c, bound_d2, stack, stack_d2
):
    """Nearest stored point with squared distance < bound_d2, searched from stored point c,
    with the neighbour lists (models without a Delaunay graph):

    1. Walk downhill: move to the nearest of the current point's first ``n_walk`` neighbours
       while one is nearer to the query.
    2. Certificate: with c the end of the walk and d0 = |q - y_c|, any point nearer than
       d = sqrt(best) satisfies |z - y_c| < d0 + d, and c's list holds every point nearer to
       y_c than its last entry; scan the list up to that distance.
    3. Only where the list is too short, a k-d tree search bounded by the best so far.

    Returns (squared distance, stored index) or (bound_d2, -1) when none is that near.
    """
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
        target, bi = _nearest_call(
            P, box, left, right, start, end, x, y, z, target, bi, stack, stack_d2
        )
    return target, bi


# ---------------------------------------------------------------------------------------------
# ADS


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
                P, box, left, right, start, end, nbr, nbr_d2, n_walk, x, y, z, c, np.inf,
                stack, stack_d2,
            )  # fmt: skip
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
    W = np.ascontiguousarray(W, dtype=np.float64)
    t = index.tree
    if len(index.adj_ptr):
        return _adds_graph_kernel(t.points, index.adj_ptr, index.adj, W)
    return _adds_kernel(t.points, *t[2:], index.nbr, index.nbr_d2, W, int(n_walk))


# ---------------------------------------------------------------------------------------------
# ICP


@njit(cache=True)
def _umeyama_moments(S):
    """Rigid transform from correspondence moments; refine._umeyama_from_moments compiled."""
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
                P, box, left, right, start, end, nbr, nbr_d2, x, y, z, match[k], r2, stack,
                stack_d2,
            )  # fmt: skip
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
    (``_correspond``).

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


# ---------------------------------------------------------------------------------------------
# FPS


@njit(cache=True)
def _fps_kernel(P, index, box, left, right, start, end, k, first):
    """Exact FPS over the float32 points P (leaf order); ``first`` is a stored-order index."""
    n = P.shape[0]
    K = box.shape[0]
    near = np.full(n, np.inf, np.float32)
    node_max = np.full(K, np.inf, np.float32)  # largest nearest-sample distance^2 in the node
    node_arg = np.empty(K, np.int64)  # its stored position (highest original index on ties)
    # Initial maxima: every distance is inf; the argmax is the highest original index.
    for node in range(K - 1, -1, -1):
        if left[node] < 0:
            best = start[node]
            for i in range(start[node], end[node]):
                if index[i] > index[best]:
                    best = i
            node_arg[node] = best
        else:
            a, b = node_arg[left[node]], node_arg[right[node]]
            node_arg[node] = a if index[a] > index[b] else b
    out = np.empty(k, np.int64)
    visit = np.empty(K, np.int64)
    stack = np.empty(K, np.int64)
    cur = first
    for s in range(k):
        out[s] = index[cur]
        sx, sy, sz = P[cur, 0], P[cur, 1], P[cur, 2]
        xs, ys, zs = np.float64(sx), np.float64(sy), np.float64(sz)
        n_visit = 0
        sp = 0
        stack[0] = 0
        sp = 1
        while sp > 0:
            sp -= 1
            node = stack[sp]
            # Skip when every point of the box is farther from the new sample than the node's
            # largest nearest distance (margin 1e-6 >> float32 rounding of a squared distance).
            if _box_d2(box, node, xs, ys, zs) * (1.0 - 1e-6) > node_max[node]:
                continue
            if left[node] >= 0:
                visit[n_visit] = node
                n_visit += 1
                stack[sp] = left[node]
                stack[sp + 1] = right[node]
                sp += 2
                continue
            best_v = np.float32(-1.0)
            best = start[node]
            for i in range(start[node], end[node]):
                dx = P[i, 0] - sx
                dy = P[i, 1] - sy
                dz = P[i, 2] - sz
                d = dx * dx + dy * dy + dz * dz  # float32, the numpy loop's expression
                v = near[i]
                if d < v:
                    v = d
                    near[i] = d
                if v > best_v or (v == best_v and index[i] > index[best]):
                    best_v = v
                    best = i
            node_max[node] = best_v
            node_arg[node] = best
        for t in range(n_visit - 1, -1, -1):  # children before parents
            node = visit[t]
            a, b = left[node], right[node]
            va, vb = node_max[a], node_max[b]
            if vb > va or (vb == va and index[node_arg[b]] > index[node_arg[a]]):
                node_max[node], node_arg[node] = vb, node_arg[b]
            else:
                node_max[node], node_arg[node] = va, node_arg[a]
        cur = node_arg[0]
    return out


def fps_order(points: np.ndarray, k: int, start: int, leaf_size: int = 128) -> np.ndarray:
    """Exact farthest point sampling: the numpy loop's order, index for index.

    Args:
        points: (N, 3) float32 points, finite.
        k: samples, 1 <= k <= N.
        start: index of the first sample.
        leaf_size: points per bucket.

    Returns:
        (k,) int64 indices into ``points``.
    """
    n = len(points)
    if not 1 <= k <= n or not 0 <= start < n:
        raise ValueError(
            f"fps_order: need 1 <= k <= N and 0 <= start < N, got {k=}, {start=}, N={n}"
        )
    tree = build_kdtree(points, leaf_size, dtype=np.float32)
    first = int(np.flatnonzero(tree.index == start)[0])
    return _fps_kernel(tree.points, tree.index, *tree[2:], int(k), first)
