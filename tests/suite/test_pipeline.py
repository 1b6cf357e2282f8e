"""The pipeline (cloudpose.suite.pipeline): data -> train -> evaluate for one config."""

from __future__ import annotations

import pytest

from cloudpose.data.dataset import data_fingerprint
from cloudpose.registry import resolve
from cloudpose.suite.pipeline import train_and_evaluate, train_run


@pytest.mark.parametrize("stage", [train_run, train_and_evaluate])
def test_a_bad_group_name_stops_before_any_data_is_made(stage, tmp_path):
    with pytest.raises(ValueError, match="group"):
        stage(resolve("shared-0", "smoke"), project_dir=tmp_path, group="no spaces!")
    assert not (tmp_path / "data").exists()


def test_a_finished_run_is_not_trained_again_and_is_evaluated(smoke_project):
    """The smoke run (trained once for the session) is found, not retrained; its evaluation
    on its own test set is logged to it, and the data passed on is the data it was trained on."""
    proj, trained = smoke_project
    cfg = resolve("shared-0", "smoke", seed=1)
    again = train_run(cfg, project_dir=proj, progress=False)
    assert (again.run_id, again.checkpoint) == (trained.run_id, trained.checkpoint)
    out = train_and_evaluate(cfg, project_dir=proj, progress=False, real=False)
    assert out.train.run_id == trained.run_id and out.real is None
    assert out.evaluation.run_id == trained.run_id
    assert 0.0 <= out.evaluation.metrics["test/ads_auc"] <= 1.0
    assert len(out.evaluation.table) == len(out.data.test)
    assert out.data.data_key == data_fingerprint(cfg.data, proj)
