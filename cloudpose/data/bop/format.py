"""The BOP ``ycbv`` layout's names and numbers (:mod:`cloudpose.data.bop`): split folders,
frame ids, the model origin, the results CSV header, and PLY model files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cloudpose.files import atomic_text

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
