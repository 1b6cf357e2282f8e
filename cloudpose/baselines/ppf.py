"""Point-pair features (Drost et al., CVPR 2010) with OpenCV's ``ppf_match_3d``.

Per model, once: normals from the model points (``computeNormalsPC3d``, turned outwards from
the model's centre), then ``PPF3DDetector.trainModel``: every pair of subsampled model points
is hashed by its feature (distance, the angles of both normals to the pair's line and to each
other), quantised relative to the model's diameter. Per segment: normals turned towards the
camera, ``match`` votes over pairs from every ``scene_sample_step``-th reference point, giving
one pose (model -> camera) and its votes per reference point.

Those poses are clustered here (:func:`cluster_poses`), not by OpenCV: OpenCV merges every pose
within ``relative_sampling_step`` *scene units* of a cluster's first one, whatever its rotation
(its default rotation threshold, ``360 / angle_step`` with the step in radians, is ~30 rad),
and averages their quaternions, which in metres (5 cm) turns a segment's poses into one of
right translation and arbitrary rotation. Python cannot set OpenCV's thresholds, so the points
go in in millimetres (:data:`UNITS_PER_METRE`), where 0.05 mm merges nothing and ``match``
returns the raw poses; everything else in OpenCV's matcher is relative to the model's size.

OpenCV's matcher draws no random numbers, so the seed changes nothing; it is kept for the
common interface.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from cloudpose.baselines.base import (
    BaselineSettings,
    NotRegistered,
    PoseEstimate,
    check_segment,
)
from cloudpose.metrics import rotation_error_deg

UNITS_PER_METRE = 1000.0
"""Points go to OpenCV in millimetres: its pose clustering (which ignores rotation) then merges
only poses within 0.05 mm, i.e. none (see the module docstring)."""


def _cv2():
    try:
        import cv2
    except ImportError as exc:  # pragma: no cover - a dependency of the package
        raise ImportError(
            "the ppf baseline needs OpenCV's contrib modules: pip install "
            "opencv-contrib-python-headless"
        ) from exc
    if not hasattr(cv2, "ppf_match_3d_PPF3DDetector"):
        raise ImportError(
            "this OpenCV has no ppf_match_3d (contrib) module: pip install "
            "opencv-contrib-python-headless (not opencv-python)"
        )
    return cv2


def cluster_poses(
    R: np.ndarray, t: np.ndarray, votes: np.ndarray, max_dist: float, max_deg: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """Drost et al.'s pose clustering: the best-supported pose of many hypotheses.

    In order of votes, each pose joins the first cluster whose first (best) pose is within
    ``max_dist`` and ``max_deg`` of it, or starts one; the cluster of most summed votes wins,
    and its pose is the vote-weighted mean of its members (chordal mean of the rotations).

    Args:
        R: (n, 3, 3) rotations, model -> camera.
        t: (n, 3) translations, metres.
        votes: (n,) votes of each pose.
        max_dist: translation threshold, metres.
        max_deg: rotation threshold, degrees.

    Returns:
        Rotation (3, 3), translation (3,) and the winning cluster's summed votes.
    """
    w = np.asarray(votes, dtype=np.float64)
    order = np.argsort(-w, kind="stable")
    heads: list[int] = []
    label = np.empty(len(w), dtype=np.int64)
    for i in order:
        if heads:
            h = np.asarray(heads)
            near = (np.linalg.norm(t[h] - t[i], axis=1) < max_dist) & (
                rotation_error_deg(R[h], R[i]) < max_deg
            )
            if near.any():
                label[i] = int(np.argmax(near))
                continue
        label[i] = len(heads)
        heads.append(int(i))
    score = np.bincount(label, weights=w, minlength=len(heads))
    best = label == int(np.argmax(score))
    wb = w[best] if w[best].sum() > 0 else np.ones(int(best.sum()))
    R_mean = Rotation.from_matrix(R[best]).mean(weights=wb).as_matrix()
    t_mean = (wb[:, None] * t[best]).sum(axis=0) / wb.sum()
    return R_mean, t_mean, float(score.max())


def _with_normals(points: np.ndarray, k: int, viewpoint: np.ndarray | None) -> np.ndarray:
    """(N, 6) float32 points and unit normals, towards ``viewpoint`` or else outwards."""
    cv2 = _cv2()
    pts = np.ascontiguousarray(points, dtype=np.float32)
    flip = viewpoint is not None
    vp = (viewpoint if flip else np.zeros(3)).astype(np.float64)
    _, pn = cv2.ppf_match_3d.computeNormalsPC3d(pts, k, flip, tuple(vp))
    pn = np.asarray(pn, dtype=np.float32).reshape(-1, 6)
    if not flip:  # outwards: away from the centre of a closed surface
        out = np.einsum("ij,ij->i", pn[:, 3:], pn[:, :3] - pn[:, :3].mean(axis=0)) < 0
        pn[out, 3:] *= -1
    return np.ascontiguousarray(pn)


class PPFEstimator:
    """PPF voting for a set of models (class id -> (P, 3) points, metres)."""

    def __init__(
        self, models_by_class: dict[int, np.ndarray], settings: BaselineSettings, seed: int = 1
    ) -> None:
        self.settings = settings
        self.seed = int(seed)
        self.calls = 0  # draws no random numbers: kept for the common interface
        self._models = {int(c): np.asarray(m, dtype=np.float64) for c, m in models_by_class.items()}
        self._detectors: dict[int, object] = {}
        # bounding-box diagonals, metres: OpenCV's "diameter" (its steps are relative to it)
        self._diameters = {
            c: float(np.linalg.norm(m.max(axis=0) - m.min(axis=0))) for c, m in self._models.items()
        }

    def _detector(self, cls_id: int):
        if cls_id not in self._detectors:
            cv2 = _cv2()
            s = self.settings
            model = _with_normals(
                self._models[cls_id] * UNITS_PER_METRE, s["normal_neighbours"], None
            )
            det = cv2.ppf_match_3d_PPF3DDetector(
                s["relative_sampling_step"], s["relative_distance_step"]
            )
            det.trainModel(model)
            self._detectors[cls_id] = det
        return self._detectors[cls_id]

    def prepare(self, cls_ids) -> None:
        """Train these classes' detectors now (else on first use; 5-35 s each on one core)."""
        for c in cls_ids:
            self._detector(int(c))

    def estimate(self, points: np.ndarray, cls_id: int) -> PoseEstimate:
        """Pose model -> camera of class ``cls_id`` from its segment (N, 3), metres."""
        s = self.settings
        pts = check_segment(points, cls_id, self._models, s["min_points"])
        det = self._detector(int(cls_id))
        scene = _with_normals(pts * UNITS_PER_METRE, s["normal_neighbours"], np.zeros(3))
        results = det.match(scene, s["scene_sample_step"], s["relative_scene_distance"])
        if not results:
            raise NotRegistered(f"segment of class {cls_id}: PPF found no pose ({len(pts)} points)")
        T = np.stack([np.asarray(r.pose, dtype=np.float64) for r in results])
        votes = np.array([r.numVotes for r in results], dtype=np.float64)
        R, t, score = cluster_poses(
            T[:, :3, :3],
            T[:, :3, 3] / UNITS_PER_METRE,
            votes,
            s["cluster_distance"] * self._diameters[int(cls_id)],
            s["cluster_degrees"],
        )
        return PoseEstimate(R, t, score)
