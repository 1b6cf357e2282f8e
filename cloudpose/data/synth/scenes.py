"""Synthetic scenes: objects on a table (in their resting poses, some stacked) or floating.

Both scene kinds stay in one file of ~650 lines on purpose: they share the :class:`Scene` and
:class:`Plane` types and the object-count and in-image rules, and most of the length is the table
sampler, whose placement and stacking steps work on one footprint raster (:class:`_Layout`).

See :mod:`cloudpose.data.synth` for the whole generator; this module samples where the objects
are and where the camera is, with no rendering. The stable resting poses the table scenes draw
from are in :mod:`cloudpose.data.synth.resting`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.transform import Rotation

from cloudpose.conventions import IMAGE_SHAPE, YCB_INTRINSICS
from cloudpose.data.synth.resting import RestingPoses
from cloudpose.kernels.backend import enabled
from cloudpose.kernels.placement import (
    close_cells,
    column_means,
    contact_cells,
    count_in_image,
    hull_margin,
    placed_cells,
    raster_cells,
    slide_steps,
    top_cells,
)

N_OBJECTS = (3, 8)
"""Objects per table scene (inclusive)."""
CAMERA_DISTANCE = (0.5, 1.3)
"""Camera to look-at point, metres."""
CAMERA_ELEVATION_DEG = (20.0, 70.0)
"""Angle of the optical axis below the horizontal."""
MAX_RANGE = 4.0
"""Depth beyond this (metres) has no reading, like the real sensor."""
MIN_VISIBLE_PIXELS = 100
"""An object with fewer visible pixels is taken out of the scene (not annotated)."""
MIN_IN_IMAGE = 0.6
"""An object with less than this share of its projected model points inside the image is taken
out of the scene (YCB-Video annotates objects that are mostly in view)."""

UPRIGHT_SHARE = 0.8
"""Share of objects put in their tallest stable pose (hand-arranged scenes stand objects up,
as in YCB-Video), the rest drawn by quasi-static probability."""
GAP_MEAN = 0.002
"""Mean gap (metres, exponential) between a new object and the cluster it joins."""
FAR_SHARE, FAR_GAP = 0.05, (0.03, 0.15)
"""Share of objects placed with a wide gap (uniform in FAR_GAP metres): the unoccluded ones."""

STACK_SHARE = 0.35
"""Version-2 scenes: share of objects (after the first) that try to rest on the top of an
object standing on the table instead of on the table (real YCB-Video scenes stack a can on a
box); an object that finds no stable place there goes on the table. About one object in ten
ends up stacked."""
STACK_MARGIN = 0.005
"""Metres the centre of mass of a stacked object must lie inside its support polygon (the
contact region of its resting face with the top of the object below)."""
STACK_CONTACT = 0.003
"""Metres: the points of the lower object within this of its top form its top surface."""

_GRID = 0.005  # footprint raster cell, metres
_GRID_HALF = 160  # cells each side of the table origin (1.6 m square)
_START = 0.5  # metres from the cluster centre where a new object starts sliding in


@dataclass
class Plane:
    """A planar background patch in world coordinates (label 0, depth only).

    Attributes:
        point: (3,) a point on the plane (the patch centre), metres.
        normal: (3,) unit normal.
        axes: (2, 3) unit in-plane axes of the patch rectangle, or None (unbounded).
        half_extent: (2,) half sizes along ``axes``, metres, or None.
    """

    point: np.ndarray
    normal: np.ndarray
    axes: np.ndarray | None = None
    half_extent: np.ndarray | None = None


@dataclass
class Scene:
    """A sampled scene before rendering.

    Attributes:
        cls_ids: (N,) 1-based class ids (distinct).
        model_to_world: (N, 3, 4) object poses in the world frame (table scenes: table top z = 0,
            z up; floating scenes: the camera frame).
        world_to_camera: (3, 4) camera extrinsics.
        look_at: (3,) the point the optical axis passes through (the scene centre), world.
        background: planes rendered in depth behind the objects.
        support: (N,) index of the object each one rests on, -1 = the table or nothing; None
            = all -1.
    """

    cls_ids: np.ndarray
    model_to_world: np.ndarray
    world_to_camera: np.ndarray
    look_at: np.ndarray
    background: list[Plane]
    support: np.ndarray | None = None

    def poses(self) -> np.ndarray:
        """(N, 3, 4) object->camera poses."""
        Rc, tc = self.world_to_camera[:, :3], self.world_to_camera[:, 3]
        R = Rc @ self.model_to_world[:, :, :3]
        t = self.model_to_world[:, :, 3] @ Rc.T + tc
        return np.concatenate([R, t[:, :, None]], axis=2)

    def subset(self, keep: np.ndarray) -> Scene:
        """The scene with only the objects where ``keep`` (bool (N,) or indices).

        An object whose support is left out goes too (it would float): use
        :meth:`supported` first to know which objects remain.
        """
        if self.support is None:
            return Scene(
                self.cls_ids[keep],
                self.model_to_world[keep],
                self.world_to_camera,
                self.look_at,
                self.background,
            )
        mask = self.supported(keep)
        new_index = np.cumsum(mask) - 1
        support = np.where(self.support >= 0, new_index[np.maximum(self.support, 0)], -1)
        return Scene(
            self.cls_ids[mask],
            self.model_to_world[mask],
            self.world_to_camera,
            self.look_at,
            self.background,
            support[mask],
        )

    def supported(self, keep: np.ndarray) -> np.ndarray:
        """(N,) bool: ``keep`` (bool (N,) or indices) less the objects whose support (or its
        support, ...) is not kept."""
        mask = np.zeros(len(self.cls_ids), dtype=bool)
        mask[keep] = True
        if self.support is None:
            return mask
        while True:
            lost = mask & (self.support >= 0) & ~mask[np.maximum(self.support, 0)]
            if not lost.any():
                return mask
            mask &= ~lost


def _yaw(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _footprint_cells(points_xy: np.ndarray) -> np.ndarray:
    """(C, 2) integer grid cells covered by a posed object's footprint (relative to its origin).

    The projected model points are rasterised, closed and hole-filled (the surface points of a
    box cover its footprint; gaps between them do not make it porous).
    """
    return _raster_cells(points_xy, True)


def look_at_camera(eye: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """(3, 4) world->camera extrinsics of an OpenCV camera at ``eye`` looking at ``target``.

    World z is up; the image x axis stays horizontal before the ``roll`` (radians) about the
    optical axis.
    """
    f = target - eye
    f = f / np.linalg.norm(f)
    right = _cross(f, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right)
    down = _cross(f, right)
    R = np.stack([right, down, f])  # rows: camera axes in world coordinates
    c, s = np.cos(roll), np.sin(roll)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R
    return np.concatenate([R, (-R @ eye)[:, None]], axis=1)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3,) ``np.cross`` of two (3,) vectors (its products and differences, without its
    broadcasting machinery)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _in_image_fraction(points_cam: np.ndarray, K: np.ndarray, shape: tuple[int, int]) -> float:
    """Share of the (P, 3) camera-frame points in front of the camera that project into the
    image; the compiled :func:`cloudpose.kernels.placement.count_in_image` where the kernels
    are enabled (the same test), else :func:`_in_image_fraction_numpy`."""

    if not enabled():
        return _in_image_fraction_numpy(points_cam, K, shape)

    uvw = points_cam @ K.T
    return count_in_image(points_cam, uvw, shape[0], shape[1]) / len(points_cam)


def _in_image_fraction_numpy(
    points_cam: np.ndarray, K: np.ndarray, shape: tuple[int, int]
) -> float:
    """The numpy twin of :func:`_in_image_fraction`."""
    z = points_cam[:, 2]
    front = z > 1e-3
    uvw = points_cam @ K.T
    zf = np.where(front, z, 1.0)
    u = uvw[:, 0] / zf
    v = uvw[:, 1] / zf
    inside = front & (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    return np.count_nonzero(inside) / len(inside)


def _raster_cells(points_xy: np.ndarray, fill: bool) -> np.ndarray:
    """(C, 2) grid cells (absolute, ``floor(xy / _GRID)``) covered by points, closed; holes
    filled when ``fill`` (a footprint), kept otherwise (a top surface may be a ring). The
    compiled :func:`cloudpose.kernels.placement.raster_cells` where the kernels are enabled
    (the same cells), else :func:`_raster_cells_numpy`."""

    if not enabled():
        return _raster_cells_numpy(points_xy, fill)

    return raster_cells(np.ascontiguousarray(points_xy, dtype=np.float64), _GRID, fill)


def _raster_cells_numpy(points_xy: np.ndarray, fill: bool) -> np.ndarray:
    """The numpy twin of :func:`_raster_cells`."""
    ij = np.floor(points_xy / _GRID).astype(np.int64)
    lo = ij.min(axis=0) - 2
    img = np.zeros(ij.max(axis=0) - lo + 3, dtype=bool)
    img[ij[:, 0] - lo[0], ij[:, 1] - lo[1]] = True
    return np.argwhere(_close(img, fill)) + lo


def _close_numpy(img: np.ndarray, fill: bool) -> np.ndarray:
    """A raster closed (two steps of the 4-neighbour cross), its holes filled when ``fill``."""
    img = ndimage.binary_closing(img, iterations=2)
    return ndimage.binary_fill_holes(img) if fill else img


def _close(img: np.ndarray, fill: bool) -> np.ndarray:
    """:func:`_close_numpy` by the compiled :func:`cloudpose.kernels.placement.close_cells`
    where the kernels are enabled (the same raster)."""

    if not enabled():
        return _close_numpy(img, fill)

    return close_cells(img, fill)


def _slide(
    cells: np.ndarray, occupied: np.ndarray, anchor: np.ndarray, step: np.ndarray
) -> np.ndarray | None:
    """Position (2,) of the last step, sliding from :data:`_START` metres out towards
    ``anchor`` along ``step``, at which the footprint ``cells`` is on the grid and free before
    it first touches ``occupied``; None if none is. The compiled
    :func:`cloudpose.kernels.placement.slide_steps` where the kernels are enabled (the same
    step), else this numpy loop."""

    if not enabled():
        return _slide_numpy(cells, occupied, anchor, step)

    k = slide_steps(cells, occupied, anchor, step, int(_START / _GRID), _GRID, _GRID_HALF)
    return None if k < 0 else anchor + step * (k * _GRID)


def _slide_numpy(
    cells: np.ndarray, occupied: np.ndarray, anchor: np.ndarray, step: np.ndarray
) -> np.ndarray | None:
    """The numpy twin of :func:`_slide` (one fancy-indexing pass per step)."""
    xy = None
    for k in range(int(_START / _GRID), -1, -1):
        cand = anchor + step * (k * _GRID)
        ij = cells + np.floor(cand / _GRID).astype(np.int64) + _GRID_HALF
        if (ij < 0).any() or (ij >= 2 * _GRID_HALF).any():
            continue
        if occupied[ij[:, 0], ij[:, 1]].any():
            break
        xy = cand
    return xy


def _cell_keys(cells: np.ndarray) -> np.ndarray:
    """(C,) int64 one key per (C, 2) grid cell (cells within 2^20 of the origin)."""
    cells = np.asarray(cells, dtype=np.int64)
    return (cells[:, 0] + (1 << 20)) * (1 << 21) + (cells[:, 1] + (1 << 20))


def _member(keys: np.ndarray, of: np.ndarray) -> np.ndarray:
    """(K,) bool: each of ``keys`` in ``of`` (``np.isin``'s answer, by a binary search of
    ``of`` sorted; the caller keeps a support's keys sorted, so the sort is a pass)."""
    of = np.sort(of)
    if not len(of):
        return np.zeros(len(keys), dtype=bool)
    return of[np.minimum(np.searchsorted(of, keys), len(of) - 1)] == keys


def _member_numpy(keys: np.ndarray, of: np.ndarray) -> np.ndarray:
    """The numpy twin of :func:`_member`."""
    return np.isin(keys, of)


def _contact_cells(bottom: np.ndarray, origin: np.ndarray, top_keys: np.ndarray) -> np.ndarray:
    """(C, 2) the cells of the (P, 2) resting face ``bottom`` moved by ``origin`` (2,) that
    are cells of a support's top (their keys, :func:`_cell_keys`, sorted: ``top_keys``), in
    raster order; the compiled :func:`cloudpose.kernels.placement.contact_cells` where the
    kernels are enabled (the same cells), else :func:`_contact_cells_numpy`."""

    if not enabled():
        return _contact_cells_numpy(bottom, origin, top_keys)

    return contact_cells(
        np.ascontiguousarray(bottom, dtype=np.float64),
        np.asarray(origin, dtype=np.float64),
        _GRID,
        np.ascontiguousarray(top_keys, dtype=np.int64),
    )


def _contact_cells_numpy(
    bottom: np.ndarray, origin: np.ndarray, top_keys: np.ndarray
) -> np.ndarray:
    """The numpy twin of :func:`_contact_cells`."""
    contact = _raster_cells(bottom + origin, fill=False)
    return contact[_member(_cell_keys(contact), top_keys)]


def _supports(contact: np.ndarray, xy_com: np.ndarray) -> bool:
    """Whether ``xy_com`` (2,) lies inside the convex hull of the (K, 2) contact cells'
    centres by :data:`STACK_MARGIN` (False where the cells are collinear). The compiled
    :func:`cloudpose.kernels.placement.hull_margin` where the kernels are enabled and its
    margin is farther than 1e-9 m from :data:`STACK_MARGIN` (qhull's facets give the same
    margin to ~1e-16 m, so the same answer), else :func:`_supports_numpy`."""

    if enabled():
        cells = np.ascontiguousarray(contact, dtype=np.int64)
        status, margin = hull_margin(cells, _GRID, float(xy_com[0]), float(xy_com[1]))
        if status == 1:  # no area: qhull raises, or finds a sliver no point is inside by a margin
            return False
        if abs(margin - STACK_MARGIN) > 1e-9:
            return margin >= STACK_MARGIN
    return _supports_numpy(contact, xy_com)


def _supports_numpy(contact: np.ndarray, xy_com: np.ndarray) -> bool:
    """The twin of :func:`_supports`, by qhull's facet equations."""
    try:
        eq = ConvexHull((np.asarray(contact, dtype=np.float64) + 0.5) * _GRID).equations
    except QhullError:  # collinear contact cells: a line, no support area
        return False
    return not -(eq[:, :2] @ xy_com + eq[:, 2]).max() < STACK_MARGIN


def _column_means(points: np.ndarray) -> np.ndarray:
    """(C,) ``np.mean(points, axis=0)`` of (P, C) float64 points: the compiled
    :func:`cloudpose.kernels.placement.column_means` where the kernels are enabled (the same
    sums in the same order), else :func:`_column_means_numpy`."""

    if not enabled():
        return _column_means_numpy(points)

    return column_means(np.ascontiguousarray(points, dtype=np.float64))


def _column_means_numpy(points: np.ndarray) -> np.ndarray:
    """The numpy twin of :func:`_column_means`."""
    return np.mean(points, axis=0)


class _Support(NamedTuple):
    """An object on the table that another may rest on: index, top height, top cells."""

    index: int
    top_z: float
    top_cells: np.ndarray


def _try_stack(
    rng: np.random.Generator,
    local: np.ndarray,
    height: float,
    supports: list[_Support],
    height_map: np.ndarray,
    tries: int = 8,
) -> tuple[int, np.ndarray, np.ndarray] | None:
    """Find a stable place for a posed object on the top of one of ``supports``.

    The object's resting face (its points within :data:`STACK_CONTACT` of its lowest point)
    and the support's top surface overlap in a contact region; the object's centre of mass
    must lie inside that region's convex hull by :data:`STACK_MARGIN`, and no other object
    under its footprint may reach above the support's top (``height_map``).

    Args:
        rng: random generator.
        local: (P, 3) the object's points rotated into its resting pose, relative to its origin.
        height: lift of the origin above the surface it rests on, metres.
        supports: candidate objects below.
        height_map: (G, G) highest point of the placed objects per grid cell, metres.

    Returns:
        (index into ``supports``, (3,) world position of the origin, (C, 2) footprint grid
        indices), or None.
    """
    bottom = local[local[:, 2] <= local[:, 2].min() + STACK_CONTACT, :2]
    com = _column_means(local)[:2]
    tops: dict[int, np.ndarray] = {}  # the top cells of each support tried, as sorted keys
    for _ in range(tries):
        k = int(rng.integers(len(supports)))
        sup = supports[k]
        cell = sup.top_cells[rng.integers(len(sup.top_cells))]
        xy_com = (cell + rng.random(2)) * _GRID
        origin = xy_com - com
        if k not in tops:
            tops[k] = np.sort(_cell_keys(sup.top_cells))
        contact = _contact_cells(bottom, origin, tops[k])
        if len(contact) < 3 or not _supports(contact, xy_com):
            continue
        foot = _raster_cells(local[:, :2] + origin, fill=True) + _GRID_HALF
        if (foot < 0).any() or (foot >= 2 * _GRID_HALF).any():
            continue
        if (height_map[foot[:, 0], foot[:, 1]] > sup.top_z + 1e-6).any():
            continue
        return k, np.array([*origin, sup.top_z + height]), foot
    return None


@dataclass
class _Layout:
    """The objects placed so far on the table, on the footprint raster.

    Attributes:
        occupied: (G, G) bool grid cells covered by a placed object's footprint.
        height_map: (G, G) highest point of the placed objects per grid cell, metres (kept only
            when stacking).
        placed_xy: (2,) table position of each placed object's origin, metres.
        poses: (class id, (3, 4) model->world pose) of each placed object.
        points: (P, 3) model points of each placed object in the world frame, metres.
        supports: the objects on the table that nothing rests on yet (stacking only).
        resting_on: index of the object each placed one rests on, -1 = the table (stacking
            only).
    """

    occupied: np.ndarray
    height_map: np.ndarray
    placed_xy: list[np.ndarray]
    poses: list[tuple[int, np.ndarray]]
    points: list[np.ndarray]
    supports: list[_Support]
    resting_on: list[int]

    @classmethod
    def empty(cls) -> _Layout:
        occupied = np.zeros((2 * _GRID_HALF, 2 * _GRID_HALF), dtype=bool)
        return cls(occupied, np.zeros(occupied.shape), [], [], [], [], [])

    def raise_heights(self, cells: np.ndarray, top: float) -> None:
        """Mark the (C, 2) grid indices ``cells`` occupied, reaching at least ``top`` metres."""
        self.occupied[cells[:, 0], cells[:, 1]] = True
        self.height_map[cells[:, 0], cells[:, 1]] = np.maximum(
            self.height_map[cells[:, 0], cells[:, 1]], top
        )


def _draw_resting_pose(rng: np.random.Generator, rp: RestingPoses) -> tuple[int, np.ndarray]:
    """(index of the stable pose, (3, 3) model->table rotation with a uniform random yaw)."""
    if rng.random() < UPRIGHT_SHARE:
        s = int(np.argmax(rp.heights_up))
    else:
        s = int(rng.choice(len(rp.probabilities), p=rp.probabilities))
    return s, _yaw(rng.uniform(0.0, 2.0 * np.pi)) @ rp.rotations[s]


def _stack_object(
    rng: np.random.Generator,
    layout: _Layout,
    c: int,
    R: np.ndarray,
    local: np.ndarray,
    rp: RestingPoses,
    s: int,
) -> bool:
    """Put object ``c`` (rotation ``R``, points ``local`` = model @ R.T, stable pose ``s``) on
    the top of one of ``layout.supports`` (:func:`_try_stack`); False if it finds no place."""
    found = _try_stack(rng, local, rp.heights[s], layout.supports, layout.height_map)
    if found is None:
        return False
    k, origin, foot = found
    layout.raise_heights(foot, origin[2] - rp.heights[s] + rp.heights_up[s])
    layout.resting_on.append(layout.supports.pop(k).index)
    layout.placed_xy.append(origin[:2])
    layout.poses.append((c, np.concatenate([R, origin[:, None]], axis=1)))
    layout.points.append(local + origin)
    return True


def _placed_cells(
    cells: np.ndarray, occupied: np.ndarray, xy: np.ndarray
) -> tuple[np.ndarray, bool]:
    """The grid indices (C, 2) of the footprint ``cells`` of an object at ``xy`` (2,) metres,
    and whether they are all on the grid and free of ``occupied``; the compiled
    :func:`cloudpose.kernels.placement.placed_cells` where the kernels are enabled (the same
    indices and answer), else :func:`_placed_cells_numpy`."""

    if not enabled():
        return _placed_cells_numpy(cells, occupied, xy)

    return placed_cells(cells, occupied, np.asarray(xy, dtype=np.float64), _GRID, _GRID_HALF)


def _placed_cells_numpy(
    cells: np.ndarray, occupied: np.ndarray, xy: np.ndarray
) -> tuple[np.ndarray, bool]:
    """The numpy twin of :func:`_placed_cells`."""
    ij = cells + np.floor(xy / _GRID).astype(np.int64) + _GRID_HALF
    off = (ij < 0).any() or (ij >= 2 * _GRID_HALF).any()
    return ij, not (off or occupied[ij[:, 0], ij[:, 1]].any())


def _top_cells(world: np.ndarray) -> tuple[np.ndarray, float]:
    """The top surface of a posed object's (P, 3) world points: the cells (closed, holes kept)
    of the points within :data:`STACK_CONTACT` of the highest, and that height, metres; the
    compiled :func:`cloudpose.kernels.placement.top_cells` where the kernels are enabled (the
    same cells), else :func:`_top_cells_numpy`."""

    if not enabled():
        return _top_cells_numpy(world)

    cells, z = top_cells(np.ascontiguousarray(world, dtype=np.float64), STACK_CONTACT, _GRID)
    return cells, float(z)


def _top_cells_numpy(world: np.ndarray) -> tuple[np.ndarray, float]:
    """The numpy twin of :func:`_top_cells`."""
    z = world[:, 2].max()
    return _raster_cells(world[world[:, 2] >= z - STACK_CONTACT, :2], False), float(z)


def _slide_object(
    rng: np.random.Generator,
    layout: _Layout,
    c: int,
    R: np.ndarray,
    local: np.ndarray,
    rp: RestingPoses,
    s: int,
    stacking: bool,
) -> None:
    """Put object ``c`` on the table: slide it in from a random direction towards the cluster
    centre until its footprint would touch, then out by a random gap; left out when the gap
    pushes it into another object or off the grid. With ``stacking``, it becomes a support."""
    cells = _footprint_cells(local[:, :2])
    direction = rng.uniform(0.0, 2.0 * np.pi)
    gap = rng.exponential(GAP_MEAN) if rng.random() > FAR_SHARE else rng.uniform(*FAR_GAP)
    anchor = _mean_xy(layout.placed_xy)
    step = np.array([np.cos(direction), np.sin(direction)])
    xy = _slide(cells, layout.occupied, anchor, step)
    if xy is None:
        return
    xy = xy + step * gap
    ij, free = _placed_cells(cells, layout.occupied, xy)
    if not free:
        return
    pose = np.concatenate([R, np.array([*xy, rp.heights[s]])[:, None]], axis=1)
    world = local + pose[:, 3]
    layout.placed_xy.append(xy)
    layout.poses.append((c, pose))
    layout.points.append(world)
    if not stacking:
        layout.occupied[ij[:, 0], ij[:, 1]] = True
        return
    layout.raise_heights(ij, rp.heights_up[s])
    top_cells, top_z = _top_cells(world)
    layout.supports.append(_Support(len(layout.poses) - 1, top_z, top_cells))
    layout.resting_on.append(-1)


def _mean_xy(xy: list[np.ndarray]) -> np.ndarray:
    """(2,) ``np.mean(xy, axis=0)`` of the (2,) positions (its sums row after row, divided by
    their number), without building the array; (0, 0) for none."""
    if not xy:
        return np.zeros(2)
    x, y = float(xy[0][0]), float(xy[0][1])
    for p in xy[1:]:
        x, y = x + float(p[0]), y + float(p[1])
    return np.array([x / len(xy), y / len(xy)])


def _place_objects(
    rng: np.random.Generator,
    ids: np.ndarray,
    models: dict[int, np.ndarray],
    resting: dict[int, RestingPoses],
    stack_share: float,
) -> _Layout:
    """Draw the classes of a table scene and place them one by one (some may not fit)."""
    n = min(int(rng.integers(N_OBJECTS[0], N_OBJECTS[1] + 1)), len(ids))
    layout = _Layout.empty()
    for c in rng.choice(ids, size=n, replace=False):
        rp = resting[int(c)]
        s, R = _draw_resting_pose(rng, rp)
        local = models[int(c)] @ R.T
        if stack_share > 0 and layout.supports and rng.random() < stack_share:
            if _stack_object(rng, layout, int(c), R, local, rp, s):
                continue
        _slide_object(rng, layout, int(c), R, local, rp, s, stack_share > 0)
    return layout


def _view_table(
    rng: np.random.Generator,
    objects: Scene,
    points: list[np.ndarray],
    K: np.ndarray,
    shape: tuple[int, int],
    tries: int = 20,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Draw a camera looking down at the placed ``objects`` (their camera fields unused) that
    keeps at least ``N_OBJECTS[0]`` of them mostly in the image; ``points``: each object's
    (P, 3) model points in the world frame (:attr:`_Layout.points`).

    Returns:
        ((3, 4) world->camera extrinsics, (3,) look-at point, (N,) bool objects kept: in the
        image, with what they rest on), or None after ``tries`` cameras.
    """
    centre_xy = objects.model_to_world[:, :2, 3].mean(axis=0)
    for _ in range(tries):
        target = np.array([*(centre_xy + rng.normal(0.0, 0.03, 2)), rng.uniform(0.0, 0.05)])
        dist = rng.uniform(*CAMERA_DISTANCE)
        elev = np.deg2rad(rng.uniform(*CAMERA_ELEVATION_DEG))
        azim = rng.uniform(0.0, 2.0 * np.pi)
        eye = target + dist * np.array(
            [np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)]
        )
        world_to_camera = look_at_camera(eye, target, roll=np.deg2rad(rng.normal(0.0, 5.0)))
        Rc, tc = world_to_camera[:, :3], world_to_camera[:, 3]
        in_image = np.array(
            [_in_image_fraction(p @ Rc.T + tc, K, shape) >= MIN_IN_IMAGE for p in points]
        )
        keep = objects.supported(in_image)  # what rests on an object out of the image goes too
        if keep.sum() >= N_OBJECTS[0]:
            return world_to_camera, target, keep
    return None


def _table_and_floor(rng: np.random.Generator, placed_xy: np.ndarray) -> list[Plane]:
    """The table, a rectangle of random size and yaw around the (N, 2) object positions
    ``placed_xy`` (metres), and the floor below it."""
    lo = placed_xy.min(axis=0) - 0.15
    hi = placed_xy.max(axis=0) + 0.15
    half = np.maximum((hi - lo) / 2.0, 0.0) + rng.uniform(0.1, 0.4, 2)
    table_yaw = _yaw(rng.uniform(0.0, np.pi))
    # a yawed rectangle must still cover the cluster: take the half-diagonal as extent
    half = np.full(2, np.linalg.norm(half))
    table = Plane(
        np.array([*((lo + hi) / 2.0), 0.0]), np.array([0.0, 0.0, 1.0]), table_yaw[:2, :3], half
    )
    floor = Plane(np.array([0.0, 0.0, -rng.uniform(0.7, 0.8)]), np.array([0.0, 0.0, 1.0]))
    return [table, floor]


def sample_table_scene(
    rng: np.random.Generator,
    models: dict[int, np.ndarray],
    resting: dict[int, RestingPoses],
    K: np.ndarray = YCB_INTRINSICS,
    shape: tuple[int, int] = IMAGE_SHAPE,
    stack_share: float = 0.0,
) -> Scene:
    """Sample objects resting on a table, clustered, and a camera looking down at them.

    Objects are placed one by one: a random already-placed anchor and direction, then the new
    object slides out from the anchor until its footprint is free, plus a small random gap (so
    objects stand close and hide each other from many viewpoints). With ``stack_share`` > 0, an
    object first tries, with that probability, to rest on the top of an object standing on the
    table (:func:`_try_stack`; one object per support). Objects mostly outside the image are
    taken out of the scene (with what rests on them); if fewer than 3 remain, the camera is
    drawn again, and after 20 cameras the objects too.

    Args:
        rng: random generator (the only source of randomness).
        models: {class id: (P, 3) model points, metres}: the classes a scene draws from
            (at least ``N_OBJECTS[0]``; a scene holds at most one object of each class).
        resting: {class id: :class:`RestingPoses`}.
        K: (3, 3) intrinsics.
        shape: (H, W) image size.
        stack_share: probability that an object tries to rest on another (0: never, and no
            random number is drawn for it).

    Returns:
        The :class:`Scene` (world = table frame, z up, table top at z = 0).
    """
    ids = np.array(sorted(models))
    if len(ids) < N_OBJECTS[0]:
        raise ValueError(
            f"a table scene holds at least {N_OBJECTS[0]} distinct objects; got models of "
            f"{len(ids)} classes {ids.tolist()}"
        )
    while True:
        layout = _place_objects(rng, ids, models, resting, stack_share)
        if len(layout.poses) < N_OBJECTS[0]:
            continue
        objects = Scene(
            np.array([c for c, _ in layout.poses], dtype=np.int64),
            np.stack([p for _, p in layout.poses]),
            np.zeros((3, 4)),
            np.zeros(3),
            [],
            np.array(layout.resting_on, dtype=np.int64) if stack_share > 0 else None,
        )
        view = _view_table(rng, objects, layout.points, K, shape)
        if view is None:
            continue
        world_to_camera, look_at, keep = view
        background = _table_and_floor(rng, np.asarray(layout.placed_xy))
        scene = Scene(
            objects.cls_ids,
            objects.model_to_world,
            world_to_camera,
            look_at,
            background,
            objects.support,
        )
        return scene.subset(keep)


def uniform_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3, 3) rotations uniform on SO(3) (scipy's ``Rotation.random``)."""
    return Rotation.random(n, rng=rng).as_matrix()


def _random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3, 3) rotations uniform on SO(3) (normalised Gaussian quaternions, WXYZ).

    The generator-version-1 sampler, kept only so that version-1 frames stay byte-identical
    (its draws fix their scenes); everything else uses :func:`uniform_rotations`.
    """
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def sample_floating_scene(
    rng: np.random.Generator,
    models: dict[int, np.ndarray],
    K: np.ndarray = YCB_INTRINSICS,
    shape: tuple[int, int] = IMAGE_SHAPE,
    rotations: Callable[[np.random.Generator, int], np.ndarray] = uniform_rotations,
) -> Scene:
    """Sample objects floating in front of the camera in uniformly random rotations.

    Objects are clustered around a centre 0.6-1.2 m in front of the camera, their bounding
    spheres disjoint (no interpenetration) but often overlapping in the image; a wall behind
    them gives background depth. World frame = camera frame.

    Args:
        rng: random generator.
        models: {class id: (P, 3) model points, metres}.
        K: (3, 3) intrinsics.
        shape: (H, W) image size.
        rotations: sampler of (n, 3, 3) uniform rotations from ``rng``.

    Returns:
        The :class:`Scene`.
    """
    ids = np.array(sorted(models))
    Kinv = np.linalg.inv(K)
    while True:
        n = int(rng.integers(N_OBJECTS[0], N_OBJECTS[1] + 1))
        cls_ids = rng.choice(ids, size=n, replace=False)
        z0 = rng.uniform(0.6, 1.2)
        pix = np.array([rng.uniform(0.3, 0.7) * shape[1], rng.uniform(0.3, 0.7) * shape[0], 1.0])
        centre = Kinv @ pix * z0
        object_rotations = rotations(rng, n)
        placed, radii, poses = [], [], []
        for c, R in zip(cls_ids, object_rotations, strict=True):
            pts = models[int(c)]
            radius = float(np.linalg.norm(pts, axis=1).max())
            for _ in range(50):
                t = centre + rng.normal(0.0, 0.08, 3) * np.array([1.0, 1.0, 1.5])
                if all(
                    np.linalg.norm(t - p) > radius + r for p, r in zip(placed, radii, strict=True)
                ):
                    break
            else:
                continue
            P = np.concatenate([R, t[:, None]], axis=1)
            if t[2] < 0.3 or _in_image_fraction(pts @ R.T + t, K, shape) < MIN_IN_IMAGE:
                continue
            placed.append(t)
            radii.append(radius)
            poses.append((int(c), P))
        if len(poses) < N_OBJECTS[0]:
            continue
        far = max(p[2] + r for p, r in zip(placed, radii, strict=True))
        tilt = rotations(rng, 1)[0]
        normal = np.array([0.0, 0.0, -1.0])
        # a wall facing the camera, tilted at most ~35 degrees, 0.2-1 m behind the objects
        for _ in range(100):
            normal = tilt @ np.array([0.0, 0.0, -1.0])
            if normal[2] < -np.cos(np.deg2rad(35.0)):
                break
            tilt = rotations(rng, 1)[0]
        wall = Plane(np.array([0.0, 0.0, far + rng.uniform(0.2, 1.0)]), normal)
        cam = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
        return Scene(
            np.array([c for c, _ in poses], dtype=np.int64),
            np.stack([p for _, p in poses]),
            cam,
            centre,
            [wall],
        )
