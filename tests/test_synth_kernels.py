"""The compiled kernels of on-line synthesis version 2 against their twins: the z-buffer against
the ray cast, the edge distance and the correlated field against scipy, the scene slide against
its numpy loop, the grid FPS against the numpy loop."""

from __future__ import annotations

import numpy as np
import pytest

from cloudpose.data.segments import farthest_point_sampling_reference
from cloudpose.data.synth.chunks import OnlineSettings
from cloudpose.data.synth.online import WINDOW_PAD, OnlineSynth
from cloudpose.data.synth.sensor import (
    correlated_uniform,
    correlated_uniform_at,
    edge_distance,
    edge_distance_compiled,
)
from cloudpose.kernels.backend import disabled, enabled

pytestmark = pytest.mark.skipif(not enabled(), reason="numba kernels off")


@pytest.fixture(scope="module")
def synth():
    return OnlineSynth(OnlineSettings(2, n_points=64), nthreads=1)


def test_zbuffer_is_the_ray_cast(synth):
    """Over 8 table scenes: the same label at every pixel but a handful (silhouette pixels
    within rounding), and the same depth to float32 rounding of ~1 m at all but a handful
    (a pixel centre on an edge-on triangle, which the ray cast misses as grazing)."""
    r = synth._gen.renderer
    pixels, off_label, off_depth = 0, 0, 0
    for k in range(8):
        scene = synth.sample_scene(np.random.default_rng([7, k]))
        wins, box = synth.windows(scene)
        a = r.render_instanced(synth.K, synth.shape, scene.cls_ids, scene.poses(), wins, box, 1)
        b, box_b = r.render_raster(synth.K, synth.shape, scene.cls_ids, scene.poses(), WINDOW_PAD)
        assert box_b == box
        np.testing.assert_array_equal(a.visible_pixels.sum(), (a.label > 0).sum())
        both = (a.label == b.label) & (a.label > 0)
        pixels += int((a.label > 0).sum())
        off_label += int((a.label != b.label).sum())
        off_depth += int((np.abs(a.depth[both].astype(np.float64) - b.depth[both]) > 1e-5).sum())
        assert np.abs(b.visible_pixels - a.visible_pixels).max() <= 3
    assert pixels > 100_000
    assert off_label <= 1e-4 * pixels and off_depth <= 1e-4 * pixels, (off_label, off_depth)


def test_zbuffer_of_an_object_behind_the_camera_casts_rays(synth):
    """An object reaching behind the camera takes the ray cast over the whole image."""
    r = synth._gen.renderer
    pose = np.concatenate([np.eye(3), [[0.0], [0.0], [0.02]]], axis=1)[None]
    got = r.render_raster(synth.K, synth.shape, np.array([2]), pose, WINDOW_PAD)
    assert got is not None and got[1] == (0, 480, 0, 640)
    assert got[0].visible_pixels[0] > 0
    far = pose.copy()
    far[0, 0, 3] = 100.0
    far[0, 2, 3] = 1.0
    assert r.render_raster(synth.K, synth.shape, np.array([2]), far, WINDOW_PAD) is None


def test_edge_distance_and_field_are_scipys():
    rng = np.random.default_rng(0)
    lab = np.zeros((70, 90), np.uint8)
    lab[10:40, 5:60] = 3
    lab[30:65, 50:85] = 5
    lab[15:20, 10:14] = 0
    np.testing.assert_array_equal(edge_distance_compiled(lab), edge_distance(lab))
    assert np.isinf(edge_distance_compiled(np.zeros((5, 6), np.uint8))).all()
    for shape in ((70, 90), (12, 20)):  # smaller than the kernel: wraps more than once
        lab = rng.integers(0, 3, shape).astype(np.uint8)
        v, u = np.nonzero(lab)
        want = correlated_uniform(np.random.default_rng(1), shape, 4.0)[v, u]
        got = correlated_uniform_at(np.random.default_rng(1), shape, 4.0, v, u)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_scenes_are_the_same_with_and_without_the_slide_kernel(synth):
    for k in range(6):
        a = synth.sample_scene(np.random.default_rng([3, k]))
        with disabled():
            b = synth.sample_scene(np.random.default_rng([3, k]))
        np.testing.assert_array_equal(a.cls_ids, b.cls_ids)
        np.testing.assert_array_equal(a.model_to_world, b.model_to_world)
        np.testing.assert_array_equal(a.world_to_camera, b.world_to_camera)


def test_footprint_rasters_and_contact_cells_are_the_numpy_twins():
    """The compiled footprint raster and the contact cells' membership of the scene sampler:
    the numpy twins' cells, in their order (the scenes of every version depend on them)."""
    from cloudpose.data.synth.scenes import _GRID, _member, _member_numpy, _raster_cells_numpy
    from cloudpose.kernels.placement import raster_cells

    rng = np.random.default_rng(4)
    for n in (1, 5, 300):
        pts = rng.normal(0.0, rng.uniform(0.001, 0.05), (n, 2)) + rng.uniform(-0.5, 0.5, 2)
        for fill in (False, True):
            np.testing.assert_array_equal(
                raster_cells(pts, _GRID, fill), _raster_cells_numpy(pts, fill)
            )
    keys, of = rng.integers(0, 60, 40), rng.integers(0, 60, 25)
    np.testing.assert_array_equal(_member(keys, of), _member_numpy(keys, of))
    assert _member(keys[:0], of).shape == (0,)


@pytest.mark.parametrize("n", [1, 2, 50, 3000])
def test_grid_fps_is_the_numpy_loop(n):
    from cloudpose.kernels.segment_cut import grid_fps

    rng = np.random.default_rng(n)
    P = np.stack([rng.uniform(0, 0.1, n), rng.uniform(0, 0.1, n), rng.uniform(1, 1.02, n)], 1)
    for pts in (P, np.round(P * 300) / 300):  # quantised: many ties (the highest index wins)
        pts = pts.astype(np.float32)
        k = min(n, 256)
        start = int(rng.integers(n))
        np.testing.assert_array_equal(
            grid_fps(pts, k, start), farthest_point_sampling_reference(pts, k, start)
        )
    flat = np.zeros((40, 3), np.float32)  # all points equal: no extent to grid
    np.testing.assert_array_equal(
        grid_fps(flat, 5, 7), farthest_point_sampling_reference(flat, 5, 7)
    )


def test_closing_and_hole_filling_are_scipys():
    from cloudpose.data.synth.scenes import _close_numpy
    from cloudpose.kernels.placement import close_cells

    rng = np.random.default_rng(0)
    for _ in range(300):
        h, w = rng.integers(1, 25, 2)
        img = rng.random((h, w)) < rng.uniform(0.05, 0.9)
        for fill in (False, True):
            np.testing.assert_array_equal(close_cells(img, fill), _close_numpy(img, fill))
    ring = np.zeros((9, 9), bool)
    ring[2:7, 2:7] = True
    ring[4, 4] = False  # a hole that closing fills, and filling keeps filled
    assert close_cells(ring, True)[4, 4] and close_cells(ring, False)[4, 4]


def test_compiled_sensor_is_the_numpy_sensor(synth):
    """The version-2 sensor on object pixels, compiled (edge distance, field at the object
    pixels, readings in one pass) and numpy, from the same draws: the same readings (a pixel
    may differ only where a probability lands within an ulp of its uniform)."""
    from cloudpose.data.synth.sensor import (
        add_sensor_noise_v2_objects,
        background_depth_at,
        object_ring,
    )

    r = synth._gen.renderer
    differ, pixels = 0, 0
    for k in range(3):
        scene = synth.sample_scene(np.random.default_rng([11, k]))
        got, (v0, _, u0, _) = r.render_raster(
            synth.K, synth.shape, scene.cls_ids, scene.poses(), WINDOW_PAD
        )
        Kw = synth.K.copy()
        Kw[0, 2] -= u0
        Kw[1, 2] -= v0
        clean = np.where(got.label > 0, got.depth.astype(np.float64), 0.0)
        rv, ru = np.nonzero(object_ring(got.label))
        clean[rv, ru] = background_depth_at(Kw, rv, ru, scene.world_to_camera, scene.background)
        a = add_sensor_noise_v2_objects(clean, got.label, Kw, np.random.default_rng(k))
        b = add_sensor_noise_v2_objects(
            clean, got.label, Kw, np.random.default_rng(k), compiled=True
        )
        differ += int((a != b).sum())
        pixels += int((got.label > 0).sum())
        assert (b > 0).sum() > 0.8 * (got.label > 0).sum()  # ~10% missing, as fitted
    assert differ <= 1e-5 * pixels, f"{differ} of {pixels} readings differ"


# --------------------------------------------------------------------------- version 3


@pytest.fixture(scope="module")
def synth3():
    return OnlineSynth(OnlineSettings(2, n_points=64, online_version=3), nthreads=1)


def test_scene_zbuffer_is_version_2s(synth3):
    """Version 3's one-pass z-buffer of a scene against version 2's per object: the same box,
    the same label at every pixel but a handful (pixel centres within rounding of an edge)
    and the same depth to version 2's float32 rounding."""
    r = synth3._gen.renderer
    pixels, off = 0, 0
    for k in range(6):
        scene = synth3.sample_scene(np.random.default_rng([7, k]))
        a, box = r.render_raster(synth3.K, synth3.shape, scene.cls_ids, scene.poses(), WINDOW_PAD)
        depth, index, visible, box3 = synth3._raster_v3(scene, scene.poses())
        assert box3 == box
        label = np.concatenate([scene.cls_ids, [0]]).astype(np.uint8)[index]
        same = (label == a.label) & (a.label > 0)
        pixels += int((a.label > 0).sum())
        off += int((label != a.label).sum())
        np.testing.assert_allclose(depth[same], a.depth[same], rtol=0, atol=2e-7)
        np.testing.assert_array_equal(visible.sum(), (index >= 0).sum())
    assert pixels > 100_000 and off <= 1e-5 * pixels, (off, pixels)


@pytest.mark.parametrize("n", [1, 2, 50, 3000])
def test_soa_fps_is_the_numpy_loop(n):
    from cloudpose.kernels.scene_pass import fps_soa

    rng = np.random.default_rng(n)
    P = np.stack([rng.uniform(0, 0.1, n), rng.uniform(0, 0.1, n), rng.uniform(1, 1.02, n)], 1)
    for pts in (P, np.round(P * 300) / 300):  # quantised: many ties (the highest index wins)
        pts = pts.astype(np.float32)
        k = min(n, 256)
        start = int(rng.integers(n))
        got = fps_soa(*(np.ascontiguousarray(pts[:, a]) for a in range(3)), k, start)
        np.testing.assert_array_equal(got, farthest_point_sampling_reference(pts, k, start))


def test_scene_points_are_the_numpy_twins(synth3):
    """Version 3's sensor and segment points of a scene, compiled and numpy, from the same
    draws: the same points (the field's float32 sums against scipy's float64 filter: a point
    differs only where its missing probability lands within ~1e-6 of its uniform), ~10% of
    the object pixels missing, as fitted; and without noise, the clean depth's points."""
    from cloudpose.data.synth.online import scene_points

    for k in range(2):
        scene = synth3.sample_scene(np.random.default_rng([11, k]))
        depth, index, visible, (v0, _, u0, _) = synth3._raster_v3(scene, scene.poses())
        Kw = synth3.K.copy()
        Kw[0, 2] -= u0
        Kw[1, 2] -= v0
        clean = depth.copy()
        clean[5:, :3][index[5:, :3] < 0] = 0.9  # background on part of the border
        args = (clean, index, visible, Kw, scene.cls_ids)
        for rng in (k, None):
            got = [
                scene_points(
                    *args, None if rng is None else np.random.default_rng(rng), 0.2, compiled
                )
                for compiled in (True, False)
            ]
            (p, off), (q, off_q) = got
            assert np.abs(off - off_q).max() <= 1e-4 * visible.sum()
            if rng is None:
                np.testing.assert_array_equal(off, off_q)
                np.testing.assert_allclose(p, q, rtol=0, atol=1e-12)
                assert off[-1] == visible.sum()
            else:
                assert 0.8 * visible.sum() < off[-1] < visible.sum()
                if np.array_equal(off, off_q):
                    np.testing.assert_allclose(p, q, rtol=0, atol=1e-12)


def test_counter_stream_normals_are_standard_normal():
    """Version 3's normals (the 256-layer ziggurat on the words of a SplitMix64 counter
    stream): a standard normal by the Kolmogorov-Smirnov test and in the tail beyond the
    ziggurat's base strip, the same draws compiled and by the numpy twin, draw i the same
    however many are taken, and the stream's uniforms the kernel's."""
    from scipy import stats

    from cloudpose.data.synth.online import standard_normals, uniform_draws
    from cloudpose.kernels.scene_pass import ZIGGURAT_R, uniform_draw

    key = 0x9E3779B97F4A7C15 ^ 12345
    x = standard_normals(key, 400_000, True).astype(np.float64)
    assert stats.kstest(x, "norm").pvalue > 1e-3
    tail = (np.abs(x) > ZIGGURAT_R).sum()
    expect = 2 * stats.norm.sf(ZIGGURAT_R) * len(x)  # ~103
    assert abs(tail - expect) < 4 * np.sqrt(expect), (tail, expect)
    np.testing.assert_array_equal(standard_normals(key, 5_000, False), x[:5_000].astype(np.float32))
    np.testing.assert_array_equal(standard_normals(key, 70, True), x[:70].astype(np.float32))
    assert not np.array_equal(standard_normals(key + 1, 70, True), x[:70].astype(np.float32))
    u = uniform_draws(key, 200_000)
    assert stats.kstest(u.astype(np.float64), "uniform").pvalue > 1e-3
    np.testing.assert_array_equal(u[:50], [uniform_draw(np.uint64(key), i) for i in range(50)])


def test_row_major_edge_distance_is_the_sensors():
    """Version 3's edge distance (columns, then row envelopes) is the version-2 sensor's exact
    transform, squared and less 1, boundaries and label-free images included."""
    from cloudpose.kernels.scene_pass import edge_squared_distance
    from cloudpose.kernels.sensor import edge_distance_kernel

    rng = np.random.default_rng(5)
    for shape in ((70, 90), (13, 21), (1, 9), (9, 1)):
        lab = rng.integers(-1, 3, (shape[0] // 4 + 1, shape[1] // 4 + 1))
        lab = np.kron(lab, np.ones((4, 4), np.int64))[: shape[0], : shape[1]]
        want = edge_distance_kernel(np.ascontiguousarray(lab + 1, dtype=np.uint8))
        got = edge_squared_distance(np.ascontiguousarray(lab))
        np.testing.assert_array_equal(np.sqrt(got) + 1.0, want)
    assert np.isinf(edge_squared_distance(np.zeros((5, 6), np.int64))).all()
