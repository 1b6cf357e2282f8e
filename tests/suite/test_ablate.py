"""The ablation runner's skip/resume logic, with training and evaluation replaced by fakes.

The fakes write into a throwaway MLflow store exactly what ``cloudpose.train.loop.train`` and
``cloudpose.evaluate.evaluate`` write that the runner looks at: a run tagged with variant,
preset, seed and data; FINISHED after training; test metrics after evaluation.
"""

from __future__ import annotations

import shutil
import types
from pathlib import Path

import pytest

from cloudpose.registry import resolve
from cloudpose.store import runs, tracking
from cloudpose.suite import ablate


class Fakes:
    """Fake train/evaluate/prepare_data recording their calls."""

    def __init__(self, root: Path):
        self.root = root
        self.trained: list[tuple[str, int]] = []
        self.evaluated: list[str] = []
        self.data_key = "data0000001234"
        self.fail_train: set[tuple[str, int]] = set()
        self.interrupt_eval: set[tuple[str, int]] = set()
        self.runs: dict[tuple[str, int, str, str], str] = {}  # resumable: same run, same settings
        self.config_tag = True  # False: runs as made before the ``config`` tag existed

    def prepare_data(self, data_cfg, project_dir=None, progress=True):
        return types.SimpleNamespace(data_key=self.data_key)

    def train(self, cfg, data=None, *, project_dir=None, group=None, progress=True, **_):
        key = (cfg.variant, cfg.seed)
        self.trained.append(key)
        if key in self.fail_train:
            raise FloatingPointError("loss became nan")
        client = tracking.setup(project_dir)
        rkey = (cfg.variant, cfg.seed, self.data_key, cfg.fingerprint())
        if rkey not in self.runs:
            exp = tracking.experiment_id(client, group, project_dir)
            tags = {
                "variant": cfg.variant,
                "group": group,
                "preset": cfg.preset,
                "seed": str(cfg.seed),
                "data": self.data_key,
                "git_commit": "c0ffee",
            }
            if self.config_tag:
                tags["config"] = cfg.fingerprint()
            run = client.create_run(
                exp, tags=tags, run_name=runs.run_name(cfg.variant, cfg.preset, cfg.seed)
            )
            for k, v in tracking.flat_params(cfg.flat()).items():
                client.log_param(run.info.run_id, k, v)
            self.runs[rkey] = run.info.run_id
        run_id = self.runs[rkey]
        client.log_metric(run_id, "time/epoch_s", 0.5, step=1)
        client.set_terminated(run_id, "FINISHED")
        rdir = project_dir / "runs" / cfg.variant / f"seed{cfg.seed}-{cfg.fingerprint()}"
        rdir.mkdir(parents=True, exist_ok=True)
        (rdir / "run_id").write_text(run_id)
        return types.SimpleNamespace(run_id=run_id, run_dir=rdir, metrics={})

    def evaluate(self, run, *, project_dir=None, progress=True, **_):
        run_id = (Path(run) / "run_id").read_text()
        client = tracking.setup(project_dir)
        r = client.get_run(run_id)
        key = (r.data.tags["variant"], int(r.data.tags["seed"]))
        self.evaluated.append(run_id)
        if key in self.interrupt_eval:
            self.interrupt_eval.discard(key)
            raise KeyboardInterrupt
        metrics = {"test/ads_auc": 0.5 + 0.01 * key[1], "test_icp/ads_auc": 0.6}
        for k, v in metrics.items():
            client.log_metric(run_id, k, v, step=0)
        return types.SimpleNamespace(metrics=metrics, run_id=run_id)


@pytest.fixture
def fakes(tmp_path, monkeypatch, empty_store):
    shutil.copy(empty_store, tmp_path / "mlflow.db")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.chdir(tmp_path)
    f = Fakes(tmp_path)
    import cloudpose.data.dataset
    import cloudpose.evaluate
    import cloudpose.train.loop

    monkeypatch.setattr(cloudpose.data.dataset, "prepare_data", f.prepare_data)
    monkeypatch.setattr(cloudpose.train.loop, "train", f.train)
    monkeypatch.setattr(cloudpose.evaluate, "evaluate", f.evaluate)
    monkeypatch.setattr(cloudpose.evaluate, "evaluate_real", lambda run, **kw: None)
    return f


def _run(tmp_path, seeds=2, **kw):
    lines = []
    res = ablate.run_group(
        "loss", "smoke", seeds, tmp_path, progress=False, report=False, echo=lines.append, **kw
    )
    return res, lines


def test_finished_runs_are_not_retrained(fakes, tmp_path):
    res, lines = _run(tmp_path)
    assert sorted(fakes.trained) == [("l2", 1), ("l2", 2), ("shared-0", 1), ("shared-0", 2)]
    assert [r.status for r in res.runs] == ["trained"] * 4
    assert "4 runs" in lines[0] and "4 to run" in lines[0]
    fakes.trained.clear()
    res, lines = _run(tmp_path)
    assert fakes.trained == []
    assert [r.status for r in res.runs] == ["skipped"] * 4
    log = (tmp_path / "runs" / "ablate-loss-smoke.log").read_text().splitlines()
    assert len(log) == 8
    assert all("\tskipped\t" in line for line in log[4:])
    assert "l2/smoke/seed2" in log[3] and "test_ads_auc=52.0" in log[3]


def test_a_missing_seed_is_trained(fakes, tmp_path):
    _run(tmp_path, seeds=1)
    fakes.trained.clear()
    res, _ = _run(tmp_path, seeds=[1, 2])
    assert sorted(fakes.trained) == [("l2", 2), ("shared-0", 2)]
    assert sorted((r.variant, r.seed, r.status) for r in res.runs) == [
        ("l2", 1, "skipped"),
        ("l2", 2, "trained"),
        ("shared-0", 1, "skipped"),
        ("shared-0", 2, "trained"),
    ]


def test_interrupted_suite_resumes_where_it_stopped(fakes, tmp_path):
    fakes.interrupt_eval.add(("l2", 1))  # Ctrl-C during the evaluation of the third run
    with pytest.raises(KeyboardInterrupt):
        _run(tmp_path)
    assert fakes.trained == [("shared-0", 1), ("shared-0", 2), ("l2", 1)]
    fakes.trained.clear()
    res, _ = _run(tmp_path)
    # the interrupted run is trained (= resumed: the same MLflow run) and evaluated again
    assert fakes.trained == [("l2", 1), ("l2", 2)]
    assert [r.status for r in res.runs] == ["skipped", "skipped", "trained", "trained"]
    l2_1 = next(r for r in res.runs if (r.variant, r.seed) == ("l2", 1))
    assert l2_1.run_id == next(
        v for k, v in fakes.runs.items() if k[:3] == ("l2", 1, fakes.data_key)
    )
    log = (tmp_path / "runs" / "ablate-loss-smoke.log").read_text()
    assert "\tinterrupted\t" in log


def test_other_data_stops_before_training_then_trains_when_asked(fakes, tmp_path):
    # the same configs finished on data of another key: a new CPU's render, or changed data;
    # hours of retraining are not started on a guess
    res, _ = _run(tmp_path, seeds=1)
    first = res.runs[0].run_id
    fakes.trained.clear()
    fakes.data_key = "otherdata9999"
    with pytest.raises(ablate.OtherDataError) as err:
        _run(tmp_path, seeds=1)
    text = str(err.value)
    assert fakes.trained == []
    assert "2 of the 2 runs" in text and "otherdata9999" in text
    assert f"cloudpose same-data --run {first}" in text and "--fresh" in text
    _run(tmp_path, seeds=1, other_data=True)
    assert sorted(fakes.trained) == [("l2", 1), ("shared-0", 1)]


def test_another_config_is_trained_again(fakes, tmp_path):
    # a quick run with overrides is not taken for the preset's run, nor the other way round
    _run(tmp_path, seeds=1, overrides={"train": {"epochs": 1}})
    fakes.trained.clear()
    res, _ = _run(tmp_path, seeds=1)
    assert sorted(fakes.trained) == [("l2", 1), ("shared-0", 1)]
    assert [r.status for r in res.runs] == ["trained"] * 2
    fakes.trained.clear()
    _run(tmp_path, seeds=1)
    _run(tmp_path, seeds=1, overrides={"train": {"epochs": 1}})
    assert fakes.trained == []


def test_runs_without_config_tag_are_matched_on_params(fakes, tmp_path):
    # runs logged before the ``config`` tag existed: the logged params decide
    fakes.config_tag = False
    _run(tmp_path, seeds=1)
    fakes.trained.clear()
    _run(tmp_path, seeds=1)
    assert fakes.trained == []
    _run(tmp_path, seeds=1, overrides={"train": {"lr": 1e-3}})
    assert sorted(fakes.trained) == [("l2", 1), ("shared-0", 1)]


def test_failure_stops_or_keeps_going(fakes, tmp_path):
    fakes.fail_train.add(("shared-0", 2))
    with pytest.raises(FloatingPointError):
        _run(tmp_path)
    assert fakes.trained == [("shared-0", 1), ("shared-0", 2)]
    fakes.trained.clear()
    res, lines = _run(tmp_path, keep_going=True)
    assert fakes.trained == [("shared-0", 2), ("l2", 1), ("l2", 2)]
    assert [r.status for r in res.runs] == ["skipped", "failed", "trained", "trained"]
    assert any("FAILED" in line for line in lines)
    assert (
        "error=FloatingPointError: loss became nan"
        in (tmp_path / "runs" / "ablate-loss-smoke.log").read_text()
    )


def test_eta_from_earlier_runs(fakes, tmp_path):
    _run(tmp_path, seeds=1)
    fakes.trained.clear()
    _, lines = _run(tmp_path, seeds=[1, 2])
    # before any run of this call finished, the estimate comes from time/epoch_s of earlier runs
    first = next(line for line in lines if "training + evaluation" in line)
    assert "2 run(s) left" in first and "unknown" not in first


@pytest.mark.parametrize("resume_first", [False, True])
def test_a_resumed_run_does_not_set_the_estimate(fakes, tmp_path, monkeypatch, resume_first):
    """A run resumed from its checkpoint takes a fraction of a run: the time left is estimated
    from whole runs only (each fake run takes 100 s of a fake clock here)."""
    import time as real_time

    ticks = iter(range(0, 10_000, 100))
    clock = types.SimpleNamespace(monotonic=lambda: next(ticks), strftime=real_time.strftime)
    monkeypatch.setattr(ablate, "time", clock)
    if resume_first:
        cfg = resolve("shared-0", "smoke", 1)
        last = runs.run_dir(cfg, fakes.data_key, tmp_path.resolve()) / "last.pt"
        last.parent.mkdir(parents=True)
        last.write_bytes(b"")
    lines = [line for line in _run(tmp_path)[1] if "training + evaluation" in line]
    assert "3 run(s) left" in lines[1]
    if resume_first:  # no earlier run in the store either: nothing to estimate from yet
        assert lines[1].endswith("estimated unknown to go")
    else:
        assert lines[1].endswith("estimated 5m00s to go")  # 100 s a run, from the first


def test_unknown_group_lists_valid_ones(tmp_path):
    with pytest.raises(ValueError, match="valid groups"):
        ablate.run_group("nope", "smoke", 1, tmp_path, report=False)


@pytest.mark.slow
def test_run_group_loss_smoke_for_real(tmp_path, monkeypatch):
    """The real thing on the smoke preset: synthesize, train, evaluate, report; rerun skips."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    lines = []
    res = ablate.run_group("loss", "smoke", 1, tmp_path, progress=False, echo=lines.append)
    assert [(r.variant, r.status) for r in res.runs] == [("shared-0", "trained"), ("l2", "trained")]
    out = tmp_path / "reports" / "smoke"
    for name in (
        "table1_overall.md",
        "table2_per_class.tex",
        "table4_rotation.csv",
        "claims.md",
        "occlusion.png",
        "curves_loss.png",
        "training_loss.png",
        "rot_err_loss.png",
        "README.md",
    ):
        assert (out / name).exists(), name
    assert "1 seed(s) of 3 needed" in (out / "claims.md").read_text()  # one seed
    res = ablate.run_group(
        "loss", "smoke", 1, tmp_path, progress=False, report=False, echo=lines.append
    )
    assert [r.status for r in res.runs] == ["skipped", "skipped"]


def _noisy_evaluate(fakes, gap: float, spread: float):
    """An evaluate that logs rot_lt_10deg: shared-0 ``gap`` above l2, seed noise ``spread``."""
    import numpy as np

    def evaluate(run, *, project_dir=None, progress=True, **_):
        run_id = (Path(run) / "run_id").read_text()
        client = tracking.setup(project_dir)
        r = client.get_run(run_id)
        variant, seed = r.data.tags["variant"], int(r.data.tags["seed"])
        rng = np.random.default_rng([seed, len(variant)])
        value = 0.5 + (gap if variant == "shared-0" else 0.0) + rng.normal(0, spread)
        metrics = {"test/ads_auc": 0.5, "test/rot_lt_10deg": float(value)}
        for k, v in metrics.items():
            client.log_metric(run_id, k, v, step=0)
        return types.SimpleNamespace(metrics=metrics, run_id=run_id)

    return evaluate


def test_resolve_claims_trains_no_seed_that_could_not_decide(fakes, tmp_path, monkeypatch):
    import cloudpose.evaluate

    monkeypatch.setattr(cloudpose.evaluate, "evaluate", _noisy_evaluate(fakes, 0.0, 0.05))
    _run(tmp_path, seeds=2)
    lines: list[str] = []
    rounds = ablate.resolve_claims(
        "loss", "smoke", tmp_path, max_seeds=5, step=2, echo=lines.append, progress=False
    )
    # no real difference, seed noise of 5 pp against a 2 pp margin: the third seed, then the
    # interval at 5 seeds would still hold 0 and reach past the margin, so no more
    assert [r.wanted for r in rounds] == [{"l2": 3, "shared-0": 3}, {}]
    assert sorted(set(fakes.trained)) == [(v, s) for v in ("l2", "shared-0") for s in range(1, 4)]
    assert "more seeds (cap 5) would decide no other claim" in lines[-1]


@pytest.mark.parametrize(
    ("gap", "noise", "seeds", "last"),
    [
        # geodesic (shared-0) 20 pp ahead of L2 with 0.5 pp noise: decided at the third seed
        (0.2, 0.005, 2, range(3, 4)),
        # 2 pp ahead with 1 pp seed noise: undecided at 3 seeds, decided by a later one
        (0.02, 0.01, 3, range(4, 11)),
    ],
)
def test_resolve_claims_adds_seeds_until_the_claim_is_decided(
    fakes, tmp_path, monkeypatch, gap, noise, seeds, last
):
    import cloudpose.evaluate

    monkeypatch.setattr(cloudpose.evaluate, "evaluate", _noisy_evaluate(fakes, gap, noise))
    _run(tmp_path, seeds=seeds)
    rounds = ablate.resolve_claims(
        "loss", "smoke", tmp_path, max_seeds=10, step=1, echo=lambda s: None, progress=False
    )
    assert rounds[-1].wanted == {} and rounds[-1].unresolved < rounds[0].unresolved
    assert max(s for _, s in fakes.trained) in last
