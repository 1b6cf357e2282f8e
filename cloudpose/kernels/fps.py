"""Exact farthest point sampling: a k-d tree's buckets let a pick skip the points it cannot
get closer to."""

from __future__ import annotations

import numpy as np

from cloudpose.kernels.backend import enabled, njit
from cloudpose.kernels.kdtree import _box_d2, build_kdtree

__all__ = ["farthest_order", "fps_order"]


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
    import fpsample

    # fps_sampling honours start_idx exactly (the bucket/kd variants in 1.0.2 do not)
    return np.asarray(fpsample.fps_sampling(points, k, start_idx=start), dtype=np.int64)


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
