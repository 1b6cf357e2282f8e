"""The on-line training source: determinism, agreement with rendered frames, resumable runs, and
that it teaches rotation where the frame recipe at the same steps does not."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from cloudpose.conventions import YCB_INTRINSICS
from cloudpose.data.dataset import prepare_data
from cloudpose.data.segments import extract_segments
from cloudpose.data.synth.chunks import OnlineSettings
from cloudpose.data.synth.frames import generate_frame
from cloudpose.data.synth.online import OnlineStream, OnlineSynth
from cloudpose.data.ycb import Frame
from cloudpose.registry import resolve
from cloudpose.suite.pipeline import train_run
from cloudpose.train.loop import TrainingInterrupted, split_frames
from tests.conftest import make_project

ONLINE = {
    "data": {"train_source": "online", "online_epoch_segments": 64, "online_reuse": 4},
    "train": {"augment_roll_deg": 15.0},
}


@pytest.mark.parametrize("online_version", [1, 2, 3])
def test_a_batch_is_a_function_of_seed_and_step(online_version):
    synth = OnlineSynth(OnlineSettings(2, n_points=64, online_version=online_version))
    a = synth.batch(3, 7, 12)
    b = OnlineSynth(OnlineSettings(2, n_points=64, online_version=online_version)).batch(3, 7, 12)
    for x, y in zip(a.tensors(), b.tensors(), strict=True):
        assert torch.equal(x, y)
    other = synth.batch(3, 8, 12)
    assert not np.array_equal(a.points, other.points)
    assert a.points.shape == (12, 64, 3) and a.points.dtype == np.float32
    # every segment lies on its posed model: the mean distance of its points to the nearest
    # model point is within the sensor noise (a few mm), not the size of the object
    from scipy.spatial import cKDTree

    models = synth._gen.models
    for p, c, R, t in zip(a.points, a.cls_id, a.R, a.t, strict=True):
        posed = models[int(c)] @ R.T + t
        d, _ = cKDTree(posed).query(p)
        assert np.median(d) < 0.01, f"class {c}: median {np.median(d):.4f} m from its model"


@pytest.mark.parametrize("online_version", [1, 2, 3])
def test_online_and_frame_segments_of_one_scene_agree(online_version):
    """Without noise and with the same FPS start, a segment cut on line from a scene is the
    segment the frame generator's rendered frame of that scene gives (version 2: its z-buffer
    instead of the ray cast, to the same tolerance)."""
    f = generate_frame("train", 5, seed=0, noise=False, version=2)
    depth = f.depth.astype(np.float32)
    frame = Frame("x", depth, f.label, YCB_INTRINSICS, f.cls_ids, f.poses, None)
    rng = np.random.default_rng(4)
    ref = extract_segments(frame, alone_pixels=f.alone_pixels, n_fps=128, rng=rng)
    synth = OnlineSynth(OnlineSettings(2, noise=False, n_points=128, online_version=online_version))
    got = synth.scene_segments(f.scene, np.random.default_rng(4))
    ref = [s for s, v in zip(ref, f.visible_pixels, strict=True) if s.valid and v >= 100]
    assert [s.cls_id for s in got] == [s.cls_id for s in ref] and len(got) >= 3
    for a, b in zip(got, ref, strict=True):
        assert a.count == b.count
        # rays cast in each model frame (on line) against meshes moved into the camera frame
        # (frames): the same hits, to float32 rounding of ~1 m distances (a few micrometres)
        np.testing.assert_allclose(a.points, b.points, atol=1e-5)
        np.testing.assert_array_equal(a.R, b.R)


def _agreement(a, b) -> tuple[float, float, float]:
    """Share of segments of two batches that are the same points (within 1e-5 m); over the
    others, the largest mean nearest-point distance (metres, both ways) and the largest
    relative difference of the point counts."""
    from scipy.spatial import cKDTree

    same, worst, count = 0, 0.0, 0.0
    for p, q, m, n in zip(a.points, b.points, a.count, b.count, strict=True):
        if np.abs(p - q).max() < 1e-5:
            same += 1
            continue
        d = (cKDTree(q).query(p)[0].mean() + cKDTree(p).query(q)[0].mean()) / 2
        worst = max(worst, float(d))
        count = max(count, abs(int(m) - int(n)) / max(int(m), 1))
    return same / len(a.points), worst, count


ONLINE_V2_SAME = 0.6
"""Least share of version-2 segments that are version 1's points. Both make the same draws
and computations up to float rounding, but a rounding flip of one silhouette pixel (z-buffer
against ray cast) changes how many object pixels draw noise, so every later draw of that scene
shifts: its segments are then other draws of the same sensor law (a few percent of scenes). On
seed 1, steps 0-3, 32 segments of 64 points each: 31, 32, 32 and 26 of 32 the same."""
ONLINE_V2_NEAR = 0.015
"""Metres: the segments of a re-drawn scene are the same surfaces with other missing-depth
blobs and another FPS start: mean nearest-point distance between the two 64-point samples up
to 10.4 mm measured (their spacing is ~1-2 cm), counts within 1.7% (``ONLINE_V2_COUNT``)."""
ONLINE_V2_COUNT = 0.03
ONLINE_V3_NEAR = 0.025
"""Metres: the largest mean nearest-point distance between a version-3 segment and version 1's
of the same object (64 points each). Other noise draws and so another FPS start: two samples
of one surface ~1-3 cm apart; 3.9-17.4 mm measured on seed 0, steps 3 and 4 (48 segments)."""
ONLINE_V3_POINTS = 0.03
"""Relative difference of the points of a batch, version 3 against version 1 (other draws of
the same missing-depth law): +0.01% and -1.4% measured on seed 0, steps 3 and 4."""


def test_online_version_2_makes_version_1s_segments():
    """The compiled path (data.online_version = 2) draws the same scenes and sensor readings
    as the ray cast path, to float rounding: the same classes and poses, and, but for scenes
    re-drawn after a rounding flip, the same points."""
    a = OnlineSynth(OnlineSettings(2, n_points=64, online_version=1)).batch(0, 3, 24)
    b = OnlineSynth(OnlineSettings(2, n_points=64, online_version=2)).batch(0, 3, 24)
    np.testing.assert_array_equal(a.cls_id, b.cls_id)
    np.testing.assert_array_equal(a.R, b.R)
    assert a.scenes == b.scenes
    same, worst, count = _agreement(a, b)
    assert same >= ONLINE_V2_SAME, f"{same:.0%} of the segments agree"
    assert worst < ONLINE_V2_NEAR, f"a differing segment is {worst * 1000:.1f} mm off"
    assert count < ONLINE_V2_COUNT, f"a differing segment has {count:.1%} other points"


def test_online_version_2_without_numba_is_its_twin():
    """Without the compiled kernels version 2 takes the twins (ray cast, scipy's transforms,
    the segment path's FPS): the same segments to float rounding."""
    from cloudpose.kernels.backend import disabled

    a = OnlineSynth(OnlineSettings(2, n_points=64, online_version=2)).batch(1, 0, 16)
    with disabled():
        b = OnlineSynth(OnlineSettings(2, n_points=64, online_version=2)).batch(1, 0, 16)
    np.testing.assert_array_equal(a.cls_id, b.cls_id)
    same, worst, count = _agreement(a, b)
    assert same >= ONLINE_V2_SAME and worst < ONLINE_V2_NEAR and count < ONLINE_V2_COUNT, (
        same,
        worst,
        count,
    )


def test_online_version_3_is_version_1s_distribution():
    """Version 3 draws the same scenes and objects as version 1, and its sensor readings from
    the same laws (other draws): the same classes and poses, as many points in all (within
    :data:`ONLINE_V3_POINTS`), every segment on its posed model, and each as near version 1's
    as two samples of one surface from other FPS starts (:data:`ONLINE_V3_NEAR`)."""
    from scipy.spatial import cKDTree

    a = OnlineSynth(OnlineSettings(2, n_points=64, online_version=1)).batch(0, 3, 24)
    synth = OnlineSynth(OnlineSettings(2, n_points=64, online_version=3))
    b = synth.batch(0, 3, 24)
    np.testing.assert_array_equal(a.cls_id, b.cls_id)
    np.testing.assert_array_equal(a.R, b.R)
    assert a.scenes == b.scenes
    assert abs(b.count.sum() / a.count.sum() - 1) < ONLINE_V3_POINTS
    _, worst, _ = _agreement(a, b)
    assert worst < ONLINE_V3_NEAR, f"a segment is {worst * 1000:.1f} mm off"
    for p, c, R, t in zip(b.points, b.cls_id, b.R, b.t, strict=True):
        d, _ = cKDTree(synth._gen.models[int(c)] @ R.T + t).query(p)
        assert np.median(d) < 0.01, f"class {c}: median {np.median(d):.4f} m from its model"


def test_online_version_3_without_numba_is_its_twin():
    """Without the compiled kernels version 3 takes its numpy twins (version 2's z-buffer,
    which casts rays, scipy's filter and edge distance, the segment path's FPS): the same
    segments to float rounding."""
    from cloudpose.kernels.backend import disabled

    a = OnlineSynth(OnlineSettings(2, n_points=64, online_version=3)).batch(1, 0, 8)
    with disabled():
        b = OnlineSynth(OnlineSettings(2, n_points=64, online_version=3)).batch(1, 0, 8)
    np.testing.assert_array_equal(a.cls_id, b.cls_id)
    same, worst, count = _agreement(a, b)
    assert same >= ONLINE_V2_SAME and worst < ONLINE_V2_NEAR and count < ONLINE_V2_COUNT, (
        same,
        worst,
        count,
    )


def test_cut_segments_is_extract_segments():
    """The one-pass segment cut (compiled and numpy) gives extract_segments' segments."""
    from cloudpose.data.synth.online import cut_segments
    from cloudpose.kernels.backend import disabled

    f = generate_frame("train", 2, seed=0, noise=True, version=2)
    frame = Frame(
        "x", f.depth.astype(np.float32), f.label, YCB_INTRINSICS, f.cls_ids, f.poses, None
    )
    ref = extract_segments(frame, n_fps=256, rng=np.random.default_rng(9))
    for ctx in (disabled, None):
        if ctx is None:
            got = cut_segments(frame, 256, 0.2, np.random.default_rng(9))
        else:
            with ctx():
                got = cut_segments(frame, 256, 0.2, np.random.default_rng(9))
        for a, b in zip(got, ref, strict=True):
            assert (a.cls_id, a.count, a.valid) == (b.cls_id, b.count, b.valid)
            np.testing.assert_allclose(a.points, b.points, atol=1e-6)
            np.testing.assert_array_equal(a.t, b.t)


def test_online_version_is_a_setting_of_its_own():
    """data.online_version 1 leaves fingerprints as they were; 2 changes the fingerprint and
    the synthesis settings; others are refused."""
    from cloudpose.config import Config

    cfg = resolve("shared-0", "cpu-online")
    d = cfg.to_dict()
    del d["data"]["online_version"]
    assert Config.from_dict(d).fingerprint() == cfg.fingerprint()
    assert OnlineSettings.from_config(cfg, []).online_version == 1
    fast = resolve("shared-0", "cpu-online", overrides={"data": {"online_version": 2}})
    assert fast.fingerprint() != cfg.fingerprint()
    assert OnlineSettings.from_config(fast, []).online_version == 2
    with pytest.raises(ValueError, match="online_version"):
        resolve("shared-0", "cpu-online", overrides={"data": {"online_version": 4}})


@pytest.mark.parametrize("online_version", [1, 3])
def test_stream_steps_reuse_each_chunk_and_restart_anywhere(online_version):
    kw = OnlineSettings(2, n_points=32, online_version=online_version)
    args = {"seed": 1, "batch_size": 8, "reuse": 2, "total_steps": 5, "spacing": 2}
    full = OnlineStream(kw, workers=0, **args)
    steps = [full.next() for _ in range(5)]
    # a segment is used in two steps two apart: the second half of step s is the first of s+2,
    # and consecutive steps share nothing
    for s in range(3):
        assert torch.equal(steps[s][0][4:], steps[s + 2][0][:4])
        assert not torch.equal(steps[s][0][4:], steps[s + 1][0][:4])
    late = OnlineStream(kw, start=3, workers=1, **args)
    for s in (3, 4):
        for x, y in zip(late.next(), steps[s], strict=True):
            assert torch.equal(x, y)
    late.close()
    with pytest.raises(ValueError, match="online_reuse"):
        OnlineStream(kw, seed=1, batch_size=8, reuse=3, total_steps=4)


def test_scenes_of_the_kept_classes_only():
    """With ``scenes="classes"`` a scene holds only kept classes, so far fewer scenes fill a
    batch; with "all" the other classes stay as occluders and segments are dropped."""
    keep = (5, 11, 15)
    only = OnlineSynth(OnlineSettings(2, n_points=32, class_ids=keep, online_scenes="classes"))
    mixed = OnlineSynth(OnlineSettings(2, n_points=32, class_ids=keep))
    for step in range(3):
        scene = only.sample_scene(np.random.default_rng([0, step]))
        assert set(scene.cls_ids.tolist()) <= set(keep) and len(scene.cls_ids) == 3
    a, b = only.batch(0, 0, 12), mixed.batch(0, 0, 12)
    assert set(a.cls_id.tolist()) <= set(keep) and set(b.cls_id.tolist()) <= set(keep)
    assert a.scenes * 2 < b.scenes, (a.scenes, b.scenes)
    # every class kept: the scenes of "all", draw for draw
    every = tuple(range(1, 22))
    full = OnlineSynth(
        OnlineSettings(2, n_points=32, class_ids=every, online_scenes="classes")
    ).batch(0, 1, 8)
    assert np.array_equal(
        full.points, OnlineSynth(OnlineSettings(2, n_points=32)).batch(0, 1, 8).points
    )
    with pytest.raises(ValueError, match="at least 3 classes"):
        OnlineSettings(2, class_ids=(5, 11), online_scenes="classes")
    with pytest.raises(ValueError, match="on-line scenes"):
        OnlineSettings(2, online_scenes="some")
    with pytest.raises(ValueError, match="online_scenes"):
        resolve("shared-0", "smoke", overrides={"data": {"online_scenes": "some"}})


def test_a_config_with_too_few_classes_for_its_scenes_is_refused_when_made():
    """The config says it, not the first training step: scenes of 2 classes cannot be drawn."""
    from cloudpose.config import ONLINE_SCENE_MIN_CLASSES
    from cloudpose.data.synth.scenes import N_OBJECTS

    assert ONLINE_SCENE_MIN_CLASSES == N_OBJECTS[0]
    two = ("006_mustard_bottle", "011_banana")
    data = {"train_source": "online", "online_scenes": "classes", "classes": two}
    with pytest.raises(ValueError, match=r"at least 3 classes.*011_banana"):
        resolve("shared-0", "smoke", overrides={"data": data})
    # with every class's scenes, or three classes, or frames, it is a config
    resolve("shared-0", "smoke", overrides={"data": {**data, "online_scenes": "all"}})
    resolve("shared-0", "smoke", overrides={"data": {**data, "classes": (*two, "035_power_drill")}})
    resolve("shared-0", "smoke", overrides={"data": {**data, "train_source": "frames"}})


def test_bad_online_settings_are_refused():
    with pytest.raises(ValueError, match="train_source"):
        resolve("shared-0", "smoke", overrides={"data": {"train_source": "stream"}})
    with pytest.raises(ValueError, match="online_reuse"):
        resolve("shared-0", "smoke", overrides={"data": {"online_reuse": 0}})
    with pytest.raises(ValueError, match="subset of the model ids"):
        OnlineSynth(OnlineSettings(2, class_ids=(99,)))


def test_frames_configs_keep_their_fingerprint():
    """The on-line fields at their defaults are left out of the fingerprint: every run stored
    before they existed keeps its identity."""
    cfg = resolve("shared-0", "cpu")
    d = cfg.to_dict()
    for k in (
        "train_source",
        "online_epoch_segments",
        "online_reuse",
        "online_workers",
        "online_scenes",
    ):
        del d["data"][k]
    from cloudpose.config import Config

    assert Config.from_dict(d).fingerprint() == cfg.fingerprint()


TWO_FORMS = {
    "data": {
        **ONLINE["data"],
        "online_version": 3,
        "online_bleed": 1.0,
        "online_bleed_branch": "translation",
    },
    "train": ONLINE["train"],
}
"""On line with the translation branch alone on bleeding masks: two forms of each segment."""


@pytest.mark.slow
@pytest.mark.parametrize("overrides", [ONLINE, TWO_FORMS], ids=["one-form", "two-forms"])
def test_online_run_resumes_bit_exact(tmp_path, smoke_data, monkeypatch, overrides):
    cfg = resolve("shared-0", "smoke", seed=2, overrides=overrides)

    def project(name: str) -> Path:
        return make_project(tmp_path / name, smoke_data, monkeypatch)

    ref = train_run(cfg, project_dir=project("ref"), progress=False)
    proj = project("cut")
    with pytest.raises(TrainingInterrupted):
        train_run(cfg, project_dir=proj, progress=False, max_steps=3)  # mid-epoch
    resumed = train_run(cfg, project_dir=proj, progress=False)
    assert resumed.metrics == ref.metrics
    assert np.isfinite(ref.metrics["train/loss"])


# --------------------------------------------------------------------------- learning

LEARN_CLASSES = ("006_mustard_bottle", "019_pitcher_base", "035_power_drill")
LEARN = {
    "data": {
        "classes": list(LEARN_CLASSES),
        "train_source": "online",
        "online_scenes": "classes",
        "online_reuse": 8,
        "online_epoch_segments": 1600,
    },
    "train": {"epochs": 2, "batch_size": 16, "augment_roll_deg": 15.0, "lr_schedule": "cosine"},
    "loss": {"symmetry_table": 2},
}
"""200 steps of batch 16 on three classes (400 fresh segments, each used 8 times)."""
LEARN_THRESHOLD_DEG = 48.0
"""Held-out median rotation error a run must get under; measured on a 2-core Intel Xeon: 40.0
degrees on line, 56.2 for the frame recipe at the same steps."""


def _held_out_rotation_error(checkpoint: Path, n_points: int) -> float:
    """Median rotation error modulo symmetry (table 2), degrees, of a network on 96 fresh
    on-line segments of :data:`LEARN_CLASSES` from a seed no run trains on."""
    from cloudpose.conventions import packaged_classes
    from cloudpose.geometry.symmetry import rotation_errors_modulo_symmetry
    from cloudpose.infer import load_checkpoint

    names = packaged_classes()
    ids = tuple(names.index(c) + 1 for c in LEARN_CLASSES)
    held = OnlineSynth(
        OnlineSettings(2, n_points=n_points, class_ids=ids, online_scenes="classes")
    ).batch(999, 0, 96)
    points, cls_id, R, _ = held.tensors()
    model, _ = load_checkpoint(checkpoint)
    with torch.no_grad():
        out = model(points, cls_id)
    err = rotation_errors_modulo_symmetry(cls_id.numpy(), R.numpy(), out.R.numpy(), names, table=2)
    return float(np.median(err))


def test_a_small_online_run_learns_rotation(tmp_path, smoke_data, monkeypatch):
    """On line, 200 steps on three classes without a symmetry that depth shows whole (the
    mustard bottle's half turn aside) bring the held-out rotation error under
    :data:`LEARN_THRESHOLD_DEG`; the frame recipe at the same steps on 200 rendered frames (144
    training segments of these classes) fits its own segments and stays above it on fresh
    ones (:func:`test_frames_at_the_same_steps_do_not_reach_it`)."""
    cfg = resolve("shared-0", "smoke", seed=1, overrides=LEARN)
    out = train_run(
        cfg, project_dir=make_project(tmp_path / "p", smoke_data, monkeypatch), progress=False
    )
    err = _held_out_rotation_error(out.checkpoint, cfg.train.n_points)
    assert err < LEARN_THRESHOLD_DEG, err


@pytest.mark.slow
def test_frames_at_the_same_steps_do_not_reach_it(tmp_path, monkeypatch):
    """The frame recipe, same network, classes, batch and steps, on the segments of 200
    rendered frames (the cpu preset's kind of training set, cut to three classes)."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    frames = {"data": {"classes": list(LEARN_CLASSES), "train_frames": 200, "test_frames": 4}}
    cfg = resolve("shared-0", "smoke", seed=1, overrides=frames)
    data = prepare_data(cfg.data, tmp_path, progress=False)
    fit = (~split_frames(data.train.frame_id, cfg.train.val_fraction)).sum()
    steps = LEARN["train"]["epochs"] * LEARN["data"]["online_epoch_segments"] // 16
    train = {**LEARN["train"], "epochs": max(round(steps * 16 / fit), 1)}
    cfg = resolve(
        "shared-0", "smoke", seed=1, overrides={**frames, "train": train, "loss": LEARN["loss"]}
    )
    out = train_run(cfg, project_dir=tmp_path, data=data, progress=False)
    assert out.metrics["fit/rot_sym_err_median_deg"] < 20.0  # it fits what it sees ...
    err = _held_out_rotation_error(out.checkpoint, cfg.train.n_points)
    assert err > LEARN_THRESHOLD_DEG, err  # ... and does not carry it to fresh segments


def test_a_bleeding_mask_grows_by_one_pixel_into_its_neighbours():
    """:func:`bleed_masks`: a pixel changes owner only when it is a 4-neighbour of a pixel of
    the object it joins; share 0 changes nothing; share 1 takes some, not all, of the ring."""
    from cloudpose.data.synth.online import bleed_masks

    index = np.full((12, 16), -1, dtype=np.int64)
    index[3:8, 3:7] = 0
    index[3:8, 7:11] = 1  # touches object 0
    same = bleed_masks(index, 2, 0.0, np.random.default_rng(0))
    np.testing.assert_array_equal(same, index)
    grown = bleed_masks(index, 2, 1.0, np.random.default_rng(1))
    changed = np.argwhere(grown != index)
    assert 0 < len(changed) < (index < 0).sum()
    for v, u in changed:
        owner = grown[v, u]
        neighbours = [index[v + dv, u + du] for dv, du in ((0, -1), (0, 1), (-1, 0), (1, 0))]
        assert owner in neighbours and owner != index[v, u], (v, u)
    np.testing.assert_array_equal(
        bleed_masks(index, 2, 1.0, np.random.default_rng(1)), grown
    )  # a function of the draws


def test_bleeding_masks_add_points_off_the_object():
    """``data.online_bleed`` (version 3): the same scenes, more points a segment, some of them
    off the posed model (the background's or a neighbour's depth), and deterministic."""

    plain = OnlineSynth(OnlineSettings(2, n_points=64, online_version=3))
    bled = OnlineSynth(OnlineSettings(2, n_points=64, online_version=3, online_bleed=1.0))
    a, b = plain.batch(0, 3, 24), bled.batch(0, 3, 24)
    np.testing.assert_array_equal(a.cls_id, b.cls_id)
    np.testing.assert_array_equal(a.R, b.R)
    assert b.count.sum() > a.count.sum()
    assert _off_model(plain, b) > _off_model(plain, a)
    again = OnlineSynth(OnlineSettings(2, n_points=64, online_version=3, online_bleed=1.0))
    np.testing.assert_array_equal(again.batch(0, 3, 24).points, b.points)


def test_a_translation_bleeding_segment_comes_in_both_forms():
    """``data.online_bleed_branch = "translation"``: each segment is cut from the rendered
    masks (its first ``n_points`` rows) and from the bleeding ones (the next): the same scenes
    and objects, the bleeding form with more points off the posed model; deterministic."""
    n = 64
    plain = OnlineSynth(OnlineSettings(2, n_points=n, online_version=3))
    pair = OnlineSynth(
        OnlineSettings(
            2, n_points=n, online_version=3, online_bleed=1.0, online_bleed_branch="translation"
        )
    )
    a, b = plain.batch(0, 3, 24), pair.batch(0, 3, 24)
    assert b.points.shape == (24, 2 * n, 3)
    np.testing.assert_array_equal(a.cls_id, b.cls_id)
    np.testing.assert_array_equal(a.R, b.R)
    np.testing.assert_array_equal(a.t, b.t)
    rendered = replace(b, points=np.ascontiguousarray(b.points[:, :n]))
    bleeding = replace(b, points=np.ascontiguousarray(b.points[:, n:]))
    assert _off_model(plain, bleeding) > _off_model(plain, rendered)
    again = OnlineSynth(pair.settings).batch(0, 3, 24)
    np.testing.assert_array_equal(again.points, b.points)


@pytest.mark.parametrize("compiled", [True, False])
def test_a_paired_bleeding_segment_keeps_the_plain_runs_rendered_form(compiled, monkeypatch):
    """``data.online_bleed_branch = "translation-paired"``: the rendered form of each segment
    is, to the bit, the segment a run without bleeding draws at the same seed and step (the
    bleeding's draws come from a stream of their own), so a translation-only run's rotation
    branch trains on the plain run's segments; "translation" draws the bleeding first, from
    the scene's stream, and its rendered form is another draw."""
    from cloudpose.data.synth import online as online_module

    monkeypatch.setattr(online_module, "enabled", lambda: compiled)  # the numpy twins too
    n = 64

    def bleeding(branch: str) -> OnlineSettings:
        return OnlineSettings(
            2, n_points=n, online_version=3, online_bleed=1.0, online_bleed_branch=branch
        )

    plain = OnlineSynth(OnlineSettings(2, n_points=n, online_version=3)).batch(0, 3, 24)
    paired = OnlineSynth(bleeding("translation-paired")).batch(0, 3, 24)
    assert paired.points.shape == (24, 2 * n, 3)
    np.testing.assert_array_equal(paired.points[:, :n], plain.points)
    for name in ("cls_id", "R", "t", "count"):
        np.testing.assert_array_equal(getattr(paired, name), getattr(plain, name))
    unpaired = OnlineSynth(bleeding("translation")).batch(0, 3, 24)
    assert not np.array_equal(unpaired.points[:, :n], plain.points)
    synth = OnlineSynth(bleeding("translation-paired"))
    rendered = replace(paired, points=np.ascontiguousarray(paired.points[:, :n]))
    bled = replace(paired, points=np.ascontiguousarray(paired.points[:, n:]))
    assert _off_model(synth, bled) > _off_model(synth, rendered)  # the second form bleeds


def test_smoothed_readings_stay_on_their_rays_and_lose_independent_noise():
    """:func:`smooth_readings`: one object's readings averaged over its own pixels; each point
    keeps its pixel's ray; independent noise shrinks; sigma 0 changes nothing."""
    from cloudpose.data.synth.sensor import smooth_readings

    K = np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]])
    v, u = np.mgrid[200:260, 300:360]
    rng = np.random.default_rng(0)
    z = 0.9 + 0.002 * rng.standard_normal(v.shape)  # a wall 0.9 m away, 2 mm of noise
    pts = np.column_stack(
        [((u - 320) / 1000 * z).ravel(), ((v - 240) / 1000 * z).ravel(), z.ravel()]
    )
    out = smooth_readings(pts, K, 1.5)
    np.testing.assert_allclose(out[:, :2] / out[:, 2:], pts[:, :2] / pts[:, 2:], atol=1e-12)
    inner = ((v > 210) & (v < 250) & (u > 310) & (u < 350)).ravel()
    assert np.std(out[inner, 2]) < 0.4 * np.std(pts[inner, 2])
    np.testing.assert_array_equal(smooth_readings(pts, K, 0.0), pts)


def test_correlated_readings_keep_the_amount_of_noise_and_the_edges():
    """:func:`correlate_readings` on a wall with a step: off the step, the noise is as large as
    the sensor's and correlated between neighbours (the ``depth_corr`` statistic near the real
    frames' ~0.4, where independent noise gives ~0); readings on the step (flying pixels among
    them) and every ray are kept; sigma 0 changes nothing; the same draws give the same points."""
    from cloudpose.data.synth.sensor import NoiseModel, _noisy, correlate_readings
    from cloudpose.studies.perturbations import depth_correlation

    K = np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]])
    clean = np.zeros((480, 640))
    clean[150:330, 230:410] = 1.0
    clean[150:330, 320:410] = 0.95  # a 5 cm step: a depth edge down the middle
    v, u = np.nonzero(clean > 0)
    z0 = clean[v, u]
    rng = np.random.default_rng(0)
    zero = np.zeros_like(z0)
    z = _noisy(z0, zero, rng.standard_normal(len(z0)), np.ones_like(z0), zero, NoiseModel())
    pts = np.column_stack([(u - 320) / 1000 * z, (v - 240) / 1000 * z, z])
    out = correlate_readings(pts, clean, K, 2.0, np.random.default_rng(1))
    np.testing.assert_allclose(out[:, :2] / out[:, 2:], pts[:, :2] / pts[:, 2:], atol=1e-12)
    edge = (u == 319) | (u == 320)
    np.testing.assert_array_equal(out[edge], pts[edge])
    assert not np.array_equal(out[~edge], pts[~edge])
    assert 0.8 < np.std(out[~edge, 2] - z0[~edge]) / np.std(z[~edge] - z0[~edge]) < 1.25

    def corr(zs: np.ndarray) -> float:
        depth = np.zeros_like(clean)
        depth[v, u] = zs
        left = np.zeros_like(clean, dtype=bool)
        left[150:330, 230:315] = True
        return depth_correlation(depth, left)

    assert abs(corr(z)) < 0.1
    assert 0.25 < corr(out[:, 2]) < 0.6
    np.testing.assert_array_equal(
        out, correlate_readings(pts, clean, K, 2.0, np.random.default_rng(1))
    )
    np.testing.assert_array_equal(correlate_readings(pts, clean, K, 0.0, rng), pts)
    with pytest.raises(ValueError, match="outside the 100x100 clean depth"):
        correlate_readings(pts, clean[:100, :100], K, 2.0, rng)


@pytest.mark.parametrize("name, value", [("online_smooth", 1.0), ("online_noise_corr", 2.0)])
def test_version_3_depth_settings_keep_scenes_and_counts(name, value):
    """``data.online_smooth`` and ``data.online_noise_corr`` (version 3): the same scenes and
    point counts, other points; deterministic."""
    plain = OnlineSynth(OnlineSettings(2, n_points=64, online_version=3))
    changed = OnlineSynth(OnlineSettings(2, n_points=64, online_version=3, **{name: value}))
    a, b = plain.batch(0, 3, 24), changed.batch(0, 3, 24)
    np.testing.assert_array_equal(a.cls_id, b.cls_id)
    np.testing.assert_array_equal(a.count, b.count)
    assert not np.array_equal(a.points, b.points)
    again = OnlineSynth(OnlineSettings(2, n_points=64, online_version=3, **{name: value}))
    np.testing.assert_array_equal(again.batch(0, 3, 24).points, b.points)
    if name == "online_noise_corr":  # the tail of points off the object stays (smoothing
        assert abs(_off_model(plain, b) - _off_model(plain, a)) < 0.01  # pulls it in)


def _off_model(synth: OnlineSynth, batch) -> float:
    """The mean share of a batch's segment points more than 1 cm off their posed model."""
    from scipy.spatial import cKDTree

    far = []
    for p, c, R, t in zip(batch.points, batch.cls_id, batch.R, batch.t, strict=True):
        d, _ = cKDTree(synth._gen.models[int(c)] @ R.T + t).query(p)
        far.append(np.mean(d > 0.01))
    return float(np.mean(far))


@pytest.mark.parametrize(
    "name, bad, limits",
    [
        ("online_bleed", 1.5, r"\[0, 1\]"),
        ("online_smooth", 6.0, r"\[0, 5\]"),
        ("online_noise_corr", 6.0, r"\[0, 5\]"),
    ],
)
def test_version_3_synthesis_settings_are_checked(name, bad, limits):
    from cloudpose.config import DataConfig

    with pytest.raises(ValueError, match=rf"data.{name} must be in {limits}"):
        DataConfig(train_source="online", online_version=3, **{name: bad})
    with pytest.raises(ValueError, match=r"needs data\.train_source='online' and"):
        DataConfig(train_source="online", online_version=2, **{name: 0.5})
    assert getattr(DataConfig(train_source="online", online_version=3, **{name: 0.5}), name)


def test_the_bleeding_branch_is_checked():
    from cloudpose.config import DataConfig

    online = {"train_source": "online", "online_version": 3}
    with pytest.raises(ValueError, match=r"online_bleed_branch='rotation': expected one of"):
        DataConfig(**online, online_bleed=1.0, online_bleed_branch="rotation")
    with pytest.raises(ValueError, match=r"needs bleeding masks \(data\.online_bleed > 0\)"):
        DataConfig(**online, online_bleed_branch="translation")
    data = {**online, "online_bleed": 1.0, "online_bleed_branch": "translation"}
    assert resolve("shared-0", "smoke", overrides={"data": data}).data.online_bleed_branch
    with pytest.raises(ValueError, match=r"share no layer \(model\.shared_layers=0\)"):
        resolve("shared-1", "smoke", overrides={"data": data})
    with pytest.raises(ValueError, match=r"needs the sensor of data\.synth_version >= 2"):
        DataConfig(**data, synth_version=1)  # version 1's sensor takes version 2's path
    assert DataConfig(**data, synth_version=1, noise=False).online_bleed
    with pytest.raises(ValueError, match=r"two forms .* need bleeding masks of version 3"):
        OnlineSettings(2, online_version=3, online_bleed_branch="translation")
