"""Training segments synthesized on line: every batch drawn fresh, none seen twice.

The frame generator (:func:`~cloudpose.data.synth.frames.generate_frame`) renders whole
640 x 480 frames, the alone-pixel counts of every object and the noise over the whole image;
~30 segments/s here. Training needs none of the frame: only the objects' segments. This module
draws a table scene with the same sampler (:func:`~cloudpose.data.synth.scenes.sample_table_scene`:
resting poses, clustering, stacking, the camera ranges), casts each object's rays only through
the pixels of its own projection, against its class's surface kept in its model frame (one BVH
per class for the whole run, :meth:`~cloudpose.data.synth.render.Renderer.render_instanced`), adds
the version's sensor model on the object pixels of the box around them (the version-2 sensor
computed where a segment can take a point, :func:`~cloudpose.data.synth.sensor.add_sensor_noise_v2_objects`,
with the background planes on the ring of pixels around the objects, so depth edges at object
borders are where the frame has them), and cuts segments by the frame path itself
(:func:`~cloudpose.data.segments.extract_segments` on a window frame: mask, back-projection,
outlier filter, farthest point sampling of the first ``n_points``). ~70 ms a scene of ~5
objects on one core here, against ~120 ms when the noise and background covered the whole box
and the scene's meshes were ray cast together (``make bench``, ``online_ms_per_scene``).

Agreement with rendered frames: for one scene, a segment from here and one from the rendered
frame of that scene are the same points without noise and with the same FPS start, to float
rounding (the shifted intrinsics; rays cast in the model frame instead of meshes moved into the
camera frame: micrometres); with noise they are draws from the same sensor model (drawn for
the object pixels instead of the whole image). What differs from the frame generator by
design: an object with fewer than :data:`~cloudpose.data.synth.scenes.MIN_VISIBLE_PIXELS`
visible pixels is dropped without re-rendering the scene (it still hides what is behind it),
and no alone-pixel count is rendered (training does not use occlusion factors).

Version 2 (``data.online_version = 2``, :data:`~cloudpose.config.ONLINE_VERSIONS`): the same
scenes, random draws and computations, by compiled kernels where version 1 used Open3D and
numpy. The scene sampler's slide loop is compiled for both versions (the same scenes, so the
frames do not change); version 2 then draws each object into a z-buffer of its mesh
(:meth:`~cloudpose.data.synth.render.Renderer.render_raster`, :mod:`cloudpose.kernels.raster`:
each triangle tested at the pixel centres of its projection, the plane's depth: what the ray
cast through those centres hits), computes the sensor's edge distance and correlated
missing-depth field by compiled kernels (the field only at the object pixels, from the same
white noise), and cuts the segments in one pass over the pixels with an FPS over a grid of
buckets (:func:`cut_segments`, :mod:`cloudpose.kernels.segment_cut`: the same order as the
k-d tree FPS). Its segments are version 1's to float rounding: a rounding flip (a silhouette
pixel, a threshold of the missing-depth field) changes one segment's pixel set, and its FPS
then picks other points of the same surface (``benchmarks/bench_online.py`` measures the share
that is bit for bit the same; tests/test_online.py holds it). Not bit for bit, so a stream of
its own: the committed on-line runs are version 1, and a preset opts in with
``data.online_version = 2`` (``--set data.online_version=2`` on the command line). Without
numba it runs the twins (ray cast, scipy, the k-d tree FPS): the same segments to rounding.

Version 3 (``data.online_version = 3``): the same scenes (the same sampler and draws), the
same z-buffer and the same sensor model, every object of a scene at once in a few compiled
passes (:mod:`cloudpose.kernels.scene_pass`), and draws of its own, so other segments of the
same distribution. One pass poses and projects every object, finds their windows and the box,
and draws every triangle into one z-buffer along scan lines (:meth:`OnlineSynth._raster_v3`);
one pass reads every object pixel (:func:`scene_points`: the jump, incidence cosine and
reading of the version-2 sensor, the missing-depth test, the back-projection and the outlier
filter; the exact missing probability only where a bound of it does not decide), and the FPS
runs over coordinate-wise buckets (:func:`cloudpose.kernels.scene_pass.fps_soa`, the exact
FPS order, the same start draws as the segment path). Its draws come from three counter
streams keyed by three words of the scene's generator (SplitMix64 outputs, read where the
pass needs them, :func:`scene_points`): per object pixel a normal, and two uniforms where it
lies on a depth edge; the white noise of the missing-depth field over the object pixels'
bounding box widened by the blob filter's reach (version 2 draws it over the whole box and
wraps the filter around it; here the field is stationary). The last scene of a batch cuts only the segments the batch keeps.
Without noise its segments are the rendered frame's (tests/test_online.py); with noise they
are other draws of the same law (the same classes and poses, as many points, each segment
on the same surface: ``benchmarks/bench_online.py`` measures how near version 1's). Without
numba it runs numpy twins (version 2's z-buffer, which casts rays; scipy's filter and edge
distance; the k-d tree FPS): the same segments to rounding, far slower.

Determinism: batch ``step`` of a run is a pure function of ``(seed, step)``: its scenes use
``np.random.default_rng([seed, ONLINE_STREAM, step, k])`` for k = 0, 1, ... until the batch is
full, so a resumed run continues with the batches an uninterrupted one would have drawn, in any
process (:class:`OnlineStream` has worker processes make them ahead of the training loop).
"""

from __future__ import annotations

import functools
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from threadpoolctl import threadpool_limits
from tqdm.auto import tqdm

from cloudpose.config import PAIRED_BRANCH
from cloudpose.conventions import IMAGE_SHAPE, YCB_INTRINSICS
from cloudpose.data.segments import (
    Segment,
    SegmentWarning,
    extract_segments,
    farthest_point_sampling,
    instance_streams,
)
from cloudpose.data.synth.chunks import ChunkStore, OnlineSettings
from cloudpose.data.synth.frames import _generator
from cloudpose.data.synth.scenes import (
    MAX_RANGE,
    MIN_VISIBLE_PIXELS,
    STACK_SHARE,
    Scene,
    sample_table_scene,
)
from cloudpose.data.synth.sensor import (
    REAL_DROPOUT,
    NoiseModel,
    _gaussian_weights,
    _noisy,
    _smoothed_std,
    add_sensor_noise,
    add_sensor_noise_v2_objects,
    background_depth,
    background_depth_at,
    correlate_readings,
    edge_distance,
    object_pixel_geometry,
    object_ring,
    smooth_readings,
)
from cloudpose.data.ycb import Frame
from cloudpose.kernels.backend import enabled
from cloudpose.kernels.scene_pass import (
    DRAW_WORDS,
    fps_soa,
    normal_draws,
    raster_scene,
    ring_pixels,
    ziggurat_tables,
)
from cloudpose.kernels.scene_pass import scene_points as compiled_scene_points
from cloudpose.kernels.segment_cut import backproject_filtered, gather_instances, grid_fps

ONLINE_STREAM = 2
"""Second word of every on-line random stream; frames use 0 (train) and 1 (test), so on-line
scenes never repeat a rendered frame's scene."""

REUSE_SPACING = 32
"""Steps between two uses of an on-line segment (:class:`OnlineStream`)."""

PREFETCH_CHUNKS = 64
"""Chunks each synthesis worker may make ahead of training: enough to keep synthesizing through
an epoch's validation (~10 s here, ~140 scenes at reuse 4), when training takes none; a few
megabytes at most."""

WINDOW_PAD = 8
"""Pixels added around the objects' window: the edge, grazing and blob terms of the sensor
model see the background just outside an object as in a whole frame."""


@dataclass(frozen=True)
class SegmentBatch:
    """Network inputs and targets of on-line segments (B of them).

    Attributes:
        points: (B, n, 3) float32 camera-frame points, metres, FPS order; (B, 2n, 3) for
            segments in two forms (``data.online_bleed_branch`` "translation" or
            "translation-paired"): the rendered masks' n points, then the bleeding masks'.
        cls_id: (B,) int64 1-based class ids.
        R: (B, 3, 3) float32 rotations model->camera.
        t: (B, 3) float32 translations, metres.
        count: (B,) int64 points of each segment after the outlier filter.
        scenes: scenes drawn to fill the batch.
    """

    points: np.ndarray
    cls_id: np.ndarray
    R: np.ndarray
    t: np.ndarray
    count: np.ndarray
    scenes: int

    def tensors(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(points, cls_id, R, t)`` as torch tensors (shared memory, no copy)."""
        return (
            torch.from_numpy(self.points),
            torch.from_numpy(self.cls_id),
            torch.from_numpy(self.R),
            torch.from_numpy(self.t),
        )


BLEED_NEIGHBOURS = ((0, -1), (0, 1), (-1, 0), (1, 0))
"""The 4-neighbours a bleeding mask grows into, in the order a pixel next to several objects
takes the first."""


def bleed_masks(
    index: np.ndarray, n: int, share_max: float, rng: np.random.Generator
) -> np.ndarray:
    """``index`` with each object's mask grown by up to one pixel (``data.online_bleed``).

    Each pixel that is not an object's own but is a 4-neighbour of one of its pixels
    (background or another object: the first such object of :data:`BLEED_NEIGHBOURS`) goes to
    that object with probability ``p``, ``p`` drawn per object uniformly in
    ``[0, share_max]``: a segmentation mask that bleeds, as a real one does, by a share of a
    pixel that differs from object to object. The draws: ``n`` uniforms (the shares), then one
    per pixel of the box, row-major.

    Args:
        index: (h, w) int64 instance of each pixel (-1 = background).
        n: the scene's instances.
        share_max: the largest share, in [0, 1].
        rng: the scene's generator.

    Returns:
        (h, w) int64, a new array.
    """
    share = rng.uniform(0.0, share_max, n)
    u = rng.random(index.shape)
    h, w = index.shape
    take = np.full(index.shape, -1, dtype=np.int64)
    for dv, du in BLEED_NEIGHBOURS:  # the label of the neighbour at (v + dv, u + du)
        nb = np.full(index.shape, -1, dtype=np.int64)
        nb[max(-dv, 0) : h - max(dv, 0), max(-du, 0) : w - max(du, 0)] = index[
            max(dv, 0) : h - max(-dv, 0), max(du, 0) : w - max(-du, 0)
        ]
        free = (take < 0) & (nb >= 0) & (nb != index)
        take[free] = nb[free]
    grow = take >= 0
    grow[grow] = u[grow] < share[take[grow]]
    return np.where(grow, take, index)


def scene_points(
    clean: np.ndarray,
    index: np.ndarray,
    visible: np.ndarray,
    Kw: np.ndarray,
    cls_ids: np.ndarray,
    rng: np.random.Generator | None,
    radius: float,
    compiled: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Each instance's points of a scene's box (version 3): the version-2 sensor's readings of
    the object pixels from version 3's draws (none without ``rng``: the clean depth), back-
    projected, less the outliers (:func:`cloudpose.kernels.scene_pass.scene_points`, or its
    numpy twin).

    The draws: three words of ``rng``'s bit generator key three counter streams
    (:func:`cloudpose.kernels.scene_pass.stream_word`, SplitMix64 outputs), read where the
    pass needs them: object pixel k (row-major) reads a standard normal (axial noise), and on
    a depth edge two uniforms (flying or not, the mix); the white noise of the missing-depth
    field is a standard normal per pixel of the object pixels' bounding box widened by the
    blob filter's reach (a stationary field, where version 2 wraps the box around), smoothed
    in float32. Normals by the ziggurat (:func:`standard_normals`), uniforms as float32.

    Args:
        clean: (h, w) float64 clean depth (the objects', the background's on their ring).
        index: (h, w) int64 instance of each pixel (-1 = background).
        visible: (N,) int64 pixels of each instance.
        Kw: (3, 3) intrinsics of the box.
        cls_ids: (N,) class id of each instance.
        rng: the scene's generator; None: no noise.
        radius: the outlier filter's, metres.
        compiled: the kernel, else the numpy twin.

    Returns:
        (M, 3) float64 points, instance by instance (row-major within each), and (N + 1,)
        int64 offsets.
    """
    weights, std, rates, noise, drop = _sensor_constants()
    r = len(weights) // 2
    keys = rng.bit_generator.random_raw(3) if rng is not None else np.zeros(3, np.uint64)
    rate = rates[np.asarray(cls_ids, dtype=np.int64)]
    Kinv = _inverse(np.ascontiguousarray(Kw, dtype=np.float64).tobytes())
    xs, fs = _ziggurat()
    if compiled:
        return compiled_scene_points(
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
            MAX_RANGE,
            float(radius),
            rng is not None,
        )
    from scipy import ndimage
    from scipy.special import ndtr

    model, dropout = NoiseModel(), REAL_DROPOUT
    v, u = np.nonzero(index >= 0)
    m = len(v)
    inst = index[v, u]
    z = clean[v, u]
    if rng is None or not m:
        reading = z.astype(np.float32).astype(np.float64)  # a frame's depth
    else:
        normal = standard_normals(int(keys[0]), m, False)
        uni = uniform_draws(int(keys[1]), 2 * m)
        hb = int(v.max()) - int(v.min()) + 1 + 2 * r
        wb = int(u.max()) - int(u.min()) + 1 + 2 * r
        white = standard_normals(int(keys[2]), hb * wb, False).reshape(hb, wb)
        lab = index + 1
        jump, cos = object_pixel_geometry(np.pad(clean, 1), np.pad(lab, 1), v, u, Kw)
        reading = _noisy(z, jump, normal.astype(np.float64), uni[0::2], uni[1::2], model)
        smooth = ndimage.correlate1d(white.astype(np.float64), weights, axis=0, mode="constant")
        smooth = ndimage.correlate1d(smooth, weights, axis=1, mode="constant")[r:-r, r:-r]
        field = ndtr(smooth[v - v.min(), u - u.min()] / std)
        p = dropout.probability(edge_distance(lab)[v, u], cos, np.asarray(cls_ids)[inst])
        reading[field < p] = 0.0
    return _cut_points_numpy(v, u, inst, reading, Kinv, len(cls_ids), radius)


@functools.cache
def _sensor_constants() -> tuple[np.ndarray, float, np.ndarray, tuple, tuple]:
    """What every scene of :func:`scene_points` uses: the blob filter's weights and the
    smoothed noise's standard deviation, the class rates (by class id), the sensor's and the
    missing-depth model's parameters as the kernel takes them."""
    model, dropout = NoiseModel(), REAL_DROPOUT
    weights = _gaussian_weights(dropout.blob_sigma)
    weights.flags.writeable = False
    rates = dropout.rate_table()
    rates.flags.writeable = False
    std = _smoothed_std(float(dropout.blob_sigma))
    return weights, std, rates, model.kernel_args(), dropout.kernel_args()


@functools.lru_cache(maxsize=4096)
def _inverse(K: bytes) -> np.ndarray:
    """(3, 3) read-only inverse of the float64 intrinsics ``K`` (its bytes: a box's, which
    repeat from scene to scene)."""
    Kinv = np.linalg.inv(np.frombuffer(K, dtype=np.float64).reshape(3, 3))
    Kinv.flags.writeable = False
    return Kinv


def _ziggurat() -> tuple[np.ndarray, np.ndarray]:
    global _ZIGGURAT
    if _ZIGGURAT is None:
        _ZIGGURAT = ziggurat_tables()
    return _ZIGGURAT


_ZIGGURAT: tuple[np.ndarray, np.ndarray] | None = None


def _stream_words(key: int, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """The numpy twin of :func:`cloudpose.kernels.scene_pass.stream_word` (uint64 arrays)."""

    c = np.asarray(i, dtype=np.uint64) * np.uint64(DRAW_WORDS) + (
        np.asarray(j, dtype=np.uint64) + np.uint64(1)
    )
    z = np.uint64(key) + c * np.uint64(0x9E3779B97F4A7C15)  # uint64 arrays wrap
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def uniform_draws(key: int, n: int) -> np.ndarray:
    """(n,) float32 draws 0 .. n - 1 of :func:`cloudpose.kernels.scene_pass.uniform_draw`."""
    w = _stream_words(key, np.arange(n), np.zeros(n, dtype=np.int64))
    return ((w >> np.uint64(40)).astype(np.float64) * (1.0 / 16777216.0)).astype(np.float32)


def standard_normals(key: int, n: int, compiled: bool) -> np.ndarray:
    """(n,) float32 standard normals: draws 0 .. n - 1 of the counter stream ``key`` by the
    256-layer ziggurat (:func:`cloudpose.kernels.scene_pass.normal_draw`), compiled or by its
    numpy twin (the same draws)."""
    xs, fs = _ziggurat()
    if compiled:
        return normal_draws(np.uint64(key), n, xs, fs)
    scale = 1.0 / 9007199254740992.0
    out = np.empty(n)
    used = np.zeros(n, dtype=np.int64)  # words each draw has read
    todo = np.arange(n)
    while len(todo):
        b = _stream_words(key, todo, used[todo])
        used[todo] += 1
        k = (b & np.uint64(255)).astype(np.int64)
        x = (b >> np.uint64(11)).astype(np.float64) * scale * xs[k]
        done = x < xs[k + 1]
        for t in np.flatnonzero(~done):
            i = int(todo[t])
            if k[t] == 0:  # the tail
                while True:
                    u1, u2 = _stream_words(key, [i, i], [used[i], used[i] + 1]) >> np.uint64(11)
                    used[i] += 2
                    a = -math.log(1.0 - float(u1) * scale) / xs[1]
                    if -2.0 * math.log(1.0 - float(u2) * scale) >= a * a:
                        break
                x[t], done[t] = xs[1] + a, True
            else:  # the wedge
                h = float(_stream_words(key, [i], [used[i]])[0] >> np.uint64(11)) * scale
                used[i] += 1
                f0, f1 = fs[k[t]], fs[k[t] + 1]
                done[t] = f0 + h * (f1 - f0) < math.exp(-0.5 * x[t] * x[t])
        neg = ((b >> np.uint64(8)) & np.uint64(1)).astype(bool)
        out[todo[done]] = np.where(neg, -x, x)[done]
        todo = todo[~done]
    return out.astype(np.float32)


def _cut_points_numpy(v, u, inst, reading, Kinv, n, radius):
    """The numpy twin of :func:`cloudpose.kernels.scene_pass.cut_points`."""
    ok = reading > 0
    order = np.argsort(inst[ok], kind="stable")  # by instance, row-major within each
    z = reading[ok][order]
    pix = np.stack([u[ok][order], v[ok][order], np.ones(len(z))], axis=1).astype(np.float64)
    pts = (pix @ Kinv.T) * z[:, None]
    counts = np.bincount(inst[ok], minlength=n)
    bounds = np.concatenate([[0], np.cumsum(counts)])
    out, offsets = [], [0]
    for i in range(n):
        p = pts[bounds[i] : bounds[i + 1]]
        if len(p):
            p = p[np.linalg.norm(p - p.mean(axis=0), axis=1) <= radius]
        out.append(p)
        offsets.append(offsets[-1] + len(p))
    return np.concatenate(out) if out else np.zeros((0, 3)), np.array(offsets, dtype=np.int64)


def cut_segments(frame, n_fps: int, outlier_radius: float, rng: np.random.Generator) -> list:
    """:func:`~cloudpose.data.segments.extract_segments` of a frame whose instances are of
    distinct classes (a synthesized scene), with the ground-truth masks, in one pass over the
    pixels instead of one per instance: the same segments, point for point (each instance's
    pixels in the same row-major order, back-projected by the same expression, the same
    outlier filter, FPS and random streams). No occlusion factor (NaN); an instance without a
    usable point comes back invalid, without a warning.

    Args:
        frame: a :class:`~cloudpose.data.ycb.Frame` with poses; distinct ``cls_ids``.
        n_fps: points kept per segment.
        outlier_radius: metres.
        rng: the frame's generator (:func:`~cloudpose.data.segments.instance_streams`).

    Returns:
        One :class:`~cloudpose.data.segments.Segment` per instance, in ``cls_ids`` order.
    """

    cls_ids = np.asarray(frame.cls_ids, dtype=np.int64)
    n = len(cls_ids)
    if len(np.unique(cls_ids)) != n:
        raise ValueError(f"cut_segments needs distinct classes, got {cls_ids.tolist()}")
    streams = instance_streams(rng, cls_ids)
    depth = np.asarray(frame.depth)
    w = depth.shape[1]
    lut = np.full(256, -1, dtype=np.int64)
    lut[cls_ids] = np.arange(n)
    compiled = enabled()
    if compiled:
        sel, offsets = gather_instances(depth, np.asarray(frame.label), lut, n)
    else:
        inst = lut[np.asarray(frame.label).ravel()]
        sel = np.flatnonzero((inst >= 0) & (depth.ravel() > 0))
        sel = sel[np.argsort(inst[sel], kind="stable")]  # by instance, row-major within each
        offsets = np.concatenate([[0], np.cumsum(np.bincount(inst[sel], minlength=n))])
    z_all = depth.ravel()
    Kinv = np.linalg.inv(np.asarray(frame.K, dtype=np.float64))
    out = []
    for i, c in enumerate(cls_ids):
        idx = sel[offsets[i] : offsets[i + 1]]
        if compiled:
            pts = backproject_filtered(depth, idx, Kinv, float(outlier_radius))
        else:
            v, u = np.divmod(idx, w)
            z = z_all[idx].astype(np.float64)
            pix = np.stack([u, v, np.ones_like(u)], axis=1).astype(np.float64)
            pts = (pix @ Kinv.T) * z[:, None]  # backproject's expression
            if len(pts):
                pts = pts[np.linalg.norm(pts - pts.mean(axis=0), axis=1) <= outlier_radius]
        valid = len(pts) > 0
        if valid and compiled and np.isfinite(pts).all():
            p32 = np.ascontiguousarray(pts, dtype=np.float32)
            first = int(streams[i].integers(len(p32)))  # farthest_point_sampling's start draw
            m = min(n_fps, len(p32))
            order = grid_fps(p32, m, first) if m > 1 else np.array([first], dtype=np.int64)
            sample = p32[np.resize(order, n_fps) if m < n_fps else order]
        elif valid:
            sample = pts[farthest_point_sampling(pts, n_fps, streams[i])].astype(np.float32)
        else:
            sample = np.zeros((n_fps, 3), dtype=np.float32)
        R = frame.poses[i, :, :3].astype(np.float32)
        t = frame.poses[i, :, 3].astype(np.float32)
        out.append(Segment(sample, len(pts), int(c), R, t, np.nan, frame.frame_id, i, valid))
    return out


class OnlineSynth:
    """Draws table scenes and cuts them into training segments (see the module doc).

    Args:
        settings: what the segments are made with (:class:`OnlineSettings`).
        K, shape: camera intrinsics and image size (YCB-Video's by default).
        nthreads: ray-casting threads (0: every core; a synthesis worker uses 1); speed only.
    """

    def __init__(
        self,
        settings: OnlineSettings,
        *,
        K: np.ndarray = YCB_INTRINSICS,
        shape: tuple[int, int] = IMAGE_SHAPE,
        nthreads: int = 0,
    ) -> None:
        self.settings = settings
        self.nthreads = int(nthreads)
        self.K = np.asarray(K, dtype=np.float64)
        self.shape = (int(shape[0]), int(shape[1]))
        self._gen = _generator(settings.synth_version)
        self._models, self._resting = self._gen.models, self._gen.resting
        self._mesh_cat: tuple[np.ndarray, ...] | None = None
        kept = settings.class_ids
        self._kept = None if kept is None else frozenset(kept)
        if kept is not None:
            if set(kept) - set(self._models):
                raise ValueError(
                    f"on-line classes {list(kept)}: expected a non-empty subset of the model "
                    f"ids {sorted(self._models)}"
                )
            if settings.online_scenes == "classes":
                self._models = {c: self._models[c] for c in kept}
                self._resting = {c: self._resting[c] for c in kept}

    # ------------------------------------------------------------------ one scene

    def sample_scene(self, rng: np.random.Generator) -> Scene:
        """A table scene as the version's frames draw them (of the kept classes only with
        ``online_scenes="classes"``)."""
        stack = 0.0 if self.settings.synth_version == 1 else STACK_SHARE
        return sample_table_scene(rng, self._models, self._resting, self.K, self.shape, stack)

    def windows(self, scene: Scene) -> tuple[np.ndarray, tuple[int, int, int, int]] | None:
        """Per object (v0, v1, u0, u1), the pixels that hold its projection (the whole image
        for an object partly behind the camera, an empty window for one outside it), and the
        box around them all plus :data:`WINDOW_PAD`, clipped to the image; None when no object
        projects into the image."""
        H, W = self.shape
        out = []
        for c, P in zip(scene.cls_ids, scene.poses(), strict=True):
            w = self._gen.renderer._window(self.K, self.shape, c, P)
            out.append((0, H, 0, W) if w is None else w)
        wins = np.array(out, dtype=np.int64).reshape(-1, 4)
        used = wins[(wins[:, 0] < wins[:, 1]) & (wins[:, 2] < wins[:, 3])]
        if not len(used):
            return None
        box = (
            max(int(used[:, 0].min()) - WINDOW_PAD, 0),
            min(int(used[:, 1].max()) + WINDOW_PAD, H),
            max(int(used[:, 2].min()) - WINDOW_PAD, 0),
            min(int(used[:, 3].max()) + WINDOW_PAD, W),
        )
        return wins, box

    def render_window(self, scene: Scene, rng: np.random.Generator | None):
        """The window of the scene's objects as a :class:`~cloudpose.data.ycb.Frame`
        (intrinsics shifted to the window) and each object's visible pixel count; noise drawn
        from ``rng`` when the source has noise. None when no object is in the image.

        Each object is ray cast in its own window only, against its class's surface kept in
        its model frame (:meth:`~cloudpose.data.synth.render.Renderer.render_instanced`); the
        frame's window is the box around them. The background depth is the version's planes
        (on the ring of pixels around the objects only where only the objects' readings are
        needed: the version-2 sensor, :func:`add_sensor_noise_v2_objects`).
        """

        poses = scene.poses()
        if self.settings.online_version >= 2:
            got = self._gen.renderer.render_raster(
                self.K, self.shape, scene.cls_ids, poses, WINDOW_PAD, self.nthreads
            )
            if got is None:
                return None
            r, (v0, v1, u0, u1) = got
        else:
            found = self.windows(scene)
            if found is None:
                return None
            wins, (v0, v1, u0, u1) = found
            r = self._gen.renderer.render_instanced(
                self.K, self.shape, scene.cls_ids, poses, wins, (v0, v1, u0, u1), self.nthreads
            )
        label = r.label
        Kw = self.K.copy()
        Kw[0, 2] -= u0
        Kw[1, 2] -= v0
        noise, version = self.settings.noise, self.settings.synth_version
        if noise and version >= 2:
            # only object pixels make segments: the background is needed where it borders them
            clean = np.where(label > 0, r.depth.astype(np.float64), 0.0)
            ring_v, ring_u = np.nonzero(object_ring(label))
            clean[ring_v, ring_u] = background_depth_at(
                Kw, ring_v, ring_u, scene.world_to_camera, scene.background
            )
            out = add_sensor_noise_v2_objects(
                clean, label, Kw, rng, compiled=self.settings.online_version >= 2
            )
        else:
            bg = background_depth(Kw, (v1 - v0, u1 - u0), scene.world_to_camera, scene.background)
            clean = np.where(label > 0, r.depth.astype(np.float64), bg)
            out = add_sensor_noise(clean, rng) if noise else clean
        frame = Frame("online", out.astype(np.float32), label, Kw, scene.cls_ids, poses, None)
        return frame, r.visible_pixels

    def scene_segments(
        self, scene: Scene, rng: np.random.Generator, limit: int | None = None
    ) -> list:
        """Valid segments (:class:`~cloudpose.data.segments.Segment`) of the scene's objects
        with at least :data:`MIN_VISIBLE_PIXELS` pixels, of the kept classes, in scene order;
        version 3 cuts the first ``limit`` only (None: all; the segments it returns are the
        first of all of them: what a batch keeps of its last scene)."""
        if self.settings.cuts_from_scene:
            return self._scene_segments_v3(scene, rng, limit)
        rendered = self.render_window(scene, rng)
        if rendered is None:
            return []
        frame, visible = rendered
        n, radius = self.settings.n_points, self.settings.outlier_radius
        if self.settings.online_version >= 2:
            segs = cut_segments(frame, n, radius, rng)
        else:
            with warnings.catch_warnings():  # an object without a usable point is dropped below
                warnings.simplefilter("ignore", SegmentWarning)
                segs = extract_segments(frame, n_fps=n, outlier_radius=radius, rng=rng)
        keep = []
        for s, v in zip(segs, visible, strict=True):
            if not s.valid or v < MIN_VISIBLE_PIXELS:
                continue
            if self._kept is not None and s.cls_id not in self._kept:
                continue
            keep.append(s)
        return keep

    # ------------------------------------------------------------------ version 3

    def _meshes(self) -> tuple[np.ndarray, ...]:
        """Every class's mesh in one array (vertices, triangles, each class's first vertex and
        triangle, the slot of each class id), built once."""
        if self._mesh_cat is None:
            ids = sorted(self._gen.models)
            Vs, Fs, vstart, fstart = [], [], [0], [0]
            for c in ids:
                V, F = self._gen.renderer._mesh_arrays(c)
                Fs.append(F.astype(np.int64) + vstart[-1])
                Vs.append(V)
                vstart.append(vstart[-1] + len(V))
                fstart.append(fstart[-1] + len(F))
            slot = np.full(256, -1, dtype=np.int64)
            slot[ids] = np.arange(len(ids))
            self._mesh_cat = (
                np.ascontiguousarray(np.concatenate(Vs)),
                np.ascontiguousarray(np.concatenate(Fs)),
                np.array(vstart, dtype=np.int64),
                np.array(fstart, dtype=np.int64),
                slot,
            )
        return self._mesh_cat

    def _raster_v3(self, scene: Scene, poses: np.ndarray):
        """The scene's z-buffer over the box around its objects plus :data:`WINDOW_PAD`:
        ``(depth, index, visible, box)``, or None when no object is in the image. One compiled
        pass (:func:`cloudpose.kernels.scene_pass.raster_scene`); an object reaching behind the
        camera is drawn by version 2's z-buffer, which casts its rays."""

        cls_ids = np.asarray(scene.cls_ids, dtype=np.int64)
        if enabled():
            V, F, vstart, fstart, slot = self._meshes()
            H, W = self.shape
            status, box, depth, index, visible = raster_scene(
                V, F, vstart, fstart, slot[cls_ids], poses, self.K, H, W, WINDOW_PAD
            )
            if status == 1:
                return None
            if status == 0:
                return depth, index, visible, tuple(int(x) for x in box)
        got = self._gen.renderer.render_raster(
            self.K, self.shape, cls_ids, poses, WINDOW_PAD, self.nthreads
        )
        if got is None:
            return None
        r, box = got
        lut = np.full(256, -1, dtype=np.int64)
        lut[cls_ids] = np.arange(len(cls_ids))
        index = lut[r.label]
        return r.depth.astype(np.float64), index, r.visible_pixels, box

    @staticmethod
    def _with_ring_v3(depth: np.ndarray, index: np.ndarray, Kw: np.ndarray, scene: Scene):
        """``depth`` (changed in place) with the background's depth on the ring of pixels
        around the objects (:func:`~cloudpose.data.synth.sensor.object_ring`; found by
        :func:`cloudpose.kernels.scene_pass.ring_pixels` where the kernels are enabled)."""

        if enabled():
            ring_v, ring_u = ring_pixels(index)
        else:
            ring_v, ring_u = np.nonzero(object_ring(index >= 0))
        depth[ring_v, ring_u] = background_depth_at(
            Kw, ring_v, ring_u, scene.world_to_camera, scene.background
        )
        return depth

    def _scene_segments_v3(self, scene: Scene, rng: np.random.Generator, limit: int | None):
        """:meth:`scene_segments` of version 3 (see the module doc): the compiled passes of
        :mod:`cloudpose.kernels.scene_pass` where the kernels are enabled, else their numpy
        twins (the same segments to float rounding)."""

        poses = scene.poses()
        drawn = self._raster_v3(scene, poses)
        if drawn is None:
            return []
        depth, index, visible, (v0, _, u0, _) = drawn
        cls_ids = np.asarray(scene.cls_ids, dtype=np.int64)
        Kw = self.K.copy()
        Kw[0, 2] -= u0
        Kw[1, 2] -= v0
        compiled = enabled()
        clean = self._with_ring_v3(depth, index, Kw, scene) if self.settings.noise else depth
        settings = self.settings
        forms = [(index, visible)]  # each form's masks and pixels per instance
        form_rngs = [rng]  # and the stream of its draws
        if settings.online_bleed:  # the ring's depth is the background's: grow into it
            # paired: the bleeding's draws from a stream of their own, so the rendered form's
            # are those of a run without bleeding (spawning leaves rng's draws as they are)
            bleed_rng = rng.spawn(1)[0] if settings.online_bleed_branch == PAIRED_BRANCH else rng
            bled = bleed_masks(index, len(cls_ids), settings.online_bleed, bleed_rng)
            counts = np.bincount(bled[bled >= 0], minlength=len(cls_ids)).astype(np.int64)
            if settings.forms == 1:
                forms = [(bled, counts)]
            else:  # the rendered masks for the rotation branch, the bleeding for translation
                forms.append((bled, counts))
                form_rngs.append(bleed_rng)
        cut = [
            self._form_points(clean, masks, counts, Kw, cls_ids, r, compiled)
            for (masks, counts), r in zip(forms, form_rngs, strict=True)
        ]
        n_fps = settings.n_points
        streams = instance_streams(rng, cls_ids)  # the FPS starts, as the segment path draws
        form_streams = [streams] + [
            streams if r is rng else instance_streams(r, cls_ids) for r in form_rngs[1:]
        ]
        keep = []
        soa: list = [None] * len(cut)
        for i, c in enumerate(cls_ids.tolist()):
            if limit is not None and len(keep) >= limit:
                break
            spans = [(int(offsets[i]), int(offsets[i + 1])) for _, offsets in cut]
            if any(b == a for a, b in spans) or visible[i] < MIN_VISIBLE_PIXELS:
                continue
            if self._kept is not None and c not in self._kept:
                continue
            samples = []
            for f, ((pts, _), (a, b)) in enumerate(zip(cut, spans, strict=True)):
                if compiled:
                    if soa[f] is None:  # every point's coordinates, x, y and z rows, float32
                        soa[f] = np.ascontiguousarray(pts.T, dtype=np.float32)
                    xyz = soa[f]
                    first = int(form_streams[f][i].integers(b - a))  # the FPS start
                    k = min(n_fps, b - a)
                    order = fps_soa(xyz[0, a:b], xyz[1, a:b], xyz[2, a:b], k, first)
                    samples.append(
                        xyz[:, a:b][:, np.resize(order, n_fps) if k < n_fps else order].T
                    )
                else:
                    p32 = pts[a:b].astype(np.float32)
                    samples.append(p32[farthest_point_sampling(p32, n_fps, form_streams[f][i])])
            sample = samples[0] if len(samples) == 1 else np.concatenate(samples)
            R = poses[i, :, :3].astype(np.float32)
            t = poses[i, :, 3].astype(np.float32)
            a, b = spans[0]
            keep.append(Segment(sample, b - a, c, R, t, np.nan, "online", i, True))
        return keep

    def _form_points(
        self,
        clean: np.ndarray,
        masks: np.ndarray,
        counts: np.ndarray,
        Kw: np.ndarray,
        cls_ids: np.ndarray,
        rng: np.random.Generator,
        compiled: bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Every instance's points of one form of a scene's masks (:func:`scene_points`, then
        the correlated noise and the smoothing of version 3's settings, object by object):
        ``(points, offsets)``."""
        settings = self.settings
        pts, offsets = scene_points(
            clean,
            masks,
            counts,
            Kw,
            cls_ids,
            rng if settings.noise else None,
            float(settings.outlier_radius),
            compiled,
        )
        corr = settings.online_noise_corr if settings.noise else 0.0
        if corr or settings.online_smooth:  # after the sensor, object by object: its
            for i in range(len(cls_ids)):  # noise redrawn correlated, its readings averaged
                a, b = int(offsets[i]), int(offsets[i + 1])
                if corr:
                    pts[a:b] = correlate_readings(pts[a:b], clean, Kw, corr, rng)
                if settings.online_smooth:
                    pts[a:b] = smooth_readings(pts[a:b], Kw, settings.online_smooth)
        return pts, offsets

    # ------------------------------------------------------------------ batches

    def batch(self, seed: int, step: int, batch_size: int) -> SegmentBatch:
        """Batch ``step`` of a run with seed ``seed``: a pure function of its arguments."""
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        segs: list = []
        k = 0
        while len(segs) < batch_size:
            rng = np.random.default_rng([int(seed), ONLINE_STREAM, int(step), k])
            segs.extend(self.scene_segments(self.sample_scene(rng), rng, batch_size - len(segs)))
            k += 1
            if k > 50 * batch_size:  # only an impossible class filter gets here
                raise RuntimeError(
                    f"{k} on-line scenes gave {len(segs)} segments of classes "
                    f"{list(self.settings.class_ids or [])}; expected at least {batch_size}"
                )
        segs = segs[:batch_size]
        return SegmentBatch(
            points=np.stack([s.points for s in segs]).astype(np.float32),
            cls_id=np.array([s.cls_id for s in segs], dtype=np.int64),
            R=np.stack([s.R for s in segs]).astype(np.float32),
            t=np.stack([s.t for s in segs]).astype(np.float32),
            count=np.array([s.count for s in segs], dtype=np.int64),
            scenes=k,
        )


class OnlineChunks(torch.utils.data.Dataset):
    """Chunks ``j = 0, 1, ...`` of on-line segments as a map-style dataset: chunk j is
    ``OnlineSynth.batch(seed, j, chunk_size)``, a pure function of ``(seed, j)``, so worker
    processes can make chunks in any order and a DataLoader hands them back in order.

    Args:
        settings: what the segments are made with (the :class:`OnlineSynth` is built in each
            process on first use: an Open3D scene cannot be pickled).
        seed: the run's seed.
        chunk_size: segments per chunk.
        n_chunks: chunks in the run.
        store: a :class:`~cloudpose.data.synth.chunks.ChunkStore` root: a chunk stored there is
            read instead of made, and a chunk made is stored (None: neither).
    """

    def __init__(
        self,
        settings: OnlineSettings,
        seed: int,
        chunk_size: int,
        n_chunks: int,
        store: str | Path | None = None,
    ) -> None:
        self.settings = settings
        self.seed = int(seed)
        self.chunk_size = int(chunk_size)
        self.n_chunks = int(n_chunks)
        self.store = None if store is None else ChunkStore(store, settings, chunk_size)
        self._synth: OnlineSynth | None = None

    def __len__(self) -> int:
        return self.n_chunks

    def __getitem__(self, j: int) -> tuple[torch.Tensor, ...]:
        if self.store is not None and (got := self.store.load(self.seed, j)) is not None:
            return got
        if self._synth is None:
            in_worker = torch.utils.data.get_worker_info() is not None
            self._synth = OnlineSynth(self.settings, nthreads=1 if in_worker else 0)
        chunk = self._synth.batch(self.seed, int(j), self.chunk_size).tensors()
        if self.store is not None:
            self.store.save(self.seed, j, chunk)
        return chunk

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_synth": None}


def _worker_init(_: int) -> None:
    torch.set_num_threads(1)
    threadpool_limits(1)


class OnlineStream:
    """The training batches of an on-line run, step after step.

    Step ``s`` is the concatenation of chunks ``s, s + D, s + 2D, ..., s + (reuse - 1) D``
    (each of ``batch_size / reuse`` segments, D = ``spacing``): every segment is trained on in
    ``reuse`` steps D apart (fewer for the last chunks), each time beside other segments, and
    the synthesis needed per step is one chunk. Two consecutive steps share no segment: reuse in
    consecutive steps (D = 1) gives batches that are 7/8 the same at reuse 8, and an Adam run on
    them learned rotation far worse (shared-0 on line, 4,096 steps: 11.7% of test rotations
    under 10 degrees modulo symmetry). ``reuse`` = 1: every segment once. A turn about the
    optical axis per use (``train.augment_roll_deg``) makes the uses different views. Batch
    ``s`` depends on ``(seed, s)`` only: a stream started at step ``s`` (a resumed run) yields
    what an uninterrupted one yields from there; it first makes the ``(reuse - 1) D + 1``
    chunks step ``s`` needs.

    Args:
        settings: what the segments are made with.
        seed: the run's seed.
        batch_size: segments per step; a multiple of ``reuse``.
        reuse: steps each segment is used in.
        total_steps: steps of the run.
        start: first step to yield.
        workers: synthesis processes (0: in the training process); while the stream is open,
            this process trains with ``torch.get_num_threads() - workers`` threads (at least 1).
        spacing: steps between two uses of a segment (D).
        store: root of a :class:`~cloudpose.data.synth.chunks.ChunkStore` to read chunks from
            and keep them in (speed only: the same batches; None: synthesize every chunk).
    """

    def __init__(
        self,
        settings: OnlineSettings,
        seed: int,
        batch_size: int,
        reuse: int,
        total_steps: int,
        start: int = 0,
        workers: int = 1,
        spacing: int = REUSE_SPACING,
        store: str | Path | None = None,
    ) -> None:
        if reuse < 1 or batch_size % reuse:
            raise ValueError(
                f"data.online_reuse={reuse} must be >= 1 and divide train.batch_size={batch_size}"
            )
        if spacing < 1:
            raise ValueError(f"spacing must be >= 1, got {spacing}")
        self.reuse = int(reuse)
        self.spacing = int(spacing)
        self.step = int(start)
        span = (self.reuse - 1) * self.spacing
        chunks = OnlineChunks(settings, seed, batch_size // reuse, total_steps + span, store)
        self._loader = torch.utils.data.DataLoader(
            chunks,
            batch_size=None,
            sampler=range(self.step, len(chunks)),
            num_workers=int(workers),
            prefetch_factor=PREFETCH_CHUNKS if workers > 0 else None,
            worker_init_fn=_worker_init if workers > 0 else None,
            multiprocessing_context="fork" if workers > 0 else None,
        )
        self._it = iter(self._loader)
        self._window: list[tuple[torch.Tensor, ...]] = []  # chunks step, step + 1, ...
        self._span = span
        # the workers take cores of their own: training keeps the rest (two threads on one
        # core's share cost more than they give; measured in benchmarks/bench_online.py)
        self._threads = torch.get_num_threads()
        if workers > 0:
            torch.set_num_threads(max(1, self._threads - int(workers)))

    def next(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(points, cls_id, R, t)`` of the next step."""
        while len(self._window) <= self._span:
            self._window.append(next(self._it))
        parts = self._window[:: self.spacing][: self.reuse]
        out = tuple(torch.cat(p) for p in zip(*parts, strict=True))
        self._window.pop(0)
        self.step += 1
        return out

    def close(self) -> None:
        """Stop the synthesis processes and give training its threads back."""
        self._it = None
        self._loader = None
        torch.set_num_threads(self._threads)


def store_chunks(
    settings: OnlineSettings,
    seed: int,
    chunk_size: int,
    n_chunks: int,
    store: str | Path,
    workers: int | None = None,
    progress: bool = True,
) -> int:
    """Make and keep the chunks ``0 .. n_chunks - 1`` of ``seed`` that ``store`` lacks, in
    ``workers`` processes (default: every core), so that runs of this seed read them
    (:mod:`cloudpose.data.synth.chunks`). Returns how many were made."""
    chunks = OnlineChunks(settings, seed, chunk_size, n_chunks, store)
    assert chunks.store is not None
    missing = [j for j in range(n_chunks) if not chunks.store.path(seed, j).is_file()]
    if workers is None:
        workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
    loader = torch.utils.data.DataLoader(
        chunks,
        batch_size=None,
        sampler=missing,
        num_workers=int(workers),
        worker_init_fn=_worker_init if workers > 0 else None,
        multiprocessing_context="fork" if workers > 0 else None,
    )
    for _ in tqdm(
        loader, total=len(missing), disable=not progress, desc=f"seed {seed}", unit="chunk"
    ):
        pass
    return len(missing)
