"""Perturbations of a frame's segments in controlled steps, and the segments they make (the
conditions of ``cloudpose stress``, :mod:`cloudpose.studies.stress`).

A *perturbation* acts either on the frame's pixels before segmentation (the instance's mask
dilated, eroded or shifted by k pixels, the depth dropped in blobs or smoothed over the mask)
or on the back-projected points of the segment before farthest point sampling (depth noise and
a bias growing with distance along each pixel's ray, a cut plane, the number of points, one
side of the visible part missing). The segment is then made as
:func:`cloudpose.data.segments.extract_segments` makes it (the 0.2 m outlier filter, FPS of
``n_fps`` points).

Level 0 of every perturbation is the identity: the unperturbed segments, shared by all of them.
Every random choice (blob centres, plane directions, the FPS start) comes from a stream keyed by
(seed, source, frame, instance) and not by the level, so the levels of one perturbation differ
by the level only (common random numbers) and a run is deterministic given its seed.

Each perturbation names a statistic of a segment that it moves (share of points more than 1 cm
off the posed model for mask dilation, share of mask pixels without depth for missing depth,
...; :data:`STATISTICS`, :func:`segment_stats`): where the real frames sit on its scale.

The sources (:func:`open_source`): the 61 packaged real development frames and the default
preset's synthetic test frames.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import ndimage
from scipy.spatial import cKDTree

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
from cloudpose.studies.baseline_runs import subsample

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
