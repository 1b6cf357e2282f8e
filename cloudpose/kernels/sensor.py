"""Per-pixel geometry of the version-2 sensor on object pixels: the depth jump to the
4-neighbours and the incidence cosine, in one pass over the pixels.

The numpy twin is :func:`cloudpose.data.synth.sensor.object_pixel_geometry` (several passes
of fancy indexing over every object pixel of an on-line scene, ~55,000 a scene); the kernel
computes the same expressions pixel by pixel.
"""

from __future__ import annotations

import numpy as np

from cloudpose.kernels.backend import njit

__all__ = ["object_pixel_geometry_kernel"]


@njit(cache=True)
def _ray(Kinv, s, x, y):  # pragma: no cover - compiled
    """Component ``s`` of ``Kinv @ (x, y, 1)``."""
    return Kinv[s, 0] * x + Kinv[s, 1] * y + Kinv[s, 2]


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
        x = float(u[i])
        y = float(v[i])
        zr, zl = pad[vp, up + 1], pad[vp, up - 1]
        zd, zu = pad[vp + 1, up], pad[vp - 1, up]
        gx0 = _ray(Kinv, 0, x + 1, y) * zr - _ray(Kinv, 0, x - 1, y) * zl
        gx1 = _ray(Kinv, 1, x + 1, y) * zr - _ray(Kinv, 1, x - 1, y) * zl
        gx2 = _ray(Kinv, 2, x + 1, y) * zr - _ray(Kinv, 2, x - 1, y) * zl
        gy0 = _ray(Kinv, 0, x, y + 1) * zd - _ray(Kinv, 0, x, y - 1) * zu
        gy1 = _ray(Kinv, 1, x, y + 1) * zd - _ray(Kinv, 1, x, y - 1) * zu
        gy2 = _ray(Kinv, 2, x, y + 1) * zd - _ray(Kinv, 2, x, y - 1) * zu
        n0 = gx1 * gy2 - gx2 * gy1
        n1 = gx2 * gy0 - gx0 * gy2
        n2 = gx0 * gy1 - gx1 * gy0
        r0 = _ray(Kinv, 0, x, y)
        r1 = _ray(Kinv, 1, x, y)
        r2 = _ray(Kinv, 2, x, y)
        norm = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2) * np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        if norm > 0:
            cos[i] = min(max(abs(n0 * r0 + n1 * r1 + n2 * r2) / norm, 0.0), 1.0)
    return jump, cos
