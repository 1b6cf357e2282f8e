"""YCB-Video reader and writer (the real dataset's layout; the synthetic set uses the same).

Reader, writer and their field checks stay in one file over ~450 lines on purpose: they are
the two halves of one file format and must change together (tests read back what is written).

Layout under a dataset root (docs/design.md, "Data")::

    classes.txt                      one class name per line; line i -> class id i + 1
    keyframe.txt                     test frames, one "SEQ/FRAME" per line
    image_sets/NAME.txt              other splits (train.txt, val.txt, ...)
    models/NAME/points.xyz           evaluation model points, metres, one "x y z" per line
    data/SEQ/FRAME-depth.png         uint16 depth, ``factor_depth`` units per metre, 0 = no reading
    data/SEQ/FRAME-label.png         uint8 class id per pixel, 0 = background
    data/SEQ/FRAME-meta.mat          cls_indexes (N, 1), poses (3, 4, N) object->camera,
                                     intrinsic_matrix (3, 3), factor_depth (1, 1)
    data/SEQ/FRAME-color.png         optional RGB

Every entry point checks its input and raises ``FileNotFoundError`` / ``ValueError`` naming the
file, the field and what was expected. Degenerate but legal data (an annotated object without
a single valid depth pixel) warns with :class:`DegenerateDataWarning` and is counted in
:data:`degenerate_counts` (and in :attr:`YCBVideo.degenerate_counts`).
"""

from __future__ import annotations

import re
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.io
from PIL import Image, UnidentifiedImageError

from cloudpose.conventions import DEPTH_FACTOR_YCB, load_classes, resource_path
from cloudpose.files import atomic_write

ROTATION_TOL = 1e-3
"""Largest allowed ``max |R R^T - I|`` for a pose's rotation part."""

_FRAME_ID = re.compile(r"^[^/\\\s]+/[^/\\\s]+$")

degenerate_counts: Counter[str] = Counter()
"""Process-wide count of degenerate-but-legal cases seen by the reader, by kind
(``"no_depth"``: an annotated instance with no pixel that has both its label and depth > 0)."""


class DegenerateDataWarning(UserWarning):
    """Legal but degenerate data (e.g. an annotated object with no valid depth pixel)."""


@dataclass
class Frame:
    """One frame of a YCB-Video-layout dataset.

    Attributes:
        frame_id: "SEQ/FRAME", e.g. "0000/000001" (empty for loose files without a name).
        depth: (H, W) float32 depth in metres, 0 = no reading.
        label: (H, W) uint8 class id per pixel, 0 = background.
        K: (3, 3) float64 camera intrinsics (pixels).
        cls_ids: (N,) int64 1-based class ids of the annotated instances (meta ``cls_indexes``;
            without meta, the sorted unique nonzero label ids).
        poses: (N, 3, 4) float64 object->camera ``[R | t]`` (t in metres), or None without
            ground truth.
        color: (H, W, 3) uint8 RGB, or None.
    """

    frame_id: str
    depth: np.ndarray
    label: np.ndarray
    K: np.ndarray
    cls_ids: np.ndarray
    poses: np.ndarray | None
    color: np.ndarray | None


# --------------------------------------------------------------------------- small files


def load_model_points(path: str | Path) -> np.ndarray:
    """Read a model's ``points.xyz`` (one "x y z" line per point, metres).

    Returns:
        (P, 3) float64 points in metres, model frame.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: unparsable, not 3 columns, empty, or not finite.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: model points not found (expected points.xyz)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numpy warns on an empty file; we raise below
            pts = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise ValueError(f"{path}: cannot parse model points ({e}); expected 'x y z' lines") from e
    if pts.size == 0:
        raise ValueError(f"{path}: no model points (expected 'x y z' lines)")
    if pts.shape[1] != 3:
        raise ValueError(f"{path}: model points have {pts.shape[1]} columns, expected 3 (x y z)")
    if not np.isfinite(pts).all():
        raise ValueError(f"{path}: model points contain NaN or inf")
    if np.abs(pts).max() > 2.0:
        raise ValueError(
            f"{path}: model points reach {np.abs(pts).max():.3g} from the origin; expected metres "
            "(YCB objects are < 0.5 m)"
        )
    return pts


def _read_lines(path: Path, what: str) -> list[str]:
    """The frame ids of a frame list, one "SEQ/FRAME" a line (blank lines skipped).

    A UTF-8 byte order mark (which Windows editors write) is dropped. A frame listed twice is
    refused, naming both lines: it would count twice in every metric and in training, and a
    list that repeats a frame is not the list its author meant (two lists joined, a split
    copied twice), so no guess of which copy is meant is made here.

    Raises:
        FileNotFoundError: no such file.
        ValueError: a line that is not a frame id, a frame listed twice, or not UTF-8 text.
    """
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what} not found")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: {what} is not UTF-8 text ({e.reason} at byte {e.start})") from e
    ids: list[str] = []
    first: dict[str, int] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        fid = line.strip()
        if not fid:
            continue
        if not _FRAME_ID.match(fid):
            raise ValueError(f"{path}, line {number}: {fid!r} is not a frame id 'SEQ/FRAME'")
        if fid in first:
            raise ValueError(
                f"{path}, line {number}: frame {fid} is listed again (first on line "
                f"{first[fid]}); it would count twice in every metric: list each frame once "
                f"(awk '!seen[$0]++' keeps the first of each)"
            )
        first[fid] = number
        ids.append(fid)
    return ids


# --------------------------------------------------------------------------- images


def _open_png(path: Path, field: str) -> Image.Image:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {field} image not found")
    try:
        im = Image.open(path)
        im.load()
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise ValueError(f"{path}: {field} image is not a readable PNG ({e})") from e
    return im


def read_depth_png(path: str | Path, depth_factor: float = DEPTH_FACTOR_YCB) -> np.ndarray:
    """Read a 16-bit depth PNG.

    Returns:
        (H, W) float32 depth in metres (raw / depth_factor), 0 = no reading.
    """
    path = Path(path)
    im = _open_png(path, "depth")
    if im.mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise ValueError(f"{path}: depth image has mode {im.mode!r}, expected 16-bit grayscale")
    raw = np.asarray(im)
    if raw.ndim != 2:
        raise ValueError(f"{path}: depth image has shape {raw.shape}, expected (H, W)")
    if raw.dtype != np.uint16:
        if raw.min() < 0 or raw.max() > 65535:
            raise ValueError(f"{path}: depth values outside 0..65535")
    return (raw.astype(np.float64) / depth_factor).astype(np.float32)


def read_label_png(path: str | Path) -> np.ndarray:
    """Read an 8-bit label PNG.

    Returns:
        (H, W) uint8 class ids, 0 = background.
    """
    path = Path(path)
    im = _open_png(path, "label")
    if im.mode not in ("L", "P"):
        raise ValueError(f"{path}: label image has mode {im.mode!r}, expected 8-bit ('L')")
    lab = np.asarray(im)
    if lab.ndim != 2:
        raise ValueError(f"{path}: label image has shape {lab.shape}, expected (H, W)")
    return np.ascontiguousarray(lab, dtype=np.uint8)


def read_color_png(path: str | Path) -> np.ndarray:
    """Read a color image. Returns (H, W, 3) uint8 RGB."""
    path = Path(path)
    im = _open_png(path, "color")
    if im.mode not in ("RGB", "RGBA", "L", "P"):
        raise ValueError(f"{path}: color image has mode {im.mode!r}, expected RGB")
    return np.asarray(im.convert("RGB"), dtype=np.uint8)


# --------------------------------------------------------------------------- checks


def _check_K(K: np.ndarray, where: str) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"{where}: intrinsics have shape {K.shape}, expected (3, 3)")
    if not np.isfinite(K).all():
        raise ValueError(f"{where}: intrinsics contain NaN or inf")
    if not (K[0, 0] > 0 and K[1, 1] > 0) or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise ValueError(
            f"{where}: intrinsics {K.tolist()} are not a pinhole matrix "
            "[[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0"
        )
    return K


def _check_poses(poses: np.ndarray, n: int, where: str) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (n, 3, 4):
        raise ValueError(f"{where}: poses have shape {poses.shape}, expected ({n}, 3, 4)")
    if not np.isfinite(poses).all():
        raise ValueError(f"{where}: poses contain NaN or inf")
    R = poses[:, :, :3]
    ortho = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    for i in range(n):
        if ortho[i] > ROTATION_TOL or det[i] < 0:
            raise ValueError(
                f"{where}: pose {i} is not a rotation (max |R R^T - I| = {ortho[i]:.3g}, "
                f"det R = {det[i]:.3g}; expected <= {ROTATION_TOL} and +1)"
            )
    return poses


def _check_cls_ids(cls_ids: np.ndarray, num_classes: int, where: str) -> np.ndarray:
    cls = np.asarray(cls_ids)
    if cls.size and not np.issubdtype(cls.dtype, np.integer):
        if not np.all(np.isfinite(cls)) or not np.all(cls == np.round(cls)):
            raise ValueError(f"{where}: class ids {cls.ravel().tolist()} are not integers")
    cls = cls.astype(np.int64).ravel()
    bad = cls[(cls < 1) | (cls > num_classes)]
    if bad.size:
        raise ValueError(
            f"{where}: class ids {bad.tolist()} out of range, expected 1..{num_classes}"
        )
    if len(np.unique(cls)) != len(cls):
        raise ValueError(
            f"{where}: class ids {cls.tolist()} repeat; YCB-Video labels by class, "
            "so each class may appear once per frame"
        )
    return cls


def _check_label_vs_classes(
    label: np.ndarray, cls_ids: np.ndarray, num_classes: int, where: str
) -> None:
    present = np.unique(label)
    present = present[present != 0].astype(np.int64)
    out = present[present > num_classes]
    if out.size:
        raise ValueError(f"{where}: label ids {out.tolist()} out of range 1..{num_classes}")
    extra = np.setdiff1d(present, cls_ids)
    if extra.size:
        raise ValueError(
            f"{where}: label image has class ids {extra.tolist()} that meta cls_indexes "
            f"{cls_ids.tolist()} does not list"
        )


def _warn_no_depth(
    depth: np.ndarray, label: np.ndarray, cls_ids: np.ndarray, where: str, counts: Counter | None
) -> None:
    valid = depth > 0
    for c in cls_ids:
        if not np.any((label == c) & valid):
            degenerate_counts["no_depth"] += 1
            if counts is not None:
                counts["no_depth"] += 1
            warnings.warn(
                f"{where}: class {int(c)} has no pixel with both its label and a depth reading",
                DegenerateDataWarning,
                stacklevel=3,
            )


def _meta_field(meta: dict, name: str, path: Path) -> np.ndarray:
    if name not in meta:
        raise ValueError(f"{path}: meta has no field {name!r}")
    return np.asarray(meta[name])


def read_meta(
    path: str | Path, num_classes: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Read and check a ``FRAME-meta.mat``.

    Returns:
        cls_ids (N,) int64, poses (N, 3, 4) float64 object->camera, K (3, 3) float64,
        factor_depth (depth PNG units per metre).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: meta file not found")
    try:
        meta = scipy.io.loadmat(path)
    except Exception as e:  # scipy raises several types on corrupt files
        raise ValueError(f"{path}: meta is not a readable .mat file ({e})") from e
    cls_raw = _meta_field(meta, "cls_indexes", path)
    if cls_raw.ndim > 2 or (cls_raw.ndim == 2 and min(cls_raw.shape) > 1):
        raise ValueError(f"{path}: cls_indexes has shape {cls_raw.shape}, expected (N, 1)")
    cls_ids = _check_cls_ids(cls_raw, num_classes, f"{path}: cls_indexes")
    n = len(cls_ids)
    poses = _meta_field(meta, "poses", path).astype(np.float64)
    if poses.ndim == 2 and n == 1:  # MATLAB drops a trailing singleton dimension
        poses = poses[:, :, None]
    if poses.ndim != 3 or poses.shape[:2] != (3, 4):
        raise ValueError(f"{path}: poses has shape {poses.shape}, expected (3, 4, {n})")
    if poses.shape[2] != n:
        raise ValueError(
            f"{path}: poses has {poses.shape[2]} poses but cls_indexes lists {n} classes"
        )
    poses = _check_poses(np.moveaxis(poses, 2, 0), n, f"{path}: poses")
    K = _check_K(_meta_field(meta, "intrinsic_matrix", path), f"{path}: intrinsic_matrix")
    fd = _meta_field(meta, "factor_depth", path).astype(np.float64).ravel()
    if fd.size != 1 or not np.isfinite(fd[0]) or fd[0] <= 0:
        raise ValueError(f"{path}: factor_depth is {fd.tolist()}, expected one positive number")
    return cls_ids, poses, K, float(fd[0])


# --------------------------------------------------------------------------- frames


def read_frame(
    depth_png: str | Path,
    label_png: str | Path,
    meta_mat: str | Path | None = None,
    color_png: str | Path | None = None,
    K: np.ndarray | None = None,
    depth_factor: float = DEPTH_FACTOR_YCB,
    frame_id: str = "",
    num_classes: int = 21,
    counts: Counter | None = None,
) -> Frame:
    """Read one frame from loose files (the YCB-Video frame files, or a user's own).

    Args:
        depth_png: 16-bit depth PNG, ``depth_factor`` units per metre.
        label_png: 8-bit label PNG (class ids, 0 = background).
        meta_mat: YCB-Video meta file; gives classes, poses, intrinsics and depth factor.
        color_png: optional RGB image.
        K: (3, 3) intrinsics; required without meta; with meta it must agree with
            ``intrinsic_matrix``.
        depth_factor: depth units per metre, used only without meta (meta's factor_depth wins).
        frame_id: name stored in the frame.
        num_classes: class ids must lie in 1..num_classes.
        counts: optional counter that degenerate cases are also added to.

    Returns:
        The :class:`Frame`; ``poses`` is None without meta, and ``cls_ids`` then holds the
        sorted unique nonzero label ids.
    """
    depth_png, label_png = Path(depth_png), Path(label_png)
    if meta_mat is not None:
        meta_mat = Path(meta_mat)
        cls_ids, poses, K_meta, depth_factor = read_meta(meta_mat, num_classes)
        if K is not None and not np.allclose(np.asarray(K, dtype=np.float64), K_meta):
            raise ValueError(
                f"{meta_mat}: intrinsic_matrix {K_meta.tolist()} disagrees with the given K "
                f"{np.asarray(K).tolist()}"
            )
        K = K_meta
    else:
        if K is None:
            raise ValueError(f"{depth_png}: no meta file, so intrinsics K (3, 3) must be given")
        K = _check_K(K, f"{depth_png}: K")
        if not (np.isfinite(depth_factor) and depth_factor > 0):
            raise ValueError(f"depth_factor must be a positive number, got {depth_factor!r}")
        poses = None
        cls_ids = None
    depth = read_depth_png(depth_png, depth_factor)
    label = read_label_png(label_png)
    if depth.shape != label.shape:
        raise ValueError(
            f"{label_png}: label image has shape {label.shape}, expected the depth image's "
            f"{depth.shape} ({depth_png})"
        )
    color = None
    if color_png is not None:
        color = read_color_png(color_png)
        if color.shape[:2] != depth.shape:
            raise ValueError(
                f"{color_png}: color image has shape {color.shape[:2]}, expected the depth "
                f"image's {depth.shape} ({depth_png})"
            )
    where = f"{label_png}"
    if cls_ids is None:
        present = np.unique(label)
        cls_ids = present[present != 0].astype(np.int64)
        _check_label_vs_classes(label, cls_ids, num_classes, where)
    else:
        _check_label_vs_classes(label, cls_ids, num_classes, f"{where} (meta {meta_mat})")
    _warn_no_depth(depth, label, cls_ids, where, counts)
    return Frame(frame_id, depth, label, K, cls_ids, poses, color)


def write_frame(
    root: str | Path,
    frame_id: str,
    depth_m: np.ndarray,
    label: np.ndarray,
    K: np.ndarray,
    cls_ids: np.ndarray,
    poses: np.ndarray,
    depth_factor: float = DEPTH_FACTOR_YCB,
    color: np.ndarray | None = None,
    extra_meta: dict[str, np.ndarray] | None = None,
) -> None:
    """Write one frame in the YCB-Video layout under ``root/data/SEQ/``.

    Writes ``FRAME-depth.png`` (uint16, ``round(depth_m * depth_factor)``), ``FRAME-label.png``
    (uint8), ``FRAME-color.png`` if color is given, and last ``FRAME-meta.mat`` (cls_indexes
    (N, 1), poses (3, 4, N), intrinsic_matrix, factor_depth). Each file is written to a
    temporary name and renamed, so a frame whose meta exists is complete. Reading it back with
    :meth:`YCBVideo.frame` returns the same arrays (depth to within 0.5 / depth_factor).

    Args:
        root: dataset root.
        frame_id: "SEQ/FRAME".
        depth_m: (H, W) depth in metres, 0 = no reading; at most 65535 / depth_factor.
        label: (H, W) integer class ids, 0 = background.
        K: (3, 3) intrinsics.
        cls_ids: (N,) 1-based class ids, unique.
        poses: (N, 3, 4) object->camera ``[R | t]``, metres.
        depth_factor: depth PNG units per metre.
        color: optional (H, W, 3) uint8 RGB.
        extra_meta: more ``meta.mat`` fields after the standard ones (the synthetic frames'
            ``alone_pixels``); a standard field's name is refused.
    """
    if not _FRAME_ID.match(frame_id):
        raise ValueError(f"frame_id {frame_id!r} is not 'SEQ/FRAME'")
    clash = sorted(
        set(extra_meta or {}) & {"cls_indexes", "poses", "intrinsic_matrix", "factor_depth"}
    )
    if clash:
        raise ValueError(f"write_frame: extra_meta may not replace the fields {clash}")
    depth_m = np.asarray(depth_m, dtype=np.float64)
    label = np.asarray(label)
    if depth_m.ndim != 2:
        raise ValueError(f"depth_m has shape {depth_m.shape}, expected (H, W)")
    if label.shape != depth_m.shape:
        raise ValueError(f"label has shape {label.shape}, expected depth's {depth_m.shape}")
    if not np.isfinite(depth_m).all() or depth_m.min(initial=0) < 0:
        raise ValueError("depth_m must be finite and >= 0 (0 = no reading)")
    raw = np.round(depth_m * depth_factor)
    if raw.max(initial=0) > 65535:
        raise ValueError(
            f"depth_m reaches {depth_m.max():.3f} m, more than uint16 holds at factor "
            f"{depth_factor} ({65535 / depth_factor:.3f} m)"
        )
    if label.min(initial=0) < 0 or label.max(initial=0) > 255:
        raise ValueError("label ids must lie in 0..255 (uint8)")
    K = _check_K(K, "write_frame: K")
    cls = _check_cls_ids(np.asarray(cls_ids), 255, "write_frame: cls_ids")
    poses = _check_poses(poses, len(cls), "write_frame: poses")
    _check_label_vs_classes(label.astype(np.uint8), cls, 255, "write_frame: label")
    if color is not None:
        color = np.asarray(color)
        if color.shape != (*depth_m.shape, 3) or color.dtype != np.uint8:
            raise ValueError(
                f"color has shape {color.shape} and dtype {color.dtype}, expected "
                f"{(*depth_m.shape, 3)} uint8"
            )
    seq, name = frame_id.split("/")
    d = Path(root) / "data" / seq
    d.mkdir(parents=True, exist_ok=True)
    depth_img = Image.fromarray(raw.astype(np.uint16))
    atomic_write(d / f"{name}-depth.png", lambda p: depth_img.save(p, format="PNG"))
    label_img = Image.fromarray(label.astype(np.uint8), mode="L")
    atomic_write(d / f"{name}-label.png", lambda p: label_img.save(p, format="PNG"))
    if color is not None:
        color_img = Image.fromarray(color, mode="RGB")
        atomic_write(d / f"{name}-color.png", lambda p: color_img.save(p, format="PNG"))
    meta = {
        "cls_indexes": cls.reshape(-1, 1).astype(np.float64),
        "poses": np.moveaxis(poses, 0, 2),
        "intrinsic_matrix": K,
        "factor_depth": np.array([[float(depth_factor)]]),
    }
    meta.update(extra_meta or {})
    atomic_write(
        d / f"{name}-meta.mat",
        lambda p: scipy.io.savemat(p, meta, do_compression=True, format="5"),
    )


# --------------------------------------------------------------------------- dataset


class ModelPointSets:
    """The toolbox model point sets of a dataset's classes, read once each: what a dataset
    reader (:class:`YCBVideo`, :class:`cloudpose.data.bop.BOPYcbv`) shares. Needs ``classes``
    (names, class id = index + 1), ``models_root`` (``NAME/points.xyz`` below it) and an empty
    dict ``_points``."""

    classes: list[str]
    models_root: Path
    _points: dict[int, np.ndarray]

    def _check_cls(self, cls_id: int) -> int:
        if not 1 <= int(cls_id) <= len(self.classes):
            raise ValueError(f"class id {cls_id} out of range, expected 1..{len(self.classes)}")
        return int(cls_id)

    def model_points(self, cls_id: int) -> np.ndarray:
        """(P, 3) float64 model points (metres, the toolbox's model frame) of class ``cls_id``
        (cached, read-only)."""
        c = self._check_cls(cls_id)
        if c not in self._points:
            pts = load_model_points(self.models_root / self.classes[c - 1] / "points.xyz")
            pts.setflags(write=False)
            self._points[c] = pts
        return self._points[c]

    def models(self) -> dict[int, np.ndarray]:
        """Model points of every class: {class id: (P, 3) float64 metres}."""
        return {c: self.model_points(c) for c in range(1, len(self.classes) + 1)}


class YCBVideo(ModelPointSets):
    """A dataset root in the YCB-Video layout (real or synthetic).

    Args:
        root: dataset root (holds ``data/``, ``keyframe.txt``, ``image_sets/``).
        models_root: folder of ``NAME/points.xyz``; used when ``root/models`` does not exist.
            Default: the 21 model point sets shipped in ``cloudpose/resources/models``.

    Attributes:
        classes: class names; index i -> class id i + 1. From ``root/classes.txt`` when
            present, else the packaged ``resources/classes.txt``.
        degenerate_counts: degenerate-but-legal cases seen by this dataset's reads, by kind.
    """

    def __init__(self, root: str | Path, models_root: str | Path | None = None) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"{self.root}: dataset root not found")
        cls_file = self.root / "classes.txt"
        self.classes: list[str] = load_classes(
            cls_file if cls_file.is_file() else resource_path("classes.txt")
        )
        if (self.root / "models").is_dir():
            self.models_root = self.root / "models"
        elif models_root is not None:
            self.models_root = Path(models_root)
            if not self.models_root.is_dir():
                raise FileNotFoundError(f"{self.models_root}: models folder not found")
        else:
            self.models_root = resource_path("models")
        self._points: dict[int, np.ndarray] = {}
        self.degenerate_counts: Counter[str] = Counter()

    def image_set(self, name: str) -> list[str]:
        """Frame ids "SEQ/FRAME" of a split: ``image_sets/NAME.txt``, ``keyframe.txt`` for
        name "keyframe", or every frame with a meta file under ``data/`` for name "all"."""
        if name == "keyframe":
            return _read_lines(self.root / "keyframe.txt", "keyframe list")
        if name == "all":
            frames = sorted(
                f"{p.parent.name}/{p.name[: -len('-meta.mat')]}"
                for p in (self.root / "data").glob("*/*-meta.mat")
            )
            if not frames:
                raise FileNotFoundError(
                    f"{self.root / 'data'}: no frames (SEQ/FRAME-meta.mat) found"
                )
            return frames
        return _read_lines(self.root / "image_sets" / f"{name}.txt", f"image set {name!r}")

    def frame_paths(self, frame_id: str) -> dict[str, Path]:
        """Paths of a frame's files: keys depth, label, meta, color."""
        if not _FRAME_ID.match(frame_id):
            raise ValueError(f"frame id {frame_id!r} is not 'SEQ/FRAME'")
        seq, name = frame_id.split("/")
        d = self.root / "data" / seq
        return {
            k: d / f"{name}-{k}.{'mat' if k == 'meta' else 'png'}"
            for k in ("depth", "label", "meta", "color")
        }

    def content_files(self, frame_id: str) -> list[Path]:
        """The files a frame's segments are made from (depth, label, meta), for content keys.

        Raises:
            FileNotFoundError: one of them is missing.
        """
        paths = self.frame_paths(frame_id)
        for kind in ("depth", "label", "meta"):
            if not paths[kind].is_file():
                raise FileNotFoundError(f"{paths[kind]}: {kind} file of frame {frame_id} not found")
        return [paths["depth"], paths["label"], paths["meta"]]

    def model_files(self) -> list[Path]:
        """Every class's model point file, ``models_root/NAME/points.xyz`` (for content keys)."""
        return [self.models_root / n / "points.xyz" for n in self.classes]

    def depth_unit_setting(self, scene: str) -> tuple[str, str, str]:
        """(where, setting, meaning) of the depth unit of scene (video) ``scene``, for the unit
        check's message (:func:`cloudpose.data.segments.check_depth_scale`)."""
        return (
            str(self.root / "data" / scene),
            "factor_depth in its -meta.mat files",
            "depth units per metre; YCB-Video 10000, millimetres 1000",
        )

    def alone_pixels(self, frame_id: str) -> np.ndarray | None:
        """(N,) pixels of each instance rendered alone, as the synthetic meta stores them
        (``alone_pixels``); None when the meta has no such field (real frames)."""
        meta = scipy.io.loadmat(self.frame_paths(frame_id)["meta"], variable_names=["alone_pixels"])
        return np.asarray(meta["alone_pixels"]).reshape(-1) if "alone_pixels" in meta else None

    def frame(self, frame_id: str, with_color: bool = False) -> Frame:
        """Read one annotated frame ("SEQ/FRAME") with its ground truth."""
        p = self.frame_paths(frame_id)
        return read_frame(
            p["depth"],
            p["label"],
            meta_mat=p["meta"],
            color_png=p["color"] if with_color else None,
            frame_id=frame_id,
            num_classes=len(self.classes),
            counts=self.degenerate_counts,
        )
