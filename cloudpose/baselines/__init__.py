"""Classical depth-only pose estimators: the answer without learning, on the same segments.

Each estimator takes what a network takes (one object's observed segment, camera frame, metres,
and its class) and returns a pose (model -> camera) and a score; evaluation then treats it
exactly as a network's estimate: the same ICP refinement after, the same per-instance errors.

- ``fpfh``: global registration with Open3D (Rusu et al., ICRA 2009): voxel-downsampled model
  and segment with normals, FPFH features, RANSAC over feature matches.
- ``ppf``: point-pair features (Drost et al., CVPR 2010), OpenCV's ``ppf_match_3d``: a hash
  table of the model's point pairs, votes of the segment's pairs.

Settings are data (``cloudpose/resources/registry/baselines.toml``), each with a one-line why.
"""

from __future__ import annotations

from cloudpose.baselines.base import (
    BaselineSettings,
    Estimator,
    NotRegistered,
    PoseEstimate,
    load_settings,
)
from cloudpose.baselines.fpfh import FPFHEstimator
from cloudpose.baselines.ppf import PPFEstimator

__all__ = [
    "METHODS",
    "BaselineSettings",
    "Estimator",
    "NotRegistered",
    "PoseEstimate",
    "load_settings",
    "make",
]

METHODS = ("fpfh", "ppf")


def make(
    method: str, models_by_class: dict, settings: BaselineSettings | None = None, seed: int = 1
) -> Estimator:
    """The estimator ``method`` (one of :data:`METHODS`) for these models."""
    settings = settings or load_settings(method)
    if method == "fpfh":
        return FPFHEstimator(models_by_class, settings, seed)
    if method == "ppf":
        return PPFEstimator(models_by_class, settings, seed)
    raise ValueError(f"baseline method {method!r}: expected one of {', '.join(METHODS)}")
