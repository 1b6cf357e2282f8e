"""Per-pixel geometry of the version-2 sensor on object pixels: the depth jump to the
4-neighbours and the incidence cosine, in one pass over the pixels.

The numpy twin is :func:`cloudpose.data.synth.sensor.object_pixel_geometry` (several passes
of fancy indexing over every object pixel of an on-line scene, ~55,000 a scene); the kernel
computes the same expressions pixel by pixel.
"""

from __future__ import annotations

import math

import numpy as np

from cloudpose.kernels.backend import njit

__all__ = ["object_pixel_geometry_kernel"]


@njit(cache=True)
def _ray(Kinv, s, x, y):  # pragma: no cover - compiled
    """Component ``s`` of ``Kinv @ (x, y, 1)``."""
    return Kinv[s, 0] * x + Kinv[s, 1] * y + Kinv[s, 2]


@njit(cache=True, inline="always")
def incidence_terms(Kinv, x, y, zl, zr, zu, zd):  # pragma: no cover - compiled
    """``(|n . r|, |n| |r|)`` at pixel (x, y): n the surface normal from central differences
    of the back-projected 4-neighbours (rays with z = 1 times the depths left, right, up and
    down), r the pixel's ray; the incidence cosine is their ratio. One expression for the
    version-2 kernel and the version-3 passes (:mod:`cloudpose.kernels.scene_pass`), which
    must agree to the bit."""
    gx0 = _ray(Kinv, 0, x + 1, y) * zr - _ray(Kinv, 0, x - 1, y) * zl
    gx1 = _ray(Kinv, 1, x + 1, y) * zr - _ray(Kinv, 1, x - 1, y) * zl
    gx2 = _ray(Kinv, 2, x + 1, y) * zr - _ray(Kinv, 2, x - 1, y) * zl
    gy0 = _ray(Kinv, 0, x, y + 1) * zd - _ray(Kinv, 0, x, y - 1) * zu
    gy1 = _ray(Kinv, 1, x, y + 1) * zd - _ray(Kinv, 1, x, y - 1) * zu
    gy2 = _ray(Kinv, 2, x, y + 1) * zd - _ray(Kinv, 2, x, y - 1) * zu
    n0 = gx1 * gy2 - gx2 * gy1
    n1 = gx2 * gy0 - gx0 * gy2
    n2 = gx0 * gy1 - gx1 * gy0
    r0, r1, r2 = _ray(Kinv, 0, x, y), _ray(Kinv, 1, x, y), _ray(Kinv, 2, x, y)
    norm = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2) * math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    return abs(n0 * r0 + n1 * r1 + n2 * r2), norm


@njit(cache=True)
def object_pixel_geometry_kernel(pad, lpad, v, u, Kinv):  # pragma: no cover - compiled
    """``(jump, cos)`` of the object pixels ``(v, u)`` of a depth image padded by one pixel
    of 0 (``pad``, float64) and its label image padded alike (``lpad``): see the twin."""
    m = v.shape[0]
    H = pad.shape[0] - 2
    W = pad.shape[1] - 2
    jump = np.zeros(m)
    cos = np.ones(m)
    dv = (-1, 1, 0, 0)
    du = (0, 0, -1, 1)
    for i in range(m):
        vp = v[i] + 1
        up = u[i] + 1
        z = pad[vp, up]
        c = lpad[vp, up]
        best = 0.0
        all_valid = True
        same = True
        for k in range(4):
            nb = pad[vp + dv[k], up + du[k]]
            if nb > 0:
                d = nb - z if z > 0 else 0.0
            else:
                d = 0.0
                all_valid = False
            if abs(d) > abs(best):
                best = d
            if lpad[vp + dv[k], up + du[k]] != c:
                same = False
        jump[i] = best
        if not (all_valid and same and 1 <= v[i] <= H - 2 and 1 <= u[i] <= W - 2):
            continue
        # central differences of the back-projected neighbours (rays with z = 1, times depth)
        zr, zl = pad[vp, up + 1], pad[vp, up - 1]
        zd, zu = pad[vp + 1, up], pad[vp - 1, up]
        dot, norm = incidence_terms(Kinv, float(u[i]), float(v[i]), zl, zr, zu, zd)
        if norm > 0:
            cos[i] = min(max(dot / norm, 0.0), 1.0)
    return jump, cos


@njit(cache=True)
def _squared_distance_1d(f, d, v, z):  # pragma: no cover - compiled
    """Felzenszwalb & Huttenlocher's lower envelope of parabolas: ``d[q] = min_p (q - p)^2 +
    f[p]`` for one row (``v``, ``z`` scratch of len(f) and len(f) + 1)."""
    n = f.shape[0]
    k = -1
    for q in range(n):
        if f[q] == np.inf:
            continue
        if k < 0:
            k = 0
            v[0] = q
            z[0] = -np.inf
            z[1] = np.inf
            continue
        s = ((f[q] + q * q) - (f[v[k]] + v[k] * v[k])) / (2.0 * q - 2.0 * v[k])
        while s <= z[k]:
            k -= 1
            s = ((f[q] + q * q) - (f[v[k]] + v[k] * v[k])) / (2.0 * q - 2.0 * v[k])
        k += 1
        v[k] = q
        z[k] = s
        z[k + 1] = np.inf
    if k < 0:
        for q in range(n):
            d[q] = np.inf
        return
    k = 0
    for q in range(n):
        while z[k + 1] < q:
            k += 1
        dq = q - v[k]
        d[q] = dq * dq + f[v[k]]


@njit(cache=True)
def on_boundary(label, y, x, H, W):  # pragma: no cover - compiled
    """Whether pixel (y, x) of the (H, W) label image has a 4-neighbour of another label."""
    c = label[y, x]
    return (
        (y > 0 and label[y - 1, x] != c)
        or (y < H - 1 and label[y + 1, x] != c)
        or (x > 0 and label[y, x - 1] != c)
        or (x < W - 1 and label[y, x + 1] != c)
    )


@njit(cache=True)
def edge_distance_kernel(label):  # pragma: no cover - compiled
    """Pixels to the nearest pixel of another label, 1 on both sides of a boundary (the exact
    Euclidean distance transform by two passes of 1-D lower envelopes, Felzenszwalb &
    Huttenlocher, Theory of Computing 2012): the twin is
    :func:`cloudpose.data.synth.sensor.edge_distance` (scipy's ``distance_transform_edt``).

    Args:
        label: (H, W) integer label image.

    Returns:
        (H, W) float64 distances (>= 1; inf everywhere when there is no boundary).
    """
    H, W = label.shape
    g = np.empty((H, W))
    for y in range(H):
        for x in range(W):
            b = on_boundary(label, y, x, H, W)
            g[y, x] = 0.0 if b else np.inf
    n = max(H, W)
    f = np.empty(n)
    d = np.empty(n)
    v = np.empty(n, np.int64)
    z = np.empty(n + 1)
    for x in range(W):  # columns
        for y in range(H):
            f[y] = g[y, x]
        _squared_distance_1d(f[:H], d[:H], v, z)
        for y in range(H):
            g[y, x] = d[y]
    out = np.empty((H, W))
    for y in range(H):  # rows
        for x in range(W):
            f[x] = g[y, x]
        _squared_distance_1d(f[:W], d[:W], v, z)
        for x in range(W):
            out[y, x] = np.sqrt(d[x]) + 1.0
    return out


@njit(cache=True)
def smoothed_at_kernel(noise, weights, v, u):  # pragma: no cover - compiled
    """A separable filter with periodic borders (scipy.ndimage's ``mode="wrap"``: along axis 0,
    then axis 1) of ``noise`` (H, W), evaluated at the pixels ``(v, u)`` only: the first pass
    over every row, the second at those pixels. ``weights``: (2r + 1,) the 1-D kernel."""
    H, W = noise.shape
    r = weights.shape[0] // 2
    # first pass into columns r .. r + W - 1 of a row padded periodically by r each side
    tmp = np.zeros((H, W + 2 * r))
    for y in range(H):
        for j in range(2 * r + 1):
            yy = (y + j - r) % H
            wj = weights[j]
            for x in range(W):
                tmp[y, r + x] += wj * noise[yy, x]
        for x in range(r):
            tmp[y, x] = tmp[y, r + (x - r) % W]
            tmp[y, r + W + x] = tmp[y, r + x % W]
    m = v.shape[0]
    out = np.empty(m)
    for i in range(m):
        s = 0.0
        y = v[i]
        for j in range(2 * r + 1):
            s += weights[j] * tmp[y, u[i] + j]
        out[i] = s
    return out


@njit(cache=True)
def object_readings_kernel(
    z, jump, cos, normal, u_edge, mix, edge_dist, field, lut, c, noise, drop, max_range
):  # pragma: no cover - compiled
    """The version-2 sensor's readings of object pixels from their draws, in one pass: the
    twin is the numpy tail of :func:`cloudpose.data.synth.sensor.add_sensor_noise_v2_objects`
    (``_noisy``, the range test, ``DropoutModel.probability`` and the field threshold).

    Args:
        z, jump, cos: (m,) clean depth, edge jump (metres) and incidence cosine.
        normal, u_edge, mix: (m,) the pixels' draws.
        edge_dist, field: (m,) distance to another label (pixels) and the correlated uniform.
        lut: (256,) missing rate per class id (0 for 0); c: (m,) class ids.
        noise: (sigma0, sigma2, focal_baseline, subpixel, edge_jump, edge_flying).
        drop: (edge_rate, edge_scale, graze_cos, graze_width).
        max_range: metres.

    Returns:
        (m,) float64 readings, metres, 0 = none.
    """
    sigma0, sigma2, fb, sub, edge_jump, edge_flying = noise
    edge_rate, edge_scale, graze_cos, graze_width = drop
    m = z.shape[0]
    out = np.empty(m)
    for i in range(m):
        zi = z[i]
        valid = zi > 0
        r = zi + normal[i] * (sigma0 + sigma2 * (zi - 0.4) ** 2)
        if abs(jump[i]) > edge_jump and u_edge[i] < edge_flying:
            r = r + mix[i] * jump[i]
        disparity = fb / (r if valid else 1.0)
        disparity = max(np.round(disparity / sub), 1.0) * sub
        r = fb / disparity
        if not valid or r <= 0 or r > max_range:
            r = 0.0
        p_edge = edge_rate * np.exp(-(edge_dist[i] - 1.0) / edge_scale)
        x = min(max((cos[i] - graze_cos) / graze_width, -50.0), 50.0)
        p_graze = 1.0 / (1.0 + np.exp(x))
        p = 1.0 - (1.0 - p_edge) * (1.0 - p_graze) * (1.0 - lut[c[i]])
        out[i] = 0.0 if field[i] < p else r
    return out
