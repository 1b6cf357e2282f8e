"""Segments of a synthesized frame in one pass: each instance's pixels gathered in row-major
order, and exact farthest point sampling over a flat grid of buckets (no tree to build).

- ``gather_instances``: the pixels of every instance with a depth reading, grouped by instance
  and row-major within each (a counting sort); the twin is one ``np.nonzero(label == c &
  depth > 0)`` per instance (:func:`cloudpose.data.segments.backproject`'s order).
- ``grid_fps``: the FPS order of :func:`cloudpose.kernels.fps.fps_order`, index for index
  (the same float32 squared distances, ties to the highest index), with the points bucketed
  by a 2-D grid over their x and y (a depth segment is a surface seen along z: ~64 points a
  cell) instead of a k-d tree: after each pick, a cell is skipped when its box is farther from
  the new sample than the largest nearest-sample distance inside it. For the 256 of ~10,000
  points that a segment keeps, building the k-d tree cost as much as the sampling.
"""

from __future__ import annotations

import math

import numpy as np

from cloudpose.kernels.backend import njit
from cloudpose.kernels.fps import grid_buckets, scan_bucket
from cloudpose.kernels.kdtree import _box_d2

__all__ = ["gather_instances", "grid_fps"]


@njit(cache=True)
def gather_instances(depth, label, lut, n):  # pragma: no cover - compiled
    """Flat pixel indices of each instance's pixels with depth > 0.

    Args:
        depth: (h, w) float depth, 0 = none.
        label: (h, w) uint8 class ids.
        lut: (256,) int64 instance of each class id (-1 = none).
        n: instances.

    Returns:
        (P,) int64 flat indices, instance by instance, row-major within each, and (n + 1,)
        int64 offsets: instance i's are ``[offsets[i], offsets[i + 1])``.
    """
    h, w = depth.shape
    counts = np.zeros(n + 1, np.int64)
    for y in range(h):
        for x in range(w):
            i = lut[label[y, x]]
            if i >= 0 and depth[y, x] > 0:
                counts[i + 1] += 1
    offsets = np.cumsum(counts)
    fill = offsets[:-1].copy()
    out = np.empty(offsets[n], np.int64)
    for y in range(h):
        for x in range(w):
            i = lut[label[y, x]]
            if i >= 0 and depth[y, x] > 0:
                out[fill[i]] = y * w + x
                fill[i] += 1
    return out, offsets


@njit(cache=True)
def grid_fps(P, k, start, per_cell=64):  # pragma: no cover - compiled
    """Exact FPS order of ``k`` of the float32 points ``P`` (N, 3) from index ``start``.

    Returns:
        (k,) int64 indices into ``P`` (1 <= k <= N).
    """
    n = P.shape[0]
    cells, cstart, index = grid_buckets(P[:, 0], P[:, 1], per_cell)
    Q = np.empty((n, 3), np.float32)
    for j in range(n):
        i = index[j]
        Q[j, 0], Q[j, 1], Q[j, 2] = P[i, 0], P[i, 1], P[i, 2]
    box = np.empty((cells, 6))
    cmax = np.full(cells, np.inf, np.float32)  # largest nearest-sample distance^2 in the cell
    carg = np.full(cells, -1, np.int64)  # its original index (highest on ties)
    for c in range(cells):
        box[c, 0] = box[c, 1] = box[c, 2] = np.inf
        box[c, 3] = box[c, 4] = box[c, 5] = -np.inf
        for j in range(cstart[c], cstart[c + 1]):
            for a in range(3):
                box[c, a] = min(box[c, a], np.float64(Q[j, a]))
                box[c, 3 + a] = max(box[c, 3 + a], np.float64(Q[j, a]))
            carg[c] = index[j]  # every distance is inf: the highest index
    near = np.full(n, np.inf, np.float32)
    out = np.empty(k, np.int64)
    cur = start
    for s in range(k):
        out[s] = cur
        px, py, pz = P[cur, 0], P[cur, 1], P[cur, 2]
        xs, ys, zs = np.float64(px), np.float64(py), np.float64(pz)
        for c in range(cells):
            if carg[c] < 0:
                continue
            # skip when every point of the cell is farther than its largest nearest distance
            # (margin 1e-6 >> float32 rounding of a squared distance; as fps_order)
            if _box_d2(box, c, xs, ys, zs) * (1.0 - 1e-6) > cmax[c]:
                continue
            cmax[c], best = scan_bucket(Q, near, index, cstart[c], cstart[c + 1], px, py, pz)
            carg[c] = index[best]
        best_v = np.float32(-1.0)
        cur = -1
        for c in range(cells):
            if carg[c] < 0:
                continue
            if cmax[c] > best_v or (cmax[c] == best_v and carg[c] > cur):
                best_v = cmax[c]
                cur = carg[c]
    return out


@njit(cache=True)
def backproject_filtered(depth, flat, Kinv, radius):  # pragma: no cover - compiled
    """Camera-frame points of the pixels ``flat`` (flat indices into ``depth``, (h, w)),
    ``z K^-1 [u, v, 1]`` in float64, less those farther than ``radius`` from their mean
    (:func:`cloudpose.data.segments.backproject` and the segment path's outlier filter).

    Returns:
        (M, 3) float64 points, in the order of ``flat``.
    """
    w = depth.shape[1]
    m = flat.shape[0]
    X = np.empty((m, 3))
    mx, my, mz = 0.0, 0.0, 0.0
    for i in range(m):
        v, u = flat[i] // w, flat[i] % w
        z = np.float64(depth[v, u])
        fu, fv = np.float64(u), np.float64(v)
        X[i, 0] = (fu * Kinv[0, 0] + fv * Kinv[0, 1] + Kinv[0, 2]) * z
        X[i, 1] = (fu * Kinv[1, 0] + fv * Kinv[1, 1] + Kinv[1, 2]) * z
        X[i, 2] = (fu * Kinv[2, 0] + fv * Kinv[2, 1] + Kinv[2, 2]) * z
        mx += X[i, 0]
        my += X[i, 1]
        mz += X[i, 2]
    if m == 0:
        return X
    mx /= m
    my /= m
    mz /= m
    keep = 0
    for i in range(m):
        dx, dy, dz = X[i, 0] - mx, X[i, 1] - my, X[i, 2] - mz
        if math.sqrt(dx * dx + dy * dy + dz * dz) <= radius:
            X[keep, 0], X[keep, 1], X[keep, 2] = X[i, 0], X[i, 1], X[i, 2]
            keep += 1
    return X[:keep]
