"""Exact farthest point sampling: a k-d tree's buckets let a pick skip the points it cannot
get closer to.

Also the two steps the other FPS kernels share with it (``segment_cut.grid_fps``,
``scene_pass.fps_soa``): :func:`scan_bucket`, one bucket's points brought up to date with a new
sample, and :func:`grid_buckets`, points bucketed by a 2-D grid over their x and y.
"""

from __future__ import annotations

import math

import fpsample
import numpy as np

from cloudpose.kernels.backend import enabled, njit
from cloudpose.kernels.kdtree import _box_d2, build_kdtree

__all__ = ["farthest_order", "fps_order", "grid_buckets", "scan_bucket"]


def farthest_order(points: np.ndarray, k: int, start: int) -> np.ndarray:
    """Exact FPS order of ``k`` of ``points`` from index ``start``: the compiled bucket FPS
    where the kernels are enabled and the points finite, else fpsample's vanilla FPS (the same
    order, ties to the highest index).

    Args:
        points: (N, 3) float32 points.
        k: samples, 1 <= k <= N.
        start: index of the first sample.

    Returns:
        (k,) int64 indices into ``points``.
    """
    if enabled() and np.isfinite(points).all():
        return fps_order(points, k, start)

    # fps_sampling honours start_idx exactly (the bucket/kd variants in 1.0.2 do not)
    return np.asarray(fpsample.fps_sampling(points, k, start_idx=start), dtype=np.int64)


@njit(cache=True, inline="always")
def scan_bucket(Q, near, index, a, b, px, py, pz):  # pragma: no cover - compiled
    """The points ``Q[a:b]`` (float32, stored order) brought up to date with the sample
    ``(px, py, pz)`` (float32): each one's squared distance to its nearest sample ``near``
    lowered where the new one is nearer, in float32 (the numpy loop's expression).

    Returns:
        The largest of them and its stored position (ties to the highest original index,
        ``index[j]``); ``b > a``.
    """
    best_v = np.float32(-1.0)
    best = a
    for j in range(a, b):
        dx = Q[j, 0] - px
        dy = Q[j, 1] - py
        dz = Q[j, 2] - pz
        d = dx * dx + dy * dy + dz * dz
        v = near[j]
        if d < v:
            v = d
            near[j] = d
        if v > best_v or (v == best_v and index[j] > index[best]):
            best_v = v
            best = j
    return best_v, best


@njit(cache=True)
def grid_buckets(X, Y, per_cell):  # pragma: no cover - compiled
    """Points ``(X, Y)`` (N,) bucketed by a g x g grid over their bounds, g = sqrt(N /
    per_cell) (at least 1): a counting sort by cell, row-major.

    Returns:
        cells (g * g), (cells + 1,) int64 offsets (cell c's points are stored at
        ``[offsets[c], offsets[c + 1])``) and (N,) int64 the original index of each stored
        point (ascending within a cell).
    """
    n = X.shape[0]
    g = max(1, int(math.sqrt(n / per_cell)))
    x0, x1, y0, y1 = np.inf, -np.inf, np.inf, -np.inf
    for i in range(n):
        x0, x1 = min(x0, np.float64(X[i])), max(x1, np.float64(X[i]))
        y0, y1 = min(y0, np.float64(Y[i])), max(y1, np.float64(Y[i]))
    sx = g / (x1 - x0) if x1 > x0 else 0.0
    sy = g / (y1 - y0) if y1 > y0 else 0.0
    cells = g * g
    cell = np.empty(n, np.int64)
    counts = np.zeros(cells + 1, np.int64)
    for i in range(n):
        cx = min(int((X[i] - x0) * sx), g - 1)
        cy = min(int((Y[i] - y0) * sy), g - 1)
        cell[i] = cy * g + cx
        counts[cell[i] + 1] += 1
    cstart = np.cumsum(counts)
    fill = cstart[:-1].copy()
    index = np.empty(n, np.int64)
    for i in range(n):
        index[fill[cell[i]]] = i
        fill[cell[i]] += 1
    return cells, cstart, index


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
            node_max[node], node_arg[node] = scan_bucket(
                P, near, index, start[node], end[node], sx, sy, sz
            )
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
