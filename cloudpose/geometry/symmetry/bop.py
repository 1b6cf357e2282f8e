"""BOP's symmetries (``models_info.json``) against the packaged table."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cloudpose.geometry.rigid import rotation_error_deg
from cloudpose.geometry.symmetry.table import ClassSymmetry, close_group, load_symmetries


def symmetry_from_bop(entry: dict, where: str = "models_info.json") -> ClassSymmetry:
    """One ``models_info.json`` entry's symmetries as a :class:`ClassSymmetry` (rotations only).

    BOP lists ``symmetries_discrete`` as row-major 4x4 matrices (16 numbers, translation in
    mm, the identity left out) and ``symmetries_continuous`` as ``{axis, offset}``; a can whose
    ends look alike has one continuous axis and the discrete flip. The translations and
    offsets (where each turn's centre lies relative to BOP's model origin, the bounding-box
    centre, :func:`cloudpose.data.bop.model_origin`) are left out, as the table's rotation
    errors leave them out.

    Raises:
        ValueError: naming ``where``: a discrete entry that is not 16 numbers forming a
            rotation, or a continuous entry without a 3-number axis.
    """
    rots = [np.eye(3)]
    for i, m in enumerate(entry.get("symmetries_discrete", [])):
        M = np.asarray(m, dtype=np.float64).reshape(-1)
        if M.size != 16:
            raise ValueError(f"{where}: symmetries_discrete[{i}] has {M.size} numbers, expected 16")
        R = M.reshape(4, 4)[:3, :3]
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
            raise ValueError(f"{where}: symmetries_discrete[{i}] is not a rotation")
        rots.append(R)
    axis, flip = None, False
    cont = entry.get("symmetries_continuous", [])
    if cont:
        a = np.asarray(cont[0].get("axis", []), dtype=np.float64).reshape(-1)
        if a.size != 3 or not np.linalg.norm(a) > 0:
            raise ValueError(f"{where}: symmetries_continuous[0] axis {a.tolist()}, expected 3")
        axis = a / np.linalg.norm(a)
        # a discrete turn that reverses the axis is the flip; the others turn about it
        flip = any(float(axis @ R @ axis) < -0.5 for R in rots[1:])
        rots = [np.eye(3)]
    return ClassSymmetry(close_group(rots), axis, flip, np.zeros(3))


def _same_rotations(A: np.ndarray, B: np.ndarray, tol_deg: float) -> bool:
    def covered(X, Y):
        return all(min(rotation_error_deg(x[None], y[None])[0] for y in Y) <= tol_deg for x in X)

    return covered(A, B) and covered(B, A)


def bop_symmetry_disagreements(
    models_info: dict, class_names: list[str], tol_deg: float = 5.0, table: int = 2
) -> list[str]:
    """Where the versioned table and BOP's ``models_info.json`` disagree about symmetries.

    Args:
        models_info: the parsed ``models_info.json`` ({obj_id: entry}); obj_id i is the class
            ``class_names[i - 1]`` (BOP ycbv numbers the YCB-Video classes in their order).
        class_names: the dataset's class names.
        tol_deg: rotations (and continuous axes) closer than this are the same.
        table: the version of the symmetry table to compare.

    Returns:
        One line per class whose symmetries differ (kind, axis, flip, or the set of discrete
        rotations), naming both descriptions; empty when they agree. Objects the table does
        not know are reported too.
    """
    table = load_symmetries(table)
    out = []
    for key in sorted(models_info, key=lambda k: int(k)):
        i = int(key)
        name = class_names[i - 1] if 1 <= i <= len(class_names) else None
        theirs = symmetry_from_bop(models_info[key], f"models_info.json, obj {i}")
        if name is None or name not in table:
            out.append(f"obj {i}: not in the symmetry table (BOP: {theirs.describe()})")
            continue
        ours = table[name]
        why = ""
        if ours.kind != theirs.kind:
            why = "kind"
        elif ours.axis is not None:
            cos = abs(float(ours.axis @ theirs.axis))
            if cos < np.cos(np.radians(tol_deg)):
                why = "axis"
            elif ours.flip != theirs.flip:
                why = "flip"
        elif not _same_rotations(ours.discrete, theirs.discrete, tol_deg):
            why = "rotations"
        if why:
            out.append(
                f"{name} (obj {i}): different {why}: table {ours.describe()}"
                f"{_axis_text(ours)}, BOP {theirs.describe()}{_axis_text(theirs)}"
            )
    return out


def bop_disagreements_at(
    bop: Path, class_names: list[str], table: int = 2
) -> tuple[Path, list[str]]:
    """:func:`bop_symmetry_disagreements` of a BOP ycbv root's ``models/models_info.json`` (or
    that file itself) against table ``table``: ``(the file read, one line per class)``.

    Raises:
        FileNotFoundError: no ``models_info.json`` there.
    """
    path = bop / "models" / "models_info.json" if bop.is_dir() else bop
    if not path.is_file():
        raise FileNotFoundError(f"{path}: BOP models_info.json not found")
    return path, bop_symmetry_disagreements(json.loads(path.read_text()), class_names, table=table)


def _axis_text(s: ClassSymmetry) -> str:
    return f" {np.round(s.axis, 3).tolist()}" if s.axis is not None else ""
