"""The BOP ``ycbv`` format: dataset reader and writer, and the results CSV.

Reader and writer stay in one module: they are the two halves of one format and must change
together (tests read back what is written). Layout under a root (bop_toolkit's
``docs/bop_datasets_format.md``)::

    models/obj_0000NN.ply             model meshes, millimetres (ascii or binary PLY)
    models/models_info.json           per obj_id: diameter, min_x.., size_x.. (mm),
                                      symmetries_discrete, symmetries_continuous
    test/SSSSSS/depth/IIIIII.png      uint16 depth; x depth_scale = millimetres
    test/SSSSSS/mask/IIIIII_GGGGGG.png       silhouette of annotation GGGGGG (alone)
    test/SSSSSS/mask_visib/IIIIII_GGGGGG.png its visible part (255 = object)
    test/SSSSSS/rgb/IIIIII.png        colour (optional)
    test/SSSSSS/scene_gt.json         {im_id: [{obj_id, cam_R_m2c (9, row-major), cam_t_m2c (mm)}]}
    test/SSSSSS/scene_camera.json     {im_id: {cam_K (9, row-major), depth_scale}}
    test/SSSSSS/scene_gt_info.json    {im_id: [{px_count_all, px_count_visib, visib_fract, ..}]}
    train_real/SSSSSS/...             training images, the same files
    test_targets_bop19.json           [{scene_id, im_id, obj_id, inst_count}]: the BOP19 targets

How it maps onto the YCB-Video layout, so one :class:`~cloudpose.data.ycb.Frame` and one segment
pipeline serve both:

- obj_id i is YCB-Video class id i (the order of ``classes.txt``).
- A frame's id is YCB-Video's ``SEQ/FRAME``: scene 48, image 1 is ``0048/000001`` in both
  layouts, so its segments (whose FPS start is seeded by the frame id) and its index in the
  toolbox's ``keyframe.txt`` (PoseCNN's results) are the same.
- The label image is built from the per-annotation ``mask_visib`` images (YCB-Video labels by
  class, at most one instance of a class per frame; a frame with two is refused).
- Frames: "keyframe" (or "test") = the images of ``test_targets_bop19.json``; "all" = every
  image of ``test/``; "train" = every image of ``train_real/``. The instances of a frame are
  every annotated object of ``scene_gt.json``, as the YCB-Video toolbox counts them (BOP19's
  targets leave out objects less than 10% visible; the targets only choose the images).
- The occlusion factor's alone-pixel count is ``px_count_all`` of ``scene_gt_info.json``.

Model frame and points (our decision): BOP's ycbv models are YCB-Video's in millimetres with
the origin moved to the centre of the bounding box of the toolbox's evaluation point set
(``points.xyz``, :func:`model_origin`): ``x_bop = 1000 (x - c)``, hence ``R_bop = R`` and
``t_bop = 1000 (t + R c)``. (The per-object offsets published with BOP-to-toolbox converters,
e.g. dornik/sporeagent ``dataset/ycbv_offsets.json``, equal ``c`` to 1e-13 mm.) The reader
converts BOP poses into the toolbox frame and every metric, ICP and the symmetry table use the
toolbox's 2,620-point sets that ship in the package, never the BOP meshes' vertices: AD/ADS
numbers stay the toolbox's on either layout. :func:`read_ply_vertices` reads a BOP model and
:meth:`BOPYcbv.check_models` tells whether its vertices are the toolbox points in that frame.
Results written for BOP (:func:`write_results_csv`) are converted back.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from cloudpose.conventions import resource_path
from cloudpose.data.ycb import (
    Frame,
    ModelPointSets,
    _check_cls_ids,
    _check_K,
    _check_poses,
    _open_png,
    _warn_no_depth,
    load_classes,
    read_color_png,
    read_depth_png,
)
from cloudpose.files import atomic_text, atomic_write

__all__ = [
    "CSV_HEADER",
    "BOPYcbv",
    "ExportSummary",
    "bop_ids",
    "check_results_csv",
    "check_results_destination",
    "export_bop",
    "frame_id_of",
    "is_bop_root",
    "model_origin",
    "read_ply_vertices",
    "write_evaluation_csv",
    "write_results_csv",
]

SPLIT_DIRS = {"test": "test", "train": "train_real"}
"""Where a split's scenes are: test images (the targets' and "all") and training images."""

TARGETS_FILE = "test_targets_bop19.json"
DEPTH_SCALE = 0.1
"""Millimetres per depth unit that the writer uses: BOP ycbv's, i.e. YCB-Video's 10000 units
per metre, so exported depth PNGs hold the same numbers."""
MIN_VISIB_FRACT = 0.1
"""BOP19 test targets are the annotated objects at least this visible (``visib_fract``)."""
CSV_HEADER = "scene_id,im_id,obj_id,score,R,t,time"
"""The BOP results CSV (bop_toolkit ``docs/bop_challenge_2019.md``): one pose per line."""


def frame_id_of(scene_id: int, im_id: int) -> str:
    """``SEQ/FRAME`` id of BOP scene ``scene_id``, image ``im_id``: ``0048/000001``."""
    return f"{int(scene_id):04d}/{int(im_id):06d}"


def bop_ids(frame_id: str) -> tuple[int, int]:
    """(scene_id, im_id) of a ``SEQ/FRAME`` id whose parts are numbers.

    Raises:
        ValueError: the id is not two numbers separated by ``/``.
    """
    seq, _, name = str(frame_id).partition("/")
    if not (seq.isdigit() and name.isdigit()):
        raise ValueError(
            f"frame id {frame_id!r}: BOP names frames by numbers, expected 'SEQ/FRAME' of digits"
        )
    return int(seq), int(name)


def model_origin(points: np.ndarray) -> np.ndarray:
    """(3,) centre of the bounding box of (P, 3) model points, metres: where BOP's ycbv models
    put their origin (module doc)."""
    points = np.asarray(points, dtype=np.float64)
    return (points.min(axis=0) + points.max(axis=0)) / 2


def is_bop_root(root: str | Path) -> bool:
    """Whether ``root`` holds the BOP layout (a targets file, or a scene with ``scene_gt.json``
    under ``test/`` or ``train_real/``)."""
    root = Path(root)
    if (root / TARGETS_FILE).is_file():
        return True
    return any(any((root / d).glob("*/scene_gt.json")) for d in SPLIT_DIRS.values())


# --------------------------------------------------------------------------- PLY


_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def read_ply_vertices(path: str | Path) -> np.ndarray:
    """The vertex positions of a PLY file (ascii or binary; the vertex element first, as BOP's
    models have it).

    Returns:
        (V, 3) float64 x, y, z in the file's unit (millimetres for BOP models).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a PLY, no vertex element first, or no x/y/z properties.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: PLY model not found")
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file (expected 'ply' on the first line)")
        fmt, elements = None, []
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: PLY header has no 'end_header'")
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and elements:
                elements[-1][2].append(words[1:])
        if not elements or elements[0][0] != "vertex":
            raise ValueError(f"{path}: expected the vertex element first in the PLY header")
        _, n, props = elements[0]
        if any(p[0] == "list" for p in props):
            raise ValueError(f"{path}: list properties in the vertex element are not supported")
        names = [p[1] for p in props]
        if not {"x", "y", "z"} <= set(names):
            raise ValueError(f"{path}: vertex element has properties {names}, expected x, y, z")
        if fmt == "ascii":
            rows = [f.readline().split() for _ in range(n)]
            try:
                data = np.array(rows, dtype=np.float64).reshape(n, len(names))
            except ValueError as e:
                raise ValueError(f"{path}: unreadable ascii vertex rows ({e})") from e
            xyz = data[:, [names.index(k) for k in "xyz"]]
        elif fmt in ("binary_little_endian", "binary_big_endian"):
            order = "<" if fmt == "binary_little_endian" else ">"
            try:
                dtype = np.dtype([(p[1], order + _PLY_TYPES[p[0]]) for p in props])
            except KeyError as e:
                raise ValueError(f"{path}: unknown PLY property type {e}") from e
            buf = f.read(dtype.itemsize * n)
            if len(buf) < dtype.itemsize * n:
                raise ValueError(f"{path}: file ends inside the vertex data")
            rec = np.frombuffer(buf, dtype=dtype, count=n)
            xyz = np.stack([rec[k].astype(np.float64) for k in "xyz"], axis=1)
        else:
            raise ValueError(f"{path}: PLY format {fmt!r}, expected ascii or binary")
    if not np.isfinite(xyz).all():
        raise ValueError(f"{path}: vertex positions contain NaN or inf")
    return xyz


def write_ply(path: str | Path, vertices: np.ndarray, triangles: np.ndarray | None) -> None:
    """An ascii PLY of (V, 3) vertices and (T, 3) triangles (vertex indices), atomically."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.zeros((0, 3), np.int64) if triangles is None else np.asarray(triangles, np.int64)
    head = [
        "ply",
        "format ascii 1.0",
        "comment cloudpose export: YCB-Video model, millimetres, BOP ycbv frame",
        f"element vertex {len(V)}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(F)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    body = [f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in V] + [f"3 {a} {b} {c}" for a, b, c in F]
    atomic_text(path, "\n".join(head + body) + "\n")


# --------------------------------------------------------------------------- reader


def _load_json(path: Path, what: str):
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what} not found")
    try:
        return json.loads(path.read_text())
    except ValueError as e:
        raise ValueError(f"{path}: {what} is not valid JSON ({e})") from e


def _numbers(entry: dict, key: str, n: int, where: str) -> np.ndarray:
    if key not in entry:
        raise ValueError(f"{where}: no field {key!r}")
    try:
        v = np.asarray(entry[key], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: {key} is not a list of numbers ({e})") from e
    if v.size != n or not np.isfinite(v).all():
        raise ValueError(f"{where}: {key} has {v.size} values, expected {n} finite numbers")
    return v


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
        self.classes: list[str] = load_classes(resource_path("classes.txt"))
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


# --------------------------------------------------------------------------- writer


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

    from cloudpose.geometry.symmetry import flip_rotation, symmetries_for

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
    import warnings

    from cloudpose.data.segment_set import SegmentSet, check_units, unit_stats
    from cloudpose.data.segments import SegmentWarning, extract_segments

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
    (millimetres, BOP frame) and ``models_info.json``. :class:`BOPYcbv` reads it back into the
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
    from tqdm import tqdm

    from cloudpose.data.render import Renderer
    from cloudpose.data.segments import ALONE_SURFACE_VERSION
    from cloudpose.data.ycb import YCBVideo

    src = YCBVideo(source)
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"--out {out}: the folder exists and is not empty; name a new one")
    splits = [("test", src.image_set(frames))]
    if train:
        splits.append(("train", src.image_set("train")))
    for _, ids in splits:
        for fid in ids:
            bop_ids(fid)
    models = src.models()
    check_export_units(src, [fid for _, ids in splits for fid in ids], models)
    # the surfaces that render a real frame's occlusion counts, so both layouts give one factor
    renderer = Renderer(
        {c: p.copy() for c, p in models.items()}, surface_version=ALONE_SURFACE_VERSION
    )
    (out / "models").mkdir(parents=True, exist_ok=True)
    for c, pts in models.items():
        tri = np.asarray(renderer.mesh(c).triangles)
        write_ply(out / "models" / f"obj_{c:06d}.ply", (pts - model_origin(pts)) * 1000.0, tri)
    atomic_text(
        out / "models" / "models_info.json",
        json.dumps(models_info(models, src.classes), indent=1) + "\n",
    )
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
                has_color = src.frame_paths(fid)["color"].is_file()
                f = src.frame(fid, with_color=has_color)
                shape = f.depth.shape
                alone = src.alone_pixels(fid)
                if alone is None:
                    alone = renderer.alone_pixels(f.K, shape, f.cls_ids, f.poses)
                _png(
                    d / "depth" / f"{im:06d}.png",
                    np.round(f.depth.astype(np.float64) * 1000.0 / DEPTH_SCALE).astype(np.uint16),
                )
                if f.color is not None:
                    _png(d / "rgb" / f"{im:06d}.png", f.color, "RGB")
                gt[str(im)], info[str(im)] = [], []
                cam[str(im)] = {"cam_K": f.K.ravel().tolist(), "depth_scale": DEPTH_SCALE}
                for g, (c, P) in enumerate(zip(f.cls_ids, f.poses, strict=True)):
                    R, t = P[:, :3], P[:, 3]
                    full = renderer.render(f.K, shape, [int(c)], P[None]).label > 0
                    visib = f.label == c
                    _png(d / "mask" / f"{im:06d}_{g:06d}.png", full.astype(np.uint8) * 255, "L")
                    _png(
                        d / "mask_visib" / f"{im:06d}_{g:06d}.png",
                        visib.astype(np.uint8) * 255,
                        "L",
                    )
                    t_mm = 1000.0 * (t + R @ origins[int(c)])
                    gt[str(im)].append(
                        {
                            "cam_R_m2c": R.ravel().tolist(),
                            "cam_t_m2c": t_mm.tolist(),
                            "obj_id": int(c),
                        }
                    )
                    n_all, n_vis = int(alone[g]), int(visib.sum())
                    # a real label can exceed the rendered silhouette by a few pixels
                    fract = min(n_vis / n_all, 1.0) if n_all > 0 else 0.0
                    info[str(im)].append(
                        {
                            "bbox_obj": _bbox(full),
                            "bbox_visib": _bbox(visib),
                            "px_count_all": n_all,
                            "px_count_valid": int((full & (f.depth > 0)).sum()),
                            "px_count_visib": n_vis,
                            "visib_fract": fract,
                        }
                    )
                    if split == "test" and fract >= MIN_VISIB_FRACT:
                        targets.append(
                            {"im_id": im, "inst_count": 1, "obj_id": int(c), "scene_id": scene_id}
                        )
                    n_inst += 1
                n_frames += 1
                bar.update()
            for name, table in (("scene_gt", gt), ("scene_camera", cam), ("scene_gt_info", info)):
                atomic_text(d / f"{name}.json", json.dumps(table, indent=1) + "\n")
    bar.close()
    targets.sort(key=lambda t: (t["scene_id"], t["im_id"], t["obj_id"]))
    atomic_text(out / TARGETS_FILE, json.dumps(targets, indent=1) + "\n")
    return ExportSummary(out, n_frames, n_inst, len(targets))


# --------------------------------------------------------------------------- results CSV


def write_results_csv(
    table,
    path: str | Path,
    method: str = "icp",
    seconds_per_object: float = -1.0,
    models: dict[int, np.ndarray] | None = None,
) -> int:
    """Write an evaluation's poses as a BOP results CSV (:data:`CSV_HEADER`), for bop_toolkit.

    One line per instance with an estimate (misses are left out: BOP counts a target without
    an estimate as a failure): ``scene_id``, ``im_id`` from the frame id, ``obj_id`` = class
    id, ``score`` 1, ``R`` row-major and ``t`` in millimetres in the BOP frame (module doc),
    ``time`` = the image's objects x ``seconds_per_object`` (the evaluation's mean), the same
    on every line of an image, or -1 when not given.

    Args:
        table: an evaluation's instance table (``frame_id``, ``cls_id``, ``miss`` and the
            method's pose columns ``{method}_R`` (9 numbers), ``{method}_t`` (metres)).
        path: CSV to write.
        method: "net" (the network's estimate) or "icp" (after ICP).
        seconds_per_object: mean time per object, seconds; negative = not available.
        models: {class id: (P, 3) toolbox points} that fix the BOP origin; default the
            packaged ones.

    Returns:
        The number of lines written (header excluded).

    Raises:
        ValueError: the table has no poses for ``method`` (an evaluation of an older version,
            or ``icp`` of an evaluation made without ICP).
    """
    from cloudpose.data.surfaces import load_packaged_models

    cols = [f"{method}_R", f"{method}_t"]
    missing = [c for c in ("frame_id", "cls_id", "miss", *cols) if c not in table]
    if missing:
        raise ValueError(
            f"instance table has no columns {missing}: evaluate the run again (the table "
            f"keeps the poses since this version){' with ICP' if method == 'icp' else ''}"
        )
    models = models or load_packaged_models()
    rows = table[~table["miss"].astype(bool)]
    per_image = rows.groupby("frame_id")["frame_id"].transform("size")
    lines = [CSV_HEADER]
    for (_, r), n in zip(rows.iterrows(), per_image, strict=True):
        scene_id, im_id = bop_ids(r["frame_id"])
        c = int(r["cls_id"])
        R = np.array(str(r[cols[0]]).split(), dtype=np.float64).reshape(3, 3)
        t = np.array(str(r[cols[1]]).split(), dtype=np.float64)
        t_mm = 1000.0 * (t + R @ model_origin(models[c]))
        time = n * seconds_per_object if seconds_per_object >= 0 else -1
        lines.append(
            f"{scene_id},{im_id},{c},1,{' '.join(f'{v:.9g}' for v in R.ravel())},"
            f"{' '.join(f'{v:.6f}' for v in t_mm)},{time:.6g}"
        )
    atomic_text(path, "\n".join(lines) + "\n")
    return len(lines) - 1


def check_results_destination(path: str | Path, force: bool = False) -> Path:
    """``path`` as a place to write a results CSV: not a folder, and not an existing file
    unless ``force`` (ValueError naming it otherwise); checked before any evaluation."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"--bop-csv {path}: is a folder; expected a CSV file to write")
    if path.exists() and not force:
        raise ValueError(f"--bop-csv {path}: exists; pass --force to overwrite it")
    return path


def write_evaluation_csv(evaluation, path: str | Path, icp: bool) -> tuple[int, str]:
    """An evaluation's poses as a checked BOP results CSV: the ICP-refined poses when ``icp``
    (else the network's), timed by the evaluation's mean ms per object (network + ICP).

    Args:
        evaluation: a :class:`cloudpose.evaluate.EvalOutcome` (its ``table``, ``metrics``
            and ``name``).
        path: CSV to write.
        icp: write the poses after ICP.

    Returns:
        (lines written, the method written: "icp" or "net"). Raises ValueError when the file
        fails :func:`check_results_csv`.
    """
    method = "icp" if icp else "net"
    ms = evaluation.metrics[f"{evaluation.name}/net_ms_per_object"]
    if icp:
        ms += evaluation.metrics[f"{evaluation.name}/icp_ms_per_object"]
    n = write_results_csv(evaluation.table, path, method, seconds_per_object=ms / 1000)
    problems = check_results_csv(path)
    if problems:
        raise ValueError(f"{path} fails the BOP format check: {problems[0]}")
    return n, method


def check_results_csv(path: str | Path, rotation_tol: float = 1e-4) -> list[str]:
    """Check a BOP results CSV against the format of bop_toolkit's documentation.

    The rules (``docs/bop_challenge_2019.md`` and bop_toolkit's ``inout.load_bop_results`` /
    ``check_consistent_timings``): the header ``scene_id,im_id,obj_id,score,R,t,time``; 7
    comma-separated fields per line; integer ids (>= 0, obj_id >= 1); a finite score; R = 9
    numbers separated by white space forming a rotation (``|R R^T - I| <= rotation_tol``,
    det +1); t = 3 numbers (millimetres: a pose with |t| under 10 mm or over 10 m reads as
    metres or nonsense); time a number, >= 0 or -1 (not available), the same (within 1 ms) on
    every line of an image.

    Returns:
        The problems, one line each naming the file and line (empty = the file passes).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: results CSV not found")
    lines = path.read_text().splitlines()
    if not lines or lines[0].strip() != CSV_HEADER:
        return [f"{path}, line 1: header {lines[0] if lines else ''!r}, expected {CSV_HEADER!r}"]
    problems: list[str] = []
    times: dict[tuple[int, int], float] = {}
    for no, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        where = f"{path}, line {no}"
        fields = line.split(",")
        if len(fields) != 7:
            problems.append(f"{where}: {len(fields)} comma-separated fields, expected 7")
            continue
        try:
            scene_id, im_id, obj_id = (int(v) for v in fields[:3])
            score = float(fields[3])
            R = np.array(fields[4].split(), dtype=np.float64)
            t = np.array(fields[5].split(), dtype=np.float64)
            time = float(fields[6])
        except ValueError as e:
            problems.append(f"{where}: unparsable field ({e})")
            continue
        if scene_id < 0 or im_id < 0 or obj_id < 1:
            problems.append(f"{where}: ids {scene_id},{im_id},{obj_id}: expected >= 0, obj_id >= 1")
        if not np.isfinite(score):
            problems.append(f"{where}: score {score} is not finite")
        if R.size != 9 or not np.isfinite(R).all():
            problems.append(f"{where}: R has {R.size} numbers, expected 9 finite ones")
        else:
            R = R.reshape(3, 3)
            ortho = float(np.abs(R @ R.T - np.eye(3)).max())
            if ortho > rotation_tol or np.linalg.det(R) < 0:
                problems.append(
                    f"{where}: R is not a rotation (max |R R^T - I| = {ortho:.2g}, det "
                    f"{np.linalg.det(R):.3g})"
                )
        if t.size != 3 or not np.isfinite(t).all():
            problems.append(f"{where}: t has {t.size} numbers, expected 3 finite ones")
        elif not 10.0 <= np.linalg.norm(t) <= 10000.0:
            problems.append(
                f"{where}: |t| = {np.linalg.norm(t):.4g}; expected millimetres (10 mm .. 10 m)"
            )
        if not (time >= 0 or time == -1):
            problems.append(f"{where}: time {time}: expected >= 0 seconds, or -1")
        key = (scene_id, im_id)
        if key in times and abs(times[key] - time) > 0.001:
            problems.append(
                f"{where}: time {time} differs from {times[key]} on an earlier line of scene "
                f"{scene_id} image {im_id}; one time per image"
            )
        times.setdefault(key, time)
    return problems
