"""The training recipe learns rotation over many classes where the paper's literal one does not.

A small multi-class set (100 synthetic frames, ~500 segments of all 21 classes), 16 epochs:
the cpu preset's recipe (xyz scale, centred rotation input, loss modulo symmetry, BN statistics
re-estimated, cosine lr) against the paper's literal recipe at the same budget. Measured on the
training segments in eval mode (the check that the network fits what it is shown: rotations
and every class's translation).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from cloudpose.registry import resolve
from cloudpose.suite.pipeline import train_run

SMALL = {
    "data": {"train_frames": 100, "test_frames": 4},
    "train": {"epochs": 16, "batch_size": 32, "n_points": 64},
}
LITERAL = {
    "model": {"rotation_input": "raw", "xyz_scale": 1.0},
    "loss": {"symmetric": False},
    "train": {"bn_recalibrate": 0},
}


@pytest.fixture
def small_project(tmp_path) -> Path:
    from cloudpose.data.dataset import prepare_data

    proj = tmp_path / "recipe"
    prepare_data(resolve("shared-0", "smoke", 1, SMALL).data, project_dir=proj, progress=False)
    return proj


def _overrides(*deltas: dict) -> dict:
    out: dict = {}
    for d in deltas:
        for section, fields in d.items():
            out.setdefault(section, {}).update(fields)
    return out


def _train(proj: Path, *deltas: dict, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    cfg = resolve("shared-0", "smoke", 1, _overrides(SMALL, *deltas))
    return cfg, train_run(cfg, project_dir=proj, progress=False)


@pytest.mark.slow
def test_recipe_fits_rotation_and_every_class(small_project, monkeypatch):
    from cloudpose.data.batches import Batchable
    from cloudpose.data.dataset import prepare_data
    from cloudpose.infer import load_checkpoint

    cfg, out = _train(small_project, monkeypatch=monkeypatch)
    assert cfg.model.xyz_scale == 0.03 and cfg.loss.symmetric  # the smoke preset's recipe
    m = out.metrics
    # measured: 25.6 degrees (the literal recipe below: 86.2)
    assert m["fit/rot_sym_err_median_deg"] < 35.0, m
    # eval mode agrees with train mode (re-estimated BN statistics)
    assert abs(m["fit/rot_err_median_deg"] - m["fit/rot_err_median_deg_batchstats"]) < 15.0, m

    # every class fits its own training segments (no class stuck at a constant output)
    train_set = prepare_data(cfg.data, project_dir=small_project, progress=False).train
    data = Batchable.from_segments(train_set, cfg.train.n_points)
    model, _ = load_checkpoint(out.checkpoint)
    with torch.no_grad():
        t = model(data.points, data.cls_id).t
    err = (t - data.t).norm(dim=1).numpy() * 1000
    per_class = {
        c: float(np.median(err[data.cls_id.numpy() == c])) for c in np.unique(data.cls_id.numpy())
    }
    assert len(per_class) == 21
    # After these ~240 steps the class medians are 22-55 mm (typical 33) and the thin marker,
    # still settling, 103 mm; a class stuck at a constant output is far beyond that (the master
    # chef can at xyz in metres: 162 mm where the others had 8-37 mm after 1,250 steps).
    typical = np.median(list(per_class.values()))
    assert max(per_class.values()) < max(4 * typical, 25.0), per_class

    # the paper's literal recipe, same data and budget, does not reach the threshold
    _, literal = _train(small_project, LITERAL, monkeypatch=monkeypatch)
    lm = literal.metrics
    assert lm["fit/rot_sym_err_median_deg"] > 60.0, lm
    # ... and its running BN statistics (momentum 0.01 from step 0) make eval mode much worse
    # than train mode on the same segments (measured: 125.1 vs 82.6 degrees)
    assert lm["fit/rot_err_median_deg"] - lm["fit/rot_err_median_deg_batchstats"] > 25.0, lm
