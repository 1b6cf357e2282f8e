"""Depth and label rendering of posed YCB objects with Open3D raycasting.

YCB-Video ships only the 2,621-point evaluation point sets of its models (no meshes here), so
each object's surface is built from its points (:func:`build_mesh`) and rendered with Open3D's
tensor ``RaycastingScene``: one ray per pixel centre through ``K^-1 [u, v, 1]``, depth =
``t_hit * ray_z`` for unit rays, class = the mesh the ray hits first.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import NamedTuple

import numpy as np
import open3d as o3d
from pykdtree.kdtree import KDTree

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


SURFACE_BPA_RADII = (1.0, 2.0, 4.0, 8.0)
"""Ball-pivoting radii, in units of the model's median nearest-neighbour spacing."""
SURFACE_ALPHA = 8.0
"""Alpha-shape radius, in median spacings: closes the small holes ball pivoting leaves without
bridging concavities (mug handle, scissors and clamp loops, the bowl's inside)."""
SURFACE_PATCH_ALPHA = 30.0
"""Radius of the coarse alpha shape whose locally planar triangles patch large sampling gaps on
flat faces (a box face can hold few points: the point sets follow the original mesh vertices)."""
SURFACE_PATCH_TOL = 1e-3
"""Metres: a patch triangle's vertices, and its k nearest model points, must lie within this of
the plane fitted to those points."""


def _alpha_shape(pcd: o3d.geometry.PointCloud, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_alpha_shape(pcd, alpha)
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def _planar_triangles(
    V: np.ndarray, F: np.ndarray, points: np.ndarray, tol: float, k: int = 12
) -> np.ndarray:
    """Keep the triangles that lie in the local plane of the model points near them.

    Args:
        V: (M, 3) vertices; F: (T, 3) triangles; points: (P, 3) model points, metres.

    Returns:
        (T', 3) the triangles of F whose k nearest model points (to the centroid) are planar
        within ``tol`` (rms), whose vertices lie within ``tol`` of that plane, and whose normal
        is within ~18 degrees of the plane's.
    """
    if len(F) == 0:
        return F
    tri = V[F]  # (T, 3, 3)
    _, idx = KDTree(points).query(tri.mean(axis=1), k=k)
    nb = points[idx]  # (T, k, 3)
    mu = nb.mean(axis=1)
    X = nb - mu[:, None]
    w, v = np.linalg.eigh(np.einsum("tki,tkj->tij", X, X) / k)
    n = v[:, :, 0]  # (T, 3) normal of the fitted plane
    rms = np.sqrt(np.maximum(w[:, 0], 0.0))
    nt = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nt /= np.linalg.norm(nt, axis=1, keepdims=True) + 1e-15
    off = np.abs(np.einsum("tvi,ti->tv", tri - mu[:, None], n)).max(axis=1)
    keep = (rms < tol) & (off < tol) & (np.abs((nt * n).sum(axis=1)) > 0.95)
    return F[keep]


def surface_triangles(points: np.ndarray) -> np.ndarray:
    """Build a triangle surface through a model's evaluation points.

    The surface is the union of three triangle sets over the same vertices (the points), which
    the raycaster treats as one surface (the first hit wins):

    1. ball pivoting (normals from 30 neighbours, consistently oriented) at radii
       :data:`SURFACE_BPA_RADII` x the median spacing: follows the points closely, with holes;
    2. the alpha shape at :data:`SURFACE_ALPHA` x the median spacing: closes most holes;
    3. the triangles of a coarse alpha shape (:data:`SURFACE_PATCH_ALPHA`) that lie in a flat
       face (:func:`_planar_triangles`): closes wide sampling gaps on box faces without
       filling concave openings, whose spanning triangles are not in a plane of nearby points.

    Fidelity against YCB-Video's own renderings is tested in tests/test_render.py. Deterministic.

    Args:
        points: (P, 3) model points in metres (model frame).

    Returns:
        (T, 3) int64 triangles as indices into ``points`` (not watertight; the raycaster does
        not need it).
    """
    points = np.array(points, dtype=np.float64)  # a writeable copy: Open3D rejects read-only
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise ValueError(f"model points have shape {points.shape}, expected (P >= 4, 3)")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    spacing = float(np.median(np.asarray(pcd.compute_nearest_neighbor_distance())))
    if not spacing > 0:
        raise ValueError("model points have zero median spacing (duplicated points?)")
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
    pcd.orient_normals_consistent_tangent_plane(30)
    bpa = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(
        pcd, o3d.utility.DoubleVector([r * spacing for r in SURFACE_BPA_RADII])
    )
    parts = [(np.asarray(bpa.vertices), np.asarray(bpa.triangles))]
    parts.append(_alpha_shape(pcd, SURFACE_ALPHA * spacing))
    Vp, Fp = _alpha_shape(pcd, SURFACE_PATCH_ALPHA * spacing)
    parts.append((Vp, _planar_triangles(Vp, Fp, points, SURFACE_PATCH_TOL)))
    # every part's vertices are input points: re-index them onto `points` and merge
    tree = KDTree(points)
    tris = []
    for V, F in parts:
        if len(F) == 0:
            continue
        dist, idx = tree.query(np.ascontiguousarray(V, dtype=np.float64), k=1)
        assert dist.max() < 1e-6, "surface vertex is not a model point"  # Qhull moves ~1e-9
        tris.append(idx[F].astype(np.int64))
    F = np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    _, first = np.unique(np.sort(F, axis=1), axis=0, return_index=True)
    F = F[np.sort(first)]
    return F


def build_mesh(points: np.ndarray, use_cache: bool = True) -> o3d.geometry.TriangleMesh:
    """The surface mesh of a model (:func:`surface_triangles`, or the packaged cache of it).

    Args:
        points: (P, 3) model points in metres (model frame).
        use_cache: look the surface up in the packaged cache first (same points and settings).

    Returns:
        Triangle mesh in the model frame, metres; its vertices are all P points.
    """
    points = np.array(points, dtype=np.float64)
    F = _cached_triangles(points) if use_cache else None
    if F is None:
        F = surface_triangles(points)
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(points), o3d.utility.Vector3iVector(F.astype(np.int32))
    )


SURFACE_VERSION = 1
"""Bump when :func:`surface_triangles` changes, so that a stale packaged cache is ignored."""

SURFACE_CACHE = ("meshes", "surfaces.npz")
"""Packaged cache of the 21 models' surfaces (``resource_path(*SURFACE_CACHE)``)."""

_surface_cache: dict[str, np.ndarray] | None = None


def surface_key(points: np.ndarray) -> str:
    """Cache key of a model's surface: the points' bytes and the build settings."""
    h = hashlib.sha1(np.ascontiguousarray(points, dtype=np.float64).tobytes())
    h.update(
        repr(
            (
                SURFACE_VERSION,
                SURFACE_BPA_RADII,
                SURFACE_ALPHA,
                SURFACE_PATCH_ALPHA,
                SURFACE_PATCH_TOL,
            )
        ).encode()
    )
    return h.hexdigest()


def _cached_triangles(points: np.ndarray) -> np.ndarray | None:
    global _surface_cache
    if _surface_cache is None:
        path = resource_path(*SURFACE_CACHE)
        _surface_cache = {}
        if path.is_file():
            with np.load(path) as z:
                _surface_cache = {k: z[k] for k in z.files}
    F = _surface_cache.get(surface_key(points))
    if F is None or (len(F) and F.max() >= len(points)):
        return None
    return F.astype(np.int64)


def write_surface_cache(path: str | Path | None = None) -> Path:
    """Build the surfaces of the 21 packaged models and save them (the packaged cache).

    Regenerate after changing :func:`surface_triangles` (and bump :data:`SURFACE_VERSION`)::

        python -c "from cloudpose.data.render import write_surface_cache as w; w()"

    Args:
        path: output .npz; default the packaged ``resources/meshes/surfaces.npz``.

    Returns:
        The path written. It maps :func:`surface_key` -> (T, 3) uint16 point indices.
    """
    global _surface_cache
    path = Path(path) if path is not None else resource_path(*SURFACE_CACHE)
    path.parent.mkdir(parents=True, exist_ok=True)
    out = {}
    for pts in load_packaged_models().values():
        F = surface_triangles(pts)
        assert len(pts) <= np.iinfo(np.uint16).max
        out[surface_key(pts)] = F.astype(np.uint16)
    np.savez_compressed(path, **out)
    _surface_cache = None
    return path


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


class Renderer:
    """Renders depth and labels of posed objects (surfaces built from model points).

    Surfaces are built on first use of a class (:func:`build_mesh`, ~0.2 s each) and cached.

    Args:
        models: {class id: (P, 3) model points in metres}; None -> the 21 packaged models
            with ids 1..21.
        use_cache: take surfaces from the packaged cache when the points match (default);
            False builds every surface afresh.
    """

    def __init__(
        self, models: dict[int, np.ndarray] | None = None, *, use_cache: bool = True
    ) -> None:
        self.models = load_packaged_models() if models is None else dict(models)
        self.use_cache = use_cache
        self._meshes: dict[int, o3d.geometry.TriangleMesh] = {}
        self._arrays: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._rays: dict[tuple, np.ndarray] = {}

    def mesh(self, cls_id: int) -> o3d.geometry.TriangleMesh:
        """Surface mesh of class ``cls_id`` (model frame, metres; its vertices are the model
        points). Taken from the packaged cache when the points match, else built; kept."""
        c = int(cls_id)
        if c not in self.models:
            raise ValueError(f"class id {c} has no model; known ids {sorted(self.models)}")
        if c not in self._meshes:
            self._meshes[c] = build_mesh(self.models[c], self.use_cache)
        return self._meshes[c]

    def _mesh_arrays(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        if c not in self._arrays:
            m = self.mesh(c)
            self._arrays[c] = (
                np.asarray(m.vertices, dtype=np.float64),
                np.asarray(m.triangles, dtype=np.uint32),
            )
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
        if cls_ids.size and (cls_ids.min() < 0 or cls_ids.max() > 255):
            raise ValueError(f"cls_ids {cls_ids.tolist()} do not fit a uint8 label image")
        depth, index = self._cast(K, shape, cls_ids, poses)
        lut = np.concatenate([cls_ids, [0]]).astype(np.uint8)
        label = lut[index]  # index -1 picks the appended background 0
        visible = np.bincount(index[index >= 0], minlength=len(cls_ids)).astype(np.int64)
        return Rendering(depth, label, visible)

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
        O = 1 - visible / alone (DESIGN.md; the paper's Fig. 5).

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
