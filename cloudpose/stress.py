"""Stress curves: the real development frames and synthetic test frames, perturbed in controlled
steps, each method measured at every step (``cloudpose stress``; issue 39).

A *perturbation* acts either on the frame's pixels before segmentation (the instance's mask
dilated, eroded or shifted by k pixels, the depth dropped in blobs or smoothed over the mask)
or on the back-projected points of the segment before farthest point sampling (depth noise and
a bias growing with distance along each pixel's ray, a cut plane, the number of points, one
side of the visible part missing). The segment is then made as
:func:`cloudpose.data.segments.extract_segments` makes it (the 0.2 m outlier filter, FPS of
``n_fps`` points), and each method estimates the pose from it: the network of each checkpoint
without and with the run's ICP, FPFH + RANSAC and point-pair features
(``cloudpose/resources/registry/baselines.toml``), each also followed by the same ICP. The
errors are the evaluation's (:func:`cloudpose.evaluate.instance_table`): ADS AUC, rotation
< 10 deg modulo symmetry, translation < 1 cm, median translation.

Level 0 of every perturbation is the identity: the unperturbed segments, shared by all of them.
Every random choice (blob centres, plane directions, the FPS start) comes from a stream keyed by
(seed, source, frame, instance) and not by the level, so the levels of one perturbation differ
by the level only (common random numbers) and a run is deterministic given its seed.

Where real frames sit: each perturbation names a statistic of a segment that it moves (share of
points more than 1 cm off the posed model for mask dilation, share of mask pixels without depth
for missing depth, ...). The statistic is measured on the unperturbed real segments and on the
synthetic ones at every level; the level at which the synthetic statistic reaches the real one
is the real frames' own level, marked on the curves (:func:`real_levels`).

Resumable: each (source, perturbation, level, method) is one CSV in ``OUT/results/``, written
once computed; a later call skips what is there. ``plan`` prints what is left and an estimate of
its time before anything runs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import ndimage
from scipy.spatial import cKDTree

from cloudpose.baselines import load_settings, make
from cloudpose.baselines.base import NotRegistered
from cloudpose.baselines.run import subsample
from cloudpose.config import PAPER_RADIUS
from cloudpose.data.layout import open_dataset, real_dev_root
from cloudpose.data.segment_set import SegmentSet
from cloudpose.data.segments import (
    ALONE_SURFACE_VERSION,
    Segment,
    backproject,
    farthest_point_sampling,
)
from cloudpose.data.synth import synthesize
from cloudpose.data.synth.render import Renderer
from cloudpose.data.synth.sensor import smooth_depth
from cloudpose.evaluate import instance_table
from cloudpose.files import atomic_write, checked_members
from cloudpose.infer import (
    Estimates,
    estimate_poses,
    load_checkpoint,
    refine_ensemble,
    refine_poses,
)
from cloudpose.metrics import summarize
from cloudpose.refine import DepthView, ICPSettings, schedule_for
from cloudpose.registry import DEFAULT_PRESET, resolve

SOURCES = ("real", "synth")
"""Where the frames come from: the 61 packaged real development frames
(:func:`cloudpose.data.layout.real_dev_root`) and the default preset's synthetic test frames."""

MIN_KEEP = 0.1
"""Least share of a segment's points the cut plane and the lateral shift leave (a segment of
no point would be a miss, not a pose)."""


# --------------------------------------------------------------------------- perturbations


def _disk(k: int) -> np.ndarray:
    r = np.arange(-k, k + 1)
    return (r[:, None] ** 2 + r[None, :] ** 2) <= k * k


def dilate_mask(mask: np.ndarray, k: float) -> np.ndarray:
    """(H, W) bool ``mask`` grown by a disk of radius ``k`` pixels into whatever lies around it
    (background, neighbours)."""
    k = round(k)
    return mask.copy() if k <= 0 else ndimage.binary_dilation(mask, structure=_disk(k))


def erode_mask(mask: np.ndarray, k: float) -> np.ndarray:
    """(H, W) bool ``mask`` shrunk by a disk of radius ``k`` pixels (its boundary band gone)."""
    k = round(k)
    return mask.copy() if k <= 0 else ndimage.binary_erosion(mask, structure=_disk(k))


def shift_mask(mask: np.ndarray, k: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) bool ``mask`` moved by ``k`` pixels in a random direction against the depth (a
    label misregistered to the depth image): one side takes in what lies beside the object,
    the other loses the object's rim. The direction is drawn first whatever ``k`` is, so
    every level of one instance moves the same way."""
    angle = rng.uniform(0.0, 2 * np.pi)
    dy, dx = round(k * np.sin(angle)), round(k * np.cos(angle))
    out = np.zeros_like(mask)
    H, W = mask.shape
    out[max(dy, 0) : H + min(dy, 0), max(dx, 0) : W + min(dx, 0)] = mask[
        max(-dy, 0) : H + min(-dy, 0), max(-dx, 0) : W + min(-dx, 0)
    ]
    return out


def drop_depth_blobs(
    depth: np.ndarray, mask: np.ndarray, share: float, rng: np.random.Generator
) -> np.ndarray:
    """``depth`` (H, W, metres) with the readings of about ``share`` of the mask's pixels with
    depth set to 0, in discs of 2-8 pixels' radius centred on mask pixels (the same centres,
    in the same order, at every share)."""
    out = depth.copy()
    v, u = np.nonzero(mask & (depth > 0))
    n = len(v)
    if share <= 0 or n == 0:
        return out
    order = rng.permutation(n)
    radii = rng.uniform(2.0, 8.0, size=n)
    H, W = depth.shape
    target = share * n
    readable = mask & (depth > 0)
    gone = np.zeros_like(mask)
    removed = 0
    for j in order:
        r = radii[j]
        ri = int(np.ceil(r))
        v0, v1 = max(v[j] - ri, 0), min(v[j] + ri + 1, H)
        u0, u1 = max(u[j] - ri, 0), min(u[j] + ri + 1, W)
        yy, xx = np.mgrid[v0:v1, u0:u1]
        disc = (yy - v[j]) ** 2 + (xx - u[j]) ** 2 <= r * r
        new = disc & ~gone[v0:v1, u0:u1]
        removed += int((new & readable[v0:v1, u0:u1]).sum())
        gone[v0:v1, u0:u1] |= disc
        if removed >= target:
            break
    out[gone & mask] = 0.0
    return out


def depth_noise(points: np.ndarray, sigma_mm: float, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) points moved along their rays by Gaussian depth noise of ``sigma_mm`` mm in z."""
    if sigma_mm <= 0 or len(points) == 0:
        return points.copy()
    z = points[:, 2]
    dz = rng.standard_normal(len(points)) * sigma_mm / 1000.0
    return points * ((z + dz) / z)[:, None]


CORR_LAG_PX = 2
CORR_SIGMA_PX = 3.0
CORR_EDGE_PX = 4


def depth_correlation(depth: np.ndarray, mask: np.ndarray) -> float:
    """How smooth a segment's depth error is: the correlation between pixels
    :data:`CORR_LAG_PX` apart (along rows) of the depth minus its Gaussian average over the
    mask (:data:`CORR_SIGMA_PX`), on the pixels at least :data:`CORR_EDGE_PX` inside the mask.
    Independent per-pixel noise gives ~0; a camera that matches over a window, ~0.4 and more.
    NaN for a mask too small to measure."""
    m = mask & (depth > 0)
    inner = ndimage.binary_erosion(m, iterations=CORR_EDGE_PX)
    if inner.sum() < 50:
        return np.nan
    residual = np.where(inner, depth - smooth_depth(depth, m, CORR_SIGMA_PX), np.nan)
    a, b = residual[:, :-CORR_LAG_PX], residual[:, CORR_LAG_PX:]
    both = ~np.isnan(a) & ~np.isnan(b)
    if both.sum() < 50 or np.std(a[both]) == 0 or np.std(b[both]) == 0:
        return np.nan
    return float(np.corrcoef(a[both], b[both])[0, 1])


def depth_bias(points: np.ndarray, mm_per_m: float) -> np.ndarray:
    """(N, 3) points moved along their rays by a depth bias of ``mm_per_m`` mm per metre of depth
    (z' = z (1 + b), a bias that grows with distance)."""
    return points * (1.0 + mm_per_m / 1000.0)


def cut_plane(points: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """The points on one side of a plane of random direction (uniform on the sphere) through
    the segment, the plane placed so that ``share`` of them are removed (at most
    ``1 - MIN_KEEP``)."""
    n = rng.standard_normal(3)
    n /= np.linalg.norm(n)
    if share <= 0 or len(points) == 0:
        return points.copy()
    s = points @ n
    keep = max(int(np.ceil(len(points) * max(1 - share, MIN_KEEP))), 1)
    order = np.argsort(s, kind="stable")
    return points[np.sort(order[:keep])]


def lateral_shift(points: np.ndarray, shift_mm: float, rng: np.random.Generator) -> np.ndarray:
    """One side of the visible part missing: the points farthest along a random direction across
    the viewing ray are removed until the centroid of the rest has moved by ``shift_mm`` mm
    (or only ``MIN_KEEP`` of the points are left)."""
    angle = rng.uniform(0.0, 2 * np.pi)
    if shift_mm <= 0 or len(points) < 2:
        return points.copy()
    ray = points.mean(axis=0)
    ray = ray / np.linalg.norm(ray)
    a = np.cross(ray, [0.0, 1.0, 0.0] if abs(ray[1]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(ray, a)
    u = np.cos(angle) * a + np.sin(angle) * b  # (3,) across the ray
    order = np.argsort(-(points @ u), kind="stable")  # farthest along u first
    N = len(points)
    total = points.sum(axis=0)
    removed = np.cumsum(points[order[:-1]], axis=0)  # (N-1, 3) sum of the first k+1 removed
    rest = N - np.arange(1, N)  # at least one point left
    cent = (total - removed) / rest[:, None]
    move = cent - total / N
    shift = np.linalg.norm(move - np.outer(move @ ray, ray), axis=1)  # across the ray
    max_removed = N - max(int(np.ceil(MIN_KEEP * N)), 1)
    ok = np.flatnonzero(shift[:max_removed] >= shift_mm / 1000.0)
    n_removed = int(ok[0]) + 1 if len(ok) else max_removed
    return points[np.sort(order[n_removed:])]


def resample_points(points: np.ndarray, factor: float, rng: np.random.Generator) -> np.ndarray:
    """``factor`` times the points before FPS: a random subset below 1, above 1 the points plus
    midpoints between random points and their nearest neighbour (a denser sampling of the same
    surface)."""
    N = len(points)
    if factor == 1 or N < 2:
        return points.copy()
    if factor < 1:
        keep = max(round(factor * N), 1)
        return points[np.sort(rng.choice(N, size=keep, replace=False))]
    extra = round((factor - 1) * N)
    src = rng.integers(N, size=extra)
    _, nn = cKDTree(points).query(points[src], k=2)
    return np.concatenate([points, 0.5 * (points[src] + points[nn[:, 1]])])


@dataclass(frozen=True)
class Perturbation:
    """One controlled change of a segment.

    Attributes:
        name: key (CLI ``--only``, result folders).
        what: one line for the report.
        unit: the level's unit, for axes and tables.
        levels: the steps, 0 (the identity) first.
        stage: "pixels" (the mask and depth before segmentation) or "points" (the
            back-projected points before FPS).
        stat: the segment statistic (:data:`STATISTICS`) that places real frames on its axis.
    """

    name: str
    what: str
    unit: str
    levels: tuple[float, ...]
    stage: str
    stat: str


PERTURBATIONS: dict[str, Perturbation] = {
    p.name: p
    for p in (
        Perturbation(
            "dilate", "mask dilated into background and neighbours", "px",
            (0, 1, 2, 4, 6, 10), "pixels", "off_model",
        ),
        Perturbation(
            "erode", "mask eroded", "px", (0, 1, 2, 4, 6, 10), "pixels", "boundary",
        ),
        Perturbation(
            "shift", "mask shifted against the depth (one side bleeds, the other is cut)",
            "px", (0, 1, 2, 4, 6, 10), "pixels", "off_model",
        ),
        Perturbation(
            "holes", "depth missing in blobs over a share of the mask", "share",
            (0, 0.1, 0.2, 0.35, 0.5, 0.7), "pixels", "no_depth",
        ),
        Perturbation(
            "noise", "depth noise along the ray (sigma)", "mm",
            (0, 1, 2, 4, 6, 10), "points", "noise",
        ),
        Perturbation(
            "smooth", "depth smoothed over the mask (Gaussian sigma)", "px",
            (0, 0.5, 1, 1.5, 2, 3), "pixels", "depth_corr",
        ),
        Perturbation(
            "bias", "depth bias growing with distance", "mm/m",
            (0, 5, 10, 20, 40, 60), "points", "bias",
        ),
        Perturbation(
            "cut", "occlusion by a cut plane (share of points removed)", "share",
            (0, 0.1, 0.2, 0.35, 0.5, 0.7), "points", "occlusion",
        ),
        Perturbation(
            "points", "number of points before FPS", "x",
            (1, 0.25, 0.5, 1.5, 2.0), "points", "count",
        ),
        Perturbation(
            "lateral", "one side missing: the visible centroid moved across the ray", "mm",
            (0, 2, 4, 8, 12, 20), "points", "lateral",
        ),
    )
}  # fmt: skip
"""Every perturbation of ``cloudpose stress``, in report order. ``points`` has 1 (x1) as its
identity; the others 0."""


def farthest_level(p: Perturbation) -> float:
    """The level of ``p`` farthest from its identity."""
    ident = identity_level(p)
    return float(max(p.levels, key=lambda lv: abs(lv - ident)))


def identity_level(p: Perturbation) -> float:
    """The level of ``p`` that changes nothing (1 for ``points``, else 0)."""
    return 1.0 if p.name == "points" else 0.0


def perturb_pixels(
    p: Perturbation,
    level: float,
    mask: np.ndarray,
    depth: np.ndarray,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """``(mask, depth)`` of one instance after a pixel-stage perturbation (others: unchanged)."""
    if p.name == "dilate":
        return dilate_mask(mask, level), depth
    if p.name == "erode":
        return erode_mask(mask, level), depth
    if p.name == "shift":
        return shift_mask(mask, level, rng), depth
    if p.name == "holes":
        return mask, drop_depth_blobs(depth, mask, level, rng)
    if p.name == "smooth":
        return mask, smooth_depth(depth, mask, level)
    return mask, depth


def perturb_points(
    p: Perturbation, level: float, points: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """(N, 3) points of one instance after a point-stage perturbation (others: unchanged)."""
    if p.name == "noise":
        return depth_noise(points, level, rng)
    if p.name == "bias":
        return depth_bias(points, level)
    if p.name == "cut":
        return cut_plane(points, level, rng)
    if p.name == "lateral":
        return lateral_shift(points, level, rng)
    if p.name == "points":
        return resample_points(points, level, rng)
    return points


# --------------------------------------------------------------------------- segments


@dataclass
class FrameData:
    """What a perturbed segment is made from: one frame, with the index it has in its source."""

    frame: object  # cloudpose.data.ycb.Frame
    index: int
    alone_pixels: np.ndarray | None


def instance_rngs(seed: int, source: str, frame_index: int, instance: int):
    """(perturbation stream, FPS stream) of one instance: keyed by seed, source, frame and
    instance, never by the perturbation's level."""
    base = [int(seed), SOURCES.index(source), int(frame_index), int(instance)]
    return np.random.default_rng([*base, 1]), np.random.default_rng([*base, 0])


def perturbed_segment(
    fd: FrameData,
    i: int,
    p: Perturbation,
    level: float,
    *,
    seed: int,
    source: str,
    n_fps: int = 1024,
    outlier_radius: float = 0.2,
) -> tuple[Segment, dict[str, float]]:
    """Instance ``i`` of a frame, perturbed, segmented as the project segments: the ground-truth
    mask, back-projection, the outlier filter, FPS of ``n_fps`` points.

    Returns:
        The segment and its pixel statistics (``mask_px``: mask pixels, ``no_depth``: share of
        them without a depth reading, ``boundary``: share of the mask within 1 pixel of its
        edge, ``depth_corr``: :func:`depth_correlation`).
    """
    f = fd.frame
    c = int(f.cls_ids[i])
    prng, frng = instance_rngs(seed, source, fd.index, i)
    mask = f.label == c
    depth = f.depth
    mask, depth = perturb_pixels(p, level, mask, depth, prng)
    pts = perturb_points(p, level, segment_points(f, depth, mask, outlier_radius), prng)
    n_mask = int(mask.sum())
    px = {
        "mask_px": float(n_mask),
        "no_depth": float((mask & (depth <= 0)).sum() / n_mask) if n_mask else np.nan,
        "boundary": float((mask & ~erode_mask(mask, 1)).sum() / n_mask) if n_mask else np.nan,
        "depth_corr": depth_correlation(depth, mask),
    }
    return sampled_segment(fd, i, pts, frng, n_fps), px


def segment_points(frame, depth: np.ndarray, mask: np.ndarray, outlier_radius: float):
    """The back-projected points of ``mask`` (with ``depth``, the frame's intrinsics) within
    ``outlier_radius`` of their mean: a segment's points before FPS, as the project cuts them."""
    pts = backproject(depth, mask, np.asarray(frame.K, dtype=np.float64))
    if len(pts):
        pts = pts[np.linalg.norm(pts - pts.mean(axis=0), axis=1) <= outlier_radius]
    return pts


def sampled_segment(
    fd: FrameData, i: int, pts: np.ndarray, frng: np.random.Generator, n_fps: int
) -> Segment:
    """Instance ``i``'s :class:`Segment` from its points before FPS: FPS of ``n_fps`` of them
    from the stream ``frng``, the ground-truth pose and the occlusion against the instance
    rendered alone (NaN without it); invalid when no point is left."""
    f = fd.frame
    c = int(f.cls_ids[i])
    R = f.poses[i, :, :3].astype(np.float32)
    t = f.poses[i, :, 3].astype(np.float32)
    occ = np.nan
    if fd.alone_pixels is not None and fd.alone_pixels[i] > 0:
        occ = float(np.clip(1 - (f.label == c).sum() / fd.alone_pixels[i], 0, 1))
    if len(pts):
        sample = pts[farthest_point_sampling(pts, n_fps, frng)].astype(np.float32)
        return Segment(sample, len(pts), c, R, t, occ, f.frame_id, i, True)
    return Segment(np.zeros((n_fps, 3), np.float32), 0, c, R, t, occ, f.frame_id, i, False)


STATISTICS = {
    "off_model": "share of segment points more than 1 cm off the posed model",
    "boundary": "share of mask pixels on its edge (1 px)",
    "no_depth": "share of mask pixels without depth",
    "depth_corr": "correlation of the depth's residual to its local average between pixels "
    f"{CORR_LAG_PX} px apart",
    "noise": "median distance of the points within 1 cm of the posed model, mm",
    "bias": "median signed depth residual to the posed model per metre of depth, mm/m",
    "occlusion": "median extra share hidden (1 - (1 - O_real) / (1 - O_synth))",
    "count": "median points after the outlier filter",
    "lateral": "median distance across the ray from the segment centroid to the posed "
    "model's visible centroid, mm",
}
"""Per-segment statistics that place real frames on a perturbation's axis, in words."""


def segment_stats(
    segs: SegmentSet, px: pd.DataFrame, trees: dict[int, cKDTree], models: dict[int, np.ndarray]
) -> pd.DataFrame:
    """Per instance, the statistics of :data:`STATISTICS` (the ``occlusion`` column is the
    occlusion factor itself; NaN for invalid segments)."""
    rows = []
    for j in range(len(segs)):
        row = {k: np.nan for k in STATISTICS}
        row.update(px.iloc[j].to_dict())
        row["occlusion"] = float(segs.occlusion[j])
        if segs.valid[j]:
            p = segs.observed(j).astype(np.float64)
            R, t = segs.R[j].astype(np.float64), segs.t[j].astype(np.float64)
            c = int(segs.cls_id[j])
            q = (p - t) @ R  # model frame
            d, nn = trees[c].query(q)
            row["off_model"] = float(np.mean(d > 0.01))
            inl = d <= 0.01
            if inl.any():
                row["noise"] = 1000 * float(np.median(d[inl]))
                m_cam = models[c][nn] @ R.T + t
                ray = p / np.linalg.norm(p, axis=1, keepdims=True)
                signed = np.einsum("ij,ij->i", p - m_cam, ray)
                row["bias"] = 1000 * float(np.median(signed[inl])) / float(np.median(p[:, 2]))
            row["count"] = float(segs.count[j])
            # the centroid of the model points nearest to the segment: the part it shows
            vis = models[c][np.unique(nn)] @ R.T + t
            off = p.mean(axis=0) - vis.mean(axis=0)
            ray = p.mean(axis=0) / np.linalg.norm(p.mean(axis=0))
            row["lateral"] = 1000 * float(np.linalg.norm(off - (off @ ray) * ray))
        rows.append(row)
    return pd.DataFrame(rows)


# --------------------------------------------------------------------------- sources


@dataclass
class Source:
    """The frames of one source and the instances the sweep takes from them.

    Attributes:
        name: one of :data:`SOURCES`.
        dataset: the opened dataset (models, class names).
        frames: the frames holding a chosen instance.
        instances: (frame position in ``frames``, instance index) per chosen instance.
        described: the frames in words, for the report.
    """

    name: str
    dataset: object
    frames: list[FrameData]
    instances: list[tuple[int, int]]
    described: str


def evenly_spaced(n: int, limit: int | None) -> np.ndarray:
    """Indices of an evenly spaced ``limit`` of ``n`` (all when None or >= n)."""
    return subsample(n, limit)


def open_source(
    name: str, cfg, out_dir: Path, *, instances: int | None, synth_frames: int, progress: bool
) -> Source:
    """The frames of ``name``: the packaged real development frames (all 61), or the first
    ``synth_frames`` synthetic test frames of the preset (written under ``out_dir/synth``:
    frame i is a pure function of the synthesis seed, split and i, so they are the preset's own
    test frames 0..synth_frames-1); ``instances`` evenly spaced instances of them."""
    if name == "real":
        ds = open_dataset(real_dev_root())
        ids = ds.image_set("all")
        described = f"the {len(ids)} packaged real development frames"
    elif name == "synth":
        root = out_dir / "synth"
        d = cfg.data
        synthesize(
            root, 0, synth_frames, seed=d.synth_seed, noise=d.noise,
            uniform_rotation=d.uniform_rotation, workers=1, progress=progress,
            version=d.synth_version,
        )  # fmt: skip
        ds = open_dataset(root)
        ids = ds.image_set("keyframe")
        described = f"synthetic test frames 0-{len(ids) - 1} of preset {cfg.preset}"
    else:
        raise ValueError(f"source {name!r}: expected one of {', '.join(SOURCES)}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        frames = [ds.frame(f) for f in ids]
    classes = set(cfg.data.classes)
    pairs = [
        (fi, i)
        for fi, f in enumerate(frames)
        for i, c in enumerate(f.cls_ids)
        if f.poses is not None and (not classes or ds.classes[int(c) - 1] in classes)
    ]
    pairs = [pairs[k] for k in evenly_spaced(len(pairs), instances)]
    used = sorted({fi for fi, _ in pairs})
    renderer = None
    fds = {}
    for fi in used:
        f = frames[fi]
        alone = ds.alone_pixels(f.frame_id) if hasattr(ds, "alone_pixels") else None
        if alone is None:
            if renderer is None:
                renderer = Renderer(
                    {c: p.copy() for c, p in ds.models().items()},
                    surface_version=ALONE_SURFACE_VERSION,
                )
            alone = renderer.alone_pixels(f.K, f.depth.shape, f.cls_ids, f.poses)
        fds[fi] = FrameData(f, fi, np.asarray(alone).reshape(-1))
    pos = {fi: k for k, fi in enumerate(used)}
    return Source(
        name,
        ds,
        [fds[fi] for fi in used],
        [(pos[fi], i) for fi, i in pairs],
        f"{len(pairs)} instances of {described}",
    )


def condition_segments(
    src: Source, p: Perturbation, level: float, seed: int, n_fps: int, outlier_radius: float
) -> tuple[SegmentSet, pd.DataFrame]:
    """The chosen instances of ``src`` under ``p`` at ``level``: the segments and their pixel
    statistics (:func:`perturbed_segment`)."""
    segs, px = [], []
    for fpos, i in src.instances:
        s, row = perturbed_segment(
            src.frames[fpos], i, p, level, seed=seed, source=src.name, n_fps=n_fps,
            outlier_radius=outlier_radius,
        )  # fmt: skip
        segs.append(s)
        px.append(row)
    return SegmentSet.from_segments(segs, n_fps), pd.DataFrame(px)


# --------------------------------------------------------------------------- methods


@dataclass(frozen=True)
class Method:
    """A pose method of the sweep: ``net-{label}`` (a checkpoint), ``ensemble`` (several, the
    refinement of best ICP fitness kept per object), ``fpfh`` or ``ppf``; each result holds
    its estimate (``net_*`` columns) and the same after ICP (``icp_*``)."""

    name: str
    checkpoint: Path | None = None
    members: tuple[Path, ...] = ()
    """The checkpoints of an ensemble (:func:`cloudpose.infer.select_refinements` by fitness:
    under a perturbation of the points the frame's depth is not what the segment shows)."""
    limit: int | None = None
    """Evenly spaced instances of the sweep's own it runs on (None: all)."""
    ends_only: bool = False
    """Only at the identity and at each perturbation's farthest level (a costly method)."""

    def runs_at(self, p: Perturbation, level: float) -> bool:
        """Whether this method is computed at ``level`` of ``p``."""
        ident = identity_level(p)
        return not self.ends_only or level in (ident, farthest_level(p))


SECONDS_PER_INSTANCE = {"segment": 0.05, "net": 0.03, "fpfh": 0.6, "ppf": 3.5}
"""Planning figures per instance on one busy core, until a result file measured them."""
SECONDS_PER_MODEL = {"fpfh": 0.03, "ppf": 25.0}
"""Planning figures of a baseline's one-off preparation per model on one busy core: FPFH's
model features, point-pair features' detector training (its hash table of model point pairs;
422-602 s for the 21 models, logged as ``prepare_s`` of the baseline runs)."""


def _kind(method: Method) -> str:
    return "net" if method.checkpoint is not None or method.members else method.name


def _networks(paths, cache: dict) -> list:
    """(model, config) of each checkpoint, loaded once per sweep call."""
    out = []
    for p in paths:
        key = ("net", str(p))
        if key not in cache:
            cache[key] = load_checkpoint(p, "cpu")
        out.append(cache[key])
    return out


def run_method(
    method: Method,
    segs: SegmentSet,
    dataset,
    seed: int,
    cache: dict,
    icp_radius: float = PAPER_RADIUS,
) -> pd.DataFrame:
    """The instance table (:func:`cloudpose.evaluate.instance_table`, ``net_*`` and ``icp_*``
    columns) of ``method`` on ``segs``; a segment a baseline cannot register is a miss. ICP
    starts at ``icp_radius`` (:func:`cloudpose.refine.schedule_for`) for every method."""
    models = cache.setdefault("models", dataset.models())
    rows = evenly_spaced(len(segs), method.limit)
    segs = segs.subset(rows)
    if method.checkpoint is not None or method.members:  # an ensemble keeps the best fit
        nets = _networks(method.members or [method.checkpoint], cache)
        table_cfg = nets[0][1]
        icp_settings = ICPSettings.from_config(table_cfg.icp)
        if method.members:
            icp_settings = dataclasses.replace(icp_settings, select="fitness")
        ests = [estimate_poses(m, segs, c.train.n_points) for m, c in nets]
    else:
        key = ("estimator", method.name)
        if key not in cache:  # per-model state (features, PPF's hash tables) built once
            cache[key] = make(method.name, models, load_settings(method.name), seed=seed)
        est = cache[key]
        est.calls = 0  # the draws of each condition start afresh: a condition's poses do not
        # depend on which others this call computed
        R = np.tile(np.eye(3), (len(segs), 1, 1))
        t = np.zeros((len(segs), 3))
        ok = np.zeros(len(segs), dtype=bool)
        for j in np.flatnonzero(segs.valid):
            try:
                pose = est.estimate(segs.observed(j), int(segs.cls_id[j]))
            except NotRegistered:
                continue
            R[j], t[j], ok[j] = pose.R, pose.t, True
        segs.valid = np.asarray(segs.valid, dtype=bool) & ok
        ests = [Estimates(R, t)]
        icp_settings = ICPSettings()
        table_cfg = cache.setdefault("cfg", resolve("shared-0", DEFAULT_PRESET, 1))
    icp_settings = dataclasses.replace(icp_settings, **schedule_for(icp_radius))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        icp, _, pick = refine_ensemble(segs, ests, models, icp_settings)
    net = Estimates.kept(ests, pick)
    table = instance_table(
        segs, {"net": net, "icp": icp}, models, dataset.classes,
        symmetry_table=table_cfg.loss.symmetry_table,
    )  # fmt: skip
    return table.drop(columns=["net_R", "net_t", "icp_R", "icp_t"])


# --------------------------------------------------------------------------- the sweep


def level_name(level: float) -> str:
    """A level as a folder name (``0.35``, ``10``)."""
    return f"{level:g}"


def result_path(out_dir: Path, source: str, pert: str, level: float, what: str) -> Path:
    """``OUT/results/{source}/{perturbation}/{level}/{what}.csv``; ``what`` is a method's
    name or ``stats`` (the segments' statistics)."""
    return out_dir / "results" / source / pert / level_name(level) / f"{what}.csv"


def level_result_path(out_dir: Path, source: str, pert: str, level: float, what: str) -> Path:
    """:func:`result_path` of ``pert`` at ``level``, where the identity of every perturbation
    is the one result computed under ``dilate`` at 0."""
    if level == identity_level(PERTURBATIONS[pert]):
        return result_path(out_dir, source, "dilate", 0.0, what)
    return result_path(out_dir, source, pert, float(level), what)


def conditions(perts: list[Perturbation]) -> list[tuple[Perturbation, float]]:
    """Every (perturbation, level) once; the identity of all of them is computed once, under
    the first."""
    out, seen_identity = [], False
    for p in perts:
        for lv in p.levels:
            if lv == identity_level(p):
                if seen_identity:
                    continue
                seen_identity = True
                out.append((PERTURBATIONS["dilate"], 0.0))
                continue
            out.append((p, float(lv)))
    return out


@dataclass(frozen=True)
class StressPlan:
    """What a sweep will compute: per (source, method), the conditions left and instances."""

    todo: dict[tuple[str, str], int]
    instances: dict[str, int]
    seconds: float

    def describe(self, methods: list[Method]) -> str:
        lines = []
        for (src, m), n in sorted(self.todo.items()):
            meth = next(x for x in methods if x.name == m)
            k = self.instances[src] if meth.limit is None else min(meth.limit, self.instances[src])
            lines.append(f"  {src:6s} {m:12s} {n:3d} conditions left x {k} instances")
        mins = self.seconds / 60
        lines.append(f"  estimated time: {mins:.0f} min (on one core; a busy machine is slower)")
        return "\n".join(lines)


def make_plan(
    out_dir: Path,
    sources: dict[str, int],
    perts: list[Perturbation],
    methods: list[Method],
    models: dict[str, int] | None = None,
) -> StressPlan:
    """The conditions left per (source, method) and the time they should take, a baseline's
    preparation of each of the source's ``models`` (a count per source; default none,
    :data:`SECONDS_PER_MODEL`) included once where it has a condition left there."""
    todo: dict[tuple[str, str], int] = {}
    secs = 0.0
    for src, n in sources.items():
        for m in methods:
            if _kind(m) in SECONDS_PER_MODEL and any(
                m.runs_at(p, lv) and not result_path(out_dir, src, p.name, lv, m.name).is_file()
                for p, lv in conditions(perts)
            ):
                k = (models or {}).get(src, 0)
                secs += (k if m.limit is None else min(m.limit, k)) * SECONDS_PER_MODEL[_kind(m)]
        seg_needed = 0
        for p, lv in conditions(perts):
            missing = [
                m
                for m in methods
                if m.runs_at(p, lv) and not result_path(out_dir, src, p.name, lv, m.name).is_file()
            ]
            if missing or not result_path(out_dir, src, p.name, lv, "stats").is_file():
                seg_needed += 1
            for m in missing:
                todo[(src, m.name)] = todo.get((src, m.name), 0) + 1
                k = n if m.limit is None else min(m.limit, n)
                secs += k * SECONDS_PER_INSTANCE[_kind(m)]
        secs += seg_needed * n * SECONDS_PER_INSTANCE["segment"]
    return StressPlan(todo, dict(sources), secs)


def model_trees(models: dict[int, np.ndarray]) -> dict[int, cKDTree]:
    """A k-d tree of each model's points (model frame)."""
    return {c: cKDTree(m) for c, m in models.items()}


def run_sweep(
    out_dir: Path,
    cfg,
    methods: list[Method],
    *,
    sources: tuple[str, ...] = SOURCES,
    only: tuple[str, ...] = (),
    instances: int | None = None,
    synth_frames: int = 60,
    seed: int = 1,
    progress: bool = True,
    echo: Callable[[str], None] = print,
    dry_run: bool = False,
    icp_radius: float = PAPER_RADIUS,
) -> StressPlan:
    """Compute every missing (source, perturbation, level, method) result into ``out_dir``
    (module doc); prints the plan first. ``only`` names perturbations (default all).
    ``icp_radius``: ICP's first radius for every method (:func:`cloudpose.refine.schedule_for`),
    kept in ``sweep.json``; results of another radius are another folder's."""
    unknown = sorted(set(only) - set(PERTURBATIONS))
    if unknown:
        raise ValueError(f"--only {unknown}: expected some of {', '.join(PERTURBATIONS)}")
    perts = [p for n, p in PERTURBATIONS.items() if not only or n in only]
    out_dir.mkdir(parents=True, exist_ok=True)
    opened = {
        s: open_source(
            s, cfg, out_dir, instances=instances, synth_frames=synth_frames, progress=progress
        )
        for s in sources
    }
    meta = {
        "preset": cfg.preset,
        "seed": seed,
        "sources": {s: src.described for s, src in opened.items()},
        "methods": {m.name: {"checkpoint": str(m.checkpoint or ""), "limit": m.limit,
                             **({"members": [str(p) for p in m.members]} if m.members else {}),
                             **({"ends_only": True} if m.ends_only else {})}
                    for m in methods},
        "perturbations": {p.name: list(p.levels) for p in perts},
        "icp_radius": icp_radius,
    }  # fmt: skip
    meta_path = out_dir / "sweep.json"
    if meta_path.is_file():  # another call's sources, methods and perturbations stay listed
        old = json.loads(meta_path.read_text())
        check_icp_radius(out_dir, old, icp_radius)
        for key, was in (("sources", old.get("sources", {})), ("methods", old.get("methods", {}))):
            changed = [k for k, v in meta[key].items() if k in was and _same(was[k]) != _same(v)]
            if changed or old.get("seed", seed) != seed:
                raise ValueError(
                    f"{out_dir} holds results of other {key} or seed ({changed or 'seed'}: "
                    f"{[was.get(k) for k in changed] or old.get('seed')}); choose another "
                    "--results folder"
                )
        for key in ("sources", "methods", "perturbations"):
            meta[key] = {**old.get(key, {}), **meta[key]}
    atomic_write(meta_path, lambda tmp: Path(tmp).write_text(json.dumps(meta, indent=1)))
    models = {
        s: len({int(src.frames[f].frame.cls_ids[i]) for f, i in src.instances})
        for s, src in opened.items()
    }
    plan = make_plan(
        out_dir, {s: len(src.instances) for s, src in opened.items()}, perts, methods, models
    )
    echo("stress plan:\n" + plan.describe(methods))
    if dry_run:
        return plan
    n_fps, radius = cfg.data.n_fps, cfg.data.outlier_radius
    for s, src in opened.items():
        cache: dict = {}
        trees = model_trees(src.dataset.models())
        for p, lv in conditions(perts):
            stats_path = result_path(out_dir, s, p.name, lv, "stats")
            missing = [
                m
                for m in methods
                if m.runs_at(p, lv) and not result_path(out_dir, s, p.name, lv, m.name).is_file()
            ]
            if not missing and stats_path.is_file():
                continue
            t0 = time.perf_counter()
            segs, px = condition_segments(src, p, lv, seed, n_fps, radius)
            if not stats_path.is_file():
                st = segment_stats(segs, px, trees, src.dataset.models())
                st.insert(0, "frame_id", segs.frame_id)
                st.insert(1, "instance", segs.instance)
                _write_csv(stats_path, st)
            for m in missing:
                t1 = time.perf_counter()
                table = run_method(m, segs, src.dataset, seed, cache, icp_radius)
                table["seconds"] = time.perf_counter() - t1
                _write_csv(result_path(out_dir, s, p.name, lv, m.name), table)
            echo(f"  {s} {p.name}={level_name(lv)}: {', '.join(m.name for m in missing)} "
                 f"({time.perf_counter() - t0:.0f} s)")  # fmt: skip
    return plan


ICP_SELECTIONS = (
    ("starts1", {}),
    ("starts24-fitness", {"starts": 24, "select": "fitness"}),
    ("starts24-depth", {"starts": 24, "select": "depth"}),
    ("starts60-fitness", {"starts": 60, "select": "fitness"}),
    ("starts60-depth", {"starts": 60, "select": "depth"}),
)
"""The ICP settings the selection comparison runs after each network (:func:`run_icp_selection`):
the run's own (one start), and 24 / 60 starts scored by fitness alone or by the depth
(:func:`cloudpose.refine.depth_score`)."""


def run_icp_selection(
    out_dir: Path,
    cfg,
    methods: list[Method],
    *,
    sources: tuple[str, ...] = SOURCES,
    instances: int | None = None,
    synth_frames: int = 60,
    seed: int = 1,
    progress: bool = True,
    echo: Callable[[str], None] = print,
    icp_radius: float = PAPER_RADIUS,
) -> None:
    """The unperturbed segments of ``instances`` evenly spaced instances per source, each network
    of ``methods`` followed by ICP under each of :data:`ICP_SELECTIONS` (from the first radius
    ``icp_radius``); one instance table per (source, setting, network) in
    ``OUT/icp_select/{source}/{setting}/{method}.csv``, skipped where it exists."""
    meta_path = out_dir / "sweep.json"
    if meta_path.is_file():
        check_icp_radius(out_dir, json.loads(meta_path.read_text()), icp_radius)

    nets = [m for m in methods if m.checkpoint is not None]
    cache: dict = {}
    ident = PERTURBATIONS["dilate"]
    for s in sources:
        todo = [
            (name, over, m)
            for name, over in ICP_SELECTIONS
            for m in nets
            if not (out_dir / "icp_select" / s / name / f"{m.name}.csv").is_file()
        ]
        if not todo:
            continue
        src = open_source(
            s, cfg, out_dir, instances=instances, synth_frames=synth_frames, progress=progress
        )
        segs, _ = condition_segments(src, ident, 0.0, seed, cfg.data.n_fps, cfg.data.outlier_radius)
        views = [
            DepthView(src.frames[fpos].frame.depth, np.asarray(src.frames[fpos].frame.K))
            for fpos, _ in src.instances
        ]
        models = src.dataset.models()
        estimates: dict[str, tuple] = {}
        for name, over, m in todo:
            if m.name not in estimates:
                ((model, mcfg),) = _networks([m.checkpoint], cache)
                estimates[m.name] = (mcfg, estimate_poses(model, segs, mcfg.train.n_points))
            mcfg, net = estimates[m.name]
            settings = dataclasses.replace(
                ICPSettings.from_config(mcfg.icp), **over, **schedule_for(icp_radius)
            )
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                icp, stats = refine_poses(segs, net, models, settings, views=views)
            table = instance_table(
                segs, {"net": net, "icp": icp}, models, src.dataset.classes,
                symmetry_table=mcfg.loss.symmetry_table,
            ).drop(columns=["net_R", "net_t", "icp_R", "icp_t"])  # fmt: skip
            table["icp_fitness"] = stats.fitness
            table["seconds"] = time.perf_counter() - t0
            _write_csv(out_dir / "icp_select" / s / name / f"{m.name}.csv", table)
            echo(f"  icp selection {s} {name} {m.name} ({table.seconds.iloc[0]:.0f} s)")


def collect_icp_selection(out_dir: Path) -> pd.DataFrame:
    """One row per (source, setting, network) of :func:`run_icp_selection`'s results: the
    summary after ICP (:data:`SUMMARY_COLUMNS`) and the instance count."""
    rows = []
    base = out_dir / "icp_select"
    for path in sorted(base.glob("*/*/*.csv")):
        table = pd.read_csv(path)
        rows.append(
            {
                "source": path.parent.parent.name,
                "setting": path.parent.name,
                "method": path.stem,
                **summary_of(table, "icp"),
                "seconds_per_instance": float(table["seconds"].iloc[0]) / max(len(table), 1),
            }
        )
    return pd.DataFrame(rows)


def check_icp_radius(out_dir: Path, meta: dict, icp_radius: float) -> None:
    """``ValueError`` unless the results in ``out_dir`` (its ``sweep.json``, ``meta``; one
    written before the radius was recorded is the paper's) were refined from ``icp_radius``."""
    was = meta.get("icp_radius", PAPER_RADIUS)
    if was != icp_radius:
        raise ValueError(
            f"{out_dir} holds results refined by ICP from a first radius of {was} m, not "
            f"{icp_radius}; choose another --results folder"
        )


def _same(entry):
    """What of a sweep.json entry decides its result files (not where a method runs)."""
    return (
        {k: v for k, v in entry.items() if k != "ends_only"} if isinstance(entry, dict) else entry
    )


def _write_csv(path: Path, df: pd.DataFrame) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: df.to_csv(tmp, index=False), suffix=".csv")


# --------------------------------------------------------------------------- results


SUMMARY_COLUMNS = ("ads_auc", "rot_sym_lt_10deg", "trans_lt_1cm", "trans_median_mm")
"""What each (source, perturbation, level, method, stage) is summed up by: ADS AUC, rotation
< 10 deg modulo symmetry, translation < 1 cm (fractions), median translation error (mm)."""


def summary_of(table: pd.DataFrame, stage: str) -> dict[str, float]:
    """:data:`SUMMARY_COLUMNS` of one method's result table at ``stage`` (``net``: its own
    estimate, ``icp``: after ICP), pooled over its instances."""
    cols = ("ad", "ads", "rot_err_deg", "rot_sym_err_deg", "trans_err")
    sub = table.rename(columns={f"{stage}_{k}": k for k in cols})
    pooled = summarize(sub, by_class=False)["pooled"]
    return {
        "ads_auc": pooled["ads_auc"],
        "rot_sym_lt_10deg": pooled["rot_sym_lt_10deg"],
        "trans_lt_1cm": pooled["trans_lt_1cm"],
        "trans_median_mm": 1000 * float(np.median(sub["trans_err"])),
        "count": float(len(sub)),
    }


def _learned(method: dict) -> bool:
    """Whether a method of ``sweep.json`` is a network (a checkpoint) or an ensemble of them
    (members), not a registration."""
    return bool(method["checkpoint"] or method.get("members"))


def collect(out_dir: Path) -> pd.DataFrame:
    """One row per (source, perturbation, level, method, stage) found under ``out_dir``:
    :data:`SUMMARY_COLUMNS` and the instance count; the identity (computed once) is repeated
    under every perturbation. Stage ``net`` is the method's own estimate, ``icp`` after ICP.
    Method ``NET@BASELINE``: network (or ensemble) NET on the instances the baseline ran on
    (its subsample), for paired comparisons."""
    meta = json.loads((out_dir / "sweep.json").read_text())
    learned = [m for m, v in meta["methods"].items() if _learned(v)]  # sweep order: stable rows
    rows = []
    for src in meta["sources"]:
        for pname, levels in meta["perturbations"].items():
            for lv in levels:
                tables = {}
                for m in meta["methods"]:
                    path = level_result_path(out_dir, src, pname, lv, m)
                    if path.is_file():
                        tables[m] = pd.read_csv(path)
                for m in learned:  # each network (or ensemble) on each baseline's rows
                    for b in meta["methods"]:
                        if b not in learned:
                            if m in tables and b in tables:
                                keys = tables[b][["frame_id", "instance"]]
                                tables[f"{m}@{b}"] = tables[m].merge(keys)
                for m, table in tables.items():
                    for stage in ("net", "icp"):
                        rows.append(
                            {
                                "source": src,
                                "perturbation": pname,
                                "level": float(lv),
                                "method": m,
                                "stage": stage,
                                **summary_of(table, stage),
                                "seconds_per_instance": float(table["seconds"].iloc[0])
                                / max(len(table), 1),
                            }
                        )
    return pd.DataFrame(rows)


def collect_stats(out_dir: Path) -> pd.DataFrame:
    """The segments' statistics (:data:`STATISTICS`) per (source, perturbation, level): the mean
    of the share-type ones (``off_model``, ``no_depth``, ``boundary``), the median of the
    others."""
    meta = json.loads((out_dir / "sweep.json").read_text())
    rows = []
    for src in meta["sources"]:
        for pname, levels in meta["perturbations"].items():
            for lv in levels:
                path = level_result_path(out_dir, src, pname, lv, "stats")
                if not path.is_file():
                    continue
                st = pd.read_csv(path)
                row = {"source": src, "perturbation": pname, "level": float(lv)}
                for k in STATISTICS:
                    if k not in st:  # a statistic added after this level was measured
                        row[k] = np.nan
                        continue
                    v = st[k].to_numpy(dtype=float)
                    v = v[np.isfinite(v)]
                    share = k in ("off_model", "no_depth", "boundary")
                    row[k] = float(v.mean() if share else np.median(v)) if len(v) else np.nan
                rows.append(row)
    return pd.DataFrame(rows)


def real_level(p: Perturbation, stats: pd.DataFrame) -> tuple[float, str]:
    """Where the real frames sit on ``p``'s axis, and how it was found, in words.

    The real segments' statistic ``p.stat`` (unperturbed) against the synthetic ones' at each
    level of ``p``, linearly interpolated; below the synthetic identity -> the identity (real
    frames show no more of it than synthetic ones); beyond the last level -> NaN. ``count``:
    the ratio of the medians; ``occlusion``: the extra share hidden,
    1 - (1 - O_real) / (1 - O_synth), of the median occlusion factors. A statistic that moves
    by less than a fifth of its identity value over the whole range places nothing (NaN).
    """
    ident = identity_level(p)
    real = stats[(stats.source == "real") & (stats.perturbation == p.name) & (stats.level == ident)]
    syn = stats[(stats.source == "synth") & (stats.perturbation == p.name)].sort_values("level")
    if real.empty or syn.empty:
        return np.nan, "needs both sources"
    r = float(real[p.stat].iloc[0])
    s0 = syn[syn.level == ident][p.stat]
    if not np.isfinite(r) or s0.empty or not np.isfinite(float(s0.iloc[0])):
        return np.nan, "statistic unknown"
    s0 = float(s0.iloc[0])
    if p.stat == "count":
        return r / s0, f"median points: real {r:.0f}, synthetic {s0:.0f}"
    if p.stat == "occlusion":
        extra = 1 - (1 - r) / (1 - s0) if s0 < 1 else np.nan
        return max(extra, 0.0), f"median occlusion factor: real {r:.2f}, synthetic {s0:.2f}"
    lv = syn.level.to_numpy(dtype=float)
    sv = syn[p.stat].to_numpy(dtype=float)
    order = np.argsort(lv)
    lv, sv = lv[order], sv[order]
    words = f"{STATISTICS[p.stat]}: real {r:.3g}, synthetic {s0:.3g} at level {ident:g}"
    ok = np.isfinite(sv)
    lv, sv = lv[ok], sv[ok]
    if len(sv) > 1 and np.ptp(sv) < 0.2 * max(abs(s0), 1e-9):
        return np.nan, words + " (the statistic does not move with this perturbation: not placed)"
    increasing = len(sv) < 2 or sv[1] >= sv[0]  # the direction of the first step
    if (r <= s0) if increasing else (r >= s0):
        return ident, words + " (real frames show no more of it)"
    for a, b, sa, sb in zip(lv[:-1], lv[1:], sv[:-1], sv[1:], strict=True):
        if min(sa, sb) <= r <= max(sa, sb) and sa != sb:
            return float(a + (r - sa) * (b - a) / (sb - sa)), words
    return np.nan, words + f" (beyond level {lv[-1]:g})"


# --------------------------------------------------------------------------- packed results

RESULT_PARTS = ("sweep.json", "results", "icp_select")
"""What a sweep's report is rendered from (:func:`pack_results` keeps these; the synthetic
frames' cache under ``synth/`` is rebuilt from the preset)."""


def pack_results(run_dir: Path, archive: Path) -> int:
    """The sweep's result files (:data:`RESULT_PARTS`) in ``run_dir`` into the ``.tar.xz``
    ``archive``, written atomically and byte-identical for identical files (sorted members, no
    times or owners); ``--results`` reads it back (:func:`results_folder`). Returns the number
    of files; ``FileNotFoundError`` without a ``sweep.json``."""
    import tarfile

    run_dir, archive = Path(run_dir), Path(archive)
    if not (run_dir / "sweep.json").is_file():
        raise FileNotFoundError(f"{run_dir}: no sweep.json (not the results of `cloudpose stress`)")
    files = sorted(
        f
        for part in RESULT_PARTS
        for f in ([run_dir / part] if part.endswith(".json") else (run_dir / part).rglob("*"))
        if f.is_file()
    )

    def plain(info: tarfile.TarInfo) -> tarfile.TarInfo:
        info.mtime, info.uid, info.gid, info.uname, info.gname = 0, 0, 0, "", ""
        return info

    def write(tmp: Path) -> None:
        with tarfile.open(tmp, "w:xz", preset=9) as tar:
            for f in files:
                tar.add(f, arcname=f.relative_to(run_dir).as_posix(), filter=plain)

    atomic_write(archive, write, suffix=".tar.xz")
    return len(files)


@contextlib.contextmanager
def results_folder(path: Path) -> Iterator[Path]:
    """A sweep's results as a folder: ``path`` itself, or an archive of :func:`pack_results`
    unpacked into a temporary folder removed afterwards. ``ValueError`` naming the archive and
    the member when one lies outside :data:`RESULT_PARTS` or outside the folder (nothing is
    unpacked then), or when the archive cannot be read."""
    import lzma
    import tarfile
    import tempfile

    path = Path(path)
    if path.is_dir():
        yield path
        return
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no stress results (a folder or a packed .tar.xz)")
    with tempfile.TemporaryDirectory(prefix="cloudpose-stress-") as tmp:
        try:
            with tarfile.open(path, "r:*") as tar:
                members = checked_members(
                    path,
                    tar,
                    tmp,
                    lambda name: name.split("/")[0] in RESULT_PARTS,
                    f"a stress result (one of {', '.join(RESULT_PARTS)})",
                )
                tar.extractall(tmp, members=members, filter="data")
        except (tarfile.TarError, EOFError, lzma.LZMAError) as exc:
            raise ValueError(
                f"{path}: not a readable archive of stress results ({type(exc).__name__}: "
                f"{exc}); pack it again (cloudpose stress --report-only --pack)"
            ) from exc
        yield Path(tmp)
