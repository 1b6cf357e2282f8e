"""A z-buffer of triangle meshes: the depth and instance of the nearest surface at every pixel
centre of a window, what a ray cast through the pixel centres gives.

A ray through pixel centre (x, y) hits a triangle in front of the camera exactly when (x, y)
lies in the triangle's projection (a central projection maps the triangle onto its image), and
the depth of the hit is the depth of the triangle's plane along that ray. So each triangle is
projected once and tested at the pixel centres of its bounding box; the depth is the plane's,
interpolated perspective-correctly (1/z is affine in the image over a planar triangle: the
barycentric weights of the pixel centre applied to 1/z of the vertices). Equal to Open3D's ray cast (the twin,
:meth:`cloudpose.data.synth.render.Renderer.render_instanced`) to float rounding: micrometres of
depth, and a pixel centre within rounding of a silhouette edge may flip between hit and miss.
No face is culled (rays hit both sides); edge-on triangles (zero projected area) are skipped,
as a ray grazing them sees the neighbouring faces.

Triangles need every vertex in front of the camera: the caller keeps the ray cast for an object
that reaches behind it.
"""

from __future__ import annotations

import math

from cloudpose.kernels.backend import njit

__all__ = ["rasterize_mesh"]


@njit(cache=True)
def rasterize_mesh(z, uv, F, v0, u0, depth, index, instance):  # pragma: no cover
    """Draw one posed mesh into a z-buffer in place.

    Args:
        z: (M,) float64 camera-frame depth of the vertices (every z > 0).
        uv: (M, 2) float64 their pixel coordinates.
        F: (T, 3) integer triangles.
        v0, u0: image pixel of the buffer's (0, 0).
        depth: (h, w) float64 z-buffer, metres (inf = nothing yet); updated.
        index: (h, w) int64 instance of the nearest surface (-1 = none); updated.
        instance: the value written to ``index`` where this mesh is nearest.
    """
    h, w = depth.shape
    for f in range(F.shape[0]):
        a, b, c = F[f, 0], F[f, 1], F[f, 2]
        ax, ay = uv[a, 0], uv[a, 1]
        bx, by = uv[b, 0], uv[b, 1]
        cx, cy = uv[c, 0], uv[c, 1]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if area == 0.0 or not math.isfinite(area):
            continue
        xlo = max(math.ceil(min(ax, bx, cx)), u0)
        xhi = min(math.floor(max(ax, bx, cx)), u0 + w - 1)
        ylo = max(math.ceil(min(ay, by, cy)), v0)
        yhi = min(math.floor(max(ay, by, cy)), v0 + h - 1)
        if xlo > xhi or ylo > yhi:
            continue
        # perspective-correct depth: 1/z is affine in the image plane over a planar triangle
        iza, izb, izc = 1.0 / z[a], 1.0 / z[b], 1.0 / z[c]
        sgn = 1.0 if area > 0 else -1.0
        for y in range(ylo, yhi + 1):
            fy = float(y)
            # edge functions are linear in x along the row: w_i = p_i x + q_i; the pixels with
            # every sgn * w_i >= 0 form one span (widened by a pixel against rounding; the
            # exact test below decides)
            p0, q0 = -(cy - by), (cx - bx) * (fy - by) + (cy - by) * bx
            p1, q1 = -(ay - cy), (ax - cx) * (fy - cy) + (ay - cy) * cx
            p2, q2 = -(by - ay), (bx - ax) * (fy - ay) + (by - ay) * ax
            lo, hi = float(xlo), float(xhi)
            for pi, qi in ((p0, q0), (p1, q1), (p2, q2)):
                ps, qs = sgn * pi, sgn * qi
                if ps > 0:
                    lo = max(lo, -qs / ps - 1.0)
                elif ps < 0:
                    hi = min(hi, -qs / ps + 1.0)
                elif qs < 0:
                    hi = lo - 1.0
            if lo > hi:
                continue
            for x in range(max(math.ceil(lo), xlo), min(math.floor(hi), xhi) + 1):
                fx = float(x)
                # edge functions, same sign as the area inside (either winding: no culling)
                w0 = (cx - bx) * (fy - by) - (cy - by) * (fx - bx)
                w1 = (ax - cx) * (fy - cy) - (ay - cy) * (fx - cx)
                w2 = (bx - ax) * (fy - ay) - (by - ay) * (fx - ax)
                if sgn * w0 < 0 or sgn * w1 < 0 or sgn * w2 < 0:
                    continue
                zp = area / (w0 * iza + w1 * izb + w2 * izc)
                py, px = y - v0, x - u0
                if zp < depth[py, px]:
                    depth[py, px] = zp
                    index[py, px] = instance
