"""Object segments: mask -> back-projection -> outlier filter -> farthest point sampling.

docs/design.md, "Data flow": per annotated instance of a frame, the pixels with label == class and
depth > 0 are back-projected with the intrinsics (metres, camera frame), points farther than
0.2 m from the segment mean are dropped, and farthest point sampling (FPS) from a random start
orders 1024 of them; any prefix of that order is itself an FPS sample, so the network takes the
first n. A segment with fewer points is filled by repeating its FPS order (the true count is
kept); an instance without a usable point is kept as invalid (a miss at test time).

The mask comes from a *segmentation source* (:mod:`cloudpose.data.mask_sources`): "gt" = the
ground-truth label image, degraded masks, or PoseCNN's published labels. The occlusion factor
always uses the ground-truth labels.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from cloudpose import kernels
from cloudpose.data.mask_sources import get_mask_source

if TYPE_CHECKING:
    from cloudpose.data.synth.render import Renderer
    from cloudpose.data.ycb import Frame


class SegmentWarning(UserWarning):
    """A degenerate but recoverable segment (no usable point, no alone-pixel count)."""


# --------------------------------------------------------------------------- FPS


def _check_fps_args(points: np.ndarray, k: int) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points have shape {points.shape}, expected (N, 3)")
    if len(points) == 0:
        raise ValueError("points are empty; FPS needs at least one point")
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    return np.ascontiguousarray(points, dtype=np.float32)


def _start(n: int, start: int | np.random.Generator | None) -> int:
    if start is None:
        start = np.random.default_rng()
    if isinstance(start, np.random.Generator):
        return int(start.integers(n))
    if not 0 <= int(start) < n:
        raise ValueError(f"start index {start} out of range 0..{n - 1}")
    return int(start)


def _fill(order: np.ndarray, k: int) -> np.ndarray:
    """FPS order of all N < k points, then repeated cyclically up to k."""
    return np.resize(order, k)


def farthest_point_sampling(
    points: np.ndarray, k: int, start: int | np.random.Generator | None = None
) -> np.ndarray:
    """Exact farthest point sampling, in float32.

    The compiled bucket FPS of :func:`cloudpose.kernels.fps_order` (a k-d tree skips the
    points a new sample cannot get closer to) where the kernels are enabled, else fpsample's
    vanilla FPS (:func:`cloudpose.kernels.farthest_order` picks). Both give the order of :func:`farthest_point_sampling_reference`, index for
    index, ties included (the highest index wins a tie, as in fpsample, so segment caches
    made with either are the same).

    Args:
        points: (N, 3) points, metres.
        k: samples wanted.
        start: first index, or a generator to draw it uniformly (None: a fresh generator).

    Returns:
        (k,) int64 indices in FPS order. If N < k: the FPS order of all N points, then
        repeated cyclically (docs/design.md: segments are filled by repeating points).
    """
    pts = _check_fps_args(points, k)
    s = _start(len(pts), start)
    m = min(k, len(pts))
    if m == 1:
        order = np.array([s], dtype=np.int64)
    else:
        order = kernels.farthest_order(pts, m, s)
    return _fill(order, k) if m < k else order


def farthest_point_sampling_reference(
    points: np.ndarray, k: int, start: int | np.random.Generator | None = None
) -> np.ndarray:
    """Slow, obviously correct twin of :func:`farthest_point_sampling` (a numpy loop).

    Same arithmetic (float32 squared distances ``(dx*dx + dy*dy) + dz*dz``; on ties the
    highest index, fpsample's rule, which decides real segments: depth is quantised), so
    equal outputs.
    """
    pts = _check_fps_args(points, k)
    s = _start(len(pts), start)
    m = min(k, len(pts))
    order = [s]
    nearest = np.full(len(pts), np.inf, dtype=np.float32)
    for _ in range(m - 1):
        d = ((pts - pts[order[-1]]) ** 2).sum(axis=1)
        nearest = np.minimum(nearest, d)
        order.append(len(pts) - 1 - int(np.argmax(nearest[::-1])))  # the last maximum
    out = np.asarray(order, dtype=np.int64)
    return _fill(out, k) if m < k else out


# --------------------------------------------------------------------------- segments


@dataclass
class Segment:
    """One object instance's observed point cloud.

    Attributes:
        points: (n_fps, 3) float32 camera-frame points, metres, in FPS order (any prefix is an
            FPS sample); zeros when invalid.
        count: points left after the outlier filter (the true count; < n_fps means repeats).
        cls_id: 1-based class id.
        R: (3, 3) float32 ground-truth rotation model->camera, or None without ground truth.
        t: (3,) float32 ground-truth translation, metres, or None.
        occlusion: occlusion factor O = 1 - lambda / nu in [0, 1] (lambda: ground-truth label
            pixels, nu: pixels of the object rendered alone); NaN when unknown.
        frame_id: "SEQ/FRAME".
        instance: index of the instance in the frame's meta (cls_indexes order).
        valid: False when the segment has no usable point (a miss at test time).
    """

    points: np.ndarray
    count: int
    cls_id: int
    R: np.ndarray | None
    t: np.ndarray | None
    occlusion: float
    frame_id: str
    instance: int
    valid: bool


def backproject(depth: np.ndarray, mask: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points of the masked pixels with a depth reading.

    Args:
        depth: (H, W) depth in metres, 0 = none.
        mask: (H, W) bool.
        K: (3, 3) intrinsics.

    Returns:
        (M, 3) float64 points ``z * K^-1 [u, v, 1]``, metres, in row-major pixel order.
    """
    v, u = np.nonzero(mask & (depth > 0))
    z = depth[v, u].astype(np.float64)
    pix = np.stack([u, v, np.ones_like(u)], axis=1).astype(np.float64)
    return (pix @ np.linalg.inv(K).T) * z[:, None]


def occlusion_factor(visible: np.ndarray, alone: np.ndarray) -> np.ndarray:
    """O = 1 - visible / alone, clipped to [0, 1]; NaN where ``alone`` is 0.

    Args:
        visible: (N,) ground-truth label pixels (lambda).
        alone: (N,) pixels of the object rendered alone (nu).

    Returns:
        (N,) float64 occlusion factors (docs/design.md, "Metrics"). On real frames the label can
        exceed the rendering by a few pixels; that clips to 0.
    """
    visible = np.asarray(visible, dtype=np.float64)
    alone = np.asarray(alone, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        o = 1.0 - visible / alone
    return np.where(alone > 0, np.clip(o, 0.0, 1.0), np.nan)


def instance_streams(rng: np.random.Generator, cls_ids) -> list[np.random.Generator]:
    """One random stream per instance of a frame.

    One draw from ``rng`` is the frame's entropy; each instance's stream is the
    ``SeedSequence`` child of it keyed by the instance's class and its rank among the frame's
    instances of that class. An instance's stream then does not depend on the other instances
    of the frame: whether they are annotated, found by a mask, or have any usable point.

    Args:
        rng: the frame's generator (one number is drawn from it).
        cls_ids: (N,) class ids of the frame's instances, in order.

    Returns:
        N generators, in ``cls_ids`` order.
    """
    entropy = int(rng.integers(2**63))
    rank: dict[int, int] = {}
    out = []
    for c in np.asarray(cls_ids, dtype=np.int64).reshape(-1).tolist():
        k = rank.get(c, 0)
        rank[c] = k + 1
        out.append(np.random.default_rng(np.random.SeedSequence(entropy, spawn_key=(c, k))))
    return out


ALONE_SURFACE_VERSION = 2
"""Surfaces (:class:`cloudpose.data.synth.render.Renderer`) that render the object-alone pixel counts
of the occlusion factor for frames that do not carry them (real YCB-Video): version 2 keeps the
holes of handles, which version 1 fills (a mug's or pitcher's occlusion came out too low). Part
of the cache key of such data only: synthetic and BOP frames carry their own counts."""


SEGMENT_STREAMS = ("instance", "frame")
"""How a frame's instances draw their FPS starts: "instance", each from its own stream
(:func:`instance_streams`); "frame", all from the frame's one generator in instance order (an
instance's points then depend on the instances before it; kept to reproduce data made so)."""


def extract_segments(
    frame: Frame,
    alone_pixels: np.ndarray | None = None,
    renderer: Renderer | None = None,
    n_fps: int = 1024,
    outlier_radius: float = 0.2,
    segmentation: str = "gt",
    rng: np.random.Generator | None = None,
    with_gt: bool = True,
    streams: str = "instance",
) -> list[Segment]:
    """Segments of every annotated instance of a frame (docs/design.md, "Data flow").

    Args:
        frame: the frame (depth, label, K, cls_ids, poses or None).
        alone_pixels: (N,) pixels of each instance rendered alone (the synthetic meta's
            ``alone_pixels``); None -> rendered with ``renderer`` when the frame has poses.
        renderer: renders the alone-pixel counts when ``alone_pixels`` is None.
        n_fps: points kept per segment.
        outlier_radius: points farther than this from the segment mean are dropped, metres.
        segmentation: mask source name (:data:`cloudpose.data.mask_sources.MASK_SOURCES`).
        rng: the frame's generator (default: a fresh one); each instance draws its FPS start
            from its own stream (:func:`instance_streams`), so one instance's points do not
            depend on the others.
        with_gt: False ignores the frame's poses (prediction): R, t None, occlusion NaN.
        streams: :data:`SEGMENT_STREAMS`; "frame" draws every instance's start from ``rng``
            itself, one after another.

    Returns:
        One :class:`Segment` per instance, in ``frame.cls_ids`` order; invalid ones (no usable
        point) warn with :class:`SegmentWarning` and are kept.
    """
    mask_of = get_mask_source(segmentation)
    if n_fps < 1:
        raise ValueError(f"n_fps must be >= 1, got {n_fps}")
    if not outlier_radius > 0:
        raise ValueError(f"outlier_radius must be > 0 metres, got {outlier_radius}")
    cls_ids = np.asarray(frame.cls_ids, dtype=np.int64)
    n = len(cls_ids)
    if streams not in SEGMENT_STREAMS:
        raise ValueError(f"streams={streams!r}: expected one of {SEGMENT_STREAMS}")
    rng = rng or np.random.default_rng()
    streams = instance_streams(rng, cls_ids) if streams == "instance" else [rng] * n
    K = np.asarray(frame.K, dtype=np.float64)
    poses = frame.poses if with_gt else None
    occlusion = np.full(n, np.nan)
    if poses is not None and n:
        if alone_pixels is None and renderer is not None:
            alone_pixels = renderer.alone_pixels(K, frame.depth.shape, cls_ids, poses)
        if alone_pixels is not None:
            alone_pixels = np.asarray(alone_pixels).reshape(-1)
            if alone_pixels.shape != (n,):
                raise ValueError(
                    f"frame {frame.frame_id}: alone_pixels has {alone_pixels.shape[0]} entries, "
                    f"expected one per instance ({n})"
                )
            visible = np.array([(frame.label == c).sum() for c in cls_ids])
            occlusion = occlusion_factor(visible, alone_pixels)
            if np.isnan(occlusion).any():
                warnings.warn(
                    f"frame {frame.frame_id}: classes {cls_ids[np.isnan(occlusion)].tolist()} "
                    "have no pixel when rendered alone; occlusion factor unknown (NaN)",
                    SegmentWarning,
                    stacklevel=2,
                )
    out = []
    for i, c in enumerate(cls_ids):
        pts = backproject(frame.depth, mask_of(frame, int(c)), K)
        if len(pts):
            pts = pts[np.linalg.norm(pts - pts.mean(axis=0), axis=1) <= outlier_radius]
        if poses is not None:
            R = poses[i, :, :3].astype(np.float32)
            t = poses[i, :, 3].astype(np.float32)
        else:
            R = t = None
        valid = len(pts) > 0
        if valid:
            sample = pts[farthest_point_sampling(pts, n_fps, streams[i])].astype(np.float32)
        else:
            sample = np.zeros((n_fps, 3), dtype=np.float32)
            warnings.warn(
                f"frame {frame.frame_id}: instance {i} (class {int(c)}) has no usable point "
                f"(segmentation {segmentation!r}); kept as a miss",
                SegmentWarning,
                stacklevel=2,
            )
        out.append(
            Segment(sample, len(pts), int(c), R, t, float(occlusion[i]), frame.frame_id, i, valid)
        )
    return out


UNIT_CHECK_OFF = "CLOUDPOSE_NO_UNIT_CHECK"
"""Environment variable that turns the depth unit check (:func:`check_depth_scale`) into a
warning: ``CLOUDPOSE_NO_UNIT_CHECK=1`` lets every command go on with depth that looks like
another unit (objects a tenth or ten times their model's size)."""

YCB_DEPTH_UNIT = "depth units per metre; YCB-Video 10000, millimetres 1000"
"""What a YCB-Video depth factor means, for the unit check's message."""


class UnitWarning(UserWarning):
    """Depth that looks like another unit, let through by :data:`UNIT_CHECK_OFF`."""


def unit_check_enabled() -> bool:
    """False when :data:`UNIT_CHECK_OFF` is set to anything but "" or "0"."""
    return os.environ.get(UNIT_CHECK_OFF, "").strip() in ("", "0")


def depth_scale_stats(
    points: list[np.ndarray], cls_ids: list[int], models_by_class: dict[int, np.ndarray]
) -> tuple[float, float] | None:
    """What the unit check looks at: the median over the segments of (segment extent / model
    diameter) and of the segment's median depth in metres; None without a usable segment.

    A segment's extent is twice the 95th percentile of its points' distance from their mean.

    Args:
        points: per segment, (N_i, 3) camera-frame points, metres (segments with N_i < 3 are
            left out).
        cls_ids: per segment, its 1-based class id (a key of ``models_by_class``; others are
            left out).
        models_by_class: (P, 3) model points, metres.
    """
    ratios, depths = [], []
    for p, c in zip(points, cls_ids, strict=True):
        if len(p) < 3 or c not in models_by_class:
            continue
        m = models_by_class[c]
        diameter = float(np.linalg.norm(m.max(0) - m.min(0)))
        extent = 2 * float(np.percentile(np.linalg.norm(p - p.mean(0), axis=1), 95))
        ratios.append(extent / diameter)
        depths.append(float(np.median(p[:, 2])))
    if not ratios:
        return None
    return float(np.median(ratios)), float(np.median(depths))


def depth_scale_problem(
    ratio: float, depth: float, source: str, flag: str, unit: str = YCB_DEPTH_UNIT
) -> str | None:
    """The unit check's one-line message for :func:`depth_scale_stats` ``(ratio, depth)``, or
    None when they look like metres (see :func:`check_depth_scale`)."""
    if 0.3 <= ratio <= 3.0 and 0.2 <= depth <= 6.0:
        return None
    factor = 10.0 ** round(float(np.log10(ratio)))
    if factor == 1.0:
        factor = 10.0 ** round(float(np.log10(depth / 1.0)))
    looks = f"{1 / factor:g} times too small" if factor < 1 else f"{factor:g} times too large"
    return (
        f"{source}: the objects look {looks} for their models (median segment extent "
        f"{ratio:.2f} x the model diameter, median depth {depth:.3f} m): is the depth in "
        f"another unit? set {flag} ({unit})"
    )


def check_depth_scale(
    points: list[np.ndarray],
    cls_ids: list[int],
    models_by_class: dict[int, np.ndarray],
    source: str,
    flag: str,
    unit: str = YCB_DEPTH_UNIT,
) -> None:
    """Raise when the segments look like depth read in the wrong unit.

    A segment's extent (twice the 95th percentile of its points' distance from their mean) is
    at most the model's diameter and, unless the object is mostly hidden, a fair part of it;
    and a depth sensor sees objects between ~0.2 and ~6 m. Depth in millimetres read as
    tenths of a millimetre (YCB-Video's factor) shrinks both by 10: objects at 0.1 m, a tenth
    of their size. The check takes the median over the segments, so one occluded object does
    not trip it. Every path that reads depth runs it: :func:`cloudpose.predict.predict` per
    frame, the segment cache (:func:`cloudpose.data.cache.prepare`) per scene, the BOP export
    per scene. With :data:`UNIT_CHECK_OFF` set it warns (:class:`UnitWarning`) instead.

    Args:
        points: per segment, (N_i, 3) camera-frame points, metres (N_i >= 3).
        cls_ids: per segment, its 1-based class id (a key of ``models_by_class``).
        models_by_class: (P, 3) model points, metres.
        source: what to name in the error (the depth file, the scene folder).
        flag: the setting that fixes it (e.g. ``--depth-factor``).
        unit: what that setting means, with common values.

    Raises:
        ValueError: naming ``source``, the factor the data looks off by, and ``flag``.
    """
    stats = depth_scale_stats(points, cls_ids, models_by_class)
    if stats is not None:
        report_depth_scale(depth_scale_problem(*stats, source, flag, unit))


def report_depth_scale(problem: str | None) -> None:
    """Raise ``ValueError(problem)`` (saying how to go on anyway); with :data:`UNIT_CHECK_OFF`
    set, warn instead."""
    if problem is None:
        return
    if unit_check_enabled():
        raise ValueError(f"{problem}; {UNIT_CHECK_OFF}=1 goes on anyway")
    warnings.warn(f"{problem}; going on ({UNIT_CHECK_OFF} is set)", UnitWarning, stacklevel=3)
