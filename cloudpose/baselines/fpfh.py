"""Global registration with FPFH features and RANSAC (Open3D), as in Open3D's global
registration tutorial and Rusu et al., ICRA 2009.

Per model, once: the model points voxel-downsampled, normals estimated and turned outwards
(away from the model's centre: the models are closed surfaces seen from outside), FPFH
features. Per segment: the same, with normals turned towards the camera (the origin), then
``registration_ransac_based_on_feature_matching`` from model to segment, whose transformation
is the pose model -> camera. RANSAC is seeded (``o3d.utility.random.seed``) per call from the
estimator's seed and a call counter, and runs on one thread: Open3D's RANSAC threads share one
random generator, so with several threads which sample goes to which hypothesis depends on their
scheduling (measured: 8 of 60 real segments got another pose in a second identical run on 2
threads). A run is then repeatable on any machine and seeds differ.
"""

from __future__ import annotations

import numpy as np

from cloudpose import runtime
from cloudpose.baselines.base import (
    BaselineSettings,
    NotRegistered,
    PoseEstimate,
    check_segment,
)


def _o3d():
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


class FPFHEstimator:
    """FPFH + RANSAC for a set of models (class id -> (P, 3) points, metres)."""

    def __init__(
        self, models_by_class: dict[int, np.ndarray], settings: BaselineSettings, seed: int = 1
    ) -> None:
        self.settings = settings
        self.seed = int(seed)
        self.calls = 0  # RANSAC runs so far: the seed of the next is derived from it
        self._models = {int(c): np.asarray(m, dtype=np.float64) for c, m in models_by_class.items()}
        self._prepared: dict[int, tuple] = {}

    def _features(self, points: np.ndarray, towards_camera: bool):
        o3d = _o3d()
        s = self.settings
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(points, np.float64)))
        pcd = pcd.voxel_down_sample(s["voxel"])
        pcd.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=s["normal_radius"], max_nn=30)
        )
        if towards_camera:
            pcd.orient_normals_towards_camera_location(np.zeros(3))
        else:  # outwards: away from the centre of a closed surface
            P, N = np.asarray(pcd.points), np.asarray(pcd.normals).copy()
            flip = np.einsum("ij,ij->i", N, P - P.mean(axis=0)) < 0
            N[flip] *= -1
            pcd.normals = o3d.utility.Vector3dVector(N)
        feat = o3d.pipelines.registration.compute_fpfh_feature(
            pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=s["feature_radius"], max_nn=100)
        )
        return pcd, feat

    def _model(self, cls_id: int):
        if cls_id not in self._prepared:
            self._prepared[cls_id] = self._features(self._models[cls_id], towards_camera=False)
        return self._prepared[cls_id]

    def prepare(self, cls_ids) -> None:
        """Features of these classes' models now (else on first use)."""
        for c in cls_ids:
            self._model(int(c))

    def estimate(self, points: np.ndarray, cls_id: int) -> PoseEstimate:
        """Pose model -> camera of class ``cls_id`` from its segment (N, 3), metres."""
        o3d = _o3d()
        reg = o3d.pipelines.registration
        s = self.settings
        pts = check_segment(points, cls_id, self._models, s["min_points"])
        model, model_feat = self._model(int(cls_id))
        seg, seg_feat = self._features(pts, towards_camera=True)
        if len(seg.points) < 3:
            raise NotRegistered(
                f"segment of class {cls_id}: {len(seg.points)} points after "
                f"the {s['voxel']} m voxel grid, need 3"
            )
        self.calls += 1
        o3d.utility.random.seed(self.seed * 1_000_003 + self.calls)
        d = s["ransac_distance"]
        with runtime.open3d_threads(1):
            res = reg.registration_ransac_based_on_feature_matching(
                model,
                seg,
                model_feat,
                seg_feat,
                True,
                d,
                reg.TransformationEstimationPointToPoint(False),
                3,
                [
                    reg.CorrespondenceCheckerBasedOnEdgeLength(s["edge_length_ratio"]),
                    reg.CorrespondenceCheckerBasedOnDistance(d),
                ],
                reg.RANSACConvergenceCriteria(s["ransac_iterations"], s["ransac_confidence"]),
            )
        T = np.asarray(res.transformation)
        return PoseEstimate(T[:3, :3].copy(), T[:3, 3].copy(), float(res.fitness))
