"""Renderer: fidelity against the real YCB-Video frame, a brute-force twin, analytic geometry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cloudpose.conventions import YCB_INTRINSICS
from cloudpose.data.synth.render import Renderer, camera_rays
from cloudpose.data.synth.surfaces import load_packaged_models
from cloudpose.data.ycb import YCBVideo

REAL = Path(__file__).parent / "data" / "ycb_real"

IOU_MIN = 0.97
DEPTH_MEDIAN_MAX = 0.008  # metres


@pytest.fixture(scope="module")
def real():
    ds = YCBVideo(REAL)
    return ds, ds.frame("0000/000001")


@pytest.fixture(scope="module")
def renderer():
    return Renderer()


def fidelity(frame, rendering) -> dict[int, tuple[float, float]]:
    """{class id: (mask IoU, median |depth difference| in metres on pixels both label as it)}."""
    out = {}
    for c in frame.cls_ids:
        a, b = frame.label == c, rendering.label == c
        both = a & b & (frame.depth > 0)
        dz = np.abs(frame.depth[both].astype(np.float64) - rendering.depth[both])
        out[int(c)] = ((a & b).sum() / (a | b).sum(), float(np.median(dz)))
    return out


@pytest.mark.parametrize(
    "use_cache, version",
    [(True, 1), (False, 1), (True, 2), pytest.param(False, 2, marks=pytest.mark.slow)],
    ids=["packaged", "fresh", "packaged-v2", "fresh-v2"],
)
def test_fidelity_on_the_real_frame(real, use_cache, version):
    """Rendering the real frame's objects at their ground-truth poses reproduces YCB-Video's
    own label image (rendered from their meshes) and the sensor depth."""
    ds, f = real
    r = Renderer(ds.models(), use_cache=use_cache, surface_version=version)
    fid = fidelity(f, r.render(f.K, f.depth.shape, f.cls_ids, f.poses))
    for c, (iou, dz) in fid.items():
        print(f"{ds.classes[c - 1]:>16}: IoU {iou:.4f}  median |dz| {1000 * dz:.2f} mm")
    for c, (iou, dz) in fid.items():
        assert iou >= IOU_MIN, (ds.classes[c - 1], iou)
        assert dz <= DEPTH_MEDIAN_MAX, (ds.classes[c - 1], dz)


# --------------------------------------------------------------------------- slow twin


def brute_force_render(K, shape, meshes, poses):
    """Obviously-correct twin: every ray against every triangle (Moller-Trumbore), float64.

    Returns depth (H, W) metres (0 = none) and index (H, W) of the nearest instance (-1).
    """
    d = camera_rays(K, shape).reshape(-1, 3).astype(np.float64)  # (R, 3)
    best_t = np.full(len(d), np.inf)
    index = np.full(len(d), -1)
    for i, (mesh, P) in enumerate(zip(meshes, poses, strict=True)):
        V = np.asarray(mesh.vertices) @ P[:, :3].T + P[:, 3]
        tri = V[np.asarray(mesh.triangles)]  # (T, 3, 3)
        e1, e2, p0 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], tri[:, 0]
        for s in range(0, len(d), 256):
            D = d[s : s + 256, None, :]  # (r, 1, 3)
            pv = np.cross(D, e2[None])  # (r, T, 3)
            det = (e1[None] * pv).sum(-1)
            ok = np.abs(det) > 1e-12
            inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
            tv = -p0[None]  # ray origin 0
            u = (tv * pv).sum(-1) * inv
            qv = np.cross(tv, e1[None])
            v = (D * qv).sum(-1) * inv
            t = (e2[None] * qv).sum(-1) * inv
            hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
            t = np.where(hit, t, np.inf).min(axis=1)
            closer = t < best_t[s : s + 256]
            best_t[s : s + 256][closer] = t[closer]
            index[s : s + 256][closer] = i
    depth = np.where(np.isfinite(best_t), best_t * d[:, 2], 0.0)
    return depth.reshape(shape), index.reshape(shape)


def small_scene():
    K = YCB_INTRINSICS * np.array([[0.08], [0.08], [1.0]])  # a 51 x 38 image, same field of view
    shape = (38, 51)
    cls = np.array([14, 8, 21])
    P = np.zeros((3, 3, 4))
    P[:, :, :3] = Rotation.from_rotvec([[0.3, -1.0, 0.2], [1.2, 0.4, 0], [0, 0.5, 2.0]]).as_matrix()
    P[:, :, 3] = [[0.0, 0.0, 0.6], [0.04, 0.02, 0.5], [-0.06, -0.03, 0.7]]  # overlapping
    return K, shape, cls, P


def test_render_agrees_with_brute_force(renderer):
    K, shape, cls, P = small_scene()
    out = renderer.render(K, shape, cls, P)
    depth, index = brute_force_render(K, shape, [renderer.mesh(c) for c in cls], P)
    label = np.where(index >= 0, cls[index], 0)
    disagree = out.label != label
    assert disagree.sum() <= 3, disagree.sum()  # rays grazing a shared edge may go either way
    same = ~disagree & (label > 0)
    assert same.sum() > 200
    np.testing.assert_allclose(out.depth[same], depth[same], atol=2e-5)
    assert np.all(out.depth[label == 0][~disagree[label == 0]] == 0)
    assert len(np.unique(label)) == 4  # all three objects show


def test_visible_and_alone_pixels(renderer):
    K, shape, cls, P = small_scene()
    out = renderer.render(K, shape, cls, P)
    np.testing.assert_array_equal(out.visible_pixels, [(out.label == c).sum() for c in cls])
    alone = renderer.alone_pixels(K, shape, cls, P)
    # slow twin: each object rendered alone over the whole image
    twin = [
        renderer.render(K, shape, cls[i : i + 1], P[i : i + 1]).visible_pixels[0] for i in range(3)
    ]
    np.testing.assert_array_equal(alone, twin)
    assert np.all(out.visible_pixels <= alone)
    assert out.visible_pixels[0] < alone[0]  # the mug is partly hidden by the gelatin box


def test_instanced_render_is_the_render_in_a_window(renderer):
    """Each object cast in its model frame through its own window: the labels and depth of
    the one-scene render, to float rounding, over the box asked for."""
    K, shape, cls, P = small_scene()
    full = renderer.render(K, shape, cls, P)
    wins = np.array([renderer._window(K, shape, c, p) for c, p in zip(cls, P, strict=True)])
    H, W = shape
    box = (
        max(int(wins[:, 0].min()) - 3, 0),
        min(int(wins[:, 1].max()) + 3, H),
        max(int(wins[:, 2].min()) - 3, 0),
        min(int(wins[:, 3].max()) + 3, W),
    )
    out = renderer.render_instanced(K, shape, cls, P, wins, box)
    v0, v1, u0, u1 = box
    ref_label, ref_depth = full.label[v0:v1, u0:u1], full.depth[v0:v1, u0:u1]
    assert out.label.shape == ref_label.shape
    assert (out.label != ref_label).sum() <= 2  # a grazing ray may flip at a silhouette
    both = (out.label == ref_label) & (ref_label > 0)
    assert both.sum() > 200
    np.testing.assert_allclose(out.depth[both], ref_depth[both], atol=1e-5)
    np.testing.assert_array_equal(out.visible_pixels, [(out.label == c).sum() for c in cls])
    with pytest.raises(ValueError, match="not inside"):
        renderer.render_instanced(K, shape, cls, P, wins, (v0 + 10, v1, u0, u1))


def test_alone_pixels_at_the_image_border_and_behind_the_camera(renderer):
    K, shape = YCB_INTRINSICS, (480, 640)
    cls = np.array([2, 5, 13, 17])
    P = np.zeros((4, 3, 4))
    P[:, :, :3] = np.eye(3)
    P[:, :, 3] = [
        [0.18, 0.0, 0.7],  # straddles the right border
        [0.0, 0.0, -0.5],  # behind the camera
        [0.0, 0.0, 0.02],  # around the camera centre: window falls back to all
        [5.0, 0.0, 1.0],
    ]  # far outside the view
    alone = renderer.alone_pixels(K, shape, cls, P)
    twin = [
        renderer.render(K, shape, cls[i : i + 1], P[i : i + 1]).visible_pixels[0] for i in range(4)
    ]
    np.testing.assert_array_equal(alone, twin)
    assert alone[0] > 0 and alone[1] == 0 and alone[3] == 0


# --------------------------------------------------------------------------- analytic


def test_cube_face_on_matches_the_pinhole_model():
    """A 10 cm cube of points seen face-on (camera inside its x/y extent, so only the front
    face shows): depth is the face distance and the mask is the face's projected rectangle."""
    g = np.linspace(-0.05, 0.05, 21)
    a, b = np.meshgrid(g, g)
    a, b = a.ravel(), b.ravel()
    s = np.full_like(a, 0.05)
    faces = [
        np.stack(x, 1)
        for x in [(a, b, s), (a, b, -s), (a, s, b), (a, -s, b), (s, a, b), (-s, a, b)]
    ]
    pts = np.unique(np.round(np.concatenate(faces), 9), axis=0)
    K = np.array([[1000.0, 0, 300.5], [0, 1100.0, 200.25], [0, 0, 1]])
    t = np.array([0.02, -0.01, 1.0])
    P = np.concatenate([np.eye(3), t[:, None]], 1)[None]
    out = Renderer({7: pts}).render(K, (480, 640), [7], P)
    z = t[2] - 0.05
    u0, u1 = K[0, 2] + K[0, 0] * (t[0] - 0.05) / z, K[0, 2] + K[0, 0] * (t[0] + 0.05) / z
    v0, v1 = K[1, 2] + K[1, 1] * (t[1] - 0.05) / z, K[1, 2] + K[1, 1] * (t[1] + 0.05) / z
    v, u = np.mgrid[0:480, 0:640]
    inside = (u > u0 + 0.5) & (u < u1 - 0.5) & (v > v0 + 0.5) & (v < v1 - 0.5)
    near = (u > u0 - 0.5) & (u < u1 + 0.5) & (v > v0 - 0.5) & (v < v1 + 0.5)
    assert np.all(out.label[inside] == 7) and np.all(out.label[~near] == 0)
    np.testing.assert_allclose(out.depth[inside], z, atol=1e-5)
    assert np.all(out.depth[~near] == 0)


def test_depth_is_along_the_optical_axis():
    """Depth is z, not ray length: a point set's rendered surface off-axis keeps z."""
    g = np.linspace(-0.05, 0.05, 21)
    a, b = np.meshgrid(g, g)
    pts = np.concatenate(
        [np.stack([a.ravel(), b.ravel(), np.full(a.size, z)], 1) for z in (-0.01, 0.01)]
    )
    pts = np.concatenate([pts, [[0, 0, 0.0]]])
    P = np.concatenate([np.eye(3), [[0.25], [0.15], [1.0]]], 1)[None]  # far off-axis
    out = Renderer({1: pts}).render(YCB_INTRINSICS, (480, 640), [1], P)
    hit = out.label == 1
    assert hit.sum() > 1000
    np.testing.assert_allclose(np.median(out.depth[hit]), 0.99, atol=1e-4)


# --------------------------------------------------------------------------- API


def test_empty_scene_and_bad_input(renderer):
    out = renderer.render(YCB_INTRINSICS, (48, 64), [], np.zeros((0, 3, 4)))
    assert out.depth.shape == (48, 64) and out.depth.dtype == np.float32
    assert out.label.dtype == np.uint8 and not out.label.any() and not out.depth.any()
    assert out.visible_pixels.shape == (0,) and out.visible_pixels.dtype == np.int64
    P = np.concatenate([np.eye(3), [[0], [0], [1.0]]], 1)[None]
    with pytest.raises(ValueError, match="class id 30 has no model"):
        renderer.render(YCB_INTRINSICS, (48, 64), [30], P)
    with pytest.raises(ValueError, match=r"poses have shape \(1, 3, 4\), expected \(2, 3, 4\)"):
        renderer.render(YCB_INTRINSICS, (48, 64), [1, 2], P)
    with pytest.raises(ValueError, match="K has shape"):
        renderer.alone_pixels(np.eye(2), (48, 64), [1], P)
    with pytest.raises(ValueError, match=r"surface version 3: expected one of \(1, 2\)"):
        Renderer(surface_version=3)


def test_mesh_is_cached_and_made_of_model_points(renderer):
    models = load_packaged_models()
    m = renderer.mesh(14)
    assert renderer.mesh(14) is m
    np.testing.assert_array_equal(np.asarray(m.vertices), models[14])
    F = np.asarray(m.triangles)
    assert len(F) > 2000 and F.min() >= 0 and F.max() < len(models[14])


def test_render_is_deterministic(renderer):
    K, shape, cls, P = small_scene()
    a = renderer.render(K, shape, cls, P)
    b = Renderer().render(K, shape, cls, P)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.label, b.label)
