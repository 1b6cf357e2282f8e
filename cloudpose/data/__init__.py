"""Data: the YCB-Video reader (``ycb``), object surfaces built from model points (``surfaces``),
the depth/label renderer that ray-casts them (``render``), synthetic scenes and the segment
pipeline (mask -> filter -> FPS) with its cache.

Submodules are imported explicitly (``from cloudpose.data.ycb import YCBVideo``); this package
file stays light so that importing it does not pull in Open3D.
"""
