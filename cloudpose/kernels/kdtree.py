"""A k-d tree of arrays (compiled code can take it apart) and its bounded nearest-neighbour
search.

Boxes split at the middle of their widest side (never empty sides), leaves of at most
``leaf_size`` points, points stored in leaf order; each node keeps the bounding box of its
points, which a search uses as its lower bound. ``nearest_bounded`` is the twin of pykdtree's
bounded query (tests compare them).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from cloudpose.kernels.backend import njit

__all__ = ["KDTree", "build_kdtree", "nearest_bounded"]


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


@njit(cache=True, inline="always")
def _box_d2(box, node, x, y, z):
    """Squared distance from (x, y, z) to a node's box (0 inside); branch-free."""
    vx = max(box[node, 0] - x, x - box[node, 3], 0.0)
    vy = max(box[node, 1] - y, y - box[node, 4], 0.0)
    vz = max(box[node, 2] - z, z - box[node, 5], 0.0)
    return vx * vx + vy * vy + vz * vz


@njit(cache=True, inline="always")
def _nearest(tree, x, y, z, best_d2, best_i, stack, stack_d2):
    """Nearest stored point of ``tree`` (a :class:`KDTree`) with squared distance < best_d2;
    else (best_d2, best_i) unchanged."""
    P, box, left, start, end = tree.points, tree.box, tree.left, tree.start, tree.end
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
def _nearest_call(tree, x, y, z, best_d2, best_i, stack, stack_d2):
    """``_nearest`` as a real call: for rare fallbacks, where inlining its loops into a hot
    loop only costs registers."""
    return _nearest(tree, x, y, z, best_d2, best_i, stack, stack_d2)


@njit(cache=True)
def _nearest_many(tree, Q, bound_d2):
    n = Q.shape[0]
    d2 = np.empty(n)
    idx = np.empty(n, np.int64)
    stack = np.empty(_STACK, np.int64)
    stack_d2 = np.empty(_STACK)
    for k in range(n):
        d2[k], idx[k] = _nearest(tree, Q[k, 0], Q[k, 1], Q[k, 2], bound_d2, -1, stack, stack_d2)
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
    d2, i = _nearest_many(tree, Q, float(bound) ** 2)
    found = i >= 0
    return d2, np.where(found, tree.index[np.maximum(i, 0)], -1)


@njit(cache=True, inline="always")
def _d2(P, j, x, y, z):
    dx = P[j, 0] - x
    dy = P[j, 1] - y
    dz = P[j, 2] - z
    return dx * dx + dy * dy + dz * dz
