"""The sensor: background depth (table, floor, wall) and a Kinect-like depth noise model."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cloudpose.data.synth.scenes import MAX_RANGE, Plane

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
