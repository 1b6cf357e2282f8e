"""The slide of a table scene's new object towards its cluster
(:func:`cloudpose.data.synth.scenes.sample_table_scene`), in one compiled loop.

The twin is the numpy loop in that function (one fancy-indexing pass over the object's
footprint cells per step); the kernel does the same float64 operations on each step's position
(``anchor + step * (k * grid)``, floored in grid cells) and the same integer tests, so it
stops at the same step: scenes stay identical, with or without numba.
"""

from __future__ import annotations

import math

import numpy as np

from cloudpose.kernels.backend import njit

__all__ = ["close_cells", "raster_cells", "slide_steps"]


@njit(cache=True)
def slide_steps(cells, occupied, anchor, step, k_max, grid, half):  # pragma: no cover
    """The last step ``k`` (counting down from ``k_max`` to 0) at which the footprint is on the
    grid and free, before the first step at which it touches an occupied cell; -1 if none.

    Args:
        cells: (C, 2) int64 footprint cells relative to the object's origin.
        occupied: (2 half, 2 half) bool occupancy grid.
        anchor, step: (2,) float64 the cluster anchor and the unit slide direction, metres.
        k_max: first step (the farthest position).
        grid: cell size, metres.
        half: cells each side of the grid's origin.
    """
    n = 2 * half
    found = -1
    for k in range(k_max, -1, -1):
        off0 = np.int64(math.floor((anchor[0] + step[0] * (k * grid)) / grid)) + half
        off1 = np.int64(math.floor((anchor[1] + step[1] * (k * grid)) / grid)) + half
        outside = False
        for c in range(cells.shape[0]):
            i, j = cells[c, 0] + off0, cells[c, 1] + off1
            if i < 0 or j < 0 or i >= n or j >= n:
                outside = True
                break
        if outside:
            continue
        hit = False
        for c in range(cells.shape[0]):
            if occupied[cells[c, 0] + off0, cells[c, 1] + off1]:
                hit = True
                break
        if hit:
            break
        found = k
    return found


@njit(cache=True)
def close_cells(img, fill):  # pragma: no cover - compiled
    """``scipy.ndimage.binary_closing(img, iterations=2)`` (the 4-neighbour cross, pixels
    outside the image 0), then, with ``fill``, ``binary_fill_holes`` (what the image's border
    cannot reach through 0 pixels by 4-neighbour steps becomes 1). The twin is
    :func:`cloudpose.data.synth.scenes._close_numpy`; the same image, pixel for pixel.

    Args:
        img: (h, w) bool.
        fill: fill the holes.

    Returns:
        (h, w) bool.
    """
    h, w = img.shape
    a = img.copy()
    b = np.zeros((h, w), np.bool_)
    for _ in range(2):  # dilations
        for y in range(h):
            for x in range(w):
                b[y, x] = (
                    a[y, x]
                    or (y > 0 and a[y - 1, x])
                    or (y < h - 1 and a[y + 1, x])
                    or (x > 0 and a[y, x - 1])
                    or (x < w - 1 and a[y, x + 1])
                )
        a, b = b, a
    for _ in range(2):  # erosions
        for y in range(h):
            for x in range(w):
                b[y, x] = (
                    a[y, x]
                    and y > 0
                    and a[y - 1, x]
                    and y < h - 1
                    and a[y + 1, x]
                    and x > 0
                    and a[y, x - 1]
                    and x < w - 1
                    and a[y, x + 1]
                )
        a, b = b, a
    if not fill:
        return a
    outside = np.zeros((h, w), np.bool_)
    stack = np.empty(h * w, np.int64)
    sp = 0
    for y in range(h):
        for x in range(w):
            if (y == 0 or y == h - 1 or x == 0 or x == w - 1) and not a[y, x]:
                outside[y, x] = True
                stack[sp] = y * w + x
                sp += 1
    while sp > 0:
        sp -= 1
        y, x = stack[sp] // w, stack[sp] % w
        for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            yy, xx = y + dy, x + dx
            if 0 <= yy < h and 0 <= xx < w and not a[yy, xx] and not outside[yy, xx]:
                outside[yy, xx] = True
                stack[sp] = yy * w + xx
                sp += 1
    for y in range(h):
        for x in range(w):
            a[y, x] = not outside[y, x]
    return a


@njit(cache=True)
def raster_cells(points_xy, grid, fill):  # pragma: no cover - compiled
    """(C, 2) int64 grid cells ``floor(xy / grid)`` covered by the (P, 2) points, closed by
    :func:`close_cells` (holes filled with ``fill``), row-major: the twin is
    :func:`cloudpose.data.synth.scenes._raster_cells_numpy` (the same float64 division and
    floor, the same raster, ``np.argwhere``'s order)."""
    n = points_xy.shape[0]
    ij = np.empty((n, 2), np.int64)
    lo0, lo1 = np.iinfo(np.int64).max, np.iinfo(np.int64).max
    hi0, hi1 = np.iinfo(np.int64).min, np.iinfo(np.int64).min
    for k in range(n):
        a = np.int64(math.floor(points_xy[k, 0] / grid))
        b = np.int64(math.floor(points_xy[k, 1] / grid))
        ij[k, 0], ij[k, 1] = a, b
        lo0, lo1, hi0, hi1 = min(lo0, a), min(lo1, b), max(hi0, a), max(hi1, b)
    lo0, lo1 = lo0 - 2, lo1 - 2
    img = np.zeros((hi0 - lo0 + 3, hi1 - lo1 + 3), np.bool_)
    for k in range(n):
        img[ij[k, 0] - lo0, ij[k, 1] - lo1] = True
    img = close_cells(img, fill)
    c = 0
    for y in range(img.shape[0]):
        for x in range(img.shape[1]):
            c += img[y, x]
    out = np.empty((c, 2), np.int64)
    c = 0
    for y in range(img.shape[0]):
        for x in range(img.shape[1]):
            if img[y, x]:
                out[c, 0], out[c, 1] = y + lo0, x + lo1
                c += 1
    return out
