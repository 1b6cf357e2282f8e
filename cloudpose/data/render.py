"""Depth and label rendering of posed YCB objects with Open3D raycasting.

YCB-Video ships only the 2,621-point evaluation point sets of its models (no meshes here), so
each object's surface is built from its points (:func:`build_mesh`) and rendered with Open3D's
tensor ``RaycastingScene``: one ray per pixel centre through ``K^-1 [u, v, 1]``, depth =
``t_hit * ray_z`` for unit rays, class = the mesh the ray hits first.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import open3d as o3d

from cloudpose.conventions import resource_path


class Rendering(NamedTuple):
    """A rendered frame.

    Attributes:
        depth: (H, W) float32 depth in metres of the nearest surface, 0 = no surface.
        label: (H, W) uint8 class id of the nearest surface, 0 = background.
        visible_pixels: (N,) int64 pixels of each instance in ``label``.
    """

    depth: np.ndarray
    label: np.ndarray
    visible_pixels: np.ndarray


def load_packaged_models() -> dict[int, np.ndarray]:
    """The 21 packaged YCB-Video model point sets: {class id 1..21: (P, 3) float64 metres}."""
    from cloudpose.data.ycb import load_classes, load_model_points

    names = load_classes(resource_path("classes.txt"))
    return {
        i + 1: load_model_points(resource_path("models", n, "points.xyz"))
        for i, n in enumerate(names)
    }


def build_mesh(points: np.ndarray) -> o3d.geometry.TriangleMesh:
    """Build a triangle surface through a model's points.

    Args:
        points: (P, 3) model points in metres.

    Returns:
        The surface mesh, model frame, metres.
    """
    points = np.asarray(points, dtype=np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    nn = np.asarray(pcd.compute_nearest_neighbor_distance())
    alpha = 4.0 * float(np.percentile(nn, 95))
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_alpha_shape(pcd, alpha)
    return mesh


def camera_rays(K: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Unit rays through every pixel centre (OpenCV: pixel (u, v) centre at u, v).

    Args:
        K: (3, 3) intrinsics.
        shape: (H, W) image size.

    Returns:
        (H, W, 3) float32 unit ray directions in the camera frame.
    """
    H, W = shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)  # (H, W, 3)
    d = pix @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return d.astype(np.float32)


def _check_inputs(K, shape, cls_ids, poses):
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K has shape {K.shape}, expected (3, 3)")
    if len(shape) != 2 or min(shape) <= 0:
        raise ValueError(f"shape {shape} is not (H, W) with H, W > 0")
    cls_ids = np.asarray(cls_ids, dtype=np.int64).reshape(-1)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (len(cls_ids), 3, 4):
        raise ValueError(f"poses have shape {poses.shape}, expected ({len(cls_ids)}, 3, 4)")
    return K, (int(shape[0]), int(shape[1])), cls_ids, poses


class Renderer:
    """Renders depth and labels of posed objects (surfaces built from model points).

    Args:
        models: {class id: (P, 3) model points in metres}; None -> the 21 packaged models
            with ids 1..21.
    """

    def __init__(self, models: dict[int, np.ndarray] | None = None) -> None:
        self.models = load_packaged_models() if models is None else dict(models)
        self._meshes: dict[int, o3d.geometry.TriangleMesh] = {}
        self._arrays: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._rays: dict[tuple, np.ndarray] = {}

    def mesh(self, cls_id: int) -> o3d.geometry.TriangleMesh:
        """Surface mesh of class ``cls_id`` (model frame, metres; built once, cached)."""
        c = int(cls_id)
        if c not in self.models:
            raise ValueError(f"class id {c} has no model; known ids {sorted(self.models)}")
        if c not in self._meshes:
            self._meshes[c] = build_mesh(self.models[c])
        return self._meshes[c]

    def _mesh_arrays(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        if c not in self._arrays:
            m = self.mesh(c)
            self._arrays[c] = (
                np.asarray(m.vertices, dtype=np.float64),
                np.asarray(m.triangles, dtype=np.uint32),
            )
        return self._arrays[c]

    def _rays_for(self, K: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        key = (shape, K.tobytes())
        if key not in self._rays:
            if len(self._rays) > 8:
                self._rays.clear()
            d = camera_rays(K, shape)
            rays = np.concatenate([np.zeros_like(d), d], axis=-1)  # (H, W, 6)
            self._rays[key] = rays
        return self._rays[key]

    def _cast(self, K, shape, cls_ids, poses):
        """Returns (depth (H, W) float32, index (H, W) int64 of the hit instance, -1 = none)."""
        scene = o3d.t.geometry.RaycastingScene()
        geom_to_inst = {}
        for i, (c, P) in enumerate(zip(cls_ids, poses, strict=True)):
            V, F = self._mesh_arrays(int(c))
            Vc = (V @ P[:, :3].T + P[:, 3]).astype(np.float32)
            gid = scene.add_triangles(o3d.core.Tensor(Vc), o3d.core.Tensor(F))
            geom_to_inst[gid] = i
        rays = self._rays_for(K, shape)
        ans = scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy()
        gids = ans["geometry_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t)
        depth = np.where(hit, t * rays[..., 5], 0.0).astype(np.float32)
        lut = np.full(max(geom_to_inst, default=0) + 2, -1, dtype=np.int64)
        for g, i in geom_to_inst.items():
            lut[g] = i
        index = np.where(hit, lut[np.where(hit, gids, -1)], -1)
        return depth, index

    def render(self, K, shape: tuple[int, int], cls_ids, poses) -> Rendering:
        """Render depth and labels of objects at their poses.

        Args:
            K: (3, 3) intrinsics.
            shape: (H, W) image size.
            cls_ids: (N,) class ids.
            poses: (N, 3, 4) object->camera ``[R | t]``, metres.

        Returns:
            :class:`Rendering` with depth (metres), label and per-instance visible pixels.
        """
        K, shape, cls_ids, poses = _check_inputs(K, shape, cls_ids, poses)
        depth, index = self._cast(K, shape, cls_ids, poses)
        lut = np.concatenate([cls_ids, [0]]).astype(np.uint8)
        label = lut[index]  # index -1 -> the appended background 0
        visible = np.bincount(index[index >= 0], minlength=len(cls_ids)).astype(np.int64)
        return Rendering(depth, label, visible)

    def alone_pixels(self, K, shape: tuple[int, int], cls_ids, poses) -> np.ndarray:
        """Pixels of each object rendered alone at its pose (the occlusion factor's nu,
        DESIGN.md: O = 1 - visible / alone).

        Returns:
            (N,) int64 pixel counts.
        """
        K, shape, cls_ids, poses = _check_inputs(K, shape, cls_ids, poses)
        out = np.zeros(len(cls_ids), dtype=np.int64)
        for i in range(len(cls_ids)):
            _, index = self._cast(K, shape, cls_ids[i : i + 1], poses[i : i + 1])
            out[i] = int((index == 0).sum())
        return out
