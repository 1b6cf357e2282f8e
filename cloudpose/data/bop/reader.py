"""A BOP ``ycbv`` root read as YCB-Video frames (:class:`BOPYcbv`; the mapping is the package doc's)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from cloudpose.conventions import packaged_classes, resource_path
from cloudpose.data.bop.format import (
    DEPTH_SCALE,
    SPLIT_DIRS,
    TARGETS_FILE,
    _load_json,
    _numbers,
    bop_ids,
    frame_id_of,
    model_origin,
    read_ply_vertices,
)
from cloudpose.data.ycb import (
    Frame,
    ModelPointSets,
    _check_cls_ids,
    _check_K,
    _check_poses,
    _open_png,
    _warn_no_depth,
    read_color_png,
    read_depth_png,
)


class BOPYcbv(ModelPointSets):
    """A dataset root in the BOP ``ycbv`` layout (module doc), read into YCB-Video frames.

    The same interface as :class:`~cloudpose.data.ycb.YCBVideo` (``classes``, ``models_root``,
    ``model_points``, ``models``, ``image_set``, ``frame``, ``content_files``, ``model_files``,
    ``alone_pixels``), so segments, caches, training and evaluation read it unchanged.

    Args:
        root: dataset root (holds ``test/``, ``test_targets_bop19.json``, ``models/``).
        models_root: folder of ``NAME/points.xyz``, the points metrics use; default the
            toolbox's 21 point sets shipped in ``cloudpose/resources/models``.
    """

    def __init__(self, root: str | Path, models_root: str | Path | None = None) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"{self.root}: dataset root not found")
        self.classes: list[str] = packaged_classes()
        self.models_root = Path(models_root) if models_root else resource_path("models")
        if not self.models_root.is_dir():
            raise FileNotFoundError(f"{self.models_root}: models folder not found")
        self._points: dict[int, np.ndarray] = {}
        self._scenes: dict[int, dict] = {}
        self.degenerate_counts: Counter[str] = Counter()

    # ---------------------------------------------------------------- models

    def model_files(self) -> list[Path]:
        """Every class's model point file (for content keys)."""
        return [self.models_root / n / "points.xyz" for n in self.classes]

    def check_models(self, tolerance: float = 0.002) -> list[str]:
        """Compare each ``models/obj_0000NN.ply`` with the toolbox points in the BOP frame.

        Returns:
            One line per model whose toolbox points, moved to the BOP frame, lie a median of
            more than ``tolerance`` metres from the PLY's nearest vertex (empty: every model is
            the toolbox's, in the frame the reader assumes). Missing PLY files are listed too.
        """
        from scipy.spatial import cKDTree

        out = []
        for c in range(1, len(self.classes) + 1):
            path = self.root / "models" / f"obj_{c:06d}.ply"
            if not path.is_file():
                out.append(f"{path}: missing")
                continue
            pts = self.model_points(c)
            d, _ = cKDTree(read_ply_vertices(path) / 1000.0).query(pts - model_origin(pts))
            if np.median(d) > tolerance:
                out.append(
                    f"{path}: the toolbox points of {self.classes[c - 1]} lie a median "
                    f"{1000 * np.median(d):.1f} mm from its vertices (expected < "
                    f"{1000 * tolerance:g} mm: is this BOP's ycbv model set?)"
                )
        return out

    # ---------------------------------------------------------------- frames

    def _scene_dir(self, scene_id: int) -> Path:
        for d in SPLIT_DIRS.values():
            path = self.root / d / f"{scene_id:06d}"
            if path.is_dir():
                return path
        raise FileNotFoundError(
            f"{self.root}: scene {scene_id:06d} not found under "
            + " or ".join(f"{d}/" for d in SPLIT_DIRS.values())
        )

    def _scene(self, scene_id: int) -> dict:
        if scene_id not in self._scenes:
            d = self._scene_dir(scene_id)
            info = d / "scene_gt_info.json"
            self._scenes[scene_id] = {
                "dir": d,
                "gt": _load_json(d / "scene_gt.json", "ground truth"),
                "camera": _load_json(d / "scene_camera.json", "camera parameters"),
                "info": _load_json(info, "ground-truth info") if info.is_file() else None,
            }
        return self._scenes[scene_id]

    def _entry(self, scene: dict, name: str, im_id: int, fid: str) -> list | dict:
        table = scene[name]
        if str(im_id) not in table:
            raise ValueError(
                f"{scene['dir'] / f'scene_{name}.json'}: no image {im_id} (frame {fid})"
            )
        return table[str(im_id)]

    def image_set(self, name: str) -> list[str]:
        """Frame ids ``SEQ/FRAME`` of a split: "keyframe" or "test" = the images of
        ``test_targets_bop19.json``; "all" = every image of ``test/``; "train" = every image
        of ``train_real/``.

        Raises:
            FileNotFoundError: a scene folder (``SSSSSS/``) of "all" or "train" without its
                ``scene_gt.json``, naming it and how many scenes lack one.
        """
        if name in ("keyframe", "test"):
            path = self.root / TARGETS_FILE
            targets = _load_json(path, "BOP19 test targets")
            try:
                ids = {(int(t["scene_id"]), int(t["im_id"])) for t in targets}
            except (TypeError, KeyError, ValueError) as e:
                raise ValueError(
                    f"{path}: expected a list of {{scene_id, im_id, obj_id, inst_count}} ({e})"
                ) from e
            return [frame_id_of(s, i) for s, i in sorted(ids)]
        split = {"all": "test", "train": "train"}.get(name)
        if split is None:
            raise ValueError(
                f"{self.root}: frame list {name!r} of a BOP root; expected keyframe (the BOP19 "
                "test targets), all (every test image) or train (train_real/)"
            )
        folder = self.root / SPLIT_DIRS[split]
        scenes = sorted(folder.glob("*/scene_gt.json"))
        if not scenes:
            raise FileNotFoundError(f"{folder}: no scenes (SSSSSS/scene_gt.json) found")
        # a scene folder without its ground truth cannot be read (scene_gt.json names the
        # objects of each image): refused, never left out of "all" without a word
        bare = [
            d
            for d in sorted(folder.iterdir())
            if d.is_dir() and d.name.isdigit() and not (d / "scene_gt.json").is_file()
        ]
        if bare:
            others = f" and {len(bare) - 1} more of its scenes" if len(bare) > 1 else ""
            raise FileNotFoundError(
                f"{bare[0] / 'scene_gt.json'}: ground truth not found, so scene "
                f"{bare[0].name}{others} of {folder} cannot be read ({len(bare)} of "
                f"{len(bare) + len(scenes)} scenes lack scene_gt.json); restore it, or move "
                f"the scene folder out of {folder.name}/ to use the other scenes"
            )
        frames = []
        for path in scenes:
            scene_id = int(path.parent.name)
            gt = _load_json(path, "ground truth")
            frames += [frame_id_of(scene_id, int(i)) for i in sorted(gt, key=int)]
        return frames

    def _paths(self, frame_id: str) -> tuple[dict, int, Path, list[Path]]:
        scene_id, im_id = bop_ids(frame_id)
        scene = self._scene(scene_id)
        gts = self._entry(scene, "gt", im_id, frame_id)
        d = scene["dir"]
        masks = [d / "mask_visib" / f"{im_id:06d}_{g:06d}.png" for g in range(len(gts))]
        return scene, im_id, d / "depth" / f"{im_id:06d}.png", masks

    def content_files(self, frame_id: str) -> list[Path]:
        """The files a frame's segments are made from (depth, visible masks, the scene's JSON
        files), for content keys.

        Raises:
            FileNotFoundError: one of them is missing.
        """
        scene, _, depth, masks = self._paths(frame_id)
        files = [depth, *masks]
        for p in files:
            if not p.is_file():
                raise FileNotFoundError(f"{p}: file of frame {frame_id} not found")
        names = ("scene_gt.json", "scene_camera.json", "scene_gt_info.json")
        return files + [scene["dir"] / n for n in names if (scene["dir"] / n).is_file()]

    def depth_unit_setting(self, scene: str) -> tuple[str, str, str]:
        """(where, setting, meaning) of the depth unit of scene ``scene`` (``SEQ`` of a frame
        id), for the unit check's message (:func:`cloudpose.data.segments.check_depth_scale`)."""
        return (
            str(self._scene_dir(int(scene))),
            "depth_scale in its scene_camera.json",
            f"millimetres per depth unit; BOP ycbv {DEPTH_SCALE:g}, millimetres 1",
        )

    def alone_pixels(self, frame_id: str) -> np.ndarray | None:
        """(N,) ``px_count_all`` of each annotation (its silhouette alone), or None without
        ``scene_gt_info.json``."""
        scene_id, im_id = bop_ids(frame_id)
        scene = self._scene(scene_id)
        if scene["info"] is None:
            return None
        info = self._entry(scene, "info", im_id, frame_id)
        try:
            return np.array([int(e["px_count_all"]) for e in info], dtype=np.int64)
        except (TypeError, KeyError, ValueError) as e:
            raise ValueError(
                f"{scene['dir'] / 'scene_gt_info.json'}: image {im_id}: px_count_all ({e})"
            ) from e

    def frame(self, frame_id: str, with_color: bool = False) -> Frame:
        """Read one annotated frame ``SEQ/FRAME`` as a YCB-Video :class:`Frame` (poses in the
        toolbox frame, depth in metres, label image from the visible masks)."""
        scene, im_id, depth_png, mask_pngs = self._paths(frame_id)
        d = scene["dir"]
        where = f"{d}, image {im_id}"
        cam = self._entry(scene, "camera", im_id, frame_id)
        K = _check_K(
            _numbers(cam, "cam_K", 9, f"{d / 'scene_camera.json'}, image {im_id}").reshape(3, 3),
            f"{d / 'scene_camera.json'}: cam_K",
        )
        scale = float(
            _numbers(cam, "depth_scale", 1, f"{d / 'scene_camera.json'}, image {im_id}")[0]
        )
        if scale <= 0:
            raise ValueError(f"{d / 'scene_camera.json'}, image {im_id}: depth_scale {scale} <= 0")
        depth = read_depth_png(depth_png, 1000.0 / scale)
        gts = self._entry(scene, "gt", im_id, frame_id)
        gt_where = f"{d / 'scene_gt.json'}, image {im_id}"
        cls_ids = _check_cls_ids(
            np.array([e.get("obj_id", -1) if isinstance(e, dict) else -1 for e in gts]),
            len(self.classes),
            f"{gt_where}: obj_id",
        )
        poses = np.zeros((len(gts), 3, 4))
        for i, (e, c) in enumerate(zip(gts, cls_ids, strict=True)):
            R = _numbers(e, "cam_R_m2c", 9, f"{gt_where}, annotation {i}").reshape(3, 3)
            t_mm = _numbers(e, "cam_t_m2c", 3, f"{gt_where}, annotation {i}")
            poses[i, :, :3] = R
            poses[i, :, 3] = t_mm / 1000.0 - R @ model_origin(self.model_points(c))
        poses = _check_poses(poses, len(gts), f"{gt_where}: cam_R_m2c")
        label = np.zeros(depth.shape, dtype=np.uint8)
        for c, path in zip(cls_ids, mask_pngs, strict=True):
            mask = np.asarray(_open_png(path, "visible mask")) > 0
            if mask.shape != depth.shape:
                raise ValueError(
                    f"{path}: mask has shape {mask.shape}, expected the depth image's "
                    f"{depth.shape} ({depth_png})"
                )
            label[mask & (label == 0)] = c
        color = None
        if with_color:
            rgb = next(
                (
                    d / "rgb" / f"{im_id:06d}{e}"
                    for e in (".png", ".jpg")
                    if (d / "rgb" / f"{im_id:06d}{e}").is_file()
                ),
                d / "rgb" / f"{im_id:06d}.png",
            )
            color = read_color_png(rgb)
        _warn_no_depth(depth, label, cls_ids, where, self.degenerate_counts)
        return Frame(frame_id, depth, label, K, cls_ids, poses, color)
