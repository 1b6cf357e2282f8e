"""cloudpose: depth-only 6D object pose regression on point-cloud segments.

Reproduction and ablation suite for Gao et al., "6D Object Pose Regression via Supervised
Learning on Point Clouds", ICRA 2020. See ``conventions`` for frames and units.
"""

__version__ = "0.1.0"
