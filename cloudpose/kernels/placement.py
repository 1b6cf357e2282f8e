"""The table-scene sampler's hot loops (:func:`cloudpose.data.synth.scenes.sample_table_scene`),
compiled: the slide of a new object towards its cluster and the test of its final place, the
footprint, top-surface and contact rasters, the support test of a stacked object (its centre
of mass inside the contact's convex hull), the mean of an object's points and the in-image
test of a camera.

Each has a numpy twin in :mod:`cloudpose.data.synth.scenes` (the ``_numpy`` functions and
qhull) and does the same float64 operations or an exact integer computation, so it gives the
same answer: scenes stay identical, with or without numba.
"""

from __future__ import annotations

import math

import numpy as np

from cloudpose.kernels.backend import njit

__all__ = [
    "close_cells",
    "column_means",
    "contact_cells",
    "count_in_image",
    "hull_margin",
    "placed_cells",
    "raster_cells",
    "slide_steps",
    "top_cells",
]


@njit(cache=True)
def slide_steps(cells, occupied, anchor, step, k_max, grid, half):  # pragma: no cover
    """The last step ``k`` (counting down from ``k_max`` to 0) at which the footprint is on the
    grid and free, before the first step at which it touches an occupied cell; -1 if none.

    A step is on the grid when the footprint's box is, and can touch only when that box meets
    the box of the occupied cells: the cells themselves are read only then (the same step as
    testing every cell at every step).

    Args:
        cells: (C, 2) int64 footprint cells relative to the object's origin.
        occupied: (2 half, 2 half) bool occupancy grid.
        anchor, step: (2,) float64 the cluster anchor and the unit slide direction, metres.
        k_max: first step (the farthest position).
        grid: cell size, metres.
        half: cells each side of the grid's origin.
    """
    n = 2 * half
    m = cells.shape[0]
    if m == 0:  # on the grid and free at every step
        return 0 if k_max >= 0 else -1
    lo0, hi0, lo1, hi1 = cells[0, 0], cells[0, 0], cells[0, 1], cells[0, 1]
    for c in range(1, m):
        lo0, hi0 = min(lo0, cells[c, 0]), max(hi0, cells[c, 0])
        lo1, hi1 = min(lo1, cells[c, 1]), max(hi1, cells[c, 1])
    r0, r1, c0, c1 = n, -1, n, -1  # the occupied cells' box (none: r1 = -1)
    for i in range(n):
        row = occupied[i]
        filled = False
        for j in range(n):
            filled |= row[j]
        if filled:
            r0, r1 = min(r0, i), i
    for i in range(r0, r1 + 1):
        row = occupied[i]
        for j in range(n):
            if row[j]:
                c0, c1 = min(c0, j), max(c1, j)
    found = -1
    for k in range(k_max, -1, -1):
        off0 = np.int64(math.floor((anchor[0] + step[0] * (k * grid)) / grid)) + half
        off1 = np.int64(math.floor((anchor[1] + step[1] * (k * grid)) / grid)) + half
        if lo0 + off0 < 0 or lo1 + off1 < 0 or hi0 + off0 >= n or hi1 + off1 >= n:
            continue
        hit = False
        if lo0 + off0 <= r1 and hi0 + off0 >= r0 and lo1 + off1 <= c1 and hi1 + off1 >= c0:
            for c in range(m):
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


@njit(cache=True)
def hull_margin(cells, grid, px, py):  # pragma: no cover - compiled
    """How far the point ``(px, py)`` (metres) lies inside the convex hull of the centres
    ``(cells + 0.5) * grid`` of the (K, 2) int64 grid cells: the smallest signed distance to
    a hull edge, positive inside (the largest of ``-(n . p + d)`` over qhull's facet equations
    ``(n, d)``, to float rounding). The hull by Andrew's monotone chain in integers, so its
    vertices are exact; collinear cells (no hull: qhull's error) give status 1.

    Returns:
        (status, margin): status 0 and the margin, metres, or 1 and 0.0.
    """
    k = cells.shape[0]
    key = np.empty(k, np.int64)
    for i in range(k):
        key[i] = cells[i, 0] * (np.int64(1) << 32) + cells[i, 1]
    order = np.argsort(key, kind="mergesort")
    pts = np.empty((k, 2), np.int64)
    for i in range(k):
        pts[i, 0], pts[i, 1] = cells[order[i], 0], cells[order[i], 1]
    hull = np.empty(2 * k + 1, np.int64)
    m = 0
    for i in range(k):  # lower chain
        while m >= 2 and _turn(pts, hull[m - 2], hull[m - 1], i) <= 0:
            m -= 1
        hull[m] = i
        m += 1
    lower = m + 1
    for i in range(k - 2, -1, -1):  # upper chain
        while m >= lower and _turn(pts, hull[m - 2], hull[m - 1], i) <= 0:
            m -= 1
        hull[m] = i
        m += 1
    m -= 1  # the last vertex is the first
    if m < 3:
        return 1, 0.0
    margin = np.inf
    for e in range(m):
        a, b = hull[e], hull[e + 1]
        ax, ay = (pts[a, 0] + 0.5) * grid, (pts[a, 1] + 0.5) * grid
        bx, by = (pts[b, 0] + 0.5) * grid, (pts[b, 1] + 0.5) * grid
        ex, ey = bx - ax, by - ay
        margin = min(margin, (ex * (py - ay) - ey * (px - ax)) / math.sqrt(ex * ex + ey * ey))
    return 0, margin


@njit(cache=True, inline="always")
def _turn(pts, a, b, c):  # pragma: no cover - compiled
    """Twice the signed area of the integer triangle (a, b, c): > 0 turning left."""
    return (pts[b, 0] - pts[a, 0]) * (pts[c, 1] - pts[a, 1]) - (pts[b, 1] - pts[a, 1]) * (
        pts[c, 0] - pts[a, 0]
    )


@njit(cache=True)
def column_means(points):  # pragma: no cover - compiled
    """(C,) float64 the mean of each column of the (P, C) float64 ``points``:
    ``np.mean(points, axis=0)`` of a C-contiguous array, whose sum runs row after row
    (the same additions in the same order), divided by P."""
    n, m = points.shape
    out = np.zeros(m)
    if n == 0:
        out[:] = np.nan
        return out
    for j in range(m):
        out[j] = points[0, j]
    for i in range(1, n):
        for j in range(m):
            out[j] += points[i, j]
    for j in range(m):
        out[j] /= n
    return out


@njit(cache=True)
def count_in_image(cam, uvw, height, width):  # pragma: no cover - compiled
    """How many of the (P, 3) camera-frame points ``cam`` (their projections ``uvw = cam @
    K.T``) are in front of the camera (z > 1 mm) and project into the (height, width) image:
    the count of :func:`cloudpose.data.synth.scenes._in_image_fraction_numpy`'s test (the
    same divisions and comparisons)."""
    c = 0
    for i in range(cam.shape[0]):
        z = cam[i, 2]
        if not z > 1e-3:
            continue
        u = uvw[i, 0] / z
        v = uvw[i, 1] / z
        if u >= 0 and u < width and v >= 0 and v < height:
            c += 1
    return c


@njit(cache=True)
def top_cells(points, contact, grid):  # pragma: no cover - compiled
    """The top surface of a posed object: the cells (:func:`raster_cells`, closed, holes kept)
    of the (P, 3) points within ``contact`` metres of the highest, and that height (the
    selection ``points[points[:, 2] >= z.max() - contact, :2]``, in order).

    Returns:
        ((C, 2) int64 cells, the highest z, metres).
    """
    n = points.shape[0]
    top = -np.inf
    for i in range(n):
        top = max(top, points[i, 2])
    low = top - contact
    m = 0
    for i in range(n):
        m += points[i, 2] >= low
    xy = np.empty((m, 2))
    m = 0
    for i in range(n):
        if points[i, 2] >= low:
            xy[m, 0], xy[m, 1] = points[i, 0], points[i, 1]
            m += 1
    return raster_cells(xy, grid, False), top


@njit(cache=True)
def contact_cells(bottom, origin, grid, of):  # pragma: no cover - compiled
    """The cells of a resting face moved by ``origin`` that are also cells of a support's top:
    :func:`raster_cells` of the (P, 2) ``bottom + origin`` (closed, holes kept), less the
    cells whose key (:func:`cloudpose.data.synth.scenes._cell_keys`) is not in the sorted
    int64 keys ``of``, in order.

    Returns:
        (C, 2) int64 cells.
    """
    n = bottom.shape[0]
    pts = np.empty((n, 2))
    for i in range(n):
        pts[i, 0], pts[i, 1] = bottom[i, 0] + origin[0], bottom[i, 1] + origin[1]
    cells = raster_cells(pts, grid, False)
    keep = np.zeros(cells.shape[0], np.bool_)
    m = 0
    if of.shape[0] > 0:
        for i in range(cells.shape[0]):
            key = (cells[i, 0] + (1 << 20)) * (1 << 21) + (cells[i, 1] + (1 << 20))
            j = np.searchsorted(of, key)
            keep[i] = j < of.shape[0] and of[j] == key
            m += keep[i]
    out = np.empty((m, 2), np.int64)
    m = 0
    for i in range(cells.shape[0]):
        if keep[i]:
            out[m, 0], out[m, 1] = cells[i, 0], cells[i, 1]
            m += 1
    return out


@njit(cache=True)
def placed_cells(cells, occupied, xy, grid, half):  # pragma: no cover - compiled
    """The grid indices of the footprint ``cells`` of an object at ``xy`` (2,) metres,
    ``cells + floor(xy / grid) + half``, and whether they are all on the (2 half)^2 grid
    and free.

    Returns:
        ((C, 2) int64 indices, bool).
    """
    n = 2 * half
    off0 = np.int64(math.floor(xy[0] / grid)) + half
    off1 = np.int64(math.floor(xy[1] / grid)) + half
    ij = np.empty_like(cells)
    ok = True
    for c in range(cells.shape[0]):
        i, j = cells[c, 0] + off0, cells[c, 1] + off1
        ij[c, 0], ij[c, 1] = i, j
        if i < 0 or j < 0 or i >= n or j >= n:
            ok = False
    if ok:
        for c in range(cells.shape[0]):
            if occupied[ij[c, 0], ij[c, 1]]:
                ok = False
                break
    return ij, ok
