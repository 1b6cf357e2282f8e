"""The symmetry tables: detection from the model points, the packaged JSON files, and lookup
by class (the package doc, :mod:`cloudpose.geometry.symmetry`, describes both versions)."""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import NamedTuple

import numpy as np

from cloudpose.config import SYMMETRY_TABLE_VERSIONS
from cloudpose.conventions import packaged_classes, resource_path
from cloudpose.geometry.rigid import rotation_error_deg

SYMMETRY_TABLES = {
    v: resource_path("symmetries.json" if v == 1 else f"symmetries-v{v}.json")
    for v in SYMMETRY_TABLE_VERSIONS
}
"""Table version -> packaged file: class name -> discrete rotations (rotation vectors, degrees),
continuous axis, flip and centre."""

SYMMETRY_FILE = SYMMETRY_TABLES[1]
"""The version-1 table (the committed cpu results' loss and metrics)."""

TOLERANCE = 0.06
"""Version 1: a rotation is a symmetry when the 95th percentile of nearest-point distances is
<= this fraction of the model's diameter."""

TOLERANCE_P99 = 0.10
"""Version 2 also asks the 99th percentile to be <= this fraction of the diameter."""

_AXES = np.eye(3)


def rotvec_deg_to_rotmat(v: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(np.asarray(v, dtype=np.float64))).as_matrix()


@dataclass(frozen=True)
class ClassSymmetry:
    """The symmetries of one object class.

    Attributes:
        discrete: (G, 3, 3) proper rotations in the model frame, identity first; (1, 3, 3)
            for an object with no discrete symmetry (and always with a continuous one).
        axis: (3,) unit axis of a continuous symmetry in the model frame, or None.
        flip: with ``axis``: the 180 degree turn reversing the axis is a symmetry too.
        centre: (3,) the point the symmetries fix (bounding-box centre), metres.
    """

    discrete: np.ndarray
    axis: np.ndarray | None
    flip: bool
    centre: np.ndarray

    @property
    def kind(self) -> str:
        """ "continuous", "discrete" or "none"."""
        if self.axis is not None:
            return "continuous"
        return "discrete" if len(self.discrete) > 1 else "none"

    def describe(self) -> str:
        """One phrase, e.g. ``continuous about z, with flip`` or ``discrete, 4 rotations``."""
        if self.axis is not None:
            name = "xyz"[int(np.argmax(np.abs(self.axis)))]
            return f"continuous about {name}" + (", with flip" if self.flip else "")
        if len(self.discrete) > 1:
            return f"discrete, {len(self.discrete)} rotations"
        return "none"


def close_group(gens: list[np.ndarray]) -> np.ndarray:
    """All products of ``gens`` (a finite rotation group), identity first; (G, 3, 3)."""
    group = [np.eye(3)]
    frontier = list(group)
    while frontier:
        new = []
        for A, B in itertools.product(frontier, gens):
            C = A @ B
            if not any(np.allclose(C, G, atol=1e-6) for G in group + new):
                new.append(C)
        group += new
        frontier = new
        if len(group) > 48:  # the largest finite group of the cube; more means a bad generator
            raise ValueError(f"symmetry generators do not close into a finite group: {len(group)}")
    return np.stack(group)


def _residual(
    points: np.ndarray, tree, R: np.ndarray, centre: np.ndarray, diam: float
) -> tuple[float, float]:
    """The 95th and 99th percentiles of the nearest-point distances of the model rotated by R
    about centre, as fractions of the diameter."""
    d, _ = tree.query((points - centre) @ R.T + centre)
    p95, p99 = np.percentile(d, [95, 99]) / diam
    return float(p95), float(p99)


def check_table_version(version: int, where: str = "loss.symmetry_table") -> int:
    """``version`` if it names a packaged table, else ``ValueError`` listing the valid ones."""
    if version not in SYMMETRY_TABLES:
        raise ValueError(f"{where}={version!r}: expected one of {sorted(SYMMETRY_TABLES)}")
    return version


def detect_symmetry(
    points: np.ndarray, tolerance: float = TOLERANCE, version: int = 2
) -> ClassSymmetry:
    """Find the symmetries of a model point set (the module doc describes both versions).

    Args:
        points: (P, 3) model points, metres.
        tolerance: largest accepted 95th-percentile residual, as a fraction of the diameter.
        version: the table version whose candidates and test to apply.

    Returns:
        The detected :class:`ClassSymmetry`.
    """
    from scipy.spatial import cKDTree

    check_table_version(version, "symmetry table version")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 10:
        raise ValueError(f"points: expected shape (P >= 10, 3), got {points.shape}")
    limits = (tolerance, TOLERANCE_P99 if version >= 2 else np.inf)
    lo, hi = points.min(0), points.max(0)
    box_centre, diam = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    tree = cKDTree(points)
    frames = [_AXES]
    centres = [box_centre]
    if version >= 2:
        centred = points - points.mean(0)
        _, principal = np.linalg.eigh(centred.T @ centred)  # columns: principal axes
        frames.append(principal.T)
        centres.append(points.mean(0))
    best, best_rank = None, -1
    for axes in frames:
        for centre in centres:
            found = _symmetry_about(points, tree, axes, centre, diam, limits)
            # a continuous symmetry (with flip) outranks any finite group
            rank = 1000 + found.flip if found.axis is not None else len(found.discrete)
            if rank > best_rank:
                best, best_rank = found, rank
    return best


def _symmetry_about(
    points: np.ndarray,
    tree,
    axes: np.ndarray,
    centre: np.ndarray,
    diam: float,
    limits: tuple[float, float],
) -> ClassSymmetry:
    """The symmetries whose axes are the rows of ``axes`` (orthonormal), through ``centre``;
    ``limits``: the largest accepted 95th and 99th percentile residuals."""

    def sym(axis: np.ndarray, deg: float) -> bool:
        p95, p99 = _residual(points, tree, rotvec_deg_to_rotmat(axis * deg), centre, diam)
        return p95 <= limits[0] and p99 <= limits[1]

    for i, a in enumerate(axes):
        if all(sym(a, deg) for deg in np.linspace(17.0, 343.0, 7)):
            flip = any(sym(axes[j], 180.0) for j in range(3) if j != i)
            return ClassSymmetry(np.eye(3)[None], a.copy(), flip, centre)
    gens = [rotvec_deg_to_rotmat(a * deg) for a in axes for deg in (90.0, 180.0) if sym(a, deg)]
    return ClassSymmetry(close_group(gens), None, False, centre)


def symmetry_to_json(s: ClassSymmetry) -> dict:
    """The table entry of one class (rotations as rotation vectors in degrees, rounded)."""
    from scipy.spatial.transform import Rotation

    rotvecs = _canonical_rotvecs(np.degrees(Rotation.from_matrix(s.discrete).as_rotvec()))
    return {
        "kind": s.kind,
        "discrete_rotvec_deg": rotvecs.tolist(),
        "axis": None if s.axis is None else s.axis.tolist(),
        "flip": s.flip,
        "centre_m": np.round(s.centre, 6).tolist(),
    }


def _canonical_rotvecs(rotvecs_deg: np.ndarray) -> np.ndarray:
    """(G, 3) rotation vectors in degrees, rounded to 1e-6, with each half turn written one
    way: ``v`` and ``-v`` of angle 180 are the same rotation, and which one an eigen-solver or
    SVD returns depends on the CPU's kernels; the largest component of a half turn is made
    positive."""
    v = np.asarray(rotvecs_deg, dtype=np.float64).copy()
    half = np.abs(np.linalg.norm(v, axis=1) - 180.0) < 1e-3
    big = v[np.arange(len(v)), np.abs(v).argmax(axis=1)]
    v[half & (big < 0)] *= -1.0
    return v.round(6) + 0.0


def table_differences(a: dict, b: dict, tol_deg: float = 1e-3, tol_m: float = 1e-6) -> list[str]:
    """Where two symmetry tables (as :func:`build_table` returns or the packaged JSON holds)
    describe different symmetries: one line per difference, empty when they agree.

    Rotations are compared as rotations (geodesic distance <= ``tol_deg``, as sets, in any
    order and either sign of a half turn), axes up to sign, centres within ``tol_m``: what a
    table means, not its digits, which differ in the last places between CPUs.
    """
    out = [
        f"{k}: {a.get(k)!r} != {b.get(k)!r}"
        for k in ("version", "tolerance", "tolerance_p99")
        if a.get(k) != b.get(k)
    ]
    ca, cb = a.get("classes", {}), b.get("classes", {})
    out += [f"{n}: in one table only" for n in sorted(set(ca) ^ set(cb))]
    for name in sorted(set(ca) & set(cb)):
        x, y = symmetry_from_json(ca[name]), symmetry_from_json(cb[name])
        if (x.axis is None) != (y.axis is None) or x.flip != y.flip:
            out.append(f"{name}: kind or flip differs ({x.describe()} vs {y.describe()})")
            continue
        if x.axis is not None and abs(float(x.axis @ y.axis)) < np.cos(np.radians(tol_deg)):
            out.append(f"{name}: axis {x.axis.tolist()} vs {y.axis.tolist()}")
        if np.abs(x.centre - y.centre).max() > tol_m:
            out.append(f"{name}: centre {x.centre.tolist()} vs {y.centre.tolist()}")
        err = rotation_error_deg(  # (Gx, Gy): every rotation of x against every one of y
            np.repeat(x.discrete, len(y.discrete), 0), np.tile(y.discrete, (len(x.discrete), 1, 1))
        ).reshape(len(x.discrete), len(y.discrete))
        if (
            len(x.discrete) != len(y.discrete)
            or err.min(1).max() > tol_deg
            or err.min(0).max() > tol_deg
        ):
            out.append(
                f"{name}: discrete rotations differ ({len(x.discrete)} vs {len(y.discrete)})"
            )
    return out


def symmetry_from_json(entry: dict) -> ClassSymmetry:
    """Inverse of :func:`symmetry_to_json`."""
    rots = np.stack([rotvec_deg_to_rotmat(v) for v in entry["discrete_rotvec_deg"]])
    axis = None if entry["axis"] is None else np.asarray(entry["axis"], dtype=np.float64)
    return ClassSymmetry(rots, axis, bool(entry["flip"]), np.asarray(entry["centre_m"]))


@cache
def load_symmetries(table: int = 1) -> dict[str, ClassSymmetry]:
    """Class name -> :class:`ClassSymmetry`, from the packaged table of version ``table``."""
    path = SYMMETRY_TABLES[check_table_version(table, "symmetry table version")]
    raw = json.loads(path.read_text())
    if raw.get("version") != table or "classes" not in raw:
        raise ValueError(f"{path}: expected a symmetry table of version {table} with 'classes'")
    return {name: symmetry_from_json(e) for name, e in raw["classes"].items()}


def symmetries_for(class_names: list[str], table: int = 1) -> list[ClassSymmetry]:
    """The entries of table version ``table`` for 1-based class ids ``1..k`` named
    ``class_names``; a class the table does not know (a user's own object) gets no symmetry."""
    table = load_symmetries(table)
    none = ClassSymmetry(np.eye(3)[None], None, False, np.zeros(3))
    return [table.get(name, none) for name in class_names]


def build_table(class_names: list[str], version: int = 1) -> dict:
    """The symmetry table of the packaged models, as written to ``SYMMETRY_TABLES[version]``."""
    classes = {}
    for name in class_names:
        points = np.loadtxt(resource_path("models", name, "points.xyz"))
        classes[name] = symmetry_to_json(detect_symmetry(points, version=version))
    return {
        "version": version,
        "tolerance": TOLERANCE,
        **({"tolerance_p99": TOLERANCE_P99} if version >= 2 else {}),
        "made_by": "cloudpose symmetries "
        + ("--write" if version == 1 else f"--table {version} --write")
        + " (cloudpose.geometry.symmetry.detect_symmetry)",
        "classes": classes,
    }


class TableSync(NamedTuple):
    """What :func:`sync_table` did: the packaged file, the table built from the models, and
    whether it was written (else checked)."""

    path: Path
    table: dict
    written: bool


def sync_table(version: int, write: bool = False) -> TableSync:
    """Build table ``version`` from the packaged models and write it to its packaged file, or
    check that the file holds exactly that (``cloudpose symmetries [--write]``).

    Raises:
        ValueError: an unknown version, or (checking) a file that differs, naming it.
    """
    path = SYMMETRY_TABLES[check_table_version(version, "--table")]
    table = build_table(packaged_classes(), version)
    text = json.dumps(table, indent=1) + "\n"
    if write:
        path.write_text(text)
    elif not path.is_file():
        raise ValueError(f"{path} not found; run with --write")
    else:
        diff = table_differences(json.loads(path.read_text()), json.loads(text))
        if diff:
            raise ValueError(
                f"{path} differs from the models' symmetries ({'; '.join(diff[:3])}); "
                "run with --write"
            )
    return TableSync(path, table, write)
