"""Fitting the version-2 sensor's missing-depth model to real frames.

:func:`object_pixels` collects the object pixels of real frames with what
:class:`~cloudpose.data.synth.sensor.DropoutModel` conditions on (edge distance, incidence
cosine, class); :func:`fit_dropout` fits the model to them by maximum likelihood.
:data:`~cloudpose.data.synth.sensor.REAL_DROPOUT` is that fit on the two real frames in
tests/data; ``cloudpose synth --compare-real`` (:mod:`cloudpose.report.fidelity`) prints a
refit beside it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.optimize import minimize

from cloudpose.data.synth.render import Renderer
from cloudpose.data.synth.sensor import DropoutModel, edge_distance, incidence_cosine
from cloudpose.data.ycb import Frame

__all__ = ["PixelSamples", "fit_dropout", "object_pixels"]


@dataclass
class PixelSamples:
    """Object pixels of real frames with what the missing-depth model conditions on.

    Attributes:
        missing: (M,) bool, no depth reading.
        edge: (M,) pixels to the nearest pixel of another label.
        cos: (M,) |cos| of the incidence angle.
        cls: (M,) class ids.
    """

    missing: np.ndarray
    edge: np.ndarray
    cos: np.ndarray
    cls: np.ndarray


def _filled_depth(depth: np.ndarray, label: np.ndarray) -> np.ndarray:
    """Depth with each missing pixel given its nearest reading of the same label, then a 5x5
    median: a surface for normals where the frame has no rendering."""
    out = depth.astype(np.float64).copy()
    for c in np.unique(label):
        m = label == c
        have = m & (depth > 0)
        if not have.any():
            continue
        _, (iy, ix) = ndimage.distance_transform_edt(~have, return_indices=True)
        fill = m & ~have
        out[fill] = depth[iy[fill], ix[fill]]
    return ndimage.median_filter(out, size=5)


def object_pixels(frames: Sequence[Frame], renderer=None) -> PixelSamples:
    """The object pixels of real frames, with edge distance and incidence cosine.

    The incidence angle comes from the rendering at the ground-truth pose where a frame has
    poses and the rendering agrees with the label, else from the frame's own depth (gaps
    filled from the nearest reading of the same object, median-filtered).

    Args:
        frames: real frames.
        renderer: :class:`~cloudpose.data.synth.render.Renderer` for frames with poses (default one
            over the packaged models, version-2 surfaces).
    """
    if renderer is None:
        renderer = Renderer(surface_version=2)
    parts = []
    for f in frames:
        obj = f.label > 0
        cos = incidence_cosine(_filled_depth(f.depth, f.label), f.K, f.label)
        if f.poses is not None:
            r = renderer.render(f.K, f.depth.shape, f.cls_ids, f.poses)
            agree = (r.label == f.label) & obj
            cos = np.where(agree, incidence_cosine(r.depth, f.K, r.label), cos)
        d = edge_distance(f.label)
        parts.append((f.depth[obj] == 0, d[obj], cos[obj], f.label[obj].astype(np.int64)))
    return PixelSamples(*(np.concatenate(x) for x in zip(*parts, strict=True)))


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def fit_dropout(samples: PixelSamples) -> DropoutModel:
    """Maximum-likelihood :class:`DropoutModel` of real object pixels.

    All parameters are fitted jointly (Bernoulli likelihood, L-BFGS); each class seen gets its
    own rate, and the default rate is the pixel-weighted mean of those (so a class the frames
    do not show gets the rate of the average object).

    Args:
        samples: :func:`object_pixels` of real frames.
    """
    # the likelihood over bins of (class, edge distance, cosine to 0.01): same optimum to
    # within the binning, ~100x fewer terms than pixels
    classes, idx = np.unique(samples.cls, return_inverse=True)
    d_bin = np.minimum(samples.edge, 64.0)
    c_bin = np.round(samples.cos, 2)
    keys = np.stack([idx, d_bin, c_bin], axis=1)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n = np.bincount(inv).astype(np.float64)
    k = np.bincount(inv, weights=samples.missing.astype(np.float64))
    cls_b, d, cos = uniq[:, 0].astype(np.int64), uniq[:, 1], uniq[:, 2]

    def unpack(th):
        return (
            _sigmoid(th[0]),
            np.exp(th[1]),
            th[2],
            np.exp(th[3]),
            _sigmoid(th[4:]),
        )

    def nll(th):
        a, lam, c50, w, rates = unpack(th)
        p_edge = a * np.exp(-(d - 1.0) / lam)
        p_graze = _sigmoid(-(cos - c50) / w)
        p = 1.0 - (1.0 - p_edge) * (1.0 - p_graze) * (1.0 - rates[cls_b])
        p = np.clip(p, 1e-9, 1.0 - 1e-9)
        return -np.sum(k * np.log(p) + (n - k) * np.log1p(-p))

    th0 = np.concatenate([[0.0, np.log(3.0), 0.3, np.log(0.1)], np.full(len(classes), -3.0)])
    res = minimize(nll, th0, method="L-BFGS-B")
    a, lam, c50, w, rates = unpack(res.x)
    counts = np.bincount(idx.reshape(-1), minlength=len(classes))
    return DropoutModel(
        edge_rate=round(float(a), 4),
        edge_scale=round(float(lam), 3),
        graze_cos=round(float(c50), 4),
        graze_width=round(float(w), 4),
        class_rates=tuple(
            (int(c), round(float(r), 4)) for c, r in zip(classes, rates, strict=True)
        ),
        default_rate=round(float((rates * counts).sum() / counts.sum()), 4),
    )
