"""What every baseline shares: its settings (from ``cloudpose/resources/registry/baselines.toml``), its result, and
the checks of its input."""

from __future__ import annotations

import hashlib
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from cloudpose.registry import BASELINES_FILE


@dataclass(frozen=True)
class BaselineSettings:
    """A method's settings: ``values`` as written in ``baselines.toml`` (without ``why``)."""

    method: str
    why: str
    values: dict[str, Any] = field(default_factory=dict)

    def with_overrides(self, overrides: dict[str, Any] | None) -> BaselineSettings:
        """These settings with some values replaced (each key must exist)."""
        unknown = sorted(set(overrides or {}) - set(self.values))
        if unknown:
            raise ValueError(
                f"baseline {self.method}: unknown settings {unknown}; "
                f"expected some of {sorted(self.values)}"
            )
        return BaselineSettings(self.method, self.why, {**self.values, **(overrides or {})})

    def __getitem__(self, key: str) -> Any:
        try:
            return self.values[key]
        except KeyError:
            raise KeyError(f"baselines.toml [baseline.{self.method}] has no {key!r}") from None


def load_settings(method: str, path: Path | None = None) -> BaselineSettings:
    """The settings of ``method`` from ``cloudpose/resources/registry/baselines.toml``."""
    raw = tomllib.loads((path or BASELINES_FILE).read_text())
    table = raw.get("baseline", {})
    if method not in table:
        raise ValueError(f"baseline method {method!r}: expected one of {', '.join(table)}")
    values = dict(table[method])
    return BaselineSettings(method, str(values.pop("why", "")), values)


class NotRegistered(ValueError):
    """A segment the method cannot register (too few points, no pose found): a miss, as a
    network's empty segment is. Any other error is a bug and is raised."""


def settings_fingerprint(settings: BaselineSettings) -> str:
    """16 hex digits of the method and its settings (MLflow tag ``config`` of a baseline run)."""
    text = json.dumps({"method": settings.method, **settings.values}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def is_current(run) -> bool:
    """Whether an MLflow baseline run was made with today's settings of its method."""
    variant = run.data.tags.get("variant", "")
    try:
        settings = load_settings(variant.removeprefix("baseline-"))
    except ValueError:
        return False
    return run.data.tags.get("config") == settings_fingerprint(settings)


@dataclass(frozen=True)
class PoseEstimate:
    """One estimate: rotation (3, 3) and translation (3,) model -> camera, metres, and the
    method's own score (inlier fitness for fpfh, votes for ppf; higher is better)."""

    R: np.ndarray
    t: np.ndarray
    score: float


class Estimator(Protocol):
    """A pose estimator for the models it was built with.

    ``calls`` counts the estimates that drew random numbers so far; each draw is seeded from
    the estimator's seed and this count, so a run that is stopped and resumed with the count
    restored gives the same poses as one that ran through.
    """

    calls: int

    def prepare(self, cls_ids) -> None:
        """Build the per-model state of these classes now (features, hash tables), so that
        :meth:`estimate` times only the per-segment work; otherwise it is built on first use."""
        ...

    def estimate(self, points: np.ndarray, cls_id: int) -> PoseEstimate:
        """Pose of class ``cls_id`` from its observed segment (N, 3), camera frame, metres."""
        ...


ROTATION_TOLERANCE = 1e-3
"""How far from orthonormal, with determinant 1, a kept estimate's rotation may be: a network's
float32 rotations are orthonormal to ~1e-6, a registration's to ~1e-12."""


def not_poses(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Per row, whether ``R`` (N, 3, 3), ``t`` (N, 3) metres is no pose at all: a value that is
    not finite, or a matrix that is not a rotation (``R^T R = I`` and ``det R = 1`` within
    :data:`ROTATION_TOLERANCE`; an all-zero matrix is not one). A check of estimates read back
    from a file, which the method could not have given."""
    R, t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    finite = np.isfinite(R).all(axis=(-2, -1)) & np.isfinite(t).all(axis=-1)
    Rf = np.where(finite[:, None, None], R, np.eye(3))
    gram = np.einsum("nji,njk->nik", Rf, Rf)  # (N, 3, 3) R^T R
    orthonormal = np.abs(gram - np.eye(3)).max(axis=(-2, -1)) <= ROTATION_TOLERANCE
    proper = np.abs(np.linalg.det(Rf) - 1.0) <= ROTATION_TOLERANCE
    return ~(finite & orthonormal & proper)


def check_segment(points: np.ndarray, cls_id: int, models: dict, min_points: int) -> np.ndarray:
    """(N, 3) float64 finite points of a segment, or a ValueError saying what is wrong."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"segment: expected points of shape (N, 3), got {pts.shape}")
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < min_points:
        raise NotRegistered(
            f"segment of class {cls_id}: {len(pts)} finite points, a baseline needs at least "
            f"{min_points} (min_points in cloudpose/resources/registry/baselines.toml)"
        )
    if int(cls_id) not in models:
        raise ValueError(f"class {cls_id}: no model points (have classes {sorted(models)})")
    return pts
