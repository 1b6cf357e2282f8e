"""End-to-end training on the smoke preset: tracking, determinism, resume after interruption."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cloudpose.config import resolve
from cloudpose.train import TrainingInterrupted, split_frames, train
from tests.conftest import make_project


def _project(tmp_path: Path, smoke_data: Path, monkeypatch) -> Path:
    return make_project(tmp_path / "proj", smoke_data, monkeypatch)


def _curve(run_id: str, proj: Path, key: str) -> list[float]:
    from cloudpose import tracking

    client = tracking.setup(proj)
    return [m.value for m in sorted(client.get_metric_history(run_id, key), key=lambda m: m.step)]


def test_split_frames_is_fixed_by_frame_ids():
    ids = np.array([f"0000/{i:06d}" for i in range(200) for _ in range(3)])
    held = split_frames(ids, 0.1)
    # whole frames are held out together
    for f in np.unique(ids):
        assert len(set(held[ids == f])) == 1
    assert 0.03 < held.mean() < 0.2
    np.testing.assert_array_equal(held, split_frames(ids[::-1], 0.1)[::-1])
    with pytest.raises(ValueError, match="val_fraction"):
        split_frames(ids, 1.5)


@pytest.mark.slow
def test_train_logs_to_mlflow_and_same_seed_same_numbers(tmp_path, smoke_data, monkeypatch):
    cfg = resolve("shared-0", "smoke", seed=3)
    a = train(cfg, project_dir=_project(tmp_path / "a", smoke_data, monkeypatch), progress=False)
    b = train(cfg, project_dir=_project(tmp_path / "b", smoke_data, monkeypatch), progress=False)
    assert a.metrics and a.metrics == b.metrics
    proj = tmp_path / "a" / "proj"
    losses = _curve(a.run_id, proj, "train/loss")
    assert len(losses) == cfg.train.epochs and all(np.isfinite(losses))

    from cloudpose import tracking

    run = tracking.setup(proj).get_run(a.run_id)
    assert run.info.run_name == "shared-0/smoke/seed3"
    assert run.info.status == "FINISHED"
    assert run.data.tags["variant"] == "shared-0" and run.data.tags["seed"] == "3"
    assert run.data.params["train.epochs"] == str(cfg.train.epochs)
    assert int(run.data.params["model.parameters"]) > 1_000_000
    exp = tracking.setup(proj).get_experiment(run.info.experiment_id)
    assert exp.name == "cloudpose-shared"
    assert run.data.tags["config"] == cfg.fingerprint()
    assert tracking.run_has_config(run, cfg)
    # a finished run is returned as it is, not trained again
    again = train(cfg, project_dir=proj, progress=False)
    assert again.run_id == a.run_id and again.metrics == a.metrics
    # another config under the same name (an override, an edited preset) is a new run and folder
    cfg1 = resolve("shared-0", "smoke", seed=3, overrides={"train": {"epochs": 1}})
    other = train(cfg1, project_dir=proj, progress=False)
    assert other.run_id != a.run_id and other.run_dir != a.run_dir
    assert other.run_dir.name.endswith(cfg1.fingerprint()[:8])
    assert len(_curve(other.run_id, proj, "train/loss")) == 1
    assert not tracking.run_has_config(tracking.setup(proj).get_run(other.run_id), cfg)


@pytest.mark.slow
def test_resume_after_interruption_matches_uninterrupted(tmp_path, smoke_data, monkeypatch):
    cfg = resolve("shared-1", "smoke", seed=2)
    ref = train(
        cfg, project_dir=_project(tmp_path / "ref", smoke_data, monkeypatch), progress=False
    )
    proj = _project(tmp_path / "cut", smoke_data, monkeypatch)
    with pytest.raises(TrainingInterrupted):
        train(cfg, project_dir=proj, progress=False, max_steps=3)  # mid-epoch
    resumed = train(cfg, project_dir=proj, progress=False)
    assert resumed.metrics == ref.metrics
    assert _curve(resumed.run_id, proj, "train/loss") == _curve(
        ref.run_id, tmp_path / "ref" / "proj", "train/loss"
    )


@pytest.mark.slow
def test_resume_after_kill_9(tmp_path, smoke_data, monkeypatch):
    cfg = resolve("shared-0", "smoke", seed=5)
    ref = train(
        cfg, project_dir=_project(tmp_path / "ref", smoke_data, monkeypatch), progress=False
    )
    proj = _project(tmp_path / "kill", smoke_data, monkeypatch)
    code = (
        "from pathlib import Path; from cloudpose.config import resolve; "
        "from cloudpose.train import train; "
        f"train(resolve('shared-0', 'smoke', seed=5), project_dir=Path({str(proj)!r}), "
        "progress=False, checkpoint_every_s=0.0)"
    )
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    proc = subprocess.Popen([sys.executable, "-c", code], env=env)
    deadline = time.monotonic() + 120
    last = None
    while time.monotonic() < deadline and proc.poll() is None:
        found = list((proj / "runs").glob("shared-0/smoke/seed5-*/last.pt"))
        if found:
            last = found[0]
            break
        time.sleep(0.05)
    assert last is not None, "training wrote no checkpoint before it ended"
    proc.send_signal(signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL, "training ended before it could be killed"
    resumed = train(cfg, project_dir=proj, progress=False)
    assert resumed.metrics == ref.metrics
    info = json.loads((last.parent / "run.json").read_text())
    assert info["finished"] and info["run_id"] == resumed.run_id
