"""Geometry: rotation representations, the geodesic distance, and poses.

Re-exports :mod:`cloudpose.geometry.rotations` (its ``__all__`` is the one list of names), so
``from cloudpose.geometry import rotvec_to_rotmat`` works.
"""

from cloudpose.geometry import rotations as _rotations
from cloudpose.geometry.rotations import *  # noqa: F403

__all__ = list(_rotations.__all__)
