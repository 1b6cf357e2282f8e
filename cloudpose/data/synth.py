"""Synthetic YCB-Video scenes rendered from the 21 real model point sets (``cloudpose synth``).

The output is a dataset root in the real YCB-Video layout (DESIGN.md, "Data"), so one reader
(:class:`cloudpose.data.ycb.YCBVideo`) and one segment pipeline serve real and synthetic data::

    ROOT/classes.txt                        the 21 YCB-Video classes (copy of the package's)
    ROOT/models/NAME/points.xyz             copies of the 21 packaged model point sets
    ROOT/data/SEQ/FRAME-{depth,label}.png   depth uint16 (10000 per metre), label uint8
    ROOT/data/SEQ/FRAME-meta.mat            cls_indexes, poses, intrinsic_matrix, factor_depth,
                                            and ``alone_pixels`` (see below)
    ROOT/image_sets/train.txt, test.txt     the requested frame counts (rewritten each call)
    ROOT/keyframe.txt                       = image_sets/test.txt, as in YCB-Video
    ROOT/synth.json                         the generator settings (checked when resuming)

Frame i of a split is a pure function of ``(seed, split, i)``: its random generator is
``np.random.default_rng([seed, split_code, i])``. Asking for more frames later only adds frames,
and a smaller preset uses a prefix of a bigger one. Train frames live in sequences 0000, 0001,
..., test frames in 1000, 1001, ..., :data:`FRAMES_PER_SEQ` frames each.

Scenes (default): 3 to 8 distinct objects resting on a table in stable poses (faces of each
model's convex hull on which its centre of mass rests, drawn with probability proportional to
their solid angle from the centre of mass, plus a random yaw), packed in a cluster without
interpenetration (a 2D footprint check), seen by a camera 0.5-1.3 m from the look-at point
(the scene centre) looking down 20-70 degrees. The table (label 0) and the floor below it are
rendered in depth, as real frames have background depth. With ``uniform_rotation`` the objects
float in front of a wall in rotations drawn uniformly from SO(3).

Sensor noise (on by default; never changes the label image): Kinect-like axial Gaussian noise
``sigma(z) = 1.2 mm + 1.9 mm/m^2 (z - 0.4 m)^2`` (Nguyen et al., 3DIMPVT 2012), disparity
quantisation to 1/8 pixel (focal 580 px, baseline 7.5 cm: 2.9 mm steps at 1 m), missing and
"flying" (mixed foreground/background) pixels at depth edges, and a small random dropout.
Pixels without a reading have depth 0.

Runs on the same root may overlap (e.g. parallel training runs that each ensure the data): a
frame is written by renaming whole files, so two runs rendering the same frame leave identical,
complete files. The frames depend on the renderer's surfaces: after a change to
``cloudpose/data/render.py`` that alters them, render into a fresh root.

``alone_pixels``: each meta also stores, per instance, the pixel count of the object rendered
alone at its pose (the occlusion factor's nu, DESIGN.md "Metrics"). The real dataset has no such
field; the segment pipeline renders it when it is absent.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import scipy.io
from scipy import ndimage
from scipy.spatial import ConvexHull

from cloudpose.files import atomic_text
from cloudpose.conventions import IMAGE_SHAPE, YCB_INTRINSICS, resource_path

GENERATOR_VERSION = 1
"""Bumped whenever a change makes frames differ; stored in ``synth.json``."""

SPLIT_CODES = {"train": 0, "test": 1}
SEQ_OFFSET = {"train": 0, "test": 1000}
FRAMES_PER_SEQ = 100

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

_GRID = 0.005  # footprint raster cell, metres
_GRID_HALF = 160  # cells each side of the table origin (1.6 m square)
_START = 0.5  # metres from the cluster centre where a new object starts sliding in


# --------------------------------------------------------------------------- resting poses


class RestingPoses(NamedTuple):
    """The stable resting poses of one model on a horizontal plane.

    Attributes:
        rotations: (S, 3, 3) model->table rotations that put a stable face down (table z up),
            before the random yaw.
        heights: (S,) metres to lift the model origin so its lowest point touches z = 0.
        heights_up: (S,) height of the resting model's top above the table, metres.
        probabilities: (S,) sampling probabilities (sum 1).
    """

    rotations: np.ndarray
    heights: np.ndarray
    heights_up: np.ndarray
    probabilities: np.ndarray


def _rotation_to(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking unit vector a to unit vector b (the shortest arc)."""
    v = np.cross(a, b)
    c = float(a @ b)
    if c < -1.0 + 1e-9:  # antiparallel: half turn about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def resting_poses(
    points: np.ndarray,
    contact_tol: float = 0.002,
    merge_deg: float = 3.0,
    margin: float = 0.003,
) -> RestingPoses:
    """Stable ways a rigid model rests on a table (quasi-static: faces of its convex hull).

    A hull face (coplanar triangles merged within ``merge_deg``) is stable when the centre of
    mass (the mean of the model points) projects inside the contact polygon (hull points
    within ``contact_tol`` of the support plane) by at least ``margin``. Its probability is
    proportional to the solid angle its triangles subtend from the centre of mass, the usual
    quasi-static estimate of how often a dropped object lands on a face.

    Args:
        points: (P, 3) model points, metres.
        contact_tol: thickness of the contact layer, metres.
        merge_deg: hull triangles whose normals differ less than this form one face.
        margin: required distance of the projected centre of mass inside the contact polygon.

    Returns:
        :class:`RestingPoses`.
    """
    points = np.asarray(points, dtype=np.float64)
    hull = ConvexHull(points)
    com = points.mean(axis=0)
    normals = hull.equations[:, :3]  # (F, 3) outward unit normals
    tri = points[hull.simplices] - com  # (F, 3, 3)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    # Van Oosterom & Strackee: solid angle of a triangle seen from the origin
    num = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
    den = (
        la * lb * lc
        + np.einsum("ij,ij->i", a, b) * lc
        + np.einsum("ij,ij->i", a, c) * lb
        + np.einsum("ij,ij->i", b, c) * la
    )
    omega = 2.0 * np.arctan2(num, den)
    cos_merge = np.cos(np.deg2rad(merge_deg))
    assigned = np.zeros(len(normals), dtype=bool)
    rotations, heights, tops, weights = [], [], [], []
    for f in np.argsort(-omega, kind="stable"):
        if assigned[f]:
            continue
        n = normals[f]
        members = ~assigned & (normals @ n > cos_merge)
        assigned |= members
        h = points @ n
        contact = points[h >= h.max() - contact_tol]
        u = np.cross(n, [1.0, 0.0, 0.0])
        if np.linalg.norm(u) < 0.1:
            u = np.cross(n, [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        c2 = np.stack([contact @ u, contact @ v], axis=1)
        if len(c2) < 3 or np.linalg.matrix_rank(c2 - c2.mean(0), tol=1e-6) < 2:
            continue
        poly = ConvexHull(c2)
        inside = -(poly.equations[:, :2] @ np.array([com @ u, com @ v]) + poly.equations[:, 2])
        if inside.min() < margin:
            continue
        rotations.append(_rotation_to(n, np.array([0.0, 0.0, -1.0])))
        heights.append(h.max())
        tops.append(h.max() - h.min())
        weights.append(omega[members].sum())
    if not rotations:
        raise ValueError("model has no stable resting face (is it a point set in metres?)")
    w = np.asarray(weights)
    return RestingPoses(np.stack(rotations), np.asarray(heights), np.asarray(tops), w / w.sum())


# --------------------------------------------------------------------------- scenes


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
    """

    cls_ids: np.ndarray
    model_to_world: np.ndarray
    world_to_camera: np.ndarray
    look_at: np.ndarray
    background: list[Plane]

    def poses(self) -> np.ndarray:
        """(N, 3, 4) object->camera poses."""
        Rc, tc = self.world_to_camera[:, :3], self.world_to_camera[:, 3]
        R = Rc @ self.model_to_world[:, :, :3]
        t = self.model_to_world[:, :, 3] @ Rc.T + tc
        return np.concatenate([R, t[:, :, None]], axis=2)

    def subset(self, keep: np.ndarray) -> Scene:
        """The scene with only the objects where ``keep`` (bool (N,) or indices)."""
        return Scene(
            self.cls_ids[keep],
            self.model_to_world[keep],
            self.world_to_camera,
            self.look_at,
            self.background,
        )


def _yaw(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _footprint_cells(points_xy: np.ndarray) -> np.ndarray:
    """(C, 2) integer grid cells covered by a posed object's footprint (relative to its origin).

    The projected model points are rasterised, closed and hole-filled (the surface points of a
    box cover its footprint; gaps between them do not make it porous).
    """
    ij = np.floor(points_xy / _GRID).astype(np.int64)
    lo = ij.min(axis=0) - 2
    size = ij.max(axis=0) - lo + 3
    img = np.zeros(size, dtype=bool)
    img[ij[:, 0] - lo[0], ij[:, 1] - lo[1]] = True
    img = ndimage.binary_fill_holes(ndimage.binary_closing(img, iterations=2))
    return np.argwhere(img) + lo


def look_at_camera(eye: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """(3, 4) world->camera extrinsics of an OpenCV camera at ``eye`` looking at ``target``.

    World z is up; the image x axis stays horizontal before the ``roll`` (radians) about the
    optical axis.
    """
    f = target - eye
    f = f / np.linalg.norm(f)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    R = np.stack([right, down, f])  # rows: camera axes in world coordinates
    c, s = np.cos(roll), np.sin(roll)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R
    return np.concatenate([R, (-R @ eye)[:, None]], axis=1)


def _in_image_fraction(points_cam: np.ndarray, K: np.ndarray, shape: tuple[int, int]) -> float:
    z = points_cam[:, 2]
    front = z > 1e-3
    uvw = points_cam @ K.T
    u = uvw[:, 0] / np.where(front, z, 1.0)
    v = uvw[:, 1] / np.where(front, z, 1.0)
    inside = front & (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    return float(inside.mean())


def sample_table_scene(
    rng: np.random.Generator,
    models: dict[int, np.ndarray],
    resting: dict[int, RestingPoses],
    K: np.ndarray = YCB_INTRINSICS,
    shape: tuple[int, int] = IMAGE_SHAPE,
) -> Scene:
    """Sample objects resting on a table, clustered, and a camera looking down at them.

    Objects are placed one by one: a random already-placed anchor and direction, then the new
    object slides out from the anchor until its footprint is free, plus a small random gap (so
    objects stand close and hide each other from many viewpoints). Objects mostly outside the
    image are taken out of the scene; if fewer than 3 remain, the camera is drawn again.

    Args:
        rng: random generator (the only source of randomness).
        models: {class id: (P, 3) model points, metres}.
        resting: {class id: :class:`RestingPoses`}.
        K: (3, 3) intrinsics.
        shape: (H, W) image size.

    Returns:
        The :class:`Scene` (world = table frame, z up, table top at z = 0).
    """
    ids = np.array(sorted(models))
    while True:
        n = int(rng.integers(N_OBJECTS[0], N_OBJECTS[1] + 1))
        cls_ids = rng.choice(ids, size=n, replace=False)
        occupied = np.zeros((2 * _GRID_HALF, 2 * _GRID_HALF), dtype=bool)
        placed_xy: list[np.ndarray] = []
        poses = []
        for c in cls_ids:
            rp = resting[int(c)]
            if rng.random() < UPRIGHT_SHARE:
                s = int(np.argmax(rp.heights_up))
            else:
                s = int(rng.choice(len(rp.probabilities), p=rp.probabilities))
            R = _yaw(rng.uniform(0.0, 2.0 * np.pi)) @ rp.rotations[s]
            local = models[int(c)] @ R.T
            cells = _footprint_cells(local[:, :2])
            direction = rng.uniform(0.0, 2.0 * np.pi)
            gap = rng.exponential(GAP_MEAN) if rng.random() > FAR_SHARE else rng.uniform(*FAR_GAP)
            anchor = np.mean(placed_xy, axis=0) if placed_xy else np.zeros(2)
            step = np.array([np.cos(direction), np.sin(direction)])
            # slide in from afar towards the cluster centre until the next step would touch
            xy = None
            for k in range(int(_START / _GRID), -1, -1):
                cand = anchor + step * (k * _GRID)
                ij = cells + np.floor(cand / _GRID).astype(np.int64) + _GRID_HALF
                if (ij < 0).any() or (ij >= 2 * _GRID_HALF).any():
                    continue
                if occupied[ij[:, 0], ij[:, 1]].any():
                    break
                xy = cand
            if xy is not None:
                xy = xy + step * gap
            if xy is None:
                continue
            ij = cells + np.floor(xy / _GRID).astype(np.int64) + _GRID_HALF
            if (ij < 0).any() or (ij >= 2 * _GRID_HALF).any() or occupied[ij[:, 0], ij[:, 1]].any():
                continue  # the gap pushed it into another object or off the grid
            occupied[ij[:, 0], ij[:, 1]] = True
            placed_xy.append(xy)
            pose = np.concatenate([R, np.array([*xy, rp.heights[s]])[:, None]], axis=1)
            poses.append((int(c), pose))
        if len(poses) < N_OBJECTS[0]:
            continue
        cls_ids = np.array([c for c, _ in poses], dtype=np.int64)
        model_to_world = np.stack([p for _, p in poses])
        centre_xy = np.asarray(placed_xy).mean(axis=0)
        lo = np.asarray(placed_xy).min(axis=0) - 0.15
        hi = np.asarray(placed_xy).max(axis=0) + 0.15
        for _ in range(20):
            target = np.array([*(centre_xy + rng.normal(0.0, 0.03, 2)), rng.uniform(0.0, 0.05)])
            dist = rng.uniform(*CAMERA_DISTANCE)
            elev = np.deg2rad(rng.uniform(*CAMERA_ELEVATION_DEG))
            azim = rng.uniform(0.0, 2.0 * np.pi)
            eye = target + dist * np.array(
                [np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)]
            )
            world_to_camera = look_at_camera(eye, target, roll=np.deg2rad(rng.normal(0.0, 5.0)))
            Rc, tc = world_to_camera[:, :3], world_to_camera[:, 3]
            keep = np.array(
                [
                    _in_image_fraction(
                        (models[int(c)] @ P[:, :3].T + P[:, 3]) @ Rc.T + tc, K, shape
                    )
                    >= MIN_IN_IMAGE
                    for c, P in zip(cls_ids, model_to_world, strict=True)
                ]
            )
            if keep.sum() >= N_OBJECTS[0]:
                break
        else:
            continue
        # the table: a rectangle around the cluster with random size and yaw; the floor below
        half = np.maximum((hi - lo) / 2.0, 0.0) + rng.uniform(0.1, 0.4, 2)
        table_yaw = _yaw(rng.uniform(0.0, np.pi))
        # a yawed rectangle must still cover the cluster: take the half-diagonal as extent
        half = np.full(2, np.linalg.norm(half))
        table = Plane(
            np.array([*((lo + hi) / 2.0), 0.0]),
            np.array([0.0, 0.0, 1.0]),
            table_yaw[:2, :3],
            half,
        )
        floor = Plane(np.array([0.0, 0.0, -rng.uniform(0.7, 0.8)]), np.array([0.0, 0.0, 1.0]))
        scene = Scene(cls_ids, model_to_world, world_to_camera, target, [table, floor])
        return scene.subset(keep)


def _random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3, 3) rotations uniform on SO(3) (normalised Gaussian quaternions)."""
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
        rotations = _random_rotations(rng, n)
        placed, radii, poses = [], [], []
        for c, R in zip(cls_ids, rotations, strict=True):
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
        tilt = _random_rotations(rng, 1)[0]
        normal = np.array([0.0, 0.0, -1.0])
        # a wall facing the camera, tilted at most ~35 degrees, 0.2-1 m behind the objects
        for _ in range(100):
            normal = tilt @ np.array([0.0, 0.0, -1.0])
            if normal[2] < -np.cos(np.deg2rad(35.0)):
                break
            tilt = _random_rotations(rng, 1)[0]
        wall = Plane(np.array([0.0, 0.0, far + rng.uniform(0.2, 1.0)]), normal)
        cam = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
        return Scene(
            np.array([c for c, _ in poses], dtype=np.int64),
            np.stack([p for _, p in poses]),
            cam,
            centre,
            [wall],
        )


# --------------------------------------------------------------------------- rendering


def background_depth(
    K: np.ndarray, shape: tuple[int, int], world_to_camera: np.ndarray, planes: Sequence[Plane]
) -> np.ndarray:
    """Depth of the nearest background plane patch along each pixel ray.

    Args:
        K: (3, 3) intrinsics.
        shape: (H, W).
        world_to_camera: (3, 4) extrinsics.
        planes: patches in world coordinates.

    Returns:
        (H, W) float64 depth (z, metres); 0 where no patch is hit within :data:`MAX_RANGE`.
    """
    H, W = shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T  # (H, W, 3), z = 1
    Rc, tc = world_to_camera[:, :3], world_to_camera[:, 3]
    out = np.full(shape, np.inf)
    for pl in planes:
        n_c = Rc @ pl.normal
        p_c = Rc @ pl.point + tc
        denom = rays @ n_c
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (p_c @ n_c) / denom
        hit = np.isfinite(z) & (z > 0)
        if pl.axes is not None:
            x_c = rays * z[..., None] - p_c  # (H, W, 3) from the patch centre, camera frame
            ax_c = pl.axes @ Rc.T  # (2, 3)
            local = np.abs(x_c @ ax_c.T)  # (H, W, 2)
            hit &= (local <= pl.half_extent).all(axis=-1)
        out = np.where(hit & (z < out), z, out)
    out[~np.isfinite(out) | (out > MAX_RANGE)] = 0.0
    return out


@dataclass(frozen=True)
class NoiseModel:
    """Depth-sensor noise (Kinect v1 / Asus Xtion-like; the real YCB-Video sensor).

    Attributes:
        sigma0: axial noise at 0.4 m, metres (Nguyen et al. 2012: 1.2 mm).
        sigma2: quadratic growth, metres per m^2 (Nguyen et al. 2012: 1.9 mm).
        focal_baseline: focal length (px) x baseline (m) of the disparity quantisation.
        subpixel: disparity resolution, pixels.
        edge_jump: a pixel lies on a depth edge when a 4-neighbour differs by more, metres.
        edge_dropout: share of edge pixels without a reading.
        edge_flying: share of edge pixels mixed with the neighbour across the edge.
        dropout: share of all pixels without a reading.
    """

    sigma0: float = 0.0012
    sigma2: float = 0.0019
    focal_baseline: float = 580.0 * 0.075
    subpixel: float = 1.0 / 8.0
    edge_jump: float = 0.02
    edge_dropout: float = 0.5
    edge_flying: float = 0.15
    dropout: float = 0.005


def add_sensor_noise(
    depth: np.ndarray, rng: np.random.Generator, model: NoiseModel = NoiseModel()
) -> np.ndarray:
    """Apply the sensor noise model to a clean depth image.

    Args:
        depth: (H, W) clean depth, metres, 0 = no surface.
        rng: random generator.
        model: noise parameters.

    Returns:
        (H, W) float64 noisy depth, metres, 0 = no reading (never a reading where there was none).
    """
    z = np.asarray(depth, dtype=np.float64)
    valid = z > 0
    H, W = z.shape
    pad = np.pad(z, 1)
    vpad = np.pad(valid, 1)
    nbs = np.stack([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]], axis=-1)
    nvalid = np.stack([vpad[:-2, 1:-1], vpad[2:, 1:-1], vpad[1:-1, :-2], vpad[1:-1, 2:]], axis=-1)
    diff = np.where(nvalid & valid[..., None], nbs - z[..., None], 0.0)  # (H, W, 4)
    k = np.abs(diff).argmax(axis=-1)
    jump = np.take_along_axis(diff, k[..., None], axis=-1)[..., 0]
    edge = np.abs(jump) > model.edge_jump
    noisy = z + rng.standard_normal((H, W)) * (model.sigma0 + model.sigma2 * (z - 0.4) ** 2)
    u_edge = rng.random((H, W))
    mix = rng.random((H, W))
    flying = edge & (u_edge < model.edge_flying)
    noisy = np.where(flying, noisy + mix * jump, noisy)
    disparity = model.focal_baseline / np.where(valid, noisy, 1.0)
    disparity = np.maximum(np.round(disparity / model.subpixel), 1.0) * model.subpixel
    noisy = model.focal_baseline / disparity
    drop = (edge & (u_edge > 1.0 - model.edge_dropout)) | (rng.random((H, W)) < model.dropout)
    noisy[~valid | drop | (noisy <= 0) | (noisy > MAX_RANGE)] = 0.0
    return noisy


class SynthFrame(NamedTuple):
    """One generated frame.

    Attributes:
        frame_id: "SEQ/FRAME".
        depth: (H, W) float64 depth written to the PNG (noisy unless noise is off), metres.
        clean_depth: (H, W) float64 depth before noise, metres.
        label: (H, W) uint8 ground-truth class ids.
        cls_ids: (N,) int64 annotated classes.
        poses: (N, 3, 4) object->camera poses.
        alone_pixels: (N,) int64 pixels of each object rendered alone.
        visible_pixels: (N,) int64 pixels of each object in ``label``.
        scene: the sampled :class:`Scene`.
    """

    frame_id: str
    depth: np.ndarray
    clean_depth: np.ndarray
    label: np.ndarray
    cls_ids: np.ndarray
    poses: np.ndarray
    alone_pixels: np.ndarray
    visible_pixels: np.ndarray
    scene: Scene


def frame_id(split: str, index: int) -> str:
    """ "SEQ/FRAME" of frame ``index`` (0-based) of a split (train 0000/000001, test 1000/...)."""
    if split not in SPLIT_CODES:
        raise ValueError(f"unknown split {split!r}; expected one of {sorted(SPLIT_CODES)}")
    seq = SEQ_OFFSET[split] + index // FRAMES_PER_SEQ
    return f"{seq:04d}/{index % FRAMES_PER_SEQ + 1:06d}"


class _Generator:
    """Holds what every frame needs (renderer with meshes, models, resting poses); build it
    with :func:`_generator` (one per process)."""

    def __init__(self) -> None:
        from cloudpose.data.render import Renderer, load_packaged_models

        self.models = load_packaged_models()
        self.renderer = Renderer(self.models)
        self.resting = {c: resting_poses(p) for c, p in self.models.items()}


@functools.cache
def _generator() -> _Generator:
    return _Generator()


def generate_frame(
    split: str,
    index: int,
    seed: int = 0,
    noise: bool = True,
    uniform_rotation: bool = False,
    generator: _Generator | None = None,
) -> SynthFrame:
    """Generate frame ``index`` of ``split``; a pure function of (seed, split, index, flags).

    Objects with fewer than :data:`MIN_VISIBLE_PIXELS` visible pixels are taken out and the
    scene rendered again.
    """
    gen = generator or _generator()
    rng = np.random.default_rng([seed, SPLIT_CODES[split], index])
    K, shape = YCB_INTRINSICS, IMAGE_SHAPE
    while True:
        if uniform_rotation:
            scene = sample_floating_scene(rng, gen.models, K, shape)
        else:
            scene = sample_table_scene(rng, gen.models, gen.resting, K, shape)
        for _ in range(8):
            r = gen.renderer.render(K, shape, scene.cls_ids, scene.poses())
            keep = r.visible_pixels >= MIN_VISIBLE_PIXELS
            if keep.all() or keep.sum() < N_OBJECTS[0]:
                break
            scene = scene.subset(keep)
        if keep.all() and len(scene.cls_ids) >= N_OBJECTS[0]:
            break
    poses = scene.poses()
    alone = gen.renderer.alone_pixels(K, shape, scene.cls_ids, poses)
    bg = background_depth(K, shape, scene.world_to_camera, scene.background)
    obj = r.label > 0
    clean = np.where(obj, r.depth.astype(np.float64), bg)
    depth = add_sensor_noise(clean, rng) if noise else clean
    return SynthFrame(
        frame_id(split, index),
        depth,
        clean,
        r.label,
        scene.cls_ids,
        poses,
        alone,
        r.visible_pixels,
        scene,
    )


# --------------------------------------------------------------------------- writing


_worker_gen: _Generator | None = None


def _frame_done(root: Path, fid: str) -> bool:
    seq, name = fid.split("/")
    d = root / "data" / seq
    return all((d / f"{name}-{k}").is_file() for k in ("depth.png", "label.png", "meta.mat"))


def _write(root: Path, f: SynthFrame) -> None:
    """Write a frame atomically: stage it whole, then rename depth, label and meta (last)."""
    from cloudpose.data.ycb import write_frame

    stage = root / ".staging" / f"{os.getpid()}"
    write_frame(stage, f.frame_id, f.depth, f.label, YCB_INTRINSICS, f.cls_ids, f.poses)
    seq, name = f.frame_id.split("/")
    src, dst = stage / "data" / seq, root / "data" / seq
    meta_path = src / f"{name}-meta.mat"
    meta = scipy.io.loadmat(meta_path)
    meta = {k: v for k, v in meta.items() if not k.startswith("__")}
    meta["alone_pixels"] = f.alone_pixels.astype(np.float64).reshape(-1, 1)
    scipy.io.savemat(meta_path, meta, do_compression=True, format="5")
    dst.mkdir(parents=True, exist_ok=True)
    for suffix in ("depth.png", "label.png", "meta.mat"):
        os.replace(src / f"{name}-{suffix}", dst / f"{name}-{suffix}")


def _init_worker() -> None:
    global _worker_gen
    _worker_gen = _generator()


def _work(args: tuple[str, str, int, int, bool, bool]) -> str:
    root, split, index, seed, noise, uniform = args
    assert _worker_gen is not None
    f = generate_frame(split, index, seed, noise, uniform, _worker_gen)
    _write(Path(root), f)
    return f.frame_id


class SynthSummary(NamedTuple):
    """What :func:`synthesize` did."""

    frames_written: int
    frames_skipped: int
    seconds: float



def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _clean_staging(root: Path) -> None:
    """Remove staged frames of processes that are gone (an interrupted run's leftovers); a
    concurrent run's own staging folder is left alone."""
    stage = root / ".staging"
    if not stage.is_dir():
        return
    for d in stage.iterdir():
        pid = int(d.name) if d.name.isdigit() else 0
        if pid <= 0 or pid == os.getpid() or not _pid_alive(pid):
            shutil.rmtree(d, ignore_errors=True)
    try:
        stage.rmdir()
    except OSError:
        pass  # another run is staging


def _prepare_root(root: Path, seed: int, noise: bool, uniform_rotation: bool) -> None:
    from cloudpose.data.render import surface_settings

    # Frames depend on the generator and on the rendered surfaces: both versions are recorded,
    # so frames made by an older renderer are never mixed with new ones on resume.
    settings = {
        "generator": "cloudpose.data.synth",
        "version": GENERATOR_VERSION,
        "surfaces": surface_settings(),
        "seed": seed,
        "noise": noise,
        "uniform_rotation": uniform_rotation,
    }
    info = root / "synth.json"
    if info.is_file():
        old = json.loads(info.read_text())
        old = {k: old.get(k) for k in settings}
        if old != settings:
            raise ValueError(
                f"{info}: this folder holds synthetic frames made with {old}, not {settings} "
                "(a missing key: made by an older cloudpose); choose another root (or delete "
                "the folder)"
            )
    root.mkdir(parents=True, exist_ok=True)
    _clean_staging(root)
    atomic_text(info, json.dumps(settings, indent=2) + "\n")
    shutil.copyfile(resource_path("classes.txt"), root / "classes.txt")
    from cloudpose.data.ycb import load_classes

    for name in load_classes(resource_path("classes.txt")):
        dst = root / "models" / name / "points.xyz"
        if not dst.is_file():
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(resource_path("models", name, "points.xyz"), dst)


def synthesize(
    root: str | Path,
    train_frames: int,
    test_frames: int,
    seed: int = 0,
    noise: bool = True,
    uniform_rotation: bool = False,
    workers: int | None = None,
    progress: bool = True,
) -> SynthSummary:
    """Write (or complete) a synthetic dataset in the YCB-Video layout under ``root``.

    Resumable: frames whose depth, label and meta files exist are kept (a frame's meta is
    renamed into place last, so an interrupted frame has none and is made again). The image
    sets list exactly the requested counts.

    Args:
        root: dataset root (created if missing).
        train_frames: frames listed in image_sets/train.txt.
        test_frames: frames listed in image_sets/test.txt and keyframe.txt.
        seed: scene seed; frame i depends on (seed, split, i) only.
        noise: apply :func:`add_sensor_noise`.
        uniform_rotation: floating objects in uniform SO(3) rotations instead of table scenes.
        workers: processes (default: all cores); 1 renders in this process.
        progress: show a tqdm progress bar.

    Returns:
        :class:`SynthSummary`.

    Raises:
        ValueError: negative counts, or ``root`` holds frames made with other settings.
    """
    if train_frames < 0 or test_frames < 0:
        raise ValueError(f"frame counts must be >= 0, got {train_frames=}, {test_frames=}")
    t0 = time.perf_counter()
    root = Path(root)
    _prepare_root(root, seed, noise, uniform_rotation)
    wanted = [("train", i) for i in range(train_frames)] + [("test", i) for i in range(test_frames)]
    todo = [(s, i) for s, i in wanted if not _frame_done(root, frame_id(s, i))]
    jobs = [(str(root), s, i, seed, noise, uniform_rotation) for s, i in todo]
    workers = min(workers or os.cpu_count() or 1, max(len(jobs), 1))
    from tqdm import tqdm

    bar = tqdm(total=len(jobs), desc="synth", unit="frame", disable=not progress or not jobs)
    if workers <= 1:
        gen = _generator() if jobs else None
        for root_s, s, i, *_ in jobs:
            _write(Path(root_s), generate_frame(s, i, seed, noise, uniform_rotation, gen))
            bar.update()
    else:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(workers, initializer=_init_worker) as pool:
            for _ in pool.imap_unordered(_work, jobs):
                bar.update()
    bar.close()
    _clean_staging(root)
    train_ids = [frame_id("train", i) for i in range(train_frames)]
    test_ids = [frame_id("test", i) for i in range(test_frames)]
    atomic_text(root / "image_sets" / "train.txt", "".join(f + "\n" for f in train_ids))
    atomic_text(root / "image_sets" / "test.txt", "".join(f + "\n" for f in test_ids))
    atomic_text(root / "keyframe.txt", "".join(f + "\n" for f in test_ids))
    return SynthSummary(len(jobs), len(wanted) - len(jobs), time.perf_counter() - t0)
