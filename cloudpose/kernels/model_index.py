"""A model's nearest-neighbour index: built once per class, shared by ICP and ADS.

Both ICP refinement (refine.py) and the ADS metric (metrics.py) ask, for many query points,
which model point is nearest. ``ModelIndex`` holds everything they need for one model:

- the compiled kernels' k-d tree and Delaunay graph (``kernels.build_nn_index``) where the
  kernels are enabled (``kernels.enabled()``), else None;
- the numpy twins' pykdtree over the points in Morton order (cache-friendly queries), and the
  same points as homogeneous rows with a zero row at index P, the index pykdtree returns for
  "no neighbour within the bound", so ICP's gather needs no mask.

``ModelIndex.of`` keeps the indexes of recently used models keyed by the bytes of their points,
so evaluation (ICP, then ADS of the same 21 models) builds each graph once.
"""

from __future__ import annotations

import hashlib

import numpy as np
from pykdtree.kdtree import KDTree

from cloudpose import kernels

__all__ = ["ModelIndex", "morton_order"]

_CACHE: dict[tuple[tuple[int, ...], bytes, bool], ModelIndex] = {}
_CACHE_SIZE = 64


class ModelIndex:
    """The nearest-neighbour structures of one model's points (model frame, metres).

    Attributes:
        points: (P, 3) float64 model points in the given order.
        sorted_points: (P, 3) the same points in Morton order (the pykdtree's order).
        tree: pykdtree KD-tree over ``sorted_points``.
        sorted_h: (P + 1, 4) homogeneous ``sorted_points`` plus a zero row at index P.
        compiled: ``kernels.build_nn_index(points)``, or None where the kernels are off.
    """

    def __init__(self, model_points: np.ndarray, compiled: bool | None = None) -> None:
        """Args:
        model_points: (P, 3) points, P >= 1.
        compiled: build the compiled kernels' index; default ``kernels.enabled()``.
        """
        X = np.asarray(model_points, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != 3 or len(X) == 0:
            raise ValueError(f"model_points: expected shape (P, 3) with P >= 1, got {X.shape}")
        self.points = X
        self.sorted_points = X[morton_order(X)]
        self.tree = KDTree(self.sorted_points)
        P = len(X)
        self.sorted_h = np.zeros((P + 1, 4))
        self.sorted_h[:P, :3] = self.sorted_points
        self.sorted_h[:P, 3] = 1.0
        use = kernels.enabled() if compiled is None else compiled
        self.compiled = kernels.build_nn_index(X) if use else None

    def __len__(self) -> int:
        return len(self.points)

    @classmethod
    def of(cls, model: np.ndarray | ModelIndex) -> ModelIndex:
        """``model`` itself if it is an index, else the cached index of these points."""
        if isinstance(model, ModelIndex):
            return model
        X = np.ascontiguousarray(model, dtype=np.float64)
        key = (X.shape, hashlib.blake2b(X.tobytes(), digest_size=16).digest(), kernels.enabled())
        index = _CACHE.get(key)
        if index is None:
            if len(_CACHE) >= _CACHE_SIZE:
                _CACHE.clear()
            index = _CACHE[key] = cls(X)
        return index


def morton_order(X: np.ndarray) -> np.ndarray:
    """Indices sorting points along a 3-D Morton (Z-order) curve, 10 bits per axis."""
    lo = X.min(axis=0)
    span = float((X.max(axis=0) - lo).max()) or 1.0
    g = np.clip(((X - lo) / span * 1023).astype(np.int64), 0, 1023)  # (P, 3)

    def spread(v: np.ndarray) -> np.ndarray:
        v = (v | (v << 16)) & 0x030000FF
        v = (v | (v << 8)) & 0x0300F00F
        v = (v | (v << 4)) & 0x030C30C3
        return (v | (v << 2)) & 0x09249249

    code = spread(g[:, 0]) | (spread(g[:, 1]) << 1) | (spread(g[:, 2]) << 2)
    return np.argsort(code, kind="stable")
