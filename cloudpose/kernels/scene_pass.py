"""On-line synthesis version 3 (:mod:`cloudpose.data.synth.online`): a scene's objects drawn,
read by the sensor and cut into segments in a few compiled passes, each over every object at
once.

- ``raster_scene``: every object of a scene into one z-buffer: the meshes posed and projected,
  the objects' windows and the box around them (:meth:`~cloudpose.data.synth.render.Renderer.render_raster`'s
  expressions), then each triangle tested at the pixel centres of each row's span between its
  edges, the nearest surface kept as the largest inverse depth (1/z is affine in the image
  over a planar triangle: :mod:`cloudpose.kernels.raster`). The same hits as the ray cast to
  float rounding.
- ``scene_points``: every object pixel of the box in one pass, row-major (the depth jumps
  and incidence cosines of a row's pixels at once, ahead of its readings): the version-2
  sensor's depth jump, incidence cosine and reading from the pixel's draws (counter
  streams: ``stream_word``, ``normal_draw``, ``uniform_draw``, read where needed)
  (:func:`cloudpose.kernels.sensor.object_pixel_geometry_kernel`'s and
  ``object_readings_kernel``'s expressions), the missing-depth field smoothed over the object
  pixels' box only (white noise drawn over it widened by the filter's reach: a stationary
  field, the kernel of :func:`cloudpose.data.synth.sensor.correlated_uniform`; drawn and
  smoothed where an object pixel reads it), the fitted missing probability with the exact
  edge distance (``edge_squared_distance``, at the object pixels), then the
  back-projection and the outlier filter of each instance's points.
- ``fps_soa``: exact farthest point sampling over a grid of buckets, the points of a bucket
  stored coordinate by coordinate, so that a bucket's distance update and the box tests are
  vector loops (the order of :func:`cloudpose.kernels.fps.fps_order`, ties included).
"""

from __future__ import annotations

import math

import numpy as np

from cloudpose.kernels.backend import njit
from cloudpose.kernels.fps import grid_buckets
from cloudpose.kernels.sensor import incidence_terms

__all__ = [
    "edge_squared_distance",
    "fps_soa",
    "normal_draw",
    "normal_draws",
    "raster_scene",
    "ring_pixels",
    "scene_points",
    "stream_word",
    "uniform_draw",
]


@njit(cache=True)
def raster_scene(V, F, vstart, fstart, cls, poses, K, H, W, pad):  # pragma: no cover
    """Every object of a scene into one z-buffer.

    Args:
        V: (M, 3) float64 vertices of every class's mesh, model frame, class after class.
        F: (T, 3) int64 triangles, indices into ``V``.
        vstart, fstart: (C + 1,) int64 first vertex and triangle of each class slot.
        cls: (N,) int64 class slot of each object.
        poses: (N, 3, 4) float64 object->camera.
        K: (3, 3) float64 intrinsics.
        H, W: image size.
        pad: pixels added around the objects' windows.

    Returns:
        ``(status, box, depth, index, visible)``: status 0 drawn, 1 no object in the image,
        2 an object reaches behind the camera (not drawn: the caller casts rays); box (4,)
        int64 (v0, v1, u0, u1); depth (h, w) float64 metres (0 = none); index (h, w) int64
        instance (-1 = none); visible (N,) int64 pixels of each instance.
    """
    n = cls.shape[0]
    wins = np.zeros((n, 4), np.int64)
    mtot = 0
    for i in range(n):
        mtot += vstart[cls[i] + 1] - vstart[cls[i]]
    zs = np.empty(mtot)  # 1 / depth of each posed vertex
    us = np.empty(mtot)
    vs = np.empty(mtot)
    vbase = np.empty(n + 1, np.int64)
    vbase[0] = 0
    box = np.zeros(4, np.int64)
    for i in range(n):
        a, b = vstart[cls[i]], vstart[cls[i] + 1]
        vbase[i + 1] = vbase[i] + (b - a)
        P = poses[i]
        umin, umax, vmin, vmax = np.inf, -np.inf, np.inf, -np.inf
        for j in range(a, b):
            x = V[j, 0] * P[0, 0] + V[j, 1] * P[0, 1] + V[j, 2] * P[0, 2] + P[0, 3]
            y = V[j, 0] * P[1, 0] + V[j, 1] * P[1, 1] + V[j, 2] * P[1, 2] + P[1, 3]
            z = V[j, 0] * P[2, 0] + V[j, 1] * P[2, 1] + V[j, 2] * P[2, 2] + P[2, 3]
            if z <= 1e-6:
                return 2, box, np.zeros((0, 0)), np.zeros((0, 0), np.int64), np.zeros(n, np.int64)
            u = (K[0, 0] * x + K[0, 1] * y + K[0, 2] * z) / z
            v = (K[1, 0] * x + K[1, 1] * y + K[1, 2] * z) / z
            k = vbase[i] + j - a
            zs[k], us[k], vs[k] = 1.0 / z, u, v
            umin, umax = min(umin, u), max(umax, u)
            vmin, vmax = min(vmin, v), max(vmax, v)
        if b == a:
            continue
        wins[i, 0] = min(max(math.floor(vmin) - 1, 0), H)
        wins[i, 1] = min(max(math.ceil(vmax) + 2, 0), H)
        wins[i, 2] = min(max(math.floor(umin) - 1, 0), W)
        wins[i, 3] = min(max(math.ceil(umax) + 2, 0), W)
    bv0, bv1, bu0, bu1 = H, 0, W, 0
    for i in range(n):
        if wins[i, 0] < wins[i, 1] and wins[i, 2] < wins[i, 3]:
            bv0, bv1 = min(bv0, wins[i, 0]), max(bv1, wins[i, 1])
            bu0, bu1 = min(bu0, wins[i, 2]), max(bu1, wins[i, 3])
    if bv0 >= bv1:
        return 1, box, np.zeros((0, 0)), np.zeros((0, 0), np.int64), np.zeros(n, np.int64)
    bv0, bv1 = max(bv0 - pad, 0), min(bv1 + pad, H)
    bu0, bu1 = max(bu0 - pad, 0), min(bu1 + pad, W)
    box[0], box[1], box[2], box[3] = bv0, bv1, bu0, bu1
    h, w = bv1 - bv0, bu1 - bu0
    inv = np.zeros((h, w))  # 1 / depth of the nearest surface (0 = none)
    index = np.full((h, w), -1, np.int64)
    flat_inv = inv.reshape(h * w)
    flat_index = index.reshape(h * w)
    for i in range(n):
        if not (wins[i, 0] < wins[i, 1] and wins[i, 2] < wins[i, 3]):
            continue
        va = vstart[cls[i]]
        base = vbase[i]
        for f in range(fstart[cls[i]], fstart[cls[i] + 1]):
            ia = base + F[f, 0] - va
            ib = base + F[f, 1] - va
            ic = base + F[f, 2] - va
            ax, ay = us[ia], vs[ia]
            bx, by = us[ib], vs[ib]
            cx, cy = us[ic], vs[ic]
            area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            if area == 0.0 or not math.isfinite(area):
                continue
            xlo = max(math.ceil(min(ax, bx, cx)), bu0)
            xhi = min(math.floor(max(ax, bx, cx)), bu1 - 1)
            ylo = max(math.ceil(min(ay, by, cy)), bv0)
            yhi = min(math.floor(max(ay, by, cy)), bv1 - 1)
            if xlo > xhi or ylo > yhi:
                continue
            s = 1.0 / area  # barycentric weights w_i / area: >= 0 inside, either winding
            iza, izb, izc = zs[ia], zs[ib], zs[ic]
            # w0, w1 and 1/z are affine in the pixel: w = A x + B y + C
            a0, b0 = -(cy - by) * s, (cx - bx) * s
            c0 = -(a0 * bx + b0 * by)
            a1, b1 = -(ay - cy) * s, (ax - cx) * s
            c1 = -(a1 * cx + b1 * cy)
            # scan lines: the vertices by row, the span of each row between the long edge
            # (first to last) and a short one, widened against rounding (the test decides)
            if ay <= by:
                px, py, qx, qy = ax, ay, bx, by
            else:
                px, py, qx, qy = bx, by, ax, ay
            if cy < py:
                px, py, qx, qy, ox, oy = cx, cy, px, py, qx, qy
            elif cy < qy:
                qx, qy, ox, oy = cx, cy, qx, qy
            else:
                ox, oy = cx, cy
            slope_long = (ox - px) / (oy - py)
            slope_a = (qx - px) / (qy - py) if qy > py else 0.0
            slope_b = (ox - qx) / (oy - qy) if oy > qy else 0.0
            for y in range(ylo, yhi + 1):
                fy = float(y)
                xa = px + (fy - py) * slope_long
                xb = px + (fy - py) * slope_a if fy < qy else qx + (fy - qy) * slope_b
                sl = max(math.ceil(min(xa, xb) - 1e-6), xlo)
                sh = min(math.floor(max(xa, xb) + 1e-6), xhi)
                r0 = b0 * fy + c0
                r1 = b1 * fy + c1
                o = (y - bv0) * w - bu0  # pixel x of the row in the flat buffers
                for x in range(sl, sh + 1):  # branch-free
                    fx = float(x)
                    w0 = a0 * fx + r0
                    w1 = a1 * fx + r1
                    w2 = 1.0 - w0 - w1
                    iz = w0 * iza + w1 * izb + w2 * izc
                    cur = flat_inv[o + x]
                    take = (w0 >= 0.0) & (w1 >= 0.0) & (w2 >= 0.0) & (iz > cur)
                    flat_inv[o + x] = iz if take else cur
                    flat_index[o + x] = i if take else flat_index[o + x]
    depth = np.zeros((h, w))
    visible = np.zeros(n, np.int64)
    for y in range(h):
        for x in range(w):
            if index[y, x] >= 0:
                depth[y, x] = 1.0 / inv[y, x]
                visible[index[y, x]] += 1
    return 0, box, depth, index, visible


@njit(cache=True)
def ring_pixels(index):  # pragma: no cover - compiled
    """(rows, cols) int64 of the background pixels (``index`` < 0) with an object pixel among
    their 4-neighbours, row-major: ``np.nonzero`` of
    :func:`cloudpose.data.synth.sensor.object_ring` of ``index >= 0``."""
    h, w = index.shape
    rv = np.empty(h * w, np.int64)
    ru = np.empty(h * w, np.int64)
    n = 0
    for y in range(h):
        for x in range(w):
            if index[y, x] >= 0:
                continue
            if (
                (y > 0 and index[y - 1, x] >= 0)
                or (y < h - 1 and index[y + 1, x] >= 0)
                or (x > 0 and index[y, x - 1] >= 0)
                or (x < w - 1 and index[y, x + 1] >= 0)
            ):
                rv[n], ru[n] = y, x
                n += 1
    return rv[:n].copy(), ru[:n].copy()


@njit(cache=True, inline="always")
def _jump_to(best, z, nb):  # pragma: no cover - compiled
    """The jump to neighbour depth ``nb`` (0 = none) if it exceeds ``best`` (first on ties)."""
    d = nb - z if (nb > 0 and z > 0) else 0.0
    return d if abs(d) > abs(best) else best


@njit(cache=True, inline="always")
def _geometry(clean, index, y, x, Kinv):  # pragma: no cover - compiled
    """The depth jump and incidence cosine of object pixel (y, x): the jump to the
    4-neighbour (up, down, left, right) that differs most, over those with depth (the first on
    ties; 0 where the pixel has none); the cosine from central differences of the
    back-projected neighbours, 1 where one has no depth or another instance and on the box's
    border (:func:`cloudpose.kernels.sensor.object_pixel_geometry_kernel`'s expressions)."""
    h, w = index.shape
    c = index[y, x]
    z = clean[y, x]
    zu = clean[y - 1, x] if y > 0 else 0.0
    zd = clean[y + 1, x] if y < h - 1 else 0.0
    zl = clean[y, x - 1] if x > 0 else 0.0
    zr = clean[y, x + 1] if x < w - 1 else 0.0
    best = _jump_to(0.0, z, zu)
    best = _jump_to(best, z, zd)
    best = _jump_to(best, z, zl)
    best = _jump_to(best, z, zr)
    if not (1 <= y <= h - 2 and 1 <= x <= w - 2):
        return best, 1.0
    if not (zu > 0 and zd > 0 and zl > 0 and zr > 0):
        return best, 1.0
    if index[y - 1, x] != c or index[y + 1, x] != c or index[y, x - 1] != c or index[y, x + 1] != c:
        return best, 1.0
    dot, norm = incidence_terms(Kinv, float(x), float(y), zl, zr, zu, zd)
    if norm > 0:
        return best, min(max(dot / norm, 0.0), 1.0)
    return best, 1.0


@njit(cache=True, error_model="numpy")
def _row_geometry(clean, index, Kinv, y, x0, x1, jump, cos):  # pragma: no cover - compiled
    """:func:`_geometry` of the pixels x0 <= x < x1 of row y (1 <= y <= h - 2,
    1 <= x0, x1 <= w - 1: not on the box's border), into ``jump[x]`` and ``cos[x]``: every
    term computed for every pixel and the result selected (the same expressions; without
    branches, and without numba's division checks, the loop is ~2x faster; a division by
    zero is left out by the selection, where :func:`_geometry` skips it)."""
    cu, cc, cd = clean[y - 1], clean[y], clean[y + 1]
    iu, ic, idn = index[y - 1], index[y], index[y + 1]
    fy = np.float64(y)
    for x in range(x0, x1):
        z = cc[x]
        zu, zd, zl, zr = cu[x], cd[x], cc[x - 1], cc[x + 1]
        has = z > 0
        d = zu - z if (zu > 0) & has else 0.0
        best = d
        d = zd - z if (zd > 0) & has else 0.0
        best = d if abs(d) > abs(best) else best
        d = zl - z if (zl > 0) & has else 0.0
        best = d if abs(d) > abs(best) else best
        d = zr - z if (zr > 0) & has else 0.0
        best = d if abs(d) > abs(best) else best
        jump[x] = best
        c = ic[x]
        ok = (zu > 0) & (zd > 0) & (zl > 0) & (zr > 0)
        ok = ok & (iu[x] == c) & (idn[x] == c) & (ic[x - 1] == c) & (ic[x + 1] == c)
        fx = np.float64(x)
        dot, norm = incidence_terms(Kinv, fx, fy, zl, zr, zu, zd)
        v = min(max(dot / norm, 0.0), 1.0)
        cos[x] = v if ok & (norm > 0) else 1.0


@njit(cache=True)
def scene_points(
    clean,
    index,
    visible,
    Kinv,
    rate,
    keys,
    xs,
    fs,
    weights,
    std,
    noise,
    drop,
    max_range,
    radius,
    noisy,
):  # pragma: no cover - compiled
    """Each instance's points of a scene's box: every object pixel's reading (the version-2
    sensor from its draws, or the clean depth as float32 without noise), back-projected
    (``z K^-1 [u, v, 1]``, row-major within an instance), less the points farther than
    ``radius`` from their instance's mean (the segment path's outlier filter).

    The sensor: Gaussian axial noise growing with depth, a flying pixel on a depth edge mixed
    towards the neighbour across it, the disparity quantisation, the range; then missing
    depth where the missing-depth field (white noise smoothed by ``weights``, the first pass
    along the image's columns, over the object pixels' bounding box widened by the filter's
    reach r, mapped to uniform; drawn and smoothed only where an object pixel reads it) is below the fitted probability (edge distance, incidence
    cosine, class rate).

    Args:
        clean: (h, w) float64 clean depth: the objects', and the background's on the ring of
            pixels around them (0 elsewhere).
        index: (h, w) int64 instance of each pixel (-1 = background).
        visible: (N,) int64 pixels of each instance.
        Kinv: (3, 3) inverse intrinsics of the box.
        rate: (N,) missing rate of each instance's class.
        keys: (3,) uint64 the keys of the scene's three counter streams
            (:func:`normal_draw`, :func:`uniform_draw`): object pixel k (row-major) reads
            draw k of the first (standard normal, axial noise) and draws 2k, 2k + 1 of the
            second (uniforms: flying or not, the mix; read on depth edges only); cell
            (y, x) of the object pixels' bounding box widened by r reads draw
            ``y * (wb + 2r) + x`` of the third (standard normal, the white noise).
        xs, fs: :func:`ziggurat_tables`.
        weights: (2r + 1,) the smoothing kernel; std: the smoothed noise's standard deviation.
        noise: (sigma0, sigma2, focal_baseline, subpixel, edge_jump, edge_flying).
        drop: (edge_rate, edge_scale, graze_cos, graze_width).
        max_range, radius: metres.
        noisy: False: the readings are the clean depth (no draw is read).

    Returns:
        (M, 3) float64 points, instance by instance, and (N + 1,) int64 offsets: instance i's
        are ``[offsets[i], offsets[i + 1])``.
    """
    sigma0, sigma2, fb, sub, edge_jump, edge_flying = noise
    edge_rate, edge_scale, graze_cos, graze_width = drop
    h, w = index.shape
    n = visible.shape[0]
    start = np.zeros(n + 1, np.int64)
    for i in range(n):
        start[i + 1] = start[i] + visible[i]
    X = np.empty((start[n], 3))
    fill = start[:-1].copy()
    vb0, vb1, ub0, ub1 = h, 0, w, 0
    row_lo = np.full(h, w, np.int64)  # the columns [row_lo, row_hi) of each row's object pixels
    row_hi = np.zeros(h, np.int64)
    for y in range(h):
        for x in range(w):
            if index[y, x] >= 0:
                row_lo[y] = min(row_lo[y], x)
                row_hi[y] = x + 1
        if row_lo[y] < row_hi[y]:
            vb0, vb1 = min(vb0, y), y + 1
            ub0, ub1 = min(ub0, row_lo[y]), max(ub1, row_hi[y])
    r = weights.shape[0] // 2
    hb, wb = max(vb1 - vb0, 0), max(ub1 - ub0, 0)
    sm = np.empty((hb, wb), np.float32)  # the smoothed field, on each row's object span
    ev0, ev1 = max(vb0 - 1, 0), min(vb1 + 1, h)
    eu0, eu1 = max(ub0 - 1, 0), min(ub1 + 1, w)
    dist2 = np.zeros((max(ev1 - ev0, 0), max(eu1 - eu0, 0)), np.int32)
    phi_low = np.empty(641)
    phi_high = np.empty(1281)
    graze_high = np.empty(257)
    graze_low = np.empty(257)
    edge_table = np.full(4096, -1.0)
    if noisy and hb > 0:
        # the white noise over the widened box, then the separable filter: first along the
        # columns, then the rows; each computed only where the field at an object pixel reads
        # it (row y of the box reads the columns of its object span widened by 2r of the white
        # noise's rows y .. y + 2r), the same sums in the same order
        wr = wb + 2 * r
        white_lo = np.full(hb + 2 * r, wr, np.int64)
        white_hi = np.zeros(hb + 2 * r, np.int64)
        for y in range(hb):
            a, b = row_lo[vb0 + y] - ub0, row_hi[vb0 + y] - ub0 + 2 * r
            if a < b:
                for j in range(2 * r + 1):
                    white_lo[y + j] = min(white_lo[y + j], a)
                    white_hi[y + j] = max(white_hi[y + j], b)
        white = np.empty((hb + 2 * r, wr), np.float32)
        for y in range(hb + 2 * r):
            for x in range(white_lo[y], white_hi[y]):
                white[y, x] = np.float32(normal_draw(keys[2], y * wr + x, xs, fs))
        tmp = np.empty((hb, wr), np.float32)
        for y in range(hb):
            a, b = row_lo[vb0 + y] - ub0, row_hi[vb0 + y] - ub0 + 2 * r
            if a >= b:
                continue
            dst = tmp[y, a:b]
            dst[:] = 0.0
            for j in range(2 * r + 1):
                wj = np.float32(weights[j])
                src = white[y + j, a:b]
                for x in range(b - a):
                    dst[x] += wj * src[x]
        for y in range(hb):
            a, b = row_lo[vb0 + y] - ub0, row_hi[vb0 + y] - ub0
            if a >= b:
                continue
            dst = sm[y, a:b]
            dst[:] = 0.0
            for j in range(2 * r + 1):
                wj = np.float32(weights[j])
                src = tmp[y, a + j : b + j]
                for x in range(b - a):
                    dst[x] += wj * src[x]
        # the exact edge distance over the objects' box and the ring around it
        # (at the object pixels only: along each row, over the columns of its object pixels)
        dist2 = _edge_squared_distance(
            index[ev0:ev1, eu0:eu1], row_lo[ev0:ev1] - eu0, row_hi[ev0:ev1] - eu0
        )
        # tables for sufficient tests of "the field keeps the reading" and of "it drops it":
        # Phi(z) from below on a grid of z <= 0 and from above on a grid of z in [-10, 10],
        # the grazing term from above and from below on a grid of cosines, the edge term by
        # the integer squared distance (filled as met); the exact test where they do not decide
        for k in range(641):
            phi_low[k] = 0.5 * math.erfc(k / 64.0 / math.sqrt(2.0)) * (1.0 - 1e-9)
        for k in range(1281):
            phi_high[k] = 0.5 * math.erfc(-(k - 640) / 64.0 / math.sqrt(2.0)) * (1.0 + 1e-9)
        for k in range(257):
            xk = min(max((k / 256.0 - graze_cos) / graze_width, -50.0), 50.0)
            graze_high[k] = 1.0 / (1.0 + math.exp(xk)) * (1.0 + 1e-9)
            xk = min(max(((k + 1) / 256.0 - graze_cos) / graze_width, -50.0), 50.0)
            graze_low[k] = 1.0 / (1.0 + math.exp(xk)) * (1.0 - 1e-9)
    k = 0
    jrow = np.zeros(w)  # the depth jump and incidence cosine of the row's inner pixels
    crow = np.ones(w)
    for y in range(vb0, vb1):
        rx0, rx1 = max(row_lo[y], 1), min(row_hi[y], w - 1)
        inner = noisy and 1 <= y <= h - 2
        if inner and rx0 < rx1:
            _row_geometry(clean, index, Kinv, y, rx0, rx1, jrow, crow)
        for x in range(ub0, ub1):
            c = index[y, x]
            if c < 0:
                continue
            zi = clean[y, x]
            i = k
            k += 1
            if not noisy:
                rd = np.float64(np.float32(zi))
            else:
                if inner and rx0 <= x < rx1:
                    jump, cos = jrow[x], crow[x]
                else:
                    jump, cos = _geometry(clean, index, y, x, Kinv)
                nz = np.float32(normal_draw(keys[0], i, xs, fs))
                rd = zi + nz * (sigma0 + sigma2 * (zi - 0.4) ** 2)
                if abs(jump) > edge_jump and uniform_draw(keys[1], 2 * i) < edge_flying:
                    rd = rd + uniform_draw(keys[1], 2 * i + 1) * jump
                disparity = fb / (rd if zi > 0 else 1.0)
                disparity = max(np.round(disparity / sub), 1.0) * sub
                rd = fb / disparity
                if not zi > 0 or rd <= 0 or rd > max_range:
                    continue
                d2 = dist2[y - ev0, x - eu0]
                if 0 <= d2 < 4096:
                    key = int(d2)
                    if edge_table[key] < 0:
                        edge_table[key] = edge_rate * math.exp(
                            -(math.sqrt(np.float64(d2)) + 1.0 - 1.0) / edge_scale
                        )
                    p_edge = edge_table[key]
                elif d2 < 0:  # no boundary in the box: an infinite distance
                    p_edge = 0.0
                else:
                    p_edge = edge_rate * math.exp(
                        -(math.sqrt(np.float64(d2)) + 1.0 - 1.0) / edge_scale
                    )
                q = (1.0 - p_edge) * (1.0 - rate[c])
                zf = np.float64(sm[y - vb0, x - ub0]) / std
                kz = 0 if zf >= 0.0 else math.ceil(-zf * 64.0)
                kc = int(cos * 256.0)
                if kz <= 640 and phi_low[kz] > 1.0 - q * (1.0 - graze_high[kc]):
                    pass  # Phi(zf) above an upper bound of p: kept
                elif zf <= 10.0 and (
                    phi_high[max(math.ceil(zf * 64.0), -640) + 640]
                    < 1.0 - q * (1.0 - graze_low[kc]) - 1e-12
                ):
                    continue  # Phi(zf) below a lower bound of p: missing
                else:  # the exact test
                    xg = min(max((cos - graze_cos) / graze_width, -50.0), 50.0)
                    p_graze = 1.0 / (1.0 + math.exp(xg))
                    p = 1.0 - (1.0 - p_edge) * (1.0 - p_graze) * (1.0 - rate[c])
                    if 0.5 * math.erfc(-zf / math.sqrt(2.0)) < p:
                        continue
            if rd > 0:
                fu, fv = np.float64(x), np.float64(y)
                j = fill[c]
                fill[c] += 1
                X[j, 0] = (fu * Kinv[0, 0] + fv * Kinv[0, 1] + Kinv[0, 2]) * rd
                X[j, 1] = (fu * Kinv[1, 0] + fv * Kinv[1, 1] + Kinv[1, 2]) * rd
                X[j, 2] = (fu * Kinv[2, 0] + fv * Kinv[2, 1] + Kinv[2, 2]) * rd
    offsets = np.zeros(n + 1, np.int64)
    keep = 0
    for c in range(n):
        a, b = start[c], fill[c]
        mx, my, mz = 0.0, 0.0, 0.0
        for j in range(a, b):
            mx += X[j, 0]
            my += X[j, 1]
            mz += X[j, 2]
        if b > a:
            mx /= b - a
            my /= b - a
            mz /= b - a
        for j in range(a, b):
            dx, dy, dz = X[j, 0] - mx, X[j, 1] - my, X[j, 2] - mz
            if math.sqrt(dx * dx + dy * dy + dz * dz) <= radius:
                X[keep, 0], X[keep, 1], X[keep, 2] = X[j, 0], X[j, 1], X[j, 2]
                keep += 1
        offsets[c + 1] = keep
    return X[:keep], offsets


@njit(cache=True)
def edge_squared_distance(label):  # pragma: no cover - compiled
    """Squared pixels to the nearest pixel of another label, 0 on both sides of a boundary
    (inf everywhere without one): the exact transform of
    :func:`cloudpose.kernels.sensor.edge_distance_kernel` (whose distance is ``sqrt`` of this
    + 1), as float64 (:func:`_edge_squared_distance`'s integers over every row)."""
    H, W = label.shape
    d = _edge_squared_distance(label, np.zeros(H, np.int64), np.full(H, W, np.int64))
    out = np.empty(d.shape)
    for y in range(d.shape[0]):
        for x in range(d.shape[1]):
            out[y, x] = np.inf if d[y, x] < 0 else np.float64(d[y, x])
    return out


@njit(cache=True)
def _edge_squared_distance(label, lo, hi):  # pragma: no cover - compiled
    """(H, W) int32 squared pixels from each pixel of the (H, W) label image to the nearest
    pixel with a 4-neighbour of another label, -1 where there is none: exact at the pixels
    of columns ``[lo[y], hi[y])`` of each row y whose run of one label (along the row) lies
    within those columns, undefined elsewhere.

    Columns first: each pixel's nearest boundary pixel in its column (a sweep down, row after
    row, the boundary test of a whole row at once, and one up); then along each row the lower
    envelope of the parabolas ``(x - p)^2 + f(p)`` over the columns ``[lo[y], hi[y])``
    (Felzenszwalb & Huttenlocher), in integers (:func:`_row_envelope`), so the values are
    exact. Why the columns suffice: a pixel's run [a, b] ends at boundary pixels (except at
    the image's edge), the nearer at distance D; its nearest boundary pixel lies within D of
    it, so its column lies in [x - D, x + D], within [a, b] (or past the edge)."""
    H, W = label.shape
    none = np.int32(1 << 30)  # a column without a boundary pixel
    g = np.empty((H, W), np.int32)
    bnd = np.empty(W, np.bool_)
    for y in range(H):
        cur = label[y]
        bnd[0] = W > 1 and cur[1] != cur[0]
        for x in range(1, W - 1):
            bnd[x] = (cur[x - 1] != cur[x]) | (cur[x + 1] != cur[x])
        if W > 1:
            bnd[W - 1] = cur[W - 2] != cur[W - 1]
        if y > 0:
            up = label[y - 1]
            for x in range(W):
                bnd[x] |= up[x] != cur[x]
        if y < H - 1:
            down = label[y + 1]
            for x in range(W):
                bnd[x] |= down[x] != cur[x]
        row = g[y]
        if y > 0:
            prev = g[y - 1]
            for x in range(W):
                row[x] = 0 if bnd[x] else min(prev[x] + 1, none)
        else:
            for x in range(W):
                row[x] = 0 if bnd[x] else none
    for y in range(H - 2, -1, -1):
        up, below = g[y], g[y + 1]
        for x in range(W):
            up[x] = min(up[x], below[x] + 1)
    f = np.empty(W, np.int64)
    v = np.empty(W, np.int64)
    zn = np.empty(W + 1, np.int64)
    zd = np.empty(W + 1, np.int64)
    for y in range(H):
        a, b = lo[y], hi[y]
        if a >= b:
            continue
        row = g[y]
        for x in range(a, b):
            c = np.int64(row[x])
            f[x - a] = -1 if c >= none else c * c
        _row_envelope(f[: b - a], row[a:b], v, zn, zd)
    return g


@njit(cache=True)
def _row_envelope(f, d, v, zn, zd):  # pragma: no cover - compiled
    """``d[q] = min_p (q - p)^2 + f[p]`` over the ``p`` with ``f[p] >= 0`` (-1 where there is
    none): Felzenszwalb & Huttenlocher's lower envelope of parabolas, each intersection kept as
    the fraction ``zn / zd`` (``zd > 0``) and compared by products, so no division.

    Args:
        f: (n,) int64 squared column distances, -1 = none.
        d: (n,) int32 out.
        v, zn, zd: scratch of (n,), (n + 1,), (n + 1,) int64.
    """
    n = f.shape[0]
    k = -1
    for q in range(n):
        fq = f[q]
        if fq < 0:
            continue
        if k < 0:
            k = 0
            v[0] = q
            continue
        while True:  # drop the parabolas the new one hides: s <= z[k] (z[0] = -inf)
            p = v[k]
            sn = (fq + q * q) - (f[p] + p * p)
            sd = 2 * (q - p)
            if k == 0 or sn * zd[k] > zn[k] * sd:
                break
            k -= 1
        k += 1
        v[k], zn[k], zd[k] = q, sn, sd
    if k < 0:
        for q in range(n):
            d[q] = -1
        return
    last = k
    k = 0
    for q in range(n):
        while k < last and zn[k + 1] < q * zd[k + 1]:
            k += 1
        dq = q - v[k]
        d[q] = dq * dq + f[v[k]]


@njit(cache=True)
def fps_soa(X, Y, Z, k, start, per_cell=64):  # pragma: no cover - compiled
    """Exact farthest point sampling of ``k`` of the float32 points ``(X, Y, Z)`` from index
    ``start``: the points bucketed by a grid over x and y, each bucket's coordinates
    contiguous; after each pick a bucket is skipped when its box is farther from the new
    sample than the largest nearest-sample distance inside it.

    Returns:
        (k,) int64 indices (1 <= k <= N): :func:`cloudpose.kernels.fps.fps_order`'s order
        (the same float32 squared distances, ties to the highest index).
    """
    n = X.shape[0]
    cells, cstart, index = grid_buckets(X, Y, per_cell)
    QX = np.empty(n, np.float32)
    QY = np.empty(n, np.float32)
    QZ = np.empty(n, np.float32)
    for j in range(n):
        i = index[j]
        QX[j], QY[j], QZ[j] = X[i], Y[i], Z[i]
    bx0, by0, bz0 = np.full(cells, np.inf), np.full(cells, np.inf), np.full(cells, np.inf)
    bx1, by1, bz1 = np.full(cells, np.inf), np.full(cells, np.inf), np.full(cells, np.inf)
    cmax = np.full(cells, np.inf, np.float32)
    carg = np.full(cells, -1, np.int64)  # stored position of the cell's farthest point
    visit = np.zeros(cells, np.bool_)
    for c in range(cells):
        if cstart[c] == cstart[c + 1]:
            cmax[c] = -1.0  # never visited, never picked
            continue
        bx1[c] = by1[c] = bz1[c] = -np.inf
        for j in range(cstart[c], cstart[c + 1]):
            bx0[c] = min(bx0[c], np.float64(QX[j]))
            by0[c] = min(by0[c], np.float64(QY[j]))
            bz0[c] = min(bz0[c], np.float64(QZ[j]))
            bx1[c] = max(bx1[c], np.float64(QX[j]))
            by1[c] = max(by1[c], np.float64(QY[j]))
            bz1[c] = max(bz1[c], np.float64(QZ[j]))
        carg[c] = cstart[c]
    used = np.empty(cells, np.int64)  # the non-empty cells: the only ones ever visited
    nu = 0
    for c in range(cells):
        if cstart[c] < cstart[c + 1]:
            used[nu] = c
            nu += 1
    near = np.full(n, np.inf, np.float32)
    out = np.empty(k, np.int64)
    cur = 0
    for j in range(n):
        if index[j] == start:
            cur = j
    for s in range(k):
        out[s] = index[cur]
        px, py, pz = QX[cur], QY[cur], QZ[cur]
        xs, ys, zs = np.float64(px), np.float64(py), np.float64(pz)
        for q in range(nu):  # each cell's box distance to the sample
            c = used[q]
            dx = max(bx0[c] - xs, 0.0, xs - bx1[c])
            dy = max(by0[c] - ys, 0.0, ys - by1[c])
            dz = max(bz0[c] - zs, 0.0, zs - bz1[c])
            # visited when a point may get closer (margin 1e-6 >> float32 rounding of a
            # squared distance)
            visit[c] = (dx * dx + dy * dy + dz * dz) * (1.0 - 1e-6) <= cmax[c]
        nxt = cur  # the next sample: the farthest point, ties to the highest index
        best_v = np.float32(-1.0)
        for q in range(nu):
            c = used[q]
            if visit[c]:
                a, b = cstart[c], cstart[c + 1]
                top = np.float32(-1.0)
                for j in range(a, b):  # one vector loop: the new distances and their largest
                    ex = QX[j] - px
                    ey = QY[j] - py
                    ez = QZ[j] - pz
                    d = min(near[j], ex * ex + ey * ey + ez * ez)
                    near[j] = d
                    top = max(top, d)
                best = b - 1
                while near[best] != top:  # ascending index within a cell: ties to the last
                    best -= 1
                cmax[c] = top
                carg[c] = best
            if cmax[c] > best_v or (cmax[c] == best_v and index[carg[c]] > index[nxt]):
                best_v = cmax[c]
                nxt = carg[c]
        cur = nxt
    return out


ZIGGURAT_R = 3.6541528853610088
"""Where the tail of the 256-layer normal ziggurat starts (Marsaglia & Tsang 2000)."""
ZIGGURAT_V = 0.00492867323399
"""The area of each of its layers (the base layer's with the tail)."""


def ziggurat_tables() -> tuple[np.ndarray, np.ndarray]:
    """(257,) float64 the right edges of the 256 layers of the normal ziggurat (layer 0's the
    width whose rectangle has the area of the base strip and the tail) and (257,) float64
    exp(-x^2 / 2) at them: layer i is the box [0, x_i] x [f(x_i), f(x_{i+1})]."""
    r, v = ZIGGURAT_R, ZIGGURAT_V
    x = np.zeros(257)
    x[0] = v / math.exp(-0.5 * r * r)
    x[1] = r
    for i in range(1, 255):
        x[i + 1] = math.sqrt(-2.0 * math.log(math.exp(-0.5 * x[i] ** 2) + v / x[i]))
    x[256] = 0.0
    return x, np.exp(-0.5 * x**2)


DRAW_WORDS = 256
"""64-bit words each draw of a counter stream owns (:func:`stream_word`); a normal takes one
word, ~1.2% of them two, the tail two per try: a draw never comes near 256."""


@njit(cache=True, inline="always")
def _mix64(z):  # pragma: no cover - compiled
    """SplitMix64's output function (Steele, Lea & Flood 2014) of a uint64."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(cache=True, inline="always")
def stream_word(key, i, j):  # pragma: no cover - compiled
    """Word ``j`` of draw ``i`` of the counter stream ``key``: output ``i * DRAW_WORDS + j``
    of the SplitMix64 generator seeded with ``key`` (a pure function of its arguments, so a
    pass reads any draw where it needs it, in any order)."""
    c = np.uint64(i) * np.uint64(DRAW_WORDS) + np.uint64(j + 1)
    return _mix64(np.uint64(key) + c * np.uint64(0x9E3779B97F4A7C15))


@njit(cache=True, inline="always")
def uniform_draw(key, i):  # pragma: no cover - compiled
    """Draw ``i`` of stream ``key`` as a float32 uniform on [0, 1) (the word's top 24 bits,
    as numpy's float32 ``random``)."""
    return np.float32(np.float64(stream_word(key, i, 0) >> np.uint64(40)) * (1.0 / 16777216.0))


@njit(cache=True, inline="always")
def normal_draw(key, i, xs, fs):  # pragma: no cover - compiled
    """Draw ``i`` of stream ``key`` as a standard normal (float64; version 3 rounds it to
    float32) by the 256-layer ziggurat (Marsaglia & Tsang 2000) on the draw's words, in order:
    of each word, bits 0-7 pick the layer, bit 8 the sign and bits 11-63 the uniform; a draw
    outside its layer's core takes one more word (the wedge's height) or two per try
    (Marsaglia's tail beyond ``ZIGGURAT_R``). ``xs``, ``fs``: :func:`ziggurat_tables`."""
    scale = 1.0 / 9007199254740992.0  # 2^-53
    r = xs[1]
    j = 0
    while True:
        b = stream_word(key, i, j)
        j += 1
        k = np.int64(b & np.uint64(255))
        neg = (b >> np.uint64(8)) & np.uint64(1)
        x = np.float64(b >> np.uint64(11)) * scale * xs[k]
        if x < xs[k + 1]:
            break
        if k == 0:  # the tail: x = r + a, a exponential, accepted as Marsaglia's
            while True:
                u1 = 1.0 - np.float64(stream_word(key, i, j) >> np.uint64(11)) * scale
                u2 = 1.0 - np.float64(stream_word(key, i, j + 1) >> np.uint64(11)) * scale
                j += 2
                a = -math.log(u1) / r
                if -2.0 * math.log(u2) >= a * a:
                    break
            x = r + a
            break
        u = np.float64(stream_word(key, i, j) >> np.uint64(11)) * scale
        j += 1
        if fs[k] + u * (fs[k + 1] - fs[k]) < math.exp(-0.5 * x * x):
            break
    return -x if neg else x


@njit(cache=True)
def normal_draws(key, n, xs, fs):  # pragma: no cover - compiled
    """(n,) float32 draws 0 .. n - 1 of :func:`normal_draw`."""
    out = np.empty(n, np.float32)
    for i in range(n):
        out[i] = np.float32(normal_draw(key, i, xs, fs))
    return out
