"""Segment pipeline: FPS (fast vs reference), back-projection, outlier filter, fill, misses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pykdtree.kdtree import KDTree

from cloudpose.conventions import YCB_INTRINSICS, transform_points
from cloudpose.data import mask_sources
from cloudpose.data import segments as sg
from cloudpose.data.ycb import Frame, YCBVideo

REAL = Path(__file__).parent / "data" / "ycb_real"


# --------------------------------------------------------------------------- FPS


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("n", [1, 2, 50, 1023, 1024, 3000])
def test_fps_fast_equals_reference(n, dtype):
    rng = np.random.default_rng(n)
    pts = (rng.normal(size=(n, 3)) * [0.05, 0.03, 0.02] + [0.1, -0.2, 0.9]).astype(dtype)
    for start in {0, n - 1, int(rng.integers(n))}:
        fast = sg.farthest_point_sampling(pts, 1024, start)
        ref = sg.farthest_point_sampling_reference(pts, 1024, start)
        assert fast.shape == (1024,)
        assert np.array_equal(fast, ref)
        assert fast[0] == start


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(2, 400),
    k=st.integers(1, 500),
    seed=st.integers(0, 2**32 - 1),
)
def test_fps_fast_equals_reference_property(n, k, seed):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3)).astype(np.float32)
    s = int(rng.integers(n))
    assert np.array_equal(
        sg.farthest_point_sampling(pts, k, s), sg.farthest_point_sampling_reference(pts, k, s)
    )


def test_fps_is_farthest_first_and_prefix_is_fps():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-0.1, 0.1, size=(5000, 3)).astype(np.float32)
    full = sg.farthest_point_sampling(pts, 1024, 17)
    assert len(np.unique(full)) == 1024
    for n in (1, 64, 256):
        assert np.array_equal(sg.farthest_point_sampling(pts, n, 17), full[:n])
    # each pick is the point farthest from those picked before
    d = np.linalg.norm(pts[:, None] - pts[full[:5]][None], axis=2).min(axis=1)
    assert np.isclose(d[full[5]], d.max())
    # a generator draws the start; same seed -> same order
    a = sg.farthest_point_sampling(pts, 32, np.random.default_rng(3))
    b = sg.farthest_point_sampling(pts, 32, np.random.default_rng(3))
    assert np.array_equal(a, b)


def test_fps_fills_small_segments_by_repeating_the_fps_order():
    pts = np.random.default_rng(0).normal(size=(10, 3))
    idx = sg.farthest_point_sampling(pts, 1024, 4)
    assert idx.shape == (1024,)
    assert sorted(idx[:10]) == list(range(10))
    assert np.array_equal(idx[10:20], idx[:10])


def _fpsample_order(pts: np.ndarray, k: int, start: int) -> np.ndarray:
    import fpsample

    return np.asarray(fpsample.fps_sampling(pts, k, start_idx=start), dtype=np.int64)


def _real_segments() -> list[np.ndarray]:
    f = YCBVideo(REAL).frame("0000/000001")
    return [sg.backproject(f.depth, f.label == c, f.K).astype(np.float32) for c in f.cls_ids]


def test_fps_on_real_segments_equals_fpsample_and_the_loop_ties_included():
    """Depth is quantised, so real segments have tied distances: all three agree on them (the
    highest index wins a tie), so caches made with the previous fpsample path are unchanged."""
    rng = np.random.default_rng(7)
    for seg in _real_segments():
        for n in (300, 3000):
            pts = seg[np.sort(rng.choice(len(seg), n, replace=False))]
            s = int(rng.integers(n))
            k = min(n, 1024)
            fast = sg.farthest_point_sampling(pts, k, s)
            assert np.array_equal(fast, _fpsample_order(pts, k, s))
            assert np.array_equal(fast, sg.farthest_point_sampling_reference(pts, k, s))
        s = int(rng.integers(len(seg)))  # a whole segment (~20k points) against fpsample
        assert np.array_equal(
            sg.farthest_point_sampling(seg, 1024, s), _fpsample_order(seg, 1024, s)
        )


def test_fps_ties_go_to_the_highest_index():
    # the corners of a cube around the start tie at every step
    pts = np.array([[0, 0, 0]] + [[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    order = sg.farthest_point_sampling(pts.astype(np.float32), 9, 0)
    assert order[1] == 8  # all 8 corners are equally far: the last one
    assert np.array_equal(order, sg.farthest_point_sampling_reference(pts, 9, 0))
    assert np.array_equal(order, _fpsample_order(pts.astype(np.float32), 9, 0))


def test_fps_fallback_without_numba_gives_the_same_order():
    from cloudpose import kernels

    pts = np.round(np.random.default_rng(8).normal(size=(2000, 3)), 2).astype(np.float32)
    fast = sg.farthest_point_sampling(pts, 256, 5)
    with kernels.disabled():
        assert np.array_equal(sg.farthest_point_sampling(pts, 256, 5), fast)
    assert np.array_equal(sg.farthest_point_sampling_reference(pts, 256, 5), fast)


def test_fps_bad_input():
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        sg.farthest_point_sampling(np.zeros((5, 2)), 4, 0)
    with pytest.raises(ValueError, match="empty"):
        sg.farthest_point_sampling(np.zeros((0, 3)), 4, 0)
    with pytest.raises(ValueError, match="start index"):
        sg.farthest_point_sampling(np.zeros((5, 3)), 4, 5)


# --------------------------------------------------------------------------- geometry


def test_backproject_inverts_the_projection():
    depth = np.zeros((480, 640), np.float32)
    depth[100:110, 200:205] = 0.8
    depth[105, 202] = 0.0  # no reading: skipped
    mask = np.zeros_like(depth, dtype=bool)
    mask[100:120, 200:203] = True
    pts = sg.backproject(depth, mask, YCB_INTRINSICS)
    assert len(pts) == 10 * 3 - 1
    uvw = pts @ YCB_INTRINSICS.T
    uv = uvw[:, :2] / uvw[:, 2:]
    v, u = np.nonzero(mask & (depth > 0))
    assert np.allclose(uv, np.stack([u, v], 1), atol=1e-6)
    assert np.allclose(pts[:, 2], 0.8, atol=1e-6)


def test_occlusion_factor():
    o = sg.occlusion_factor(np.array([50, 100, 110, 0, 3]), np.array([100, 100, 100, 100, 0]))
    assert np.allclose(o[:4], [0.5, 0.0, 0.0, 1.0])  # more label than render clips to 0
    assert np.isnan(o[4])


def _frame(depth, label, cls_ids, poses=None, fid="0000/000001"):
    return Frame(fid, depth, label, YCB_INTRINSICS, np.asarray(cls_ids), poses, None)


def _poses(n):
    P = np.zeros((n, 3, 4))
    P[:, :, :3] = np.eye(3)
    P[:, 2, 3] = 1.0
    return P


def test_outlier_filter_and_fill():
    depth = np.zeros((480, 640), np.float32)
    label = np.zeros((480, 640), np.uint8)
    label[200:230, 300:330] = 5  # 900 pixels at 1 m
    depth[200:230, 300:330] = 1.0
    depth[200, 300:310] = 2.0  # 10 pixels 1 m behind: a flying-pixel streak
    label[50:53, 50:53] = 7  # a tiny object: 9 points
    depth[50:53, 50:53] = 0.7
    f = _frame(depth, label, [5, 7], _poses(2))
    s5, s7 = sg.extract_segments(f, alone_pixels=np.array([1000, 9]), rng=np.random.default_rng(0))
    assert s5.valid and s5.count == 890
    assert s5.points.shape == (1024, 3) and s5.points.dtype == np.float32
    assert np.abs(s5.points[:, 2] - 1.0).max() < 1e-6  # the streak is gone
    assert np.isclose(s5.occlusion, 1 - 900 / 1000)
    assert s7.count == 9 and len(np.unique(s7.points, axis=0)) == 9
    assert np.array_equal(s7.points[9:18], s7.points[:9])
    assert np.isclose(s7.occlusion, 0.0)
    assert np.allclose(s5.R, np.eye(3)) and np.allclose(s5.t, [0, 0, 1])
    assert (s5.frame_id, s5.instance, s7.instance, s5.cls_id) == ("0000/000001", 0, 1, 5)
    # a larger radius keeps the streak
    (s5b, _) = sg.extract_segments(f, np.array([1000, 9]), outlier_radius=1.5)
    assert s5b.count == 900
    # a set's observed points: the first `count` of the FPS order, at most all of it
    from cloudpose.data.segment_set import SegmentSet

    segs = SegmentSet.from_segments([s5, s7])
    assert np.array_equal(segs.observed(0), s5.points[:890])
    assert np.array_equal(segs.observed(1), s7.points[:9])
    segs.count[0] = 5000  # more points than FPS kept
    assert np.array_equal(segs.observed(0), s5.points)


def test_instance_without_points_is_kept_as_a_miss():
    depth = np.zeros((480, 640), np.float32)
    label = np.zeros((480, 640), np.uint8)
    label[10:20, 10:20] = 3
    depth[10:20, 10:20] = 0.9
    label[30:40, 30:40] = 4  # labelled but no depth reading
    f = _frame(depth, label, [3, 4, 9], _poses(3))  # class 9: no pixel at all
    with pytest.warns(sg.SegmentWarning, match="no usable point"):
        segs = sg.extract_segments(f, np.array([100, 100, 100]), n_fps=16)
    assert [s.valid for s in segs] == [True, False, False]
    assert [s.count for s in segs] == [100, 0, 0]
    assert segs[2].points.shape == (16, 3) and not segs[2].points.any()
    assert segs[2].R is not None and np.isclose(segs[2].occlusion, 1.0)


def _three_objects():
    depth = np.zeros((480, 640), np.float32)
    label = np.zeros((480, 640), np.uint8)
    for k, c in enumerate((3, 4, 9)):
        label[10 + 60 * k : 50 + 60 * k, 10:50] = c
        depth[10 + 60 * k : 50 + 60 * k, 10:50] = 0.8 + 0.05 * k
    return depth, label


def test_an_instance_dropped_or_missed_leaves_the_others_points_unchanged():
    """Each instance samples from its own random stream: dropping one instance from a frame,
    or one without a usable point, leaves the points of every other instance as they were."""
    depth, label = _three_objects()

    def points(cls_ids, d=depth):
        segs = sg.extract_segments(
            _frame(d, label, cls_ids), n_fps=64, rng=np.random.default_rng(7)
        )
        return {s.cls_id: s.points for s in segs if s.valid}

    full = points([3, 4, 9])
    assert len({p[0].tobytes() for p in full.values()}) == 3
    dropped = points([3, 9])
    np.testing.assert_array_equal(dropped[9], full[9])
    np.testing.assert_array_equal(dropped[3], full[3])
    missed = depth.copy()
    missed[label == 3] = 0  # the first instance has no depth: a miss
    with pytest.warns(sg.SegmentWarning, match="no usable point"):
        got = points([3, 4, 9], missed)
    assert set(got) == {4, 9}
    np.testing.assert_array_equal(got[4], full[4])
    np.testing.assert_array_equal(got[9], full[9])
    # the frame's generator still decides: another seed, other start points
    other = sg.extract_segments(_frame(depth, label, [3]), n_fps=64, rng=np.random.default_rng(8))
    assert not np.array_equal(other[0].points, full[3])


def test_instance_streams_are_keyed_by_class_and_rank():
    a = sg.instance_streams(np.random.default_rng(1), [5, 2, 5])
    b = sg.instance_streams(np.random.default_rng(1), [2, 5])
    draw = [g.integers(2**32) for g in a]
    assert [g.integers(2**32) for g in b] == [draw[1], draw[0]]
    assert len(set(draw)) == 3  # a class's second instance has a stream of its own


def test_frame_streams_reproduce_one_stream_per_frame():
    """``streams="frame"``: every instance draws from the frame's generator in turn (as data
    made before per-instance streams), so dropping the first instance moves the later ones."""
    depth, label = _three_objects()

    def points(cls_ids, streams):
        segs = sg.extract_segments(
            _frame(depth, label, cls_ids), n_fps=64, rng=np.random.default_rng(7), streams=streams
        )
        return {s.cls_id: s.points for s in segs}

    frame_mode, own = points([3, 4, 9], "frame"), points([3, 4, 9], "instance")
    assert any(not np.array_equal(frame_mode[c], own[c]) for c in (3, 4, 9))
    # one instance: its start is the frame generator's first draw in both layouts of the code
    single = points([4], "frame")[4]
    first = sg.extract_segments(
        _frame(depth, label, [4, 9]), n_fps=64, rng=np.random.default_rng(7), streams="frame"
    )[0].points
    np.testing.assert_array_equal(single, first)
    assert not np.array_equal(points([4, 9], "frame")[9], frame_mode[9])
    with pytest.raises(ValueError, match="streams"):
        sg.extract_segments(_frame(depth, label, [3]), n_fps=64, streams="scene")


def test_the_committed_cpu_presets_keep_one_stream_per_frame():
    from cloudpose.config import Config
    from cloudpose.data import cache
    from cloudpose.registry import resolve

    for preset in ("cpu", "cpu-paper"):
        cfg = resolve("shared-0", preset, 1)
        assert cfg.data.segment_streams == "frame", preset
        assert cache._settings(cfg.data)["pipeline_version"] == 1
    # a stored config (no such field) reads as "frame" and keeps its fingerprint
    cpu = resolve("shared-0", "cpu", 1)
    stored = cpu.to_dict()
    del stored["data"]["segment_streams"]
    assert Config.from_dict(stored) == cpu
    assert cpu.fingerprint() == "ef338e3a7c1144f5"  # the config tag of the committed cpu store
    online = resolve("shared-0", "online", 1)
    assert online.data.segment_streams == "instance"
    assert cache._settings(online.data)["pipeline_version"] == cache.PIPELINE_VERSION == 2


def test_frame_without_ground_truth():
    depth = np.full((480, 640), 1.0, np.float32)
    label = np.zeros((480, 640), np.uint8)
    label[:40, :40] = 2
    segs = sg.extract_segments(_frame(depth, label, [2]), n_fps=32)
    assert segs[0].R is None and segs[0].t is None and np.isnan(segs[0].occlusion)
    assert segs[0].valid and segs[0].count == 1600
    # a frame with poses, read for prediction: the ground truth is ignored
    f = _frame(depth, label, [2], _poses(1))
    (s,) = sg.extract_segments(f, np.array([1600]), n_fps=32, with_gt=False)
    assert s.R is None and s.t is None and np.isnan(s.occlusion) and s.count == 1600


def test_segmentation_sources():
    depth = np.full((480, 640), 1.0, np.float32)
    label = np.zeros((480, 640), np.uint8)
    label[:40, :40] = 2
    f = _frame(depth, label, [2])
    with pytest.raises(ValueError, match="valid segmentations: gt"):
        sg.extract_segments(f, segmentation="posecnn")
    mask_sources.register_mask_source(
        "left-half", lambda fr, c: (fr.label == c) & (np.arange(640) < 20)
    )
    try:
        (s,) = sg.extract_segments(f, segmentation="left-half", n_fps=8)
        assert s.count == 40 * 20
    finally:
        del mask_sources.MASK_SOURCES["left-half"]


# --------------------------------------------------------------------------- real frame


def test_real_frame_segments_lie_on_the_posed_models():
    from cloudpose.data.synth.render import Renderer

    ds = YCBVideo(REAL)
    frame = ds.frame("0000/000001")
    renderer = Renderer({c: p.copy() for c, p in ds.models().items()})
    segs = sg.extract_segments(frame, renderer=renderer, rng=np.random.default_rng(0))
    assert [s.cls_id for s in segs] == frame.cls_ids.tolist()
    for s, P in zip(segs, frame.poses, strict=True):
        assert s.valid and s.count >= 1024
        model = transform_points(ds.model_points(s.cls_id), P[:, :3], P[:, 3])
        d, _ = KDTree(model).query(s.points.astype(np.float64), k=1)
        assert np.median(d) < 0.01, (s.cls_id, np.median(d))
        assert np.allclose(s.R, P[:, :3]) and np.allclose(s.t, P[:, 3])
        assert 0.0 <= s.occlusion <= 1.0
        pixels = int(((frame.label == s.cls_id) & (frame.depth > 0)).sum())
        assert s.count <= pixels


# --------------------------------------------------------------------------- synthetic training set


def test_synthetic_training_segments_match_their_labels(smoke_data):
    """Every cached training segment lies on its own class's model at its own pose.

    The check that rules out label bugs (pose of another instance, transposed rotation, another
    class's model) when a network fails to learn rotation: each alternative is measured too and
    must fit worse.
    """
    from cloudpose.data.cache import SegmentSet
    from cloudpose.geometry.symmetry import symmetric_rotation_error_deg, symmetries_for

    (path,) = (smoke_data / "synth-seed0-v2" / "cache").glob("*-train-*.npz")
    s = SegmentSet.load(path)
    ds = YCBVideo(smoke_data / "synth-seed0-v2")
    models, syms = ds.models(), symmetries_for(ds.classes)
    checked = 0
    for i in np.flatnonzero(s.valid):
        P = s.observed(i).astype(np.float64)
        c, R, t = int(s.cls_id[i]), s.R[i].astype(np.float64), s.t[i].astype(np.float64)

        def fit(X, P=P):
            return float(np.median(KDTree(X).query(P, k=1)[0]))

        own = fit(transform_points(models[c], R, t))
        assert own < 0.006, (s.frame_id[i], c, own)  # sensor noise + model point spacing
        # R^T differs from R by this angle, modulo the class's symmetries (a can's R^T can be
        # one of its equivalent rotations)
        turned = symmetric_rotation_error_deg(R[None], R.T[None], syms[c - 1])[0]
        if turned > 30:
            assert fit(transform_points(models[c], R.T, t)) > own + 0.002
        assert fit(transform_points(models[c % 21 + 1], R, t)) > own
        checked += 1
    assert checked >= 20


@pytest.mark.parametrize(
    ("scale", "looks"), [(1.0, None), (0.1, "10 times too small"), (10.0, "10 times too large")]
)
def test_depth_unit_check_raises_or_with_the_override_warns(monkeypatch, scale, looks):
    """Segments of a whole model at 0.8 m pass; scaled by 10 either way (depth read in another
    unit) they stop with one line, or warn under CLOUDPOSE_NO_UNIT_CHECK=1."""
    from cloudpose.data.synth.surfaces import load_packaged_models

    models = load_packaged_models()
    points = [(models[c] + [0, 0, 0.8]) * scale for c in (1, 2, 3)]
    args = (points, [1, 2, 3], models, "scene/0000", "--depth-factor")
    monkeypatch.delenv(sg.UNIT_CHECK_OFF, raising=False)
    if looks is None:
        sg.check_depth_scale(*args)
        return
    with pytest.raises(ValueError, match=looks) as info:
        sg.check_depth_scale(*args)
    assert str(info.value).startswith("scene/0000: ") and "\n" not in str(info.value)
    assert str(info.value).endswith(f"{sg.UNIT_CHECK_OFF}=1 goes on anyway")
    monkeypatch.setenv(sg.UNIT_CHECK_OFF, "1")
    with pytest.warns(sg.UnitWarning, match=looks):
        sg.check_depth_scale(*args)
    monkeypatch.setenv(sg.UNIT_CHECK_OFF, "0")  # "0" is not an override
    with pytest.raises(ValueError, match=looks):
        sg.check_depth_scale(*args)
