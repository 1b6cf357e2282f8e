"""The experiment log lists a group's runs with their overrides and rotation errors."""

from __future__ import annotations

import pytest

from cloudpose.registry import resolve
from cloudpose.report.experiments import (
    collect,
    config_changes,
    experiment_table,
    steps_per_epoch,
    write_log,
)
from tests.conftest import train_smoke_project


@pytest.fixture(scope="module")
def group_store(tmp_path_factory, smoke_data):
    """A project whose store holds one run of the shared group: shared-0 trained on the smoke
    preset. Its own store, not the session's smoke project, which other tests add runs to."""
    return train_smoke_project(tmp_path_factory.mktemp("experiments"), smoke_data)


def test_config_changes_lists_overrides_only():
    cfg = resolve("shared-0", "cpu", 1, {"model": {"xyz_scale": 0.1}, "train": {"epochs": 3}})
    assert config_changes(cfg) == {"model.xyz_scale": 0.1, "train.epochs": 3}
    assert config_changes(resolve("l2", "cpu")) == {}
    literal = config_changes(resolve("shared-0", "cpu"), against="cpu-paper")
    assert literal["model.xyz_scale"] == 0.03 and literal["loss.symmetric"] is True


def test_log_of_a_trained_smoke_run(group_store, tmp_path, monkeypatch):
    proj, _ = group_store
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    (exp,) = collect("shared", proj)
    assert exp.name == "shared-0/smoke/seed1" and exp.changes == "(none)"
    assert exp.command == "cloudpose run --variant shared-0 --preset smoke --seed 1 --group shared"
    assert exp.values["steps"] > 0 and "fit/rot_err_median_deg_batchstats" in exp.values
    df = experiment_table([exp])
    assert df.loc[0, "Adam steps"] == exp.values["steps"]
    path = write_log("shared", tmp_path / "log.md", "cloudpose experiments ...", proj)
    text = path.read_text()
    assert "| 1 | shared-0/smoke/seed1 | (none) |" in text
    assert (tmp_path / "log.csv").exists()


def test_log_of_several_groups_and_one_preset(group_store, tmp_path, monkeypatch):
    proj, _ = group_store
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    (exp,) = collect(["shared", "shared"], proj, preset="smoke")  # each run once
    assert exp.name == "shared-0/smoke/seed1"
    assert exp.command.endswith("--group shared")
    assert collect(["shared"], proj, preset="cpu") == []
    with pytest.raises(ValueError, match="no MLflow experiment for group 'nothing'"):
        collect(["shared", "nothing"], proj)
    with pytest.raises(ValueError, match="preset"):
        collect("shared", proj, preset="cpu' or '1")
    path = write_log(
        ["shared"], tmp_path / "log.md", "cloudpose experiments ...", proj, None, "smoke"
    )
    assert path.read_text().startswith("# Experiment log: shared (smoke)")
    assert "real + ICP < 10° mod sym (%)" in path.read_text()


def test_steps_of_an_online_epoch():
    cfg = resolve("shared-0", "cpu-online")
    assert steps_per_epoch(cfg, {"data.train_segments": "online"}) == 8192 // 32
    assert steps_per_epoch(resolve("shared-0", "cpu"), {"data.train_segments": "3546"}) == 110
