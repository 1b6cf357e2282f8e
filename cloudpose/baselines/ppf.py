"""Point-pair features (Drost et al., CVPR 2010) with OpenCV's ``ppf_match_3d``.

Per model, once: normals from the model points (``computeNormalsPC3d``, turned outwards from
the model's centre), then ``PPF3DDetector.trainModel``: every pair of subsampled model points
is hashed by its feature (distance, the angles of both normals to the pair's line and to each
other), quantised relative to the model's diameter. Per segment: normals turned towards the
camera, ``match`` votes over pairs from every ``scene_sample_step``-th reference point, and the
pose with the most votes (after OpenCV's pose clustering) is the estimate, model -> camera.

OpenCV's matcher draws no random numbers, so the seed changes nothing; it is kept for the
common interface.
"""

from __future__ import annotations

import numpy as np

from cloudpose.baselines.base import (
    BaselineSettings,
    NotRegistered,
    PoseEstimate,
    check_segment,
)


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

    def _detector(self, cls_id: int):
        if cls_id not in self._detectors:
            cv2 = _cv2()
            s = self.settings
            model = _with_normals(self._models[cls_id], s["normal_neighbours"], None)
            det = cv2.ppf_match_3d_PPF3DDetector(
                s["relative_sampling_step"], s["relative_distance_step"]
            )
            det.trainModel(model)
            self._detectors[cls_id] = det
        return self._detectors[cls_id]

    def estimate(self, points: np.ndarray, cls_id: int) -> PoseEstimate:
        """Pose model -> camera of class ``cls_id`` from its segment (N, 3), metres."""
        s = self.settings
        pts = check_segment(points, cls_id, self._models, s["min_points"])
        det = self._detector(int(cls_id))
        scene = _with_normals(pts, s["normal_neighbours"], np.zeros(3))
        results = det.match(scene, s["scene_sample_step"], s["relative_scene_distance"])
        if not results:
            raise NotRegistered(f"segment of class {cls_id}: PPF found no pose ({len(pts)} points)")
        best = max(results, key=lambda r: r.numVotes)
        T = np.asarray(best.pose, dtype=np.float64)
        return PoseEstimate(T[:3, :3].copy(), T[:3, 3].copy(), float(best.numVotes))
