"""The on-line training source: determinism, agreement with rendered frames, resumable runs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from cloudpose.config import resolve
from cloudpose.conventions import YCB_INTRINSICS
from cloudpose.data.segments import extract_segments
from cloudpose.data.synth.frames import generate_frame
from cloudpose.data.synth.online import OnlineStream, OnlineSynth
from cloudpose.data.ycb import Frame
from cloudpose.pipeline import train_run
from cloudpose.train import TrainingInterrupted
from tests.conftest import make_project

ONLINE = {
    "data": {"train_source": "online", "online_epoch_segments": 64, "online_reuse": 4},
    "train": {"augment_roll_deg": 15.0},
}


def test_a_batch_is_a_function_of_seed_and_step():
    synth = OnlineSynth(2, n_points=64)
    a, b = synth.batch(3, 7, 12), OnlineSynth(2, n_points=64).batch(3, 7, 12)
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


def test_online_and_frame_segments_of_one_scene_agree():
    """Without noise and with the same FPS start, a segment cut on line from a scene is the
    segment the frame generator's rendered frame of that scene gives."""
    f = generate_frame("train", 5, seed=0, noise=False, version=2)
    depth = f.depth.astype(np.float32)
    frame = Frame("x", depth, f.label, YCB_INTRINSICS, f.cls_ids, f.poses, None)
    rng = np.random.default_rng(4)
    ref = extract_segments(frame, alone_pixels=f.alone_pixels, n_fps=128, rng=rng)
    synth = OnlineSynth(2, noise=False, n_points=128)
    got = synth.scene_segments(f.scene, np.random.default_rng(4))
    ref = [s for s, v in zip(ref, f.visible_pixels, strict=True) if s.valid and v >= 100]
    assert [s.cls_id for s in got] == [s.cls_id for s in ref] and len(got) >= 3
    for a, b in zip(got, ref, strict=True):
        assert a.count == b.count
        np.testing.assert_allclose(a.points, b.points, atol=1e-6)
        np.testing.assert_array_equal(a.R, b.R)


def test_stream_steps_reuse_each_chunk_and_restart_anywhere():
    kw = {"version": 2, "n_points": 32}
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
    only = OnlineSynth(2, n_points=32, class_ids=keep, scenes="classes")
    mixed = OnlineSynth(2, n_points=32, class_ids=keep)
    for step in range(3):
        scene = only.sample_scene(np.random.default_rng([0, step]))
        assert set(scene.cls_ids.tolist()) <= set(keep) and len(scene.cls_ids) == 3
    a, b = only.batch(0, 0, 12), mixed.batch(0, 0, 12)
    assert set(a.cls_id.tolist()) <= set(keep) and set(b.cls_id.tolist()) <= set(keep)
    assert a.scenes * 2 < b.scenes, (a.scenes, b.scenes)
    # every class kept: the scenes of "all", draw for draw
    every = tuple(range(1, 22))
    full = OnlineSynth(2, n_points=32, class_ids=every, scenes="classes").batch(0, 1, 8)
    assert np.array_equal(full.points, OnlineSynth(2, n_points=32).batch(0, 1, 8).points)
    with pytest.raises(ValueError, match="at least 3 classes"):
        OnlineSynth(2, class_ids=(5, 11), scenes="classes")
    with pytest.raises(ValueError, match="on-line scenes"):
        OnlineSynth(2, scenes="some")
    with pytest.raises(ValueError, match="online_scenes"):
        resolve("shared-0", "smoke", overrides={"data": {"online_scenes": "some"}})


def test_bad_online_settings_are_refused():
    with pytest.raises(ValueError, match="train_source"):
        resolve("shared-0", "smoke", overrides={"data": {"train_source": "stream"}})
    with pytest.raises(ValueError, match="online_reuse"):
        resolve("shared-0", "smoke", overrides={"data": {"online_reuse": 0}})
    with pytest.raises(ValueError, match="subset of the model ids"):
        OnlineSynth(2, class_ids=(99,))


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


@pytest.mark.slow
def test_online_run_resumes_bit_exact(tmp_path, smoke_data, monkeypatch):
    cfg = resolve("shared-0", "smoke", seed=2, overrides=ONLINE)

    def project(name: str) -> Path:
        return make_project(tmp_path / name, smoke_data, monkeypatch)

    ref = train_run(cfg, project_dir=project("ref"), progress=False)
    proj = project("cut")
    with pytest.raises(TrainingInterrupted):
        train_run(cfg, project_dir=proj, progress=False, max_steps=3)  # mid-epoch
    resumed = train_run(cfg, project_dir=proj, progress=False)
    assert resumed.metrics == ref.metrics
    assert np.isfinite(ref.metrics["train/loss"])
