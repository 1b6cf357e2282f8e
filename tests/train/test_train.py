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
import torch

from cloudpose.registry import resolve
from cloudpose.suite.pipeline import train_run
from cloudpose.train.loop import TrainingInterrupted, split_frames
from tests.conftest import make_project


def _first_checkpoint(proc, proj: Path, seed: int, timeout_s: float = 120.0) -> Path:
    """The first ``last.pt`` a training subprocess of shared-0/smoke writes (polled)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        found = list((proj / "runs").glob(f"shared-0/smoke/seed{seed}-*/last.pt"))
        if found:
            return found[0]
        time.sleep(0.05)
    raise AssertionError("training wrote no checkpoint before it ended")


def _project(tmp_path: Path, smoke_data: Path, monkeypatch) -> Path:
    return make_project(tmp_path / "proj", smoke_data, monkeypatch)


def _curve(run_id: str, proj: Path, key: str) -> list[float]:
    from cloudpose.store import tracking

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
    a = train_run(
        cfg, project_dir=_project(tmp_path / "a", smoke_data, monkeypatch), progress=False
    )
    b = train_run(
        cfg, project_dir=_project(tmp_path / "b", smoke_data, monkeypatch), progress=False
    )
    assert a.metrics and a.metrics == b.metrics
    proj = tmp_path / "a" / "proj"
    losses = _curve(a.run_id, proj, "train/loss")
    assert len(losses) == cfg.train.epochs and all(np.isfinite(losses))

    from cloudpose.store import runs, tracking

    run = tracking.setup(proj).get_run(a.run_id)
    assert run.info.run_name == "shared-0/smoke/seed3"
    assert run.info.status == "FINISHED"
    assert run.data.tags["variant"] == "shared-0" and run.data.tags["seed"] == "3"
    assert run.data.params["train.epochs"] == str(cfg.train.epochs)
    assert int(run.data.params["model.parameters"]) > 1_000_000
    exp = tracking.setup(proj).get_experiment(run.info.experiment_id)
    assert exp.name == "cloudpose-shared"
    assert run.data.tags["config"] == cfg.fingerprint()
    assert runs.run_has_config(run, cfg)
    # a finished run is returned as it is, not trained again
    again = train_run(cfg, project_dir=proj, progress=False)
    assert again.run_id == a.run_id and again.metrics == a.metrics
    # another config under the same name (an override, an edited preset) is a new run and folder
    cfg1 = resolve("shared-0", "smoke", seed=3, overrides={"train": {"epochs": 1}})
    other = train_run(cfg1, project_dir=proj, progress=False)
    assert other.run_id != a.run_id and other.run_dir != a.run_dir
    assert other.run_dir.name.endswith(cfg1.fingerprint()[:8])
    assert len(_curve(other.run_id, proj, "train/loss")) == 1
    assert not runs.run_has_config(tracking.setup(proj).get_run(other.run_id), cfg)


def _cut_and_resumed(cfg, max_steps: int, tmp_path: Path, smoke_data: Path, monkeypatch):
    """(uninterrupted run, the same run stopped after ``max_steps`` steps and resumed, the
    resumed run's project), each in a project of its own."""
    ref = train_run(
        cfg, project_dir=_project(tmp_path / "ref", smoke_data, monkeypatch), progress=False
    )
    proj = _project(tmp_path / "cut", smoke_data, monkeypatch)
    with pytest.raises(TrainingInterrupted):
        train_run(cfg, project_dir=proj, progress=False, max_steps=max_steps)
    return ref, train_run(cfg, project_dir=proj, progress=False), proj


@pytest.mark.slow
def test_resume_after_interruption_matches_uninterrupted(tmp_path, smoke_data, monkeypatch):
    cfg = resolve("shared-1", "smoke", seed=2)
    ref, resumed, proj = _cut_and_resumed(cfg, 3, tmp_path, smoke_data, monkeypatch)  # mid-epoch
    assert resumed.metrics == ref.metrics
    assert _curve(resumed.run_id, proj, "train/loss") == _curve(
        ref.run_id, tmp_path / "ref" / "proj", "train/loss"
    )


@pytest.mark.slow
def test_purpose_streams_resume_to_the_same_numbers(tmp_path, smoke_data, monkeypatch):
    """``train.seed_streams = "purpose"`` with both augmentations: a run cut mid-epoch and
    resumed ends as an uninterrupted one, whose numbers differ from the seed arithmetic's."""
    aug = {"augment_roll_deg": 30.0, "augment_depth_noise_mm": 2.0}
    cfg = resolve("shared-0", "smoke", 2, {"train": {**aug, "seed_streams": "purpose"}})
    ref, resumed, _ = _cut_and_resumed(cfg, 1, tmp_path, smoke_data, monkeypatch)
    assert resumed.metrics == ref.metrics
    arithmetic = resolve("shared-0", "smoke", 2, {"train": aug})
    other = train_run(
        arithmetic,
        project_dir=_project(tmp_path / "arith", smoke_data, monkeypatch),
        progress=False,
    )
    assert other.metrics["train/loss"] != ref.metrics["train/loss"]


@pytest.mark.slow
def test_resume_after_kill_9(tmp_path, smoke_data, monkeypatch):
    cfg = resolve("shared-0", "smoke", seed=5)
    ref = train_run(
        cfg, project_dir=_project(tmp_path / "ref", smoke_data, monkeypatch), progress=False
    )
    proj = _project(tmp_path / "kill", smoke_data, monkeypatch)
    code = (
        "from pathlib import Path; from cloudpose.registry import resolve; "
        "from cloudpose.suite.pipeline import train_run; "
        f"train_run(resolve('shared-0', 'smoke', seed=5), project_dir=Path({str(proj)!r}), "
        "progress=False, checkpoint_every_s=0.0)"
    )
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    proc = subprocess.Popen([sys.executable, "-c", code], env=env)
    last = _first_checkpoint(proc, proj, seed=5)
    proc.send_signal(signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL, "training ended before it could be killed"
    resumed = train_run(cfg, project_dir=proj, progress=False)
    assert resumed.metrics == ref.metrics
    info = json.loads((last.parent / "run.json").read_text())
    assert info["finished"] and info["run_id"] == resumed.run_id


def test_class_balanced_sampler_draws_classes_uniformly():
    from cloudpose.data.batches import Batchable
    from cloudpose.train.loop import epoch_order
    from cloudpose.train.seeds import generator

    cls_id = torch.tensor([1] * 900 + [2] * 90 + [3] * 10)
    fit = Batchable(
        torch.zeros(1000, 4, 3), cls_id, torch.eye(3).expand(1000, 3, 3), torch.zeros(1000, 3)
    )

    def order(sampler: str, epoch: int, n: int) -> torch.Tensor:
        return epoch_order(fit, sampler, n, generator(1, "order", epoch))

    idx = order("class_balanced", 0, 3000)
    counts = torch.bincount(cls_id[idx])[1:].float() / 3000
    assert torch.allclose(counts, torch.full((3,), 1 / 3), atol=0.04)
    assert torch.equal(idx, order("class_balanced", 0, 3000))
    assert not torch.equal(idx, order("class_balanced", 1, 3000))
    perm = order("shuffle", 0, 1000)
    assert sorted(perm.tolist()) == list(range(1000))


def test_cosine_schedule_ends_at_zero():
    from cloudpose.train.loop import lr_at

    cfg = resolve("shared-0", "smoke", overrides={"train": {"lr_schedule": "cosine", "lr": 1e-3}})
    assert lr_at(cfg, 0, 100) == pytest.approx(1e-3)
    assert lr_at(cfg, 50, 100) == pytest.approx(5e-4)
    assert lr_at(cfg, 100, 100) == pytest.approx(0.0, abs=1e-12)
    assert lr_at(resolve("shared-0", "smoke"), 70, 100) == resolve("shared-0", "smoke").train.lr


def test_roll_keeps_segments_on_their_posed_models():
    from cloudpose.train.augment import roll_about_optical_axis

    g = torch.Generator().manual_seed(0)
    model = torch.randn(50, 3, dtype=torch.float64) * 0.05
    R = torch.linalg.qr(torch.randn(4, 3, 3, dtype=torch.float64))[0]
    R = R * torch.det(R)[:, None, None]
    t = torch.tensor([[0.1, -0.05, 0.9]], dtype=torch.float64).expand(4, 3)
    pts = model @ R.mT + t[:, None]  # (4, 50, 3) the model at its pose
    p2, R2, t2 = roll_about_optical_axis(pts, R, t, 180.0, g)
    torch.testing.assert_close(p2, model @ R2.mT + t2[:, None])
    torch.testing.assert_close(p2[..., 2], pts[..., 2])  # depth unchanged: a roll about z
    assert not torch.allclose(p2, pts)


@pytest.mark.slow
def test_run_continues_from_its_logged_checkpoint_on_a_machine_without_its_folder(
    tmp_path, smoke_data, monkeypatch
):
    """With checkpoints logged to MLflow (as against a tracking server), a run whose folder is
    gone (another machine) continues from the logged checkpoint into the same MLflow run and
    ends as an uninterrupted run; the finished run keeps model.pt, not the checkpoint."""
    import shutil

    from cloudpose.store import runs, tracking

    cfg = resolve("shared-0", "smoke", seed=4)
    ref = train_run(
        cfg, project_dir=_project(tmp_path / "ref", smoke_data, monkeypatch), progress=False
    )
    proj = _project(tmp_path / "cut", smoke_data, monkeypatch)
    with pytest.raises(TrainingInterrupted) as cut:
        train_run(cfg, project_dir=proj, progress=False, max_steps=4, checkpoint_artifacts=True)
    run_id = runs.read_info(cut.value.args[0])["run_id"]
    shutil.rmtree(proj / "runs")  # the next attempt runs where the folder is not
    resumed = train_run(cfg, project_dir=proj, progress=False, checkpoint_artifacts=True)
    assert resumed.run_id == run_id and resumed.metrics == ref.metrics
    assert len(_curve(run_id, proj, "train/loss")) == cfg.train.epochs
    client = tracking.setup(proj)
    assert {f.path for f in client.list_artifacts(run_id)} >= {"model.pt"}
    assert not client.list_artifacts(run_id, "checkpoint")
    # a finished run is rebuilt from its model.pt, not trained again
    shutil.rmtree(proj / "runs")
    again = train_run(cfg, project_dir=proj, progress=False, checkpoint_artifacts=True)
    assert again.run_id == run_id and again.metrics == ref.metrics
    assert (again.run_dir / "model.pt").exists()


def test_depth_noise_moves_points_along_their_rays_at_a_level_drawn_per_segment():
    from cloudpose.train.augment import jitter_along_rays

    rng = torch.Generator().manual_seed(0)
    pts = torch.randn(64, 200, 3, generator=rng) * 0.03 + torch.tensor([0.1, -0.05, 0.9])
    out = jitter_along_rays(pts, 0.003, torch.Generator().manual_seed(5))
    again = jitter_along_rays(pts, 0.003, torch.Generator().manual_seed(5))
    assert torch.equal(out, again)
    d = out - pts
    ray = pts / pts.norm(dim=-1, keepdim=True)
    along = (d * ray).sum(-1)  # (64, 200)
    # only along each ray: no component across it
    torch.testing.assert_close(d, along[..., None] * ray, atol=1e-6, rtol=0)
    # one level per segment, spread over [0, 3 mm]: some segments barely moved, none beyond
    level = along.std(dim=1)
    assert level.max() < 0.0035 and level.min() < 0.0005 and level.max() > 0.0025


def test_a_pair_of_forms_augments_its_first_form_as_a_batch_of_one_form():
    """:func:`augment_forms` (``data.online_bleed_branch = "translation-paired"``): the first
    form and the poses exactly as :func:`augment` gives them for that form alone; the second
    form turned by the same angles and moved by depth noise of its own."""
    from cloudpose.train.augment import augment, augment_forms

    cfg = resolve("shared-0", "cpu-online", seed=3)
    assert cfg.train.augment_roll_deg > 0 and cfg.train.augment_depth_noise_mm > 0
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(16, 64, 3, generator=g) * 0.03 + torch.tensor([0.1, -0.05, 0.9])
    other = pts + 0.002 * torch.randn(pts.shape, generator=g)
    R = torch.linalg.qr(torch.randn(16, 3, 3, generator=g))[0]
    t = torch.randn(16, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, 0.9])
    alone = augment(pts, R, t, cfg, 2, 5)
    first, second, R2, t2 = augment_forms(pts, other, R, t, cfg, 2, 5)
    for a, b in zip(alone, (first, R2, t2), strict=True):
        assert torch.equal(a, b)
    # the same roll: the second form's turn about the optical axis is the first's
    Q = R2 @ R.transpose(1, 2)
    rolled_only = torch.einsum("bij,bnj->bni", Q, other)
    d = second - rolled_only
    ray = rolled_only / rolled_only.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(d, (d * ray).sum(-1, keepdim=True) * ray, atol=1e-6, rtol=0)
    assert not torch.equal(second - rolled_only, first - torch.einsum("bij,bnj->bni", Q, pts))


@pytest.mark.slow
def test_a_translation_only_change_trains_the_plain_runs_rotation_branch(
    tmp_path, smoke_data, monkeypatch
):
    """shared-0 on line (version 3) with ``data.online_bleed_branch = "translation-paired"``,
    and ``centre-trimmed-translation`` (a robust centre for the translation residual only),
    each beside the same run of shared-0 without it: after a few steps the rotation networks
    are the same numbers (the rotation branch's segments, augmentation and updates are the
    plain run's), the translation networks are not. With "translation" the rotation branch is
    another draw."""
    online = {"train_source": "online", "online_version": 3, "synth_version": 2}
    aug = {"augment_roll_deg": 15.0, "augment_depth_noise_mm": 3.0}
    weights = {}
    for name, variant, extra in (
        ("plain", "shared-0", {}),
        ("paired", "shared-0", {"online_bleed": 1.0, "online_bleed_branch": "translation-paired"}),
        ("unpaired", "shared-0", {"online_bleed": 1.0, "online_bleed_branch": "translation"}),
        ("centre", "centre-trimmed-translation", {}),
    ):
        cfg = resolve(variant, "smoke", 1, overrides={"data": online | extra, "train": aug})
        proj = make_project(tmp_path / name, smoke_data, monkeypatch)
        with pytest.raises(TrainingInterrupted) as stop:
            train_run(cfg, project_dir=proj, progress=False, max_steps=4)
        weights[name] = torch.load(stop.value.args[0] / "last.pt", weights_only=True)["model"]
    plain, unpaired = weights["plain"], weights["unpaired"]
    rot = [k for k in plain if k.startswith("rotation_net.")]
    trans = [k for k in plain if k.startswith("translation_net.") and plain[k].is_floating_point()]
    assert rot and trans
    for name in ("paired", "centre"):
        assert weights[name].keys() == plain.keys(), name
        assert all(torch.equal(plain[k], weights[name][k]) for k in rot), name
        assert any(not torch.equal(plain[k], weights[name][k]) for k in trans), name
    assert any(not torch.equal(plain[k], unpaired[k]) for k in rot if plain[k].is_floating_point())


def _steps(run_id: str, proj: Path, key: str = "train/loss") -> list[int]:
    from cloudpose.store import tracking

    return sorted(m.step for m in tracking.setup(proj).get_metric_history(run_id, key))


@pytest.mark.slow
def test_a_torn_checkpoint_falls_back_to_the_previous_one(
    tmp_path, smoke_data, smoke_run, monkeypatch
):
    """A truncated last.pt: the run resumes from last.prev.pt with a warning naming the torn
    file, and ends as an uninterrupted run, each epoch logged once."""
    _, ref = smoke_run
    cfg = resolve("shared-0", "smoke", seed=1)
    proj = _project(tmp_path, smoke_data, monkeypatch)
    with pytest.raises(TrainingInterrupted) as cut:
        train_run(cfg, project_dir=proj, progress=False, max_steps=2)
    with pytest.raises(TrainingInterrupted):
        train_run(cfg, project_dir=proj, progress=False, max_steps=2)
    last = cut.value.args[0] / "last.pt"
    last.write_bytes(last.read_bytes()[:1000])
    with pytest.warns(UserWarning, match=r"last\.pt is not a readable checkpoint.*last\.prev\.pt"):
        resumed = train_run(cfg, project_dir=proj, progress=False)
    assert resumed.metrics == ref.metrics
    assert _steps(resumed.run_id, proj) == list(range(1, cfg.train.epochs + 1))
    assert not (last.parent / "last.prev.pt").exists()  # a finished run keeps last.pt only


def test_an_empty_checkpoint_without_a_previous_one_is_one_line(tmp_path, smoke_data, monkeypatch):
    from cloudpose.data.dataset import prepare_data
    from cloudpose.store import runs
    from tests.conftest import cli, one_line_error

    cfg = resolve("shared-0", "smoke", seed=1)
    proj = _project(tmp_path, smoke_data, monkeypatch)
    monkeypatch.chdir(proj)
    rdir = runs.run_dir(cfg, prepare_data(cfg.data, proj, progress=False).data_key, proj)
    rdir.mkdir(parents=True)
    (rdir / "last.pt").write_bytes(b"")
    res = cli("train", "--preset", "smoke", "--seed", "1", "--no-progress")
    line = one_line_error(res, str(rdir / "last.pt"), "empty")
    assert "rm " in line or "delete" in line


@pytest.mark.slow
def test_a_full_disk_is_one_line_and_the_resumed_run_logs_each_epoch_once(
    tmp_path, smoke_data, smoke_run, monkeypatch
):
    """No space for the checkpoint after epoch 2 was logged: one line naming last.pt and the
    space it needs, the run FAILED; after space is freed the rerun resumes and logs epoch 2 once."""
    import errno

    from cloudpose.store import runs, tracking
    from cloudpose.train import loop as train_module
    from tests.conftest import cli, one_line_error

    _, ref = smoke_run
    cfg = resolve("shared-0", "smoke", seed=1)
    proj = _project(tmp_path, smoke_data, monkeypatch)
    monkeypatch.chdir(proj)
    write, calls = train_module.atomic_write, []

    def full_disk(path, *args, **kwargs):
        if Path(path).name == "last.pt":
            calls.append(Path(path))
            if len(calls) == cfg.train.epochs:
                raise OSError(errno.ENOSPC, "No space left on device")
        return write(path, *args, **kwargs)

    monkeypatch.setattr(train_module, "atomic_write", full_disk)
    res = cli("train", "--preset", "smoke", "--seed", "1", "--no-progress")
    line = one_line_error(res, str(calls[0]), "no space left", "MB")
    assert "needs" in line
    run_id = runs.read_info(calls[0].parent)["run_id"]
    assert tracking.setup(proj).get_run(run_id).info.status == "FAILED"
    monkeypatch.setattr(train_module, "atomic_write", write)
    resumed = train_run(cfg, project_dir=proj, progress=False)
    assert resumed.run_id == run_id and resumed.metrics == ref.metrics
    assert _steps(run_id, proj) == list(range(1, cfg.train.epochs + 1))


@pytest.mark.slow
def test_sigterm_stops_training_as_ctrl_c_does(tmp_path, smoke_data, smoke_run, monkeypatch):
    """SIGTERM: the MLflow run is marked KILLED (not left RUNNING), and the rerun resumes it."""
    from cloudpose.store import runs, tracking

    _, ref = smoke_run
    cfg = resolve("shared-0", "smoke", seed=1)
    proj = _project(tmp_path, smoke_data, monkeypatch)
    code = (
        "from pathlib import Path; from cloudpose.registry import resolve; "
        "from cloudpose.suite.pipeline import train_run; "
        f"train_run(resolve('shared-0', 'smoke', seed=1), project_dir=Path({str(proj)!r}), "
        "progress=False, checkpoint_every_s=0.0)"
    )
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    proc = subprocess.Popen([sys.executable, "-c", code], env=env, stderr=subprocess.PIPE)
    last = _first_checkpoint(proc, proj, seed=1)
    proc.send_signal(signal.SIGTERM)
    rc = proc.wait()
    assert rc != -signal.SIGTERM, "training was killed by SIGTERM, not stopped"
    assert rc != 0, "training ended before it could be stopped"
    run_id = runs.read_info(last.parent)["run_id"]
    assert tracking.setup(proj).get_run(run_id).info.status == "KILLED"
    resumed = train_run(cfg, project_dir=proj, progress=False)
    assert resumed.run_id == run_id and resumed.metrics == ref.metrics
    assert _steps(run_id, proj) == list(range(1, cfg.train.epochs + 1))


def test_a_finished_runs_torn_model_is_rewritten_from_its_last_checkpoint(
    smoke_run, tmp_path, monkeypatch
):
    """A torn model.pt of a finished run: the rerun rewrites it from last.pt (the model of the
    last epoch) with a warning naming it, and trains nothing; its metrics stay."""
    import shutil

    from cloudpose.infer import load_checkpoint
    from cloudpose.store import runs

    src, ref = smoke_run
    proj = tmp_path / "copy"
    shutil.copytree(src, proj, symlinks=True)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    model = proj / ref.run_dir.relative_to(src) / "model.pt"
    good = model.read_bytes()
    model.write_bytes(good[: len(good) // 2])
    cfg = resolve("shared-0", "smoke", seed=1)
    with pytest.warns(UserWarning, match=r"model\.pt is not a readable checkpoint.*last\.pt"):
        again = train_run(cfg, project_dir=proj, progress=False, max_steps=0)
    assert again.run_id == ref.run_id and again.metrics == ref.metrics
    rewritten = runs.read_checkpoint(model)
    for k, v in torch.load(ref.checkpoint, weights_only=True)["model"].items():
        assert torch.equal(rewritten["model"][k], v), k
    load_checkpoint(model)


@pytest.mark.slow
def test_a_run_stopped_after_its_last_checkpoint_ends_with_its_metrics(
    tmp_path, smoke_data, smoke_run, monkeypatch
):
    """Stopped between the last epoch's checkpoint and model.pt: the rerun trains nothing and
    ends with the metrics the run logged (they were lost: {})."""
    from cloudpose.train import loop as train_module

    _, ref = smoke_run
    cfg = resolve("shared-0", "smoke", seed=1)
    proj = _project(tmp_path, smoke_data, monkeypatch)
    write = train_module.atomic_write

    def stopped_at_model(path, *args, **kwargs):
        if Path(path).name == "model.pt":
            raise KeyboardInterrupt
        return write(path, *args, **kwargs)

    monkeypatch.setattr(train_module, "atomic_write", stopped_at_model)
    with pytest.raises(KeyboardInterrupt):
        train_run(cfg, project_dir=proj, progress=False)
    monkeypatch.setattr(train_module, "atomic_write", write)
    again = train_run(cfg, project_dir=proj, progress=False, max_steps=0)
    assert again.metrics == ref.metrics
    assert json.loads((again.run_dir / "run.json").read_text())["metrics"] == ref.metrics
