"""Inference (cloudpose.infer): a network from its checkpoint, batched forwards, poses and ICP."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cloudpose.data.segment_set import SegmentSet
from cloudpose.data.synth.surfaces import load_packaged_models
from cloudpose.infer import estimate_poses, forward_in_batches, load_checkpoint
from cloudpose.models import build_model
from cloudpose.models.folded import FoldedPoseNet
from cloudpose.refine import Estimates, refine_poses
from cloudpose.registry import resolve


def _trained_like(variant: str = "shared-0"):
    """A network with running statistics that are not the initial ones, in eval mode."""
    cfg = resolve(variant, "smoke", seed=1)
    torch.manual_seed(0)
    model = build_model(cfg.model)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for _ in range(3):
            pts = torch.randn(8, 32, 3, generator=g) * 0.05 + 0.8
            model(pts, torch.randint(1, cfg.model.num_classes + 1, (8,), generator=g))
    return cfg, model.eval()


def _segments(m: int = 7, n_fps: int = 48) -> SegmentSet:
    g = np.random.default_rng(2)
    valid = np.ones(m, bool)
    valid[1::3] = False  # rows 1, 4, ...: misses
    return SegmentSet(
        points=(g.normal(size=(m, n_fps, 3)) * 0.03 + [0.1, -0.1, 0.8]).astype(np.float32),
        count=np.full(m, n_fps, np.int32),
        cls_id=g.integers(1, 22, m).astype(np.int16),
        R=np.tile(np.eye(3, dtype=np.float32), (m, 1, 1)),
        t=np.zeros((m, 3), np.float32),
        occlusion=np.zeros(m, np.float32),
        frame_id=np.array([f"0001/{i:06d}" for i in range(m)]),
        instance=np.zeros(m, np.int16),
        valid=valid,
    )


def test_load_checkpoint_gives_the_folded_network_and_its_config(tmp_path):
    cfg, model = _trained_like("shared-2")
    path = tmp_path / "model.pt"
    torch.save({"model": model.state_dict(), "config": cfg.to_dict()}, path)
    folded, back = load_checkpoint(path)
    assert isinstance(folded, FoldedPoseNet)
    assert back.fingerprint() == cfg.fingerprint()
    pts = torch.randn(5, 40, 3) * 0.05 + 0.8
    cls_id = torch.tensor([1, 3, 5, 7, 21])
    with torch.no_grad():
        ref = model(pts, cls_id)
    out = folded(pts, cls_id)
    torch.testing.assert_close(out.R, ref.R, rtol=2e-5, atol=2e-5)
    torch.testing.assert_close(out.t, ref.t, rtol=2e-5, atol=2e-5)


def test_load_checkpoint_refuses_what_is_no_checkpoint(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_checkpoint(tmp_path / "none.pt")
    text = tmp_path / "notes.pt"
    text.write_text("not a checkpoint")
    with pytest.raises(ValueError, match="is not a cloudpose checkpoint"):
        load_checkpoint(text)
    keys = tmp_path / "keys.pt"
    torch.save({"weights": {}}, keys)
    with pytest.raises(ValueError, match="expected keys 'model', 'config'"):
        load_checkpoint(keys)
    cfg, _ = _trained_like("shared-0")
    _, other = _trained_like("shared-all")
    wrong = tmp_path / "wrong.pt"
    torch.save({"model": other.state_dict(), "config": cfg.to_dict()}, wrong)
    with pytest.raises(ValueError, match="do not fit its config's network"):
        load_checkpoint(wrong)


def test_forward_in_batches_covers_every_row_and_restores_the_mode():
    _, model = _trained_like()
    model.train()
    pts = torch.randn(11, 32, 3) * 0.05 + 0.8
    cls_id = torch.arange(1, 12)
    parts = list(forward_in_batches(model, pts, cls_id, "cpu", batch_size=4))
    assert [(sl.start, sl.stop) for sl, _ in parts] == [(0, 4), (4, 8), (8, 12)]
    assert model.training
    model.eval()
    with torch.no_grad():
        whole = model(pts, cls_id)
    torch.testing.assert_close(torch.cat([o.t for _, o in parts]), whole.t)
    torch.testing.assert_close(torch.cat([o.R for _, o in parts]), whole.R)


def test_estimate_poses_fills_valid_rows_and_leaves_misses_nan():
    _, model = _trained_like()
    segs = _segments()
    est = estimate_poses(model, segs, n_points=32, batch_size=2)
    assert est.R.shape == (7, 3, 3) and est.t.shape == (7, 3)
    assert np.isnan(est.t[~segs.valid]).all() and np.isfinite(est.t[segs.valid]).all()
    with torch.no_grad():
        ref = model(
            torch.from_numpy(segs.points[segs.valid, :32]),
            torch.from_numpy(segs.cls_id[segs.valid].astype(np.int64)),
        )
    np.testing.assert_allclose(est.t[segs.valid], ref.t.double().numpy(), rtol=1e-6, atol=1e-7)


def test_refine_poses_recovers_a_shifted_pose_of_a_model():
    """Observed points: a model posed at (R, t); the estimate off by 4 mm. ICP moves it back."""
    models = load_packaged_models()
    c = 5
    rng = np.random.default_rng(3)
    pts = models[c][rng.choice(len(models[c]), 256, replace=False)]
    t = np.array([0.05, -0.02, 0.7])
    segs = _segments(m=2, n_fps=256)
    segs.points[0] = (pts + t).astype(np.float32)
    segs.cls_id[:] = c
    segs.valid[:] = [True, False]
    est = Estimates(np.tile(np.eye(3), (2, 1, 1)), np.stack([t + np.array([0.004, 0.0, 0.0]), t]))
    out, stats = refine_poses(segs, est, {c: models[c]})
    np.testing.assert_allclose(out.t[0], t, atol=1e-3)
    assert stats.fitness[0] > 0.9 and not stats.fallback[0]
    assert np.isnan(stats.fitness[1]) and np.array_equal(out.t[1], est.t[1])  # a miss: untouched
