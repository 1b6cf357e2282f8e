"""Depth and label rendering of posed YCB objects with Open3D raycasting.

Each object's surface is a triangle mesh through its model points
(:mod:`cloudpose.data.synth.surfaces`), rendered with Open3D's tensor ``RaycastingScene``: one ray per
pixel centre through ``K^-1 [u, v, 1]``, depth = ``t_hit * ray_z`` for unit rays, class = the
mesh the ray hits first.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from cloudpose.data.synth.surfaces import (
    build_mesh,
    check_surface_version,
    load_packaged_models,
    surface_arrays,
)
from cloudpose.kernels.backend import enabled
from cloudpose.kernels.raster import rasterize_mesh

if TYPE_CHECKING:  # Open3D is imported where it casts rays: the compiled raster needs none
    import open3d as o3d


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
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise ValueError(f"K has shape {K.shape}, expected finite (3, 3) intrinsics")
    if len(shape) != 2 or min(shape) <= 0:
        raise ValueError(f"shape {tuple(shape)} is not (H, W) with H, W > 0")
    cls_ids = np.asarray(cls_ids).reshape(-1)
    if cls_ids.size and not np.issubdtype(cls_ids.dtype, np.integer):
        raise ValueError(f"cls_ids {cls_ids.tolist()} are not integers")
    cls_ids = cls_ids.astype(np.int64)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.size == 0 and len(cls_ids) == 0:
        poses = poses.reshape(0, 3, 4)
    if poses.shape != (len(cls_ids), 3, 4):
        raise ValueError(f"poses have shape {poses.shape}, expected ({len(cls_ids)}, 3, 4)")
    if not np.isfinite(poses).all():
        raise ValueError("poses contain NaN or inf")
    return K, (int(shape[0]), int(shape[1])), cls_ids, poses


def _check_labels(cls_ids: np.ndarray) -> None:
    if cls_ids.size and (cls_ids.min() < 0 or cls_ids.max() > 255):
        raise ValueError(f"cls_ids {cls_ids.tolist()} do not fit a uint8 label image")


def _rendering(cls_ids: np.ndarray, depth: np.ndarray, index: np.ndarray) -> Rendering:
    """The :class:`Rendering` of depth and the index of the instance each pixel hits first
    (-1 = none)."""
    lut = np.concatenate([cls_ids, [0]]).astype(np.uint8)
    label = lut[index]  # index -1 picks the appended background 0
    visible = np.bincount(index[index >= 0], minlength=len(cls_ids)).astype(np.int64)
    return Rendering(depth, label, visible)


class Renderer:
    """Renders depth and labels of posed objects (surfaces built from model points).

    Surfaces are taken from the packaged cache or built on first use of a class
    (:func:`cloudpose.data.synth.surfaces.build_mesh`: ~0.2 s each, ~1 s with carving) and kept.

    Args:
        models: {class id: (P, 3) model points in metres}; None -> the 21 packaged models
            with ids 1..21.
        use_cache: take surfaces from the packaged cache when the points match (default);
            False builds every surface afresh.
        surface_version: which surfaces (:data:`cloudpose.data.synth.surfaces.SURFACE_VERSIONS`; 2
            keeps through-holes).
    """

    def __init__(
        self,
        models: dict[int, np.ndarray] | None = None,
        *,
        use_cache: bool = True,
        surface_version: int = 1,
    ) -> None:
        check_surface_version(surface_version)
        self.models = load_packaged_models() if models is None else dict(models)
        self.use_cache = use_cache
        self.surface_version = surface_version
        self._meshes: dict[int, o3d.geometry.TriangleMesh] = {}
        self._arrays: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._rays: dict[tuple, np.ndarray] = {}
        self._scenes: dict[int, o3d.t.geometry.RaycastingScene] = {}

    def mesh(self, cls_id: int) -> o3d.geometry.TriangleMesh:
        """Surface mesh of class ``cls_id`` (model frame, metres; its vertices are the model
        points). Taken from the packaged cache when the points match, else built; kept."""
        c = int(cls_id)
        if c not in self.models:
            raise ValueError(f"class id {c} has no model; known ids {sorted(self.models)}")
        if c not in self._meshes:
            self._meshes[c] = build_mesh(self.models[c], self.use_cache, self.surface_version)
        return self._meshes[c]

    def _mesh_arrays(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`mesh`'s vertices (float64) and triangles (uint32), without Open3D."""
        if c not in self.models:
            raise ValueError(f"class id {c} has no model; known ids {sorted(self.models)}")
        if c not in self._arrays:
            V, F = surface_arrays(self.models[c], self.use_cache, self.surface_version)
            self._arrays[c] = (V, F.astype(np.uint32))
        return self._arrays[c]

    def _unit_rays(self, K: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        key = (shape, K.tobytes())
        if key not in self._rays:
            if len(self._rays) >= 8:
                self._rays.clear()
            self._rays[key] = camera_rays(K, shape)
        return self._rays[key]

    def _cast(self, K, shape, cls_ids, poses, window=None):
        """Cast one ray per pixel (of ``window`` = (v0, v1, u0, u1) if given).

        Returns:
            depth (h, w) float32 metres (0 = no hit) and index (h, w) int64 of the instance
            hit first (-1 = none), over the window.
        """
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        gid_to_inst = {}
        for i, (c, P) in enumerate(zip(cls_ids, poses, strict=True)):
            V, F = self._mesh_arrays(int(c))
            Vc = (V @ P[:, :3].T + P[:, 3]).astype(np.float32)  # (M, 3) camera frame
            gid = scene.add_triangles(o3d.core.Tensor(Vc), o3d.core.Tensor(F))
            gid_to_inst[gid] = i
        d = self._unit_rays(K, shape)
        if window is not None:
            v0, v1, u0, u1 = window
            d = d[v0:v1, u0:u1]
        rays = np.concatenate([np.zeros_like(d), d], axis=-1)  # (h, w, 6) origin, direction
        t = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
        t_hit = t["t_hit"].numpy()
        gids = t["geometry_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t_hit)
        depth = np.where(hit, t_hit * d[..., 2], 0.0).astype(np.float32)
        lut = np.full(max(gid_to_inst, default=0) + 1, -1, dtype=np.int64)
        for g, i in gid_to_inst.items():
            lut[g] = i
        index = np.full(hit.shape, -1, dtype=np.int64)
        index[hit] = lut[gids[hit]]
        return depth, index

    def render(self, K, shape: tuple[int, int], cls_ids, poses) -> Rendering:
        """Render depth and labels of objects at their poses.

        Args:
            K: (3, 3) intrinsics.
            shape: (H, W) image size.
            cls_ids: (N,) class ids (keys of ``models``).
            poses: (N, 3, 4) object->camera ``[R | t]``, metres.

        Returns:
            :class:`Rendering`: depth (metres of the nearest surface), label (its class id) and
            per-instance visible pixel counts.
        """
        K, shape, cls_ids, poses = _check_inputs(K, shape, cls_ids, poses)
        _check_labels(cls_ids)
        return _rendering(cls_ids, *self._cast(K, shape, cls_ids, poses))

    def _class_scene(self, c: int) -> o3d.t.geometry.RaycastingScene:
        """A ray-casting scene of class ``c``'s mesh in its model frame, built once (its BVH
        too: the first cast commits it) and kept."""
        if c not in self._scenes:
            import open3d as o3d

            V, F = self._mesh_arrays(c)
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F))
            self._scenes[c] = scene
        return self._scenes[c]

    def render_instanced(
        self, K, shape: tuple[int, int], cls_ids, poses, windows, box, nthreads=0
    ) -> Rendering:
        """:meth:`render` by casting each object's rays against its class's own scene in the
        model frame: no scene is built per call (the BVH of a class is built once), and each
        object gets only the rays of its own window. The nearest hit over the objects wins.

        Depth and labels equal :meth:`render`'s up to float rounding (the rays are moved into
        each model frame instead of the meshes into the camera frame): a pixel whose ray
        grazes a silhouette edge within that rounding can flip between hit and miss.

        Args:
            K, shape, cls_ids, poses: as :meth:`render`.
            windows: (N, 4) per object (v0, v1, u0, u1) pixel windows of the image that hold
                its projection (:meth:`_window`); rays outside an object's window cannot hit
                it. Empty windows (v0 >= v1 or u0 >= u1) cast nothing.
            box: (v0, v1, u0, u1) of the output in the image; it holds every object window.
            nthreads: ray-casting threads (0: every core).

        Returns:
            :class:`Rendering` over the output window.
        """
        import open3d as o3d

        K, shape, cls_ids, poses = _check_inputs(K, shape, cls_ids, poses)
        _check_labels(cls_ids)
        windows = np.asarray(windows, dtype=np.int64).reshape(-1, 4)
        ov, ov1, ou, ou1 = (int(x) for x in box)
        d_all = self._unit_rays(K, shape)
        best = np.full((ov1 - ov, ou1 - ou), np.inf, dtype=np.float32)
        index = np.full(best.shape, -1, dtype=np.int64)
        for i, (c, P) in enumerate(zip(cls_ids, poses, strict=True)):
            v0, v1, u0, u1 = (int(x) for x in windows[i])
            if v0 >= v1 or u0 >= u1:
                continue
            if v0 < ov or v1 > ov1 or u0 < ou or u1 > ou1:
                raise ValueError(f"object window {windows[i].tolist()} is not inside {box}")
            d = d_all[v0:v1, u0:u1].reshape(-1, 3).astype(np.float64)
            R, t = P[:, :3], P[:, 3]
            origin_m = np.broadcast_to(-(R.T @ t), d.shape)
            rays = np.concatenate([origin_m, d @ R], axis=-1).astype(np.float32)
            hit = self._class_scene(int(c)).cast_rays(o3d.core.Tensor(rays), nthreads=nthreads)
            t_hit = hit["t_hit"].numpy().reshape(v1 - v0, u1 - u0)
            sub = (slice(v0 - ov, v1 - ov), slice(u0 - ou, u1 - ou))
            closer = t_hit < best[sub]
            best[sub] = np.where(closer, t_hit, best[sub])
            index[sub] = np.where(closer, i, index[sub])
        found = np.isfinite(best)
        d_out = d_all[ov : ov + best.shape[0], ou : ou + best.shape[1], 2]
        return _rendering(cls_ids, np.where(found, best * d_out, 0.0).astype(np.float32), index)

    def render_raster(
        self, K, shape: tuple[int, int], cls_ids, poses, pad: int = 0, nthreads: int = 0
    ) -> tuple[Rendering, tuple[int, int, int, int]] | None:
        """:meth:`render_instanced` by a z-buffer of the posed meshes
        (:func:`cloudpose.kernels.raster.rasterize_mesh`: each triangle tested at the pixel
        centres of its projection, the depth of its plane along the pixel's ray), over the box
        around the objects' windows (:meth:`_window`) plus ``pad`` pixels, clipped to the image.

        Depth and labels equal the ray cast's to float rounding (micrometres; a pixel centre
        within rounding of a silhouette edge may flip). Without the compiled kernels, or when an
        object reaches behind the camera, it casts the rays instead (:meth:`render_instanced`,
        the twin), over the same box.

        Args:
            K, shape, cls_ids, poses: as :meth:`render`.
            pad: pixels added around the objects' windows.
            nthreads: ray-casting threads where it casts (0: every core).

        Returns:
            (:class:`Rendering` over the box, box (v0, v1, u0, u1)), or None when no object
            projects into the image.
        """

        K, shape, cls_ids, poses = _check_inputs(K, shape, cls_ids, poses)
        _check_labels(cls_ids)
        H, W = shape
        compiled = enabled()
        projected, windows = [], []
        for c, P in zip(cls_ids, poses, strict=True):
            # :meth:`_window`'s expressions: the same windows, so the same box, to the bit
            V, _ = self._mesh_arrays(int(c))
            X = V @ P[:, :3].T + P[:, 3]  # (M, 3) camera frame
            if len(X) == 0 or X[:, 2].min() <= 1e-6:
                compiled = False  # partly behind the camera: its window is the whole image
                windows.append((0, H, 0, W))
                projected.append(None)
                continue
            uv = (X @ K.T)[:, :2] / X[:, 2:3]
            u0, v0 = np.floor(uv.min(axis=0)).astype(np.int64) - 1
            u1, v1 = np.ceil(uv.max(axis=0)).astype(np.int64) + 2
            windows.append(
                (
                    int(np.clip(v0, 0, H)),
                    int(np.clip(v1, 0, H)),
                    int(np.clip(u0, 0, W)),
                    int(np.clip(u1, 0, W)),
                )
            )
            projected.append((X[:, 2].copy(), np.ascontiguousarray(uv)))
        wins = np.array(windows, dtype=np.int64).reshape(-1, 4)
        used = wins[(wins[:, 0] < wins[:, 1]) & (wins[:, 2] < wins[:, 3])]
        if not len(used):
            return None
        box = (
            max(int(used[:, 0].min()) - pad, 0),
            min(int(used[:, 1].max()) + pad, H),
            max(int(used[:, 2].min()) - pad, 0),
            min(int(used[:, 3].max()) + pad, W),
        )
        if not compiled:
            return self.render_instanced(K, shape, cls_ids, poses, wins, box, nthreads), box

        bv0, bv1, bu0, bu1 = box
        depth = np.full((bv1 - bv0, bu1 - bu0), np.inf)
        index = np.full(depth.shape, -1, dtype=np.int64)
        for i, (c, zuv) in enumerate(zip(cls_ids, projected, strict=True)):
            if zuv is None or wins[i, 0] >= wins[i, 1] or wins[i, 2] >= wins[i, 3]:
                continue
            _, F = self._mesh_arrays(int(c))
            rasterize_mesh(zuv[0], zuv[1], F, bv0, bu0, depth, index, i)
        found = np.isfinite(depth)
        return _rendering(cls_ids, np.where(found, depth, 0.0).astype(np.float32), index), box

    def _window(self, K, shape, c, P):
        """Pixel window (v0, v1, u0, u1) that holds the projection of the posed mesh, or None
        (whole image) when part of it is not in front of the camera."""
        V, _ = self._mesh_arrays(int(c))
        X = V @ P[:, :3].T + P[:, 3]  # (M, 3) camera frame
        if len(X) == 0 or X[:, 2].min() <= 1e-6:
            return None
        uv = (X @ K.T)[:, :2] / X[:, 2:3]
        u0, v0 = np.floor(uv.min(axis=0)).astype(np.int64) - 1
        u1, v1 = np.ceil(uv.max(axis=0)).astype(np.int64) + 2
        H, W = shape
        return (
            int(np.clip(v0, 0, H)),
            int(np.clip(v1, 0, H)),
            int(np.clip(u0, 0, W)),
            int(np.clip(u1, 0, W)),
        )

    def alone_pixels(self, K, shape: tuple[int, int], cls_ids, poses) -> np.ndarray:
        """Pixels of each object rendered alone at its pose: the nu of the occlusion factor
        O = 1 - visible / alone (docs/design.md; the paper's Fig. 5).

        Args:
            K: (3, 3) intrinsics.
            shape: (H, W) image size.
            cls_ids: (N,) class ids.
            poses: (N, 3, 4) object->camera ``[R | t]``, metres.

        Returns:
            (N,) int64 pixel counts inside the image.
        """
        K, shape, cls_ids, poses = _check_inputs(K, shape, cls_ids, poses)
        out = np.zeros(len(cls_ids), dtype=np.int64)
        for i in range(len(cls_ids)):
            win = self._window(K, shape, cls_ids[i], poses[i])
            if win is not None and (win[0] >= win[1] or win[2] >= win[3]):
                continue  # projects outside the image
            _, index = self._cast(K, shape, cls_ids[i : i + 1], poses[i : i + 1], win)
            out[i] = int((index == 0).sum())
        return out
