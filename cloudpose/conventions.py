"""Frames, units and the one vector convention used everywhere in cloudpose.

- Units: metres for every length (points, translations, depth after scaling), radians inside
  the code, degrees only in reported rotation errors.
- A pose (R, t) maps object (model) coordinates to camera coordinates with column vectors:
  ``p_cam = R @ p_model + t`` (bop_toolkit's ``R_m2c``, YCB-Video's ``poses[:, :, i]``).
  Batched points are row-major ``(..., N, 3)``, so in code this reads ``p @ R.mT + t``.
- Camera frame: OpenCV pinhole, x right, y down, z forward; pixel (u, v) = (column, row),
  ``u = fx * x / z + cx``, ``v = fy * y / z + cy``.
- Class ids are 1-based as in YCB-Video label images and ``cls_indexes`` (0 = background);
  one-hot network inputs use ``class_id - 1``: class id i is line i of a ``classes.txt``
  (:func:`load_classes`; the package's own list: :func:`packaged_classes`).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

DEPTH_FACTOR_YCB = 10000.0
"""YCB-Video depth PNG units per metre."""

YCB_INTRINSICS = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])
"""Intrinsics of YCB-Video camera 1 (used by sequences 0000-0059 and the keyframes)."""

IMAGE_SHAPE = (480, 640)
"""(height, width) of YCB-Video images."""


def resource_path(*parts: str) -> Path:
    """Path of a file shipped inside the package (model points, class list, paper tables)."""
    return Path(str(resources.files("cloudpose").joinpath("resources", *parts)))


def load_classes(path: str | Path) -> list[str]:
    """Read a ``classes.txt``: one class name per line, line i -> class id i + 1.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: it holds no class name, or a name twice.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: class list not found (expected classes.txt)")
    text = path.read_text(encoding="utf-8-sig")  # a byte order mark is no part of a name
    names = [line.strip() for line in text.splitlines() if line.strip()]
    if not names:
        raise ValueError(f"{path}: class list is empty (expected one class name per line)")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{path}: class names listed twice: {dup}")
    return names


def packaged_classes() -> list[str]:
    """The 21 YCB-Video class names the package ships models of, in class-id order."""
    return load_classes(resource_path("classes.txt"))


def transform_points(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Apply ``p_cam = R @ p + t`` to row-major points.

    Args:
        points: (..., N, 3) points in metres.
        R: (..., 3, 3) rotation.
        t: (..., 3) translation in metres.

    Returns:
        (..., N, 3) transformed points.
    """
    return points @ np.swapaxes(R, -1, -2) + t[..., None, :]
