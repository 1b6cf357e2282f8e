"""Synthetic frames against real ones: the side-by-side table.

The frame statistics, the per-object fidelity and a refit of the missing-depth model
(:mod:`cloudpose.data.synth.sensor_fit`) are all measured on the same real frames and go into
one report.

``cloudpose synth --compare-real DIR`` (:func:`compare_real`) measures the same statistics on
real frames and on synthetic frames of each generator version:

- per frame set: depth noise (robust std of depth minus the rendering at the ground-truth pose,
  inside masks), the share of mask pixels without depth (all, on the boundary ring, inside),
  depth points per segment, occlusion factors;
- per object of the annotated real frames: the mask IoU and median |dz| of the rendering at
  the ground-truth pose (the surfaces of each version), and the missing share of the real frame
  beside the one the version's sensor model gives on that rendering.

Real frames are read from YCB-Video roots (every ``data/SEQ/FRAME-meta.mat``; annotated) and
from loose folders holding ``depth.png`` and ``label.png`` (unannotated, YCB-Video intrinsics).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy import ndimage

from cloudpose.config import check_synth_version
from cloudpose.conventions import YCB_INTRINSICS, packaged_classes
from cloudpose.data.synth.frames import _generator, generate_frame
from cloudpose.data.synth.render import Renderer
from cloudpose.data.synth.sensor import (
    REAL_DROPOUT,
    add_sensor_noise,
    add_sensor_noise_v2,
    edge_distance,
)
from cloudpose.data.synth.sensor_fit import fit_dropout, object_pixels
from cloudpose.data.ycb import Frame, YCBVideo, read_frame

__all__ = [
    "FrameSetStats",
    "ObjectFidelity",
    "compare_real",
    "frame_set_stats",
    "object_fidelity",
    "read_real_frames",
]


def read_real_frames(paths: Sequence[str | Path]) -> list[Frame]:
    """Real frames from YCB-Video roots and loose ``depth.png`` + ``label.png`` folders.

    Args:
        paths: each a YCB-Video-layout root (all frames under ``data/`` with a meta file) or a
            folder with ``depth.png`` and ``label.png`` (read with the YCB-Video intrinsics and
            depth factor; no poses).

    Returns:
        The frames, in the order given (a root's frames sorted by id).

    Raises:
        FileNotFoundError: a path that is neither.
    """
    frames = []
    for p in map(Path, paths):
        if (p / "depth.png").is_file() and (p / "label.png").is_file():
            frames.append(
                read_frame(p / "depth.png", p / "label.png", K=YCB_INTRINSICS, frame_id=p.name)
            )
            continue
        metas = sorted((p / "data").glob("*/*-meta.mat"))
        if not metas:
            raise FileNotFoundError(
                f"{p}: no real frames (expected a YCB-Video root with data/SEQ/FRAME-meta.mat, "
                "or a folder with depth.png and label.png)"
            )
        ds = YCBVideo(p)
        for m in metas:
            frames.append(ds.frame(f"{m.parent.name}/{m.name[: -len('-meta.mat')]}"))
    return frames


# --------------------------------------------------------------------------- statistics


def _robust_std(x: np.ndarray) -> float:
    """1.4826 x the median absolute deviation (the std of a Gaussian, blind to outliers)."""
    if len(x) == 0:
        return float("nan")
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def _neighbour_missing(depth: np.ndarray, label: np.ndarray) -> tuple[int, int]:
    """(pairs of 4-neighbours in one object mask that both miss depth, pairs where the first
    misses): their ratio is the chance a pixel next to a missing one misses too."""
    m = depth == 0
    both = hits = 0
    for a, b, la, lb in (
        (m[:, 1:], m[:, :-1], label[:, 1:], label[:, :-1]),
        (m[1:], m[:-1], label[1:], label[:-1]),
    ):
        same = (la == lb) & (la > 0)
        hits += int((a & b & same).sum())
        both += int((b & same).sum())
    return hits, both


@dataclass
class FrameSetStats:
    """Statistics of a set of frames, as :func:`frame_set_stats` measures them.

    Attributes:
        frames, instances: counts (instances: annotated, or label ids without annotation).
        noise_std: robust std of depth minus the rendering at the ground-truth pose on object
            pixels where both have depth, metres (NaN without poses).
        missing: share of mask pixels without depth.
        missing_edge: the same on pixels at most 2 px from another label.
        missing_inside: the same on pixels more than 8 px from another label.
        missing_next: chance that a mask pixel next to a missing one (same mask) misses too.
        points: median depth points per instance mask.
        occlusion: mean occlusion factor (NaN without poses).
        occluded_half: share of instances with occlusion factor > 0.5 (NaN without poses).
        stacked: share of instances resting on another object (NaN when unknown).
    """

    frames: int
    instances: int
    noise_std: float
    missing: float
    missing_edge: float
    missing_inside: float
    missing_next: float
    points: float
    occlusion: float
    occluded_half: float
    stacked: float


def frame_set_stats(
    frames: Sequence[Frame],
    rendered: Sequence[np.ndarray | None],
    alone: Sequence[np.ndarray | None],
    stacked: float = float("nan"),
) -> FrameSetStats:
    """Measure a set of frames.

    Args:
        frames: the frames.
        rendered: per frame the (H, W) depth of its objects rendered at their ground-truth
            poses, metres, or None (no poses).
        alone: per frame (N,) pixels of each annotated instance rendered alone, or None.
        stacked: share of stacked instances, when the caller knows it.
    """
    dz, occ, points = [], [], []
    n_obj = n_miss = n_edge = m_edge = n_in = m_in = hits = pairs = instances = 0
    for f, ren, al in zip(frames, rendered, alone, strict=True):
        obj = f.label > 0
        miss = f.depth == 0
        d = edge_distance(f.label)
        n_obj += int(obj.sum())
        n_miss += int((obj & miss).sum())
        n_edge += int((obj & (d <= 2)).sum())
        m_edge += int((obj & (d <= 2) & miss).sum())
        n_in += int((obj & (d > 8)).sum())
        m_in += int((obj & (d > 8) & miss).sum())
        h, p = _neighbour_missing(f.depth, f.label)
        hits, pairs = hits + h, pairs + p
        ids = f.cls_ids
        instances += len(ids)
        for i, c in enumerate(ids):
            mask = f.label == c
            points.append(int((mask & ~miss).sum()))
            if al is not None and al[i] > 0:
                occ.append(1.0 - mask.sum() / al[i])
        if ren is not None:
            both = obj & ~miss & (ren > 0)
            dz.append((f.depth[both] - ren[both]).astype(np.float64))
    occ_a = np.array(occ)
    return FrameSetStats(
        frames=len(frames),
        instances=instances,
        noise_std=_robust_std(np.concatenate(dz)) if dz else float("nan"),
        missing=n_miss / max(n_obj, 1),
        missing_edge=m_edge / max(n_edge, 1),
        missing_inside=m_in / max(n_in, 1),
        missing_next=hits / max(pairs, 1),
        points=float(np.median(points)) if points else float("nan"),
        occlusion=float(occ_a.mean()) if len(occ_a) else float("nan"),
        occluded_half=float((occ_a > 0.5).mean()) if len(occ_a) else float("nan"),
        stacked=stacked,
    )


class ObjectFidelity(NamedTuple):
    """One annotated real object against its rendering at the ground-truth pose.

    Attributes:
        frame_id, name: where and what.
        iou: mask IoU of the real label and the rendered label.
        dz: median |real depth - rendered depth| on pixels both label as it, metres.
        missing_real: share of the real mask without depth.
        missing_synth: the same after the version's sensor model is applied to the rendering
            (over the real frame's background depth).
    """

    frame_id: str
    name: str
    iou: float
    dz: float
    missing_real: float
    missing_synth: float


def _background(f: Frame) -> np.ndarray:
    """The real frame's depth off the objects, gaps filled from the nearest reading."""
    have = (f.label == 0) & (f.depth > 0)
    _, (iy, ix) = ndimage.distance_transform_edt(~have, return_indices=True)
    return f.depth[iy, ix].astype(np.float64)


def object_fidelity(
    frames: Sequence[Frame], renderer, version: int, names: Sequence[str], seed: int = 0
) -> list[ObjectFidelity]:
    """Per annotated object: the rendering at its ground-truth pose against the real frame.

    Args:
        frames: real frames (those without poses are skipped).
        renderer: renderer with the version's surfaces.
        version: generator version whose sensor model gives ``missing_synth``.
        names: class names, index = class id - 1.
        seed: seed of the sensor noise.
    """
    rows = []
    for f in frames:
        if f.poses is None:
            continue
        r = renderer.render(f.K, f.depth.shape, f.cls_ids, f.poses)
        clean = np.where(r.label > 0, r.depth.astype(np.float64), _background(f))
        rng = np.random.default_rng(seed)
        if version == 1:
            sim = add_sensor_noise(clean, rng)
        else:
            sim = add_sensor_noise_v2(clean, r.label, f.K, rng)
        for c in f.cls_ids:
            a, b = f.label == c, r.label == c
            both = a & b & (f.depth > 0)
            dz = np.abs(f.depth[both].astype(np.float64) - r.depth[both])
            rows.append(
                ObjectFidelity(
                    f.frame_id,
                    names[c - 1],
                    float((a & b).sum() / max((a | b).sum(), 1)),
                    float(np.median(dz)) if len(dz) else float("nan"),
                    float((f.depth[a] == 0).mean()),
                    float((sim[b] == 0).mean()) if b.any() else float("nan"),
                )
            )
    return rows


# --------------------------------------------------------------------------- the report


def _synthetic_frames(version: int, n: int, seed: int) -> tuple[list[Frame], list, list, float]:
    gen = _generator(version)
    frames, rendered, alone, stacked, total = [], [], [], 0, 0
    for i in range(n):
        s = generate_frame("test", i, seed, generator=gen, version=version)
        frames.append(Frame(s.frame_id, s.depth, s.label, YCB_INTRINSICS, s.cls_ids, s.poses, None))
        rendered.append(np.where(s.label > 0, s.clean_depth, 0.0))
        alone.append(s.alone_pixels)
        if s.scene.support is not None:
            stacked += int((s.scene.support >= 0).sum())
        total += len(s.cls_ids)
    return frames, rendered, alone, stacked / max(total, 1)


def _pct(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{100 * x:.1f}%"


def _num(x: float, scale: float = 1.0, digits: int = 1) -> str:
    return "-" if not np.isfinite(x) else f"{scale * x:.{digits}f}"


def compare_real(
    real: Sequence[str | Path],
    versions: Sequence[int] = (1, 2),
    frames: int = 20,
    seed: int = 0,
    command: str = "",
) -> str:
    """The side-by-side report of real frames and synthetic frames of each version (Markdown).

    Args:
        real: YCB-Video roots and loose frame folders (:func:`read_real_frames`).
        versions: generator versions to compare.
        frames: synthetic test frames per version (rendered in memory, ~3 s each).
        seed: synthetic scene seed.
        command: the command line that made the report (written at its top).
    """
    versions = [check_synth_version(v) for v in versions]
    names = packaged_classes()
    real_frames = read_real_frames(real)
    renderers = {v: Renderer(surface_version=v) for v in versions}
    newest = renderers[max(versions)]
    rendered, alone = [], []
    for f in real_frames:
        if f.poses is None:
            rendered.append(None)
            alone.append(None)
            continue
        r = newest.render(f.K, f.depth.shape, f.cls_ids, f.poses)
        rendered.append(np.where(r.label == f.label, r.depth, 0.0))
        alone.append(newest.alone_pixels(f.K, f.depth.shape, f.cls_ids, f.poses))
    cols = {"real": frame_set_stats(real_frames, rendered, alone)}
    for v in versions:
        cols[f"synthetic v{v}"] = frame_set_stats(*_synthetic_frames(v, frames, seed))
    annotated = sum(f.poses is not None for f in real_frames)

    out = ["# Synthetic frames against real ones", ""]
    if command:
        out += ["Made by", "", f"    {command}", ""]
    out += [
        f"Real: {len(real_frames)} frames ({annotated} annotated) from "
        + ", ".join(f"`{p}`" for p in real)
        + f". Synthetic: test frames 0-{frames - 1} of seed {seed} of each generator version, "
        "rendered in memory. Noise and occlusion need poses: on the real side they come from "
        f"the annotated frames only (rendered with version-{max(versions)} surfaces).",
        "",
        "| | " + " | ".join(cols) + " |",
        "|---|" + "---|" * len(cols),
    ]
    rows = [
        ("frames / instances", lambda s: f"{s.frames} / {s.instances}"),
        ("depth noise, robust std (mm)", lambda s: _num(s.noise_std, 1000.0, 2)),
        ("missing depth in masks", lambda s: _pct(s.missing)),
        ("... <= 2 px from another label", lambda s: _pct(s.missing_edge)),
        ("... > 8 px from another label", lambda s: _pct(s.missing_inside)),
        ("P(missing / 4-neighbour missing)", lambda s: _num(s.missing_next, 1.0, 2)),
        ("depth points per segment (median)", lambda s: _num(s.points, 1.0, 0)),
        ("occlusion factor (mean)", lambda s: _num(s.occlusion, 1.0, 2)),
        ("instances with occlusion > 0.5", lambda s: _pct(s.occluded_half)),
        ("instances resting on another", lambda s: _pct(s.stacked)),
    ]
    for title, fmt in rows:
        out.append(f"| {title} | " + " | ".join(fmt(s) for s in cols.values()) + " |")

    fid = {v: object_fidelity(real_frames, renderers[v], v, names, seed) for v in versions}
    if annotated:
        out += [
            "",
            "## Annotated real objects, rendered at their ground-truth poses",
            "",
            "IoU of the real and rendered masks, median |dz| on pixels both label as the object, "
            "and the mask's missing depth: real, and the version's sensor model applied to the "
            "rendering (over the real background).",
            "",
            "| frame | object | "
            + " | ".join(f"IoU v{v}" for v in versions)
            + " | "
            + " | ".join(f"median dz v{v} (mm)" for v in versions)
            + " | missing real | "
            + " | ".join(f"missing v{v}" for v in versions)
            + " |",
            "|---|---|" + "---|" * (3 * len(versions) + 1),
        ]
        for i, row in enumerate(fid[versions[0]]):
            per = [fid[v][i] for v in versions]
            out.append(
                f"| {row.frame_id} | {row.name} | "
                + " | ".join(f"{p.iou:.4f}" for p in per)
                + " | "
                + " | ".join(_num(p.dz, 1000.0, 2) for p in per)
                + f" | {_pct(row.missing_real)} | "
                + " | ".join(_pct(p.missing_synth) for p in per)
                + " |"
            )

    fitted = fit_dropout(object_pixels(real_frames, renderers[max(versions)]))
    out += [
        "",
        "## Missing-depth model (version 2), refitted on these real frames",
        "",
        "| parameter | shipped (REAL_DROPOUT) | fitted here |",
        "|---|---|---|",
    ]
    for name in ("edge_rate", "edge_scale", "graze_cos", "graze_width", "default_rate"):
        out.append(f"| {name} | {getattr(REAL_DROPOUT, name)} | {getattr(fitted, name)} |")
    for c, r in fitted.class_rates:
        out.append(f"| rate of {names[c - 1]} | {REAL_DROPOUT.class_rate(c)} | {r} |")
    return "\n".join(out) + "\n"
