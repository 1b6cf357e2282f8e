"""Stable resting poses of a rigid model on a horizontal plane (faces of its convex hull).

:func:`resting_poses` lists the faces a model can stand on, with quasi-static probabilities;
:func:`cloudpose.data.synth.scenes.sample_table_scene` puts the objects of a table scene in
them.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial import ConvexHull


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
