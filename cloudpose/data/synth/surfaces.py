"""Triangle surfaces of YCB objects built from their model point sets, and their packaged cache.

YCB-Video ships only the 2,621-point evaluation point sets of its models (no meshes here), so
each object's surface is built from its points (:func:`surface_triangles`). The 21 packaged
models' surfaces ship precomputed in ``resources/meshes/`` (:func:`build_mesh` looks them up,
:func:`write_surface_cache` regenerates them); :mod:`cloudpose.data.synth.render` ray-casts them.

Surface versions (:data:`SURFACE_VERSIONS`): 1 is the union of ball pivoting and alpha shapes,
which closes through-holes (the inside of a mug's or pitcher's handle, the scissors' and
clamps' loops); 2 is version 1 with the triangles that span a through-hole carved away
(:func:`carve_through_holes`). Synthetic frames record which one rendered them.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pykdtree.kdtree import KDTree
from scipy import ndimage

from cloudpose.conventions import packaged_classes, resource_path
from cloudpose.data.ycb import load_model_points

if TYPE_CHECKING:  # Open3D is imported where a surface is built: the packaged ones need none
    import open3d as o3d


def load_packaged_models() -> dict[int, np.ndarray]:
    """The 21 packaged YCB-Video model point sets: {class id 1..21: (P, 3) float64 metres}."""

    names = packaged_classes()
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
    import open3d as o3d

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


def surface_triangles(points: np.ndarray, version: int = 1) -> np.ndarray:
    """Build a triangle surface through a model's evaluation points.

    The surface is the union of three triangle sets over the same vertices (the points), which
    the raycaster treats as one surface (the first hit wins):

    1. ball pivoting (normals from 30 neighbours, consistently oriented) at radii
       :data:`SURFACE_BPA_RADII` x the median spacing: follows the points closely, with holes;
    2. the alpha shape at :data:`SURFACE_ALPHA` x the median spacing: closes most holes;
    3. the triangles of a coarse alpha shape (:data:`SURFACE_PATCH_ALPHA`) that lie in a flat
       face (:func:`_planar_triangles`): closes wide sampling gaps on box faces without
       filling concave openings, whose spanning triangles are not in a plane of nearby points.

    Version 2 then removes the triangles that span a through-hole (:func:`carve_through_holes`).
    Fidelity against YCB-Video's own renderings is tested in tests/test_render.py. Deterministic.

    Args:
        points: (P, 3) model points in metres (model frame).
        version: surface version, one of :data:`SURFACE_VERSIONS`.

    Returns:
        (T, 3) int64 triangles as indices into ``points`` (not watertight; the raycaster does
        not need it).
    """
    check_surface_version(version)
    points = np.array(points, dtype=np.float64)  # a writeable copy: Open3D rejects read-only
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise ValueError(f"model points have shape {points.shape}, expected (P >= 4, 3)")
    F = _union_triangles(points)
    if version == 2:
        F = F[carve_through_holes(points, F)]
    return F


def _union_triangles(points: np.ndarray) -> np.ndarray:
    """The version-1 surface of :func:`surface_triangles` (points already checked)."""
    import open3d as o3d

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


CARVE_VIEWS = 96
"""Viewing directions (a Fibonacci half sphere; a silhouette seen from -d is the mirror image
of the one from d) in which :func:`carve_through_holes` looks for through-holes."""
CARVE_NEIGHBOUR = 4
"""A projected point's splat radius is its distance to its k-th nearest projected neighbour:
sparse regions seen face-on get wide splats, dense outlines (a hole's rim) narrow ones."""
CARVE_RADIUS = (1.0, 8.0)
"""Splat radius bounds, in median model point spacings."""
CARVE_MIN_HOLE = 64.0
"""Enclosed background regions of a silhouette smaller than this (square median spacings) are
sampling gaps, not holes, and are filled."""
CARVE_KEEP_NEAR = 3.0
"""A triangle sample within this many median spacings of a model point is never carved: only
triangles that reach well into empty space are taken out."""
CARVE_SAMPLES = 3
"""Barycentric subdivision level of the sample points tested per triangle (level 3: the
centroid, 6 edge points and 3 more inside; the vertices themselves are model points)."""


def _half_sphere(n: int) -> np.ndarray:
    """(n, 3) unit directions spread evenly over the half sphere z > 0 (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = i / n
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _barycentric(level: int) -> np.ndarray:
    """(S, 3) barycentric weights of a level-``level`` triangle grid without its corners."""
    w = np.array(
        [(i, j, level - i - j) for i in range(level + 1) for j in range(level + 1 - i)], float
    )
    w /= level
    return w[(w > 0).sum(axis=1) >= 2]


def _point_silhouette(p2: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Silhouette of orthographically projected points, each splatted as a disk.

    Args:
        p2: (P, 2) projected points, metres.
        spacing: median 3D spacing of the model points, metres.

    Returns:
        (G0, G1) bool raster (True = covered), its origin (2,) in metres, and its cell size.
    """
    cell = spacing / 2.0
    lo_r, hi_r = CARVE_RADIUS[0] * spacing, CARVE_RADIUS[1] * spacing
    d2, _ = KDTree(p2).query(p2, k=CARVE_NEIGHBOUR + 1)
    radius = np.clip(d2[:, CARVE_NEIGHBOUR], lo_r, hi_r)
    # radii rounded up to 8 geometric bins: one distance transform per bin
    edges = np.geomspace(lo_r, hi_r * 1.0001, 9)[1:]
    which = np.searchsorted(edges, radius)
    pad = hi_r + 2.0 * cell
    origin = p2.min(axis=0) - pad
    ij = np.floor((p2 - origin) / cell).astype(np.int64)
    shape = tuple(ij.max(axis=0) + int(pad / cell) + 2)
    covered = np.zeros(shape, dtype=bool)
    for b in np.unique(which):
        seeds = np.zeros(shape, dtype=bool)
        sel = which == b
        seeds[ij[sel, 0], ij[sel, 1]] = True
        covered |= ndimage.distance_transform_edt(~seeds) * cell <= edges[b]
    holes, n = ndimage.label(ndimage.binary_fill_holes(covered) & ~covered)
    if n:
        area = np.bincount(holes.ravel())[1:] * cell * cell
        small = np.concatenate([[False], area < CARVE_MIN_HOLE * spacing * spacing])
        covered |= small[holes]
    return covered, origin, cell


def carve_through_holes(points: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Which triangles of a surface through model points do not span a through-hole.

    A through-hole (a handle's inside, a loop of the scissors) shows as an enclosed empty
    region in the silhouette of the points seen from across it. For each of
    :data:`CARVE_VIEWS` directions the points are projected orthographically and splatted as
    disks (:data:`CARVE_NEIGHBOUR`, :data:`CARVE_RADIUS`; gaps below :data:`CARVE_MIN_HOLE`
    filled); a triangle goes when one of its sample points (:data:`CARVE_SAMPLES`) that lies
    farther than :data:`CARVE_KEEP_NEAR` spacings from every model point projects outside the
    silhouette in some direction. A triangle on the surface projects onto the disks of the
    points around it in every direction, so only triangles across empty space are taken out.
    Deterministic.

    Args:
        points: (P, 3) model points, metres.
        F: (T, 3) triangles as indices into ``points``.

    Returns:
        (T,) bool, True = keep.
    """
    points = np.asarray(points, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    tree = KDTree(points)
    nn, _ = tree.query(points, k=2)
    spacing = float(np.median(nn[:, 1]))
    samples = np.einsum("sv,tvi->tsi", _barycentric(CARVE_SAMPLES), points[F])  # (T, S, 3)
    near, _ = tree.query(samples.reshape(-1, 3), k=1)
    near = (near <= CARVE_KEEP_NEAR * spacing).reshape(samples.shape[:2])  # (T, S)
    keep = np.ones(len(F), dtype=bool)
    for d in _half_sphere(CARVE_VIEWS):
        a = np.cross(d, [1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.cross(d, [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        B = np.stack([a, np.cross(d, a)], axis=1)  # (3, 2) image-plane axes
        covered, origin, cell = _point_silhouette(np.ascontiguousarray(points @ B), spacing)
        ij = np.floor((samples @ B - origin) / cell).astype(np.int64)  # (T, S, 2)
        ij = np.clip(ij, 0, np.array(covered.shape) - 1)
        keep &= (covered[ij[..., 0], ij[..., 1]] | near).all(axis=1)
    return keep


def surface_arrays(
    points: np.ndarray, use_cache: bool = True, version: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """A model's surface as arrays (:func:`surface_triangles`, or the packaged cache of it):
    ``(V, F)``, V the (P, 3) float64 model points in metres (model frame), F the (T, 3) int32
    point indices of its triangles. The packaged models' need no Open3D.

    Args:
        points: (P, 3) model points in metres (model frame).
        use_cache: look the surface up in the packaged cache first (same points and settings).
        version: surface version, one of :data:`SURFACE_VERSIONS`.
    """
    points = np.array(points, dtype=np.float64)
    F = _cached_triangles(points, version) if use_cache else None
    if F is None:
        F = surface_triangles(points, version)
    return points, F.astype(np.int32)


def build_mesh(
    points: np.ndarray, use_cache: bool = True, version: int = 1
) -> o3d.geometry.TriangleMesh:
    """:func:`surface_arrays` as an Open3D triangle mesh; its vertices are all P points."""
    import open3d as o3d

    V, F = surface_arrays(points, use_cache, version)
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F))


SURFACE_VERSION = 1
"""Version of the union surface (:func:`surface_triangles` version 1): bump when it changes,
so that a stale packaged cache is ignored."""

SURFACE_VERSIONS = (1, 2)
"""1: the union of ball pivoting and alpha shapes; 2: the same with through-holes carved
(:func:`carve_through_holes`)."""

SURFACE_CACHE = ("meshes", "surfaces.npz")
"""Packaged cache of the 21 models' version-1 surfaces (``resource_path(*SURFACE_CACHE)``):
:func:`surface_key` -> (T, 3) uint16 point indices."""

SURFACE_CARVE_CACHE = ("meshes", "surfaces-v2.npz")
"""Packaged cache of the version-2 surfaces, as the carved triangles only (a few KiB):
:func:`surface_key` of version 2 -> (C,) uint16 indices into the cached version-1 triangles
of the same points."""

_surface_cache: dict[str, np.ndarray] | None = None
_carve_cache: dict[str, np.ndarray] | None = None


def check_surface_version(version: int) -> None:
    """Raise ``ValueError`` unless ``version`` is one of :data:`SURFACE_VERSIONS`."""
    if version not in SURFACE_VERSIONS:
        raise ValueError(f"surface version {version!r}: expected one of {SURFACE_VERSIONS}")


def surface_settings(version: int = 1) -> str:
    """A surface version's build settings, as one string (in cache keys and synth.json)."""
    check_surface_version(version)
    union = (
        SURFACE_VERSION,
        SURFACE_BPA_RADII,
        SURFACE_ALPHA,
        SURFACE_PATCH_ALPHA,
        SURFACE_PATCH_TOL,
    )
    if version == 1:
        return repr(union)
    carve = (
        CARVE_VIEWS,
        CARVE_NEIGHBOUR,
        CARVE_RADIUS,
        CARVE_MIN_HOLE,
        CARVE_KEEP_NEAR,
        CARVE_SAMPLES,
    )
    return repr((version, union, carve))


def surface_key(points: np.ndarray, version: int = 1) -> str:
    """Cache key of a model's surface: the points' bytes and the version's build settings."""
    h = hashlib.sha1(np.ascontiguousarray(points, dtype=np.float64).tobytes())
    h.update(surface_settings(version).encode())
    return h.hexdigest()


def _load_npz(parts: tuple[str, str]) -> dict[str, np.ndarray]:
    path = resource_path(*parts)
    if not path.is_file():
        return {}
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _cached_triangles(points: np.ndarray, version: int = 1) -> np.ndarray | None:
    global _surface_cache, _carve_cache
    if _surface_cache is None:
        _surface_cache = _load_npz(SURFACE_CACHE)
    F = _surface_cache.get(surface_key(points))
    if F is None or (len(F) and F.max() >= len(points)):
        return None
    F = F.astype(np.int64)
    if version == 1:
        return F
    if _carve_cache is None:
        _carve_cache = _load_npz(SURFACE_CARVE_CACHE)
    carved = _carve_cache.get(surface_key(points, version))
    if carved is None or (len(carved) and carved.max() >= len(F)):
        return None
    keep = np.ones(len(F), dtype=bool)
    keep[carved.astype(np.int64)] = False
    return F[keep]


def write_surface_cache(version: int = 1, path: str | Path | None = None) -> Path:
    """Build the surfaces of the 21 packaged models and save them (the packaged cache).

    Version 1 writes :data:`SURFACE_CACHE` (regenerate after changing the union surface, and
    bump :data:`SURFACE_VERSION`: the synthetic frames of generator version 1 depend on it).
    Version 2 writes :data:`SURFACE_CARVE_CACHE` from the packaged version-1 triangles::

        python -c "from cloudpose.data.synth.surfaces import write_surface_cache as w; w(2)"

    Args:
        version: which cache to write.
        path: output .npz; default the packaged file of that version.

    Returns:
        The path written.
    """
    global _surface_cache, _carve_cache
    check_surface_version(version)
    default = SURFACE_CACHE if version == 1 else SURFACE_CARVE_CACHE
    path = Path(path) if path is not None else resource_path(*default)
    path.parent.mkdir(parents=True, exist_ok=True)
    out = {}
    for pts in load_packaged_models().values():
        assert len(pts) <= np.iinfo(np.uint16).max
        if version == 1:
            out[surface_key(pts)] = surface_triangles(pts).astype(np.uint16)
            continue
        F = _cached_triangles(pts, 1)
        if F is None:
            raise ValueError(
                f"{resource_path(*SURFACE_CACHE)}: no current version-1 surface for a packaged "
                "model; write that cache first (write_surface_cache(1))"
            )
        assert len(F) <= np.iinfo(np.uint16).max
        carved = np.flatnonzero(~carve_through_holes(pts, F))
        out[surface_key(pts, version)] = carved.astype(np.uint16)
    np.savez_compressed(path, **out)
    _surface_cache = _carve_cache = None
    return path
