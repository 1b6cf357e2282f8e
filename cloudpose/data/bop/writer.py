"""Synthetic or YCB-Video frames written as a BOP ``ycbv`` root (:func:`export_bop`), with its
``models_info.json`` (:func:`models_info`)."""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from PIL import Image
from tqdm import tqdm

from cloudpose.data.bop.format import (
    DEPTH_SCALE,
    MIN_VISIB_FRACT,
    SPLIT_DIRS,
    TARGETS_FILE,
    bop_ids,
    model_origin,
    write_ply,
)
from cloudpose.data.segment_set import SegmentSet, check_units, unit_stats
from cloudpose.data.segments import ALONE_SURFACE_VERSION, SegmentWarning, extract_segments
from cloudpose.data.synth.render import Renderer
from cloudpose.data.ycb import YCBVideo
from cloudpose.files import atomic_text, atomic_write
from cloudpose.geometry.symmetry import flip_rotation, symmetries_for

if TYPE_CHECKING:  # Open3D is imported where a frame is rendered, not to read this module
    from cloudpose.data.synth.render import Renderer


@dataclass(frozen=True)
class ExportSummary:
    """What :func:`export_bop` wrote: frames, instances, BOP19 targets, under ``root``."""

    root: Path
    frames: int
    instances: int
    targets: int


def _bbox(mask: np.ndarray) -> list[int]:
    """BOP's (x, y, width, height) of a mask's pixels; (-1, -1, 0, 0) when empty."""
    v, u = np.nonzero(mask)
    if not len(v):
        return [-1, -1, 0, 0]
    return [int(u.min()), int(v.min()), int(u.max() - u.min() + 1), int(v.max() - v.min() + 1)]


def _png(path: Path, array: np.ndarray, mode: str | None = None) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    img = Image.fromarray(array, mode=mode) if mode else Image.fromarray(array)
    atomic_write(path, lambda p: img.save(p, format="PNG"))


EXPORT_SYMMETRY_TABLE = 2
"""The symmetry table the exported ``models_info.json`` carries (``cloudpose.geometry.symmetry``)."""


def models_info(models: dict[int, np.ndarray], class_names: list[str]) -> dict:
    """BOP ``models_info.json`` of toolbox model points in the BOP frame (module doc): diameter
    and bounding box in millimetres, and the package's symmetry table
    (:data:`EXPORT_SYMMETRY_TABLE`) as BOP writes symmetries: a rotation ``S`` about the table's
    centre ``c`` is, in the BOP frame centred on the bounding box ``o``, the 4x4 transform with
    rotation ``S`` and translation ``1000 (I - S)(c - o)`` mm; a continuous axis passes through
    the offset ``1000 (c - o)`` mm."""
    from scipy.spatial.distance import pdist

    syms = symmetries_for(list(class_names), EXPORT_SYMMETRY_TABLE)
    info = {}
    for c, pts in sorted(models.items()):
        V = (pts - model_origin(pts)) * 1000.0
        lo, hi = V.min(axis=0), V.max(axis=0)
        entry = {"diameter": float(pdist(V).max()) if len(V) > 1 else 0.0}
        entry.update({f"min_{a}": float(lo[i]) for i, a in enumerate("xyz")})
        entry.update({f"size_{a}": float(hi[i] - lo[i]) for i, a in enumerate("xyz")})
        s = syms[c - 1]
        rots = list(s.discrete[1:])
        shift = (s.centre - model_origin(pts)) * 1000.0  # (3,) the centre in the BOP frame, mm
        if s.axis is not None:
            entry["symmetries_continuous"] = [
                {"axis": s.axis.tolist(), "offset": np.round(shift, 6).tolist()}
            ]
            if s.flip:
                rots.append(flip_rotation(s.axis))
        if rots:
            entry["symmetries_discrete"] = [
                np.round(
                    np.block([[R, ((np.eye(3) - R) @ shift)[:, None]], [np.zeros((1, 3)), 1.0]]),
                    12,
                )
                .ravel()
                .tolist()
                for R in rots
            ]
        info[str(c)] = entry
    return info


EXPORT_UNIT_FRAMES = 3
"""Frames per scene (evenly spaced) whose segments the export's depth unit check measures."""


def check_export_units(src, frame_ids: list[str], models: dict[int, np.ndarray]) -> None:
    """The depth unit check (:func:`cloudpose.data.segment_set.check_units`) of the frames an
    export is about to write, on :data:`EXPORT_UNIT_FRAMES` frames of each scene, before any file
    is written: depth in another unit than the source says stops the export in one line."""
    by_scene: dict[str, list[str]] = {}
    for fid in frame_ids:
        by_scene.setdefault(fid.split("/", 1)[0], []).append(fid)
    segments = []
    for fids in by_scene.values():
        pick = np.unique(np.linspace(0, len(fids) - 1, EXPORT_UNIT_FRAMES).round().astype(int))
        for i in pick:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", SegmentWarning)
                segments += extract_segments(
                    src.frame(fids[i]), n_fps=256, rng=np.random.default_rng(0), with_gt=False
                )
    check_units(src, unit_stats(SegmentSet.from_segments(segments, 256), models))


def _export_splits(src: YCBVideo, frames: str, train: bool) -> list[tuple[str, list[str]]]:
    """``(split, frame ids)`` to export: ``frames`` as ``test``, the training frames as
    ``train`` when ``train``; a frame id that is not numbers raises (:func:`bop_ids`)."""
    splits = [("test", src.image_set(frames))]
    if train:
        splits.append(("train", src.image_set("train")))
    for _, ids in splits:
        for fid in ids:
            bop_ids(fid)
    return splits


def _write_models(out: Path, models: dict[int, np.ndarray], renderer: Renderer, classes) -> None:
    """``models/``: each model's surface as a PLY (millimetres, BOP frame) and
    ``models_info.json``."""
    (out / "models").mkdir(parents=True, exist_ok=True)
    for c, pts in models.items():
        tri = np.asarray(renderer.mesh(c).triangles)
        write_ply(out / "models" / f"obj_{c:06d}.ply", (pts - model_origin(pts)) * 1000.0, tri)
    atomic_text(
        out / "models" / "models_info.json",
        json.dumps(models_info(models, classes), indent=1) + "\n",
    )


class _FrameAnnotations(NamedTuple):
    """One exported frame's entries of its scene's ``scene_gt``, ``scene_camera`` and
    ``scene_gt_info``: one gt and one info per object, in the frame's order."""

    gt: list[dict]
    camera: dict
    info: list[dict]


def _write_frame(
    src: YCBVideo,
    fid: str,
    scene_dir: Path,
    renderer: Renderer,
    origins: dict[int, np.ndarray],
) -> _FrameAnnotations:
    """Write frame ``fid``'s depth, rgb (where the source has colour) and per-object ``mask``
    (rendered alone) and ``mask_visib`` (its label pixels) under ``scene_dir``; its
    annotations."""
    im = bop_ids(fid)[1]
    has_color = src.frame_paths(fid)["color"].is_file()
    f = src.frame(fid, with_color=has_color)
    shape = f.depth.shape
    alone = src.alone_pixels(fid)
    if alone is None:
        alone = renderer.alone_pixels(f.K, shape, f.cls_ids, f.poses)
    _png(
        scene_dir / "depth" / f"{im:06d}.png",
        np.round(f.depth.astype(np.float64) * 1000.0 / DEPTH_SCALE).astype(np.uint16),
    )
    if f.color is not None:
        _png(scene_dir / "rgb" / f"{im:06d}.png", f.color, "RGB")
    gt, info = [], []
    for g, (c, P) in enumerate(zip(f.cls_ids, f.poses, strict=True)):
        R, t = P[:, :3], P[:, 3]
        full = renderer.render(f.K, shape, [int(c)], P[None]).label > 0
        visib = f.label == c
        _png(scene_dir / "mask" / f"{im:06d}_{g:06d}.png", full.astype(np.uint8) * 255, "L")
        _png(scene_dir / "mask_visib" / f"{im:06d}_{g:06d}.png", visib.astype(np.uint8) * 255, "L")
        t_mm = 1000.0 * (t + R @ origins[int(c)])
        gt.append({"cam_R_m2c": R.ravel().tolist(), "cam_t_m2c": t_mm.tolist(), "obj_id": int(c)})
        n_all, n_vis = int(alone[g]), int(visib.sum())
        # a real label can exceed the rendered silhouette by a few pixels
        fract = min(n_vis / n_all, 1.0) if n_all > 0 else 0.0
        info.append(
            {
                "bbox_obj": _bbox(full),
                "bbox_visib": _bbox(visib),
                "px_count_all": n_all,
                "px_count_valid": int((full & (f.depth > 0)).sum()),
                "px_count_visib": n_vis,
                "visib_fract": fract,
            }
        )
    camera = {"cam_K": f.K.ravel().tolist(), "depth_scale": DEPTH_SCALE}
    return _FrameAnnotations(gt, camera, info)


def export_bop(
    source: str | Path,
    out: str | Path,
    frames: str = "keyframe",
    train: bool = False,
    progress: bool = True,
) -> ExportSummary:
    """Write a YCB-Video-layout dataset (real or synthetic) in the BOP ``ycbv`` layout.

    ``frames`` of the source go to ``test/`` (their objects at least :data:`MIN_VISIB_FRACT`
    visible are the BOP19 targets), its training frames (``image_sets/train.txt``) to
    ``train_real/`` when ``train``. Per frame: depth (uint16, ``depth_scale`` 0.1 mm),
    ``mask_visib`` (the label image's pixels of each object), ``mask`` (the object rendered
    alone), ``rgb`` when the source has colour, and the scene's ``scene_gt``/``scene_camera``/
    ``scene_gt_info`` (``px_count_all`` = the alone pixels the segments' occlusion factor
    uses: the synthetic meta's, else rendered); ``models/`` holds each model's surface as a PLY
    (millimetres, BOP frame) and ``models_info.json``. :class:`~cloudpose.data.bop.reader.BOPYcbv` reads it back into the
    same frames, hence the same segments.

    Args:
        source: YCB-Video-layout root.
        out: new folder (it must not exist, or be empty).
        frames: frame list of the source: "keyframe", "all" or an image set name.
        train: also write the training frames.
        progress: progress bar.

    Raises:
        ValueError: ``out`` is not empty; a frame id that is not numbers (BOP names scenes
            and images by numbers); depth that looks like another unit than the source's
            ``factor_depth`` (:func:`check_export_units`).
    """
    src = YCBVideo(source)
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"--out {out}: the folder exists and is not empty; name a new one")
    splits = _export_splits(src, frames, train)
    models = src.models()
    check_export_units(src, [fid for _, ids in splits for fid in ids], models)

    # the surfaces that render a real frame's occlusion counts, so both layouts give one factor
    renderer = Renderer(
        {c: p.copy() for c, p in models.items()}, surface_version=ALONE_SURFACE_VERSION
    )
    _write_models(out, models, renderer, src.classes)
    origins = {c: model_origin(p) for c, p in models.items()}
    n_frames = n_inst = 0
    targets = []
    total = sum(len(ids) for _, ids in splits)
    bar = tqdm(total=total, desc="export bop", unit="frame", disable=not progress)
    for split, ids in splits:
        by_scene: dict[int, list[str]] = {}
        for fid in ids:
            by_scene.setdefault(bop_ids(fid)[0], []).append(fid)
        for scene_id, fids in sorted(by_scene.items()):
            d = out / SPLIT_DIRS[split] / f"{scene_id:06d}"
            gt, cam, info = {}, {}, {}
            for fid in fids:
                im = bop_ids(fid)[1]
                ann = _write_frame(src, fid, d, renderer, origins)
                gt[str(im)], cam[str(im)], info[str(im)] = ann
                targets += [
                    {"im_id": im, "inst_count": 1, "obj_id": g["obj_id"], "scene_id": scene_id}
                    for g, i in zip(ann.gt, ann.info, strict=True)
                    if split == "test" and i["visib_fract"] >= MIN_VISIB_FRACT
                ]
                n_inst += len(ann.gt)
                n_frames += 1
                bar.update()
            for name, table in (("scene_gt", gt), ("scene_camera", cam), ("scene_gt_info", info)):
                atomic_text(d / f"{name}.json", json.dumps(table, indent=1) + "\n")
    bar.close()
    targets.sort(key=lambda t: (t["scene_id"], t["im_id"], t["obj_id"]))
    atomic_text(out / TARGETS_FILE, json.dumps(targets, indent=1) + "\n")
    return ExportSummary(out, n_frames, n_inst, len(targets))
