"""The sensor: background depth (table, floor, wall) and a Kinect-like depth noise model."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.special import ndtr

from cloudpose.data.synth.scenes import MAX_RANGE, Plane
from cloudpose.kernels.backend import enabled
from cloudpose.kernels.sensor import (
    edge_distance_kernel,
    object_pixel_geometry_kernel,
    object_readings_kernel,
    smoothed_at_kernel,
)

# --------------------------------------------------------------------------- rendering


def background_depth(
    K: np.ndarray, shape: tuple[int, int], world_to_camera: np.ndarray, planes: Sequence[Plane]
) -> np.ndarray:
    """Depth of the nearest background plane patch along each pixel ray.

    Args:
        K: (3, 3) intrinsics.
        shape: (H, W).
        world_to_camera: (3, 4) extrinsics.
        planes: patches in world coordinates.

    Returns:
        (H, W) float64 depth (z, metres); 0 where no patch is hit within :data:`MAX_RANGE`.
    """
    H, W = shape
    v, u = np.mgrid[0:H, 0:W]
    return _plane_depth(pixel_rays(np.linalg.inv(K), v, u), world_to_camera, planes)


def pixel_rays(K_inv: np.ndarray, v: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Rays through the pixel centres ``(v, u)`` (any shape, alike), scaled to z = 1.

    Args:
        K_inv: (3, 3) inverse intrinsics.
        v, u: pixel rows and columns.

    Returns:
        (..., 3) float64 ``K^-1 (u, v, 1)``.
    """
    pix = np.stack([u, v, np.ones_like(u)], axis=-1).astype(np.float64)
    return pix @ K_inv.T


def _plane_depth(
    rays: np.ndarray, world_to_camera: np.ndarray, planes: Sequence[Plane]
) -> np.ndarray:
    """Depth (z) of the nearest background plane patch along rays (..., 3) with z = 1; 0 where
    none is hit within :data:`MAX_RANGE`."""
    Rc, tc = world_to_camera[:, :3], world_to_camera[:, 3]
    out = np.full(rays.shape[:-1], np.inf)
    for pl in planes:
        n_c = Rc @ pl.normal
        p_c = Rc @ pl.point + tc
        denom = rays @ n_c
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (p_c @ n_c) / denom
        hit = np.isfinite(z) & (z > 0)
        if pl.axes is not None:
            x_c = rays * z[..., None] - p_c  # (..., 3) from the patch centre, camera frame
            ax_c = pl.axes @ Rc.T  # (2, 3)
            local = np.abs(x_c @ ax_c.T)  # (..., 2)
            hit &= (local <= pl.half_extent).all(axis=-1)
        out = np.where(hit & (z < out), z, out)
    out[~np.isfinite(out) | (out > MAX_RANGE)] = 0.0
    return out


@dataclass(frozen=True)
class NoiseModel:
    """Depth-sensor noise (Kinect v1 / Asus Xtion-like; the real YCB-Video sensor).

    Attributes:
        sigma0: axial noise at 0.4 m, metres (Nguyen et al. 2012: 1.2 mm).
        sigma2: quadratic growth, metres per m^2 (Nguyen et al. 2012: 1.9 mm).
        focal_baseline: focal length (px) x baseline (m) of the disparity quantisation.
        subpixel: disparity resolution, pixels.
        edge_jump: a pixel lies on a depth edge when a 4-neighbour differs by more, metres.
        edge_dropout: share of edge pixels without a reading.
        edge_flying: share of edge pixels mixed with the neighbour across the edge.
        dropout: share of all pixels without a reading.
    """

    sigma0: float = 0.0012
    sigma2: float = 0.0019
    focal_baseline: float = 580.0 * 0.075
    subpixel: float = 1.0 / 8.0
    edge_jump: float = 0.02
    edge_dropout: float = 0.5
    edge_flying: float = 0.15
    dropout: float = 0.005

    def kernel_args(self) -> tuple[float, ...]:
        """The parameters as the compiled sensor kernels take them: (sigma0, sigma2,
        focal_baseline, subpixel, edge_jump, edge_flying)."""
        return (
            self.sigma0,
            self.sigma2,
            self.focal_baseline,
            self.subpixel,
            self.edge_jump,
            self.edge_flying,
        )


def add_sensor_noise(
    depth: np.ndarray, rng: np.random.Generator, model: NoiseModel = NoiseModel()
) -> np.ndarray:
    """Apply the sensor noise model to a clean depth image.

    Args:
        depth: (H, W) clean depth, metres, 0 = no surface.
        rng: random generator.
        model: noise parameters.

    Returns:
        (H, W) float64 noisy depth, metres, 0 = no reading (never a reading where there was none).
    """
    noisy, drop = _readings(depth, rng, model)
    noisy[drop] = 0.0
    return noisy


def _readings(
    depth: np.ndarray, rng: np.random.Generator, model: NoiseModel
) -> tuple[np.ndarray, np.ndarray]:
    """The noisy readings of :func:`add_sensor_noise` and the pixels its dropout takes out.

    Returns:
        (H, W) float64 readings, metres (0 where there is no surface or it is out of range),
        and (H, W) bool edge and random dropout (not yet applied).
    """
    z = np.asarray(depth, dtype=np.float64)
    H, W = z.shape
    pad = np.pad(z, 1)
    nbs = np.stack([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]], axis=-1)
    jump = _depth_jump(z, nbs)
    normal = rng.standard_normal((H, W))
    u_edge = rng.random((H, W))
    noisy = _noisy(z, jump, normal, u_edge, rng.random((H, W)), model)
    edge = np.abs(jump) > model.edge_jump
    drop = (edge & (u_edge > 1.0 - model.edge_dropout)) | (rng.random((H, W)) < model.dropout)
    return noisy, drop


def _depth_jump(z: np.ndarray, nbs: np.ndarray) -> np.ndarray:
    """The depth jump of each pixel: the signed difference to the 4-neighbour that differs
    most (the first on ties), over neighbours with depth; 0 where the pixel has none.

    Args:
        z: (...) clean depth, metres, 0 = none.
        nbs: (..., 4) the clean depth of the neighbours up, down, left, right (0 = none).

    Returns:
        (...) float64 jumps, metres.
    """
    diff = np.where((nbs > 0) & (z > 0)[..., None], nbs - z[..., None], 0.0)  # (..., 4)
    k = np.abs(diff).argmax(axis=-1)
    return np.take_along_axis(diff, k[..., None], axis=-1)[..., 0]


def _noisy(z, jump, normal, u_edge, mix, model: NoiseModel) -> np.ndarray:
    """Readings from clean depth ``z`` (any shape, metres, 0 = none), its depth jump and the
    draws of one pixel each: Gaussian axial noise growing with depth (``normal``), a flying
    pixel on a depth edge mixed towards the neighbour across it (``u_edge`` < ``edge_flying``,
    by the share ``mix``), and the disparity quantisation; 0 where there is no surface or the
    reading is out of range."""
    valid = z > 0
    noisy = z + normal * (model.sigma0 + model.sigma2 * (z - 0.4) ** 2)
    flying = (np.abs(jump) > model.edge_jump) & (u_edge < model.edge_flying)
    noisy = np.where(flying, noisy + mix * jump, noisy)
    disparity = model.focal_baseline / np.where(valid, noisy, 1.0)
    disparity = np.maximum(np.round(disparity / model.subpixel), 1.0) * model.subpixel
    noisy = model.focal_baseline / disparity
    noisy[~valid | (noisy <= 0) | (noisy > MAX_RANGE)] = 0.0
    return noisy


# --------------------------------------------------------------------------- missing depth


@dataclass(frozen=True)
class DropoutModel:
    """Missing depth on object pixels, as the real YCB-Video frames show it.

    A reading on an object pixel is missing with probability
    ``1 - (1 - p_edge) (1 - p_graze) (1 - p_class)``:

    - ``p_edge = edge_rate * exp(-(d - 1) / edge_scale)``, d = pixels to the nearest pixel of
      another label (1 on the boundary ring): depth edges and the projector's shadow;
    - ``p_graze = 1 / (1 + exp((cos - graze_cos) / graze_width))``, cos = cosine of the angle
      between the pixel's ray and the surface normal: grazing surfaces return no pattern;
    - ``p_class``: a rate per class for dark or specular surfaces (``class_rates``), the
      ``default_rate`` for classes the fit did not see.

    The defaults are :func:`cloudpose.data.synth.sensor_fit.fit_dropout` on the two real
    frames the repository carries (see that function; ``cloudpose synth --compare-real``
    prints the fit beside these values).

    Attributes:
        edge_rate: missing share on the boundary ring.
        edge_scale: decay length of the edge term, pixels.
        graze_cos: incidence cosine at which half of the readings are missing.
        graze_width: width of the logistic in cosine units.
        class_rates: ((class id, rate), ...) for the classes seen in the fit.
        default_rate: rate of the other classes.
        blob_sigma: pixels; the missing pixels are drawn from a spatially correlated uniform
            field (Gaussian-smoothed white noise of this width, mapped back to uniform), so
            they come in small blobs as in the real frames, at the same rate. 0 = independent.
    """

    edge_rate: float = 0.0
    edge_scale: float = 1.0
    graze_cos: float = 0.0
    graze_width: float = 0.05
    class_rates: tuple[tuple[int, float], ...] = ()
    default_rate: float = 0.0
    blob_sigma: float = 0.0

    def class_rate(self, cls_id: int) -> float:
        """The missing rate of class ``cls_id`` away from edges and grazing angles."""
        return dict(self.class_rates).get(int(cls_id), self.default_rate)

    def probability(
        self, edge_distance: np.ndarray, cos_incidence: np.ndarray, label: np.ndarray
    ) -> np.ndarray:
        """Per-pixel missing probability (any shape; the three arrays alike).

        Args:
            edge_distance: pixels to the nearest pixel of another label (>= 1).
            cos_incidence: |cos| of the angle between ray and surface normal, in [0, 1].
            label: class ids (0 = background: the class term is 0 there).
        """
        p_edge = self.edge_rate * np.exp(-(np.asarray(edge_distance) - 1.0) / self.edge_scale)
        x = np.clip((np.asarray(cos_incidence) - self.graze_cos) / self.graze_width, -50, 50)
        p_graze = 1.0 / (1.0 + np.exp(x))
        ids = np.asarray(label).astype(np.int64)
        p_class = self.rate_table(int(ids.max(initial=0)) + 1)[ids]
        return 1.0 - (1.0 - p_edge) * (1.0 - p_graze) * (1.0 - p_class)

    def kernel_args(self) -> tuple[float, ...]:
        """The parameters as the compiled sensor kernels take them: (edge_rate, edge_scale,
        graze_cos, graze_width); the class term is :meth:`rate_table`."""
        return (self.edge_rate, self.edge_scale, self.graze_cos, self.graze_width)

    def rate_table(self, size: int = 256) -> np.ndarray:
        """(max(256, size),) float64 the class term of every class id (0 for background)."""
        lut = np.full(max(256, size), self.default_rate)
        for c, r in self.class_rates:
            lut[c] = r
        lut[0] = 0.0
        return lut


REAL_DROPOUT = DropoutModel(
    edge_rate=0.4835,
    edge_scale=3.619,
    graze_cos=0.1097,
    graze_width=0.0751,
    class_rates=(
        (2, 0.0),
        (4, 0.0),
        (5, 0.0),
        (8, 0.0),
        (10, 0.0),
        (14, 0.0452),
        (15, 0.0951),
        (21, 0.0314),
    ),
    default_rate=0.0269,
    blob_sigma=4.0,
)
"""The missing-depth model of the version-2 sensor:
:func:`~cloudpose.data.synth.sensor_fit.fit_dropout` on the two real frames in tests/data
(ycb_real, annotated: 009_gelatin_box, 025_mug, 061_foam_brick; demo_no_gt, unannotated:
003_cracker_box, 005_tomato_soup_can, 006_mustard_bottle, 011_banana, 035_power_drill),
141,656 object pixels, 10.7% of them without depth. Two frames support the edge and grazing
terms and a rate for these eight classes (the black drill 9.5%, the glossy mug 4.5%); the
other 13 classes get the pixel-weighted mean rate.
``blob_sigma`` is chosen, not fitted: at 4 px the chance that an object pixel next to a
missing one misses too is 0.84-0.86 on synthetic frames, 0.86 and 0.90 on the two real ones
(independent draws give 0.33)."""


def edge_distance(label: np.ndarray) -> np.ndarray:
    """Pixels to the nearest pixel of another label: 1 on both sides of a label boundary.

    Args:
        label: (H, W) integer label image.

    Returns:
        (H, W) float64 Euclidean distance in pixels (>= 1).
    """
    lab = np.asarray(label)
    boundary = np.zeros(lab.shape, dtype=bool)
    dv = lab[1:] != lab[:-1]
    dh = lab[:, 1:] != lab[:, :-1]
    boundary[1:] |= dv
    boundary[:-1] |= dv
    boundary[:, 1:] |= dh
    boundary[:, :-1] |= dh
    if not boundary.any():
        return np.full(lab.shape, np.inf)
    return ndimage.distance_transform_edt(~boundary) + 1.0


def incidence_cosine(
    depth: np.ndarray, K: np.ndarray, label: np.ndarray | None = None
) -> np.ndarray:
    """|cos| of the angle between each pixel's ray and the surface normal of a depth image.

    Normals from central differences of the back-projected points; 1 (facing the camera)
    where a neighbour has no depth or, given ``label``, another label (no normal across a
    depth edge).

    Args:
        depth: (H, W) depth, metres, 0 = none.
        K: (3, 3) intrinsics.
        label: optional (H, W) label image.

    Returns:
        (H, W) float64 in [0, 1].
    """
    z = np.asarray(depth, dtype=np.float64)
    H, W = z.shape
    v, u = np.mgrid[0:H, 0:W]
    rays = pixel_rays(np.linalg.inv(K), v, u)  # (H, W, 3)
    X = rays * z[..., None]
    gx = np.zeros_like(X)
    gy = np.zeros_like(X)
    gx[:, 1:-1] = X[:, 2:] - X[:, :-2]
    gy[1:-1] = X[2:] - X[:-2]
    ok = np.zeros((H, W), dtype=bool)
    ok[1:-1, 1:-1] = (z[1:-1, 2:] > 0) & (z[1:-1, :-2] > 0) & (z[2:, 1:-1] > 0) & (z[:-2, 1:-1] > 0)
    if label is not None:
        lab = np.asarray(label)
        c = lab[1:-1, 1:-1]
        ok[1:-1, 1:-1] &= (
            (lab[1:-1, 2:] == c)
            & (lab[1:-1, :-2] == c)
            & (lab[2:, 1:-1] == c)
            & (lab[:-2, 1:-1] == c)
        )
    return _ray_cosine(gx, gy, rays, ok)


def _ray_cosine(gx: np.ndarray, gy: np.ndarray, rays: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """|cos| of the angle between each ray and the surface normal ``gx x gy``, in [0, 1]; 1
    (facing the camera) where not ``ok`` or the normal vanishes.

    Args:
        gx, gy: (..., 3) surface tangents (central differences of back-projected points).
        rays: (..., 3) pixel rays.
        ok: (...) bool, where the tangents are valid.
    """
    n = np.cross(gx, gy)
    norm = np.linalg.norm(n, axis=-1) * np.linalg.norm(rays, axis=-1)
    cos = np.abs((n * rays).sum(axis=-1)) / np.where(norm > 0, norm, 1.0)
    return np.where(ok & (norm > 0), np.clip(cos, 0.0, 1.0), 1.0)


def correlated_uniform(
    rng: np.random.Generator, shape: tuple[int, int], sigma: float
) -> np.ndarray:
    """Uniform(0, 1) values per pixel whose neighbours are correlated over ~``sigma`` pixels.

    White Gaussian noise smoothed by a Gaussian of width ``sigma`` (pixels), scaled to unit
    variance and mapped through the normal CDF: each pixel is exactly uniform, so a threshold
    p keeps the rate p, and the pixels below it form blobs. ``sigma`` = 0: independent.

    Returns:
        (H, W) float64 in (0, 1).
    """
    if sigma <= 0:
        return rng.random(shape)

    return ndtr(correlated_normal(rng, shape, sigma))


def correlated_normal(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Standard normal values per pixel whose neighbours are correlated over ~``sigma`` pixels:
    white Gaussian noise smoothed by a Gaussian of width ``sigma`` (pixels, the image wrapped
    around) and scaled to unit variance. ``sigma`` = 0: independent.

    Returns:
        (H, W) float64.
    """
    if sigma <= 0:
        return rng.standard_normal(shape)
    z = ndimage.gaussian_filter(rng.standard_normal(shape), sigma, mode="wrap")
    return z / _smoothed_std(float(sigma))


def _gaussian_weights(sigma: float, truncate: float = 4.0) -> np.ndarray:
    """(2r + 1,) the 1-D kernel ``scipy.ndimage.gaussian_filter`` uses (r = truncate sigma,
    rounded)."""
    r = int(truncate * float(sigma) + 0.5)
    x = np.arange(-r, r + 1, dtype=np.float64)
    w = np.exp(-0.5 / float(sigma) ** 2 * x**2)
    return w / w.sum()


def correlated_uniform_at(
    rng: np.random.Generator,
    shape: tuple[int, int],
    sigma: float,
    v: np.ndarray,
    u: np.ndarray,
) -> np.ndarray:
    """``correlated_uniform(rng, shape, sigma)[v, u]`` with the same draws, computed at the
    pixels ``(v, u)`` only (the compiled :func:`cloudpose.kernels.sensor.smoothed_at_kernel`
    where the kernels are enabled): equal to float rounding (the filter's sums in another
    order).

    Returns:
        (m,) float64 in (0, 1).
    """

    if sigma <= 0 or not enabled():
        return correlated_uniform(rng, shape, sigma)[v, u]

    z = smoothed_at_kernel(
        rng.standard_normal(shape), _gaussian_weights(sigma), v.astype(np.int64), u.astype(np.int64)
    )
    return ndtr(z / _smoothed_std(float(sigma)))


@functools.cache
def _smoothed_std(sigma: float) -> float:
    """Standard deviation of unit white noise smoothed as :func:`correlated_uniform` does."""
    delta = np.zeros((int(8 * sigma) + 3,) * 2)
    delta[len(delta) // 2, len(delta) // 2] = 1.0
    return float(np.sqrt((ndimage.gaussian_filter(delta, sigma, mode="constant") ** 2).sum()))


def edge_distance_compiled(label: np.ndarray) -> np.ndarray:
    """:func:`edge_distance` by the compiled exact transform
    (:func:`cloudpose.kernels.sensor.edge_distance_kernel`) where the kernels are enabled: the
    same values (both exact Euclidean distances)."""

    if not enabled():
        return edge_distance(label)

    return edge_distance_kernel(np.ascontiguousarray(label))


def add_sensor_noise_v2(
    depth: np.ndarray,
    label: np.ndarray,
    K: np.ndarray,
    rng: np.random.Generator,
    model: NoiseModel = NoiseModel(),
    dropout: DropoutModel | None = None,
) -> np.ndarray:
    """The version-2 sensor: :func:`add_sensor_noise`'s readings; on background pixels its
    edge and random dropout, on object pixels the fitted :class:`DropoutModel` instead.

    Args:
        depth: (H, W) clean depth, metres, 0 = no surface.
        label: (H, W) class ids (0 = background).
        K: (3, 3) intrinsics.
        rng: random generator.
        model: noise parameters.
        dropout: missing-depth model of object pixels (default :data:`REAL_DROPOUT`).

    Returns:
        (H, W) float64 noisy depth, metres, 0 = no reading.
    """
    dropout = REAL_DROPOUT if dropout is None else dropout
    noisy, drop = _readings(depth, rng, model)
    obj = np.asarray(label) > 0
    p = dropout.probability(edge_distance(label), incidence_cosine(depth, K, label), label)
    missing = np.where(obj, correlated_uniform(rng, noisy.shape, dropout.blob_sigma) < p, drop)
    noisy[missing] = 0.0
    return noisy


# --------------------------------------------------------------------------- object pixels only


def background_depth_at(
    K: np.ndarray,
    v: np.ndarray,
    u: np.ndarray,
    world_to_camera: np.ndarray,
    planes: Sequence[Plane],
) -> np.ndarray:
    """:func:`background_depth` at the pixels ``(v, u)`` only: (m,) float64 metres, 0 where
    no patch is hit within :data:`MAX_RANGE`."""
    return _plane_depth(pixel_rays(np.linalg.inv(K), v, u), world_to_camera, planes)


def object_ring(label: np.ndarray) -> np.ndarray:
    """(h, w) bool: background pixels (label 0) with an object pixel among their 4-neighbours,
    the only background whose depth an object pixel's readings depend on (the jump of a
    depth edge)."""
    obj = np.asarray(label) > 0
    near = np.zeros_like(obj)
    near[1:] |= obj[:-1]
    near[:-1] |= obj[1:]
    near[:, 1:] |= obj[:, :-1]
    near[:, :-1] |= obj[:, 1:]
    return near & ~obj


def add_sensor_noise_v2_objects(
    depth: np.ndarray,
    label: np.ndarray,
    K: np.ndarray,
    rng: np.random.Generator,
    model: NoiseModel = NoiseModel(),
    dropout: DropoutModel | None = None,
    compiled: bool = False,
) -> np.ndarray:
    """:func:`add_sensor_noise_v2` on the object pixels only: the same model, computed and
    drawn where a segment can take a point (background pixels come back 0).

    Each object pixel's reading is a draw from the same law as there: Gaussian axial noise
    growing with depth, flying pixels and the edge test against the clean 4-neighbours (so
    ``depth`` needs the background only on :func:`object_ring`), disparity quantisation, and
    missing depth from the fitted :class:`DropoutModel` (edge distance, incidence cosine and
    class rate, thresholded by the same spatially correlated field over the whole image). What
    differs is how many numbers are drawn: none for background pixels, so for one generator
    the object readings are other draws than :func:`add_sensor_noise_v2` makes. On-line
    synthesis uses it (most of a scene's window is background; its noise feeds no segment).

    Args:
        depth: (H, W) clean depth, metres, 0 = no surface (needed on object pixels and their
            ring).
        label: (H, W) class ids (0 = background).
        K: (3, 3) intrinsics.
        rng: random generator.
        model: noise parameters.
        dropout: missing-depth model of object pixels (default :data:`REAL_DROPOUT`).
        compiled: the edge distance, the correlated field and the readings by the compiled
            kernels where they are enabled (:func:`edge_distance_compiled`,
            :func:`correlated_uniform_at`, :func:`cloudpose.kernels.sensor.object_readings_kernel`:
            the same draws, the field only at the object pixels; on-line synthesis version 2).
            The same values to float rounding.

    Returns:
        (H, W) float64 noisy depth on object pixels, metres, 0 = no reading or background.
    """

    dropout = REAL_DROPOUT if dropout is None else dropout
    z_all = np.asarray(depth, dtype=np.float64)
    lab = np.asarray(label)
    H, W = z_all.shape
    out = np.zeros((H, W))
    v, u = np.nonzero(lab > 0)
    if len(v) == 0:
        return out
    pad = np.pad(z_all, 1)
    lpad = np.pad(lab, 1)
    z = z_all[v, u]
    jump, cos = object_pixel_geometry(pad, lpad, v, u, K)
    m = len(z)
    normal = rng.standard_normal(m)
    u_edge = rng.random(m)
    c = lab[v, u]
    if compiled and enabled():
        mix = rng.random(m)
        field = correlated_uniform_at(rng, (H, W), dropout.blob_sigma, v, u)
        out[v, u] = object_readings_kernel(
            z,
            jump,
            cos,
            normal,
            u_edge,
            mix,
            edge_distance_compiled(lab)[v, u],
            field,
            dropout.rate_table(),
            c.astype(np.int64),
            model.kernel_args(),
            dropout.kernel_args(),
            MAX_RANGE,
        )
        return out
    noisy = _noisy(z, jump, normal, u_edge, rng.random(m), model)
    if compiled:
        p = dropout.probability(edge_distance_compiled(lab)[v, u], cos, c)
        field = correlated_uniform_at(rng, (H, W), dropout.blob_sigma, v, u)
    else:
        p = dropout.probability(edge_distance(lab)[v, u], cos, c)
        field = correlated_uniform(rng, (H, W), dropout.blob_sigma)[v, u]
    noisy[field < p] = 0.0
    out[v, u] = noisy
    return out


def object_pixel_geometry(
    pad: np.ndarray, lpad: np.ndarray, v: np.ndarray, u: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The depth jump and incidence cosine of the object pixels ``(v, u)``.

    ``pad`` and ``lpad`` are the (H, W) clean depth and label images padded by one pixel of 0.
    The jump is :func:`add_sensor_noise`'s: the signed difference to the 4-neighbour (up, down,
    left, right; the first on ties) that differs most, over neighbours with depth (0 when the
    pixel has none). The cosine is :func:`incidence_cosine` with the label: 1 on the image
    border and where a 4-neighbour has no depth or another label. The compiled kernel
    (:func:`cloudpose.kernels.sensor.object_pixel_geometry_kernel`) where the kernels are
    enabled, else numpy.

    Returns:
        (m,) float64 jumps, metres, and (m,) float64 cosines in [0, 1].
    """

    Kinv = np.linalg.inv(np.asarray(K, dtype=np.float64))
    v = np.asarray(v, dtype=np.int64)
    u = np.asarray(u, dtype=np.int64)
    if enabled():
        return object_pixel_geometry_kernel(pad, lpad, v, u, Kinv)
    H, W = pad.shape[0] - 2, pad.shape[1] - 2
    vp, up = v + 1, u + 1
    nb = np.stack([pad[vp - 1, up], pad[vp + 1, up], pad[vp, up - 1], pad[vp, up + 1]], axis=-1)
    jump = _depth_jump(pad[vp, up], nb)

    def point(dv: int, du: int) -> np.ndarray:
        return pixel_rays(Kinv, v + dv, u + du) * pad[vp + dv, up + du][:, None]

    gx = point(0, 1) - point(0, -1)
    gy = point(1, 0) - point(-1, 0)
    c = lpad[vp, up]
    inner = (v >= 1) & (v <= H - 2) & (u >= 1) & (u <= W - 2)
    same = (
        (lpad[vp, up + 1] == c)
        & (lpad[vp, up - 1] == c)
        & (lpad[vp + 1, up] == c)
        & (lpad[vp - 1, up] == c)
    )
    ok = inner & (nb > 0).all(axis=-1) & same
    return jump, _ray_cosine(gx, gy, pixel_rays(Kinv, v, u), ok)


def smooth_depth(depth: np.ndarray, mask: np.ndarray, sigma_px: float) -> np.ndarray:
    """``depth`` with the readings of ``mask`` replaced by their Gaussian average over the
    mask's own readings (``sigma_px`` pixels; a normalized convolution, so neither the
    background nor the missing readings leak in): the spatially correlated error of a depth
    camera that matches over a window, at the same surface."""
    out = depth.copy()
    m = mask & (depth > 0)
    if sigma_px <= 0 or not m.any():
        return out
    pad = _filter_reach(sigma_px)
    v, u = np.nonzero(m)
    box = (
        slice(max(v.min() - pad, 0), v.max() + pad + 1),
        slice(max(u.min() - pad, 0), u.max() + pad + 1),
    )
    mb, db = m[box], depth[box]
    weight = ndimage.gaussian_filter(mb.astype(np.float64), sigma_px)
    total = ndimage.gaussian_filter(np.where(mb, db, 0.0).astype(np.float64), sigma_px)
    out[box][mb] = (total[mb] / weight[mb]).astype(depth.dtype)
    return out


def smooth_readings(points: np.ndarray, K: np.ndarray, sigma_px: float) -> np.ndarray:
    """One object's back-projected readings (N, 3; one per pixel, camera frame, metres) with
    each depth replaced by its Gaussian average over the object's readings
    (:func:`smooth_depth` on the pixels the points project to), every point kept on its ray."""
    if sigma_px <= 0 or len(points) == 0:
        return points.copy()
    z, v, u, (v0, u0), shape = _reading_box(points, K, sigma_px)
    depth = np.zeros(shape)
    depth[v - v0, u - u0] = z
    mask = depth > 0
    smoothed = smooth_depth(depth, mask, sigma_px)[v - v0, u - u0]
    return (points * (smoothed / z)[:, None]).astype(points.dtype)


def _filter_reach(sigma_px: float) -> int:
    """Pixels a Gaussian filter of ``sigma_px`` reaches (scipy truncates at 4 sigma), plus one."""
    return int(np.ceil(4 * sigma_px)) + 1


def _reading_box(points: np.ndarray, K: np.ndarray, sigma_px: float):
    """Where one object's readings (N, 3; one per pixel) were read, for a filter of
    ``sigma_px`` over them: their depth, the pixel ``rint(K p / z)`` of each, and a box around
    those pixels widened by the filter's reach (nothing wraps or is cut).

    Returns:
        ((N,) float64 z, (N,) int64 rows v, (N,) int64 columns u, (v0, u0) the box's corner
        in the image, (h, w) the box's shape).
    """
    z = points[:, 2].astype(np.float64)
    u = np.rint(K[0, 0] * points[:, 0] / z + K[0, 2]).astype(np.int64)
    v = np.rint(K[1, 1] * points[:, 1] / z + K[1, 2]).astype(np.int64)
    reach = _filter_reach(sigma_px)
    u0, v0 = u.min() - reach, v.min() - reach
    shape = (int(v.max() - v0 + reach + 1), int(u.max() - u0 + reach + 1))
    return z, v, u, (v0, u0), shape


def correlate_readings(
    points: np.ndarray,
    clean: np.ndarray,
    K: np.ndarray,
    sigma_px: float,
    rng: np.random.Generator,
    model: NoiseModel = NoiseModel(),
) -> np.ndarray:
    """One object's back-projected readings (N, 3; one per pixel, camera frame, metres) with
    the axial noise of its pixels off depth edges drawn again from a spatially correlated
    field (:func:`correlated_normal`, ``sigma_px`` pixels, over the points' bounding box):
    the per-pixel law of :func:`add_sensor_noise` (Gaussian, standard deviation growing with
    depth, the disparity quantisation) with the texture of a camera that matches over a
    window. Readings on a depth edge of the clean image (flying pixels among them) and where
    the clean depth is 0 are kept, as is every point's ray.

    Unlike :func:`smooth_readings`, which averages the readings and so also pulls the flying
    pixels onto the surface and lowers the noise, this keeps both the amount of noise and the
    tail of off-surface points.

    Args:
        points: (N, 3) the readings, each at the pixel ``rint(K p / z)``.
        clean: (h, w) the clean depth of the image the points were read from (the object's,
            and its 4-neighbours', metres, 0 = none).
        K: (3, 3) intrinsics of that image.
        sigma_px: the field's Gaussian, pixels (0: the points unchanged).
        rng: draws one standard normal per pixel of the box (widened by the filter's reach).
        model: the sensor's noise parameters.

    Returns:
        (N, 3) the new readings, ``points``' dtype.
    """
    if sigma_px <= 0 or len(points) == 0:
        return points.copy()
    z, v, u, (v0, u0), box = _reading_box(points, K, sigma_px)
    H, W = clean.shape
    if u.min() < 0 or v.min() < 0 or u.max() >= W or v.max() >= H:
        raise ValueError(
            f"correlate_readings: points project outside the {H}x{W} clean depth "
            f"(u {u.min()}..{u.max()}, v {v.min()}..{v.max()})"
        )
    pad_z = np.pad(np.asarray(clean, dtype=np.float64), 1)
    vp, up = v + 1, u + 1
    nbs = np.stack([pad_z[vp - 1, up], pad_z[vp + 1, up], pad_z[vp, up - 1], pad_z[vp, up + 1]], -1)
    z0 = pad_z[vp, up]
    field = correlated_normal(rng, box, sigma_px)[v - v0, u - u0]  # the box: no wrap
    zero = np.zeros_like(z0)
    redrawn = _noisy(z0, zero, field, np.ones_like(z0), zero, model)
    keep = (np.abs(_depth_jump(z0, nbs)) > model.edge_jump) | (z0 <= 0) | (redrawn <= 0)
    new_z = np.where(keep, z, redrawn)
    return (points * (new_z / z)[:, None]).astype(points.dtype)
