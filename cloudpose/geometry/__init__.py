"""Geometry: rotation representations, the geodesic distance, and poses.

Re-exports :mod:`cloudpose.geometry.rotations`, so ``from cloudpose.geometry import
rotvec_to_rotmat`` works.
"""

from cloudpose.geometry.rotations import (
    normalize_quat,
    random_rotmat,
    rot6d_to_rotmat,
    rotmat_geodesic_distance,
    rotmat_to_rot6d,
    rotmat_to_rotvec,
    rotmat_to_unitquat,
    rotvec_to_rotmat,
    safe_norm,
    skew,
    unitquat_to_rotmat,
    vee,
)

__all__ = [
    "normalize_quat",
    "random_rotmat",
    "rot6d_to_rotmat",
    "rotmat_geodesic_distance",
    "rotmat_to_rot6d",
    "rotmat_to_rotvec",
    "rotmat_to_unitquat",
    "rotvec_to_rotmat",
    "safe_norm",
    "skew",
    "unitquat_to_rotmat",
    "vee",
]
