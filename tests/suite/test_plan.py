"""What the long commands say before they start: plans, dry runs, help, and where reports go.

Everything here runs against a throwaway MLflow store in ``tmp_path``; nothing trains.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import warnings
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cloudpose.cli import app
from cloudpose.registry import get_group, groups, groups_of, resolve
from cloudpose.store import tracking
from cloudpose.suite import ablate
from cloudpose.suite import plan as plans

VARIANTS_DOC = Path(__file__).resolve().parents[2] / "docs" / "variants.md"


@pytest.fixture
def project(tmp_path, monkeypatch, empty_store) -> Path:
    shutil.copy(empty_store, tmp_path / "mlflow.db")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _finished_run(project: Path, variant: str, preset: str, seed: int) -> str:
    """A finished, evaluated run of the config in the store, as the runner leaves one."""
    cfg = resolve(variant, preset, seed)
    client = tracking.setup(project)
    exp = tracking.experiment_id(client, "shared", project)
    tags = {
        "variant": variant,
        "preset": preset,
        "seed": str(seed),
        "data": "somedata",
        "config": cfg.fingerprint(),
    }
    run = client.create_run(exp, tags=tags, run_name=f"{variant}/{preset}/seed{seed}")
    client.log_metric(run.info.run_id, "test/ads_auc", 0.5)
    client.set_terminated(run.info.run_id, "FINISHED")
    return run.info.run_id


def test_plan_counts_frames_runs_and_time(project):
    plan = plans.plan_group("shared", "cpu", 3, project)
    n = len(get_group("shared").members) * 3
    assert len(plan.runs) == n and len(plan.to_train) == n
    assert plan.frames == {"data/synth-seed0": (950, 950)}  # 800 train + 150 test frames
    assert "from the preset" in plan.per_run_source
    assert 5 * 60 < plan.per_run_s < 20 * 60  # the cpu preset: ~10 min a run on 2 cores
    text = plan.text()
    assert "render 950 of 950 frames" in text
    assert f"{n} run(s) x ~" in text and "total: ~" in text
    assert "shared-all-2x" in text and "reports/cpu/" in text


def test_plan_time_comes_from_the_store_when_it_has_runs(project):
    _finished_run(project, "shared-0", "smoke", 1)
    plan = plans.plan_runs(["shared-0"], "smoke", [1, 2], title="t", project_dir=project)
    assert "median wall time of 1 finished smoke run" in plan.per_run_source
    # the data is not rendered: the run of the same config counts as finished (the runner
    # then skips it, or stops when its data turns out to be other data), the other to train
    assert [r.status for r in plan.runs] == ["finished", "to train"]
    assert plan.matched_elsewhere == 1 and "not rendered yet" in plan.text()


def test_plan_time_leaves_out_a_run_trained_partly_elsewhere(project):
    run_id = _finished_run(project, "shared-0", "smoke", 1)
    tracking.setup(project).log_param(run_id, "train.machine_steps", 3)
    plan = plans.plan_runs(["shared-0"], "smoke", [2], title="t", project_dir=project)
    assert "from the preset" in plan.per_run_source


def test_plan_time_comes_from_runs_on_this_device(project, monkeypatch):
    """A gpu-preset run that trained on CUDA (or began there) says nothing of a run on a CPU,
    and the other way round; a run without a device param counts."""
    client = tracking.setup(project)
    for seed, device in ((1, "cuda"), (2, "cuda, then cpu")):
        client.log_param(_finished_run(project, "shared-0", "smoke", seed), "device", device)
    monkeypatch.setattr(plans, "training_device", lambda cfg: "cpu")
    plan = plans.plan_runs(["shared-0"], "smoke", [3], title="t", project_dir=project)
    assert "from the preset" in plan.per_run_source
    monkeypatch.setattr(plans, "training_device", lambda cfg: "cuda")
    plan = plans.plan_runs(["shared-0"], "smoke", [3], title="t", project_dir=project)
    assert "median wall time of 1 finished smoke run(s) on cuda" in plan.per_run_source
    _finished_run(project, "shared-0", "smoke", 4)
    plan = plans.plan_runs(["shared-0"], "smoke", [3], title="t", project_dir=project)
    assert "median wall time of 2 finished smoke run(s) on cuda" in plan.per_run_source


def test_estimate_grows_with_the_preset():
    smoke, _ = plans.estimate_run_s(resolve("shared-0", "smoke"))
    cpu, _ = plans.estimate_run_s(resolve("shared-0", "cpu"))
    paper, _ = plans.estimate_run_s(resolve("shared-0", "paper"))
    assert smoke < 90 and smoke < cpu < paper


def test_ablate_dry_run_prints_the_plan_and_trains_nothing(project, monkeypatch):
    def no_training(*args, **kwargs):
        raise AssertionError("a dry run trained")

    monkeypatch.setattr(ablate, "run_group", no_training)
    res = CliRunner().invoke(
        app, ["ablate", "--group", "loss", "--preset", "smoke", "--seeds", "2", "--dry-run"]
    )
    assert res.exit_code == 0, res.output
    store, plan = res.output.split("\n", 1)
    assert store.startswith("store: sqlite:///") and store.endswith("(MLFLOW_TRACKING_URI)")
    assert plan.startswith("plan: ablation loss/smoke, seeds 1-2")
    assert "4 to train + evaluate" in res.output and "render 16 of 16 frames" in res.output
    assert not (project / "data").exists()


def test_ablate_only_plans_the_named_members_and_refuses_a_stranger(project, monkeypatch):
    def no_training(*args, **kwargs):
        raise AssertionError("a dry run trained")

    monkeypatch.setattr(ablate, "run_group", no_training)
    args = ["ablate", "--group", "shared", "--preset", "smoke", "--seeds", "3", "--dry-run"]
    res = CliRunner().invoke(app, [*args, "--only", "shared-all", "--only", "shared-0"])
    assert res.exit_code == 0, res.output
    assert "6 to train + evaluate" in res.output
    assert "shared-all" in res.output and "shared-3" not in res.output
    res = CliRunner().invoke(app, [*args, "--only", "quaternion"])
    assert res.exit_code != 0
    assert "no member 'quaternion'" in res.output and "shared-all-2x" in res.output


def test_group_pick_keeps_the_groups_order():
    g = get_group("rotation")
    assert g.pick(None) == g.pick([]) == g.members
    assert g.pick(["quaternion", "shared-0"]) == ("shared-0", "quaternion")
    with pytest.raises(ValueError, match="no member 'l2'"):
        g.pick(["l2"])


def test_masks_and_main_job_dry_runs(project):
    res = CliRunner().invoke(
        app, ["ablate-masks", "--preset", "smoke", "--seeds", "1", "--dry-run"]
    )
    assert res.exit_code == 0, res.output
    assert "plan: mask ablation smoke" in res.output
    assert "degraded-strong masks" in res.output and "table_masks" in res.output
    res = CliRunner().invoke(app, ["run", "--preset", "smoke", "--dry-run"])
    assert res.exit_code == 0, res.output
    assert "plan: main job shared-0/smoke/seed1" in res.output and "1 to train" in res.output
    assert not (project / "data").exists()


def test_occlusion_report_never_trains_without_asking(project, monkeypatch):
    def no_training(*args, **kwargs):
        raise AssertionError("occlusion-report trained")

    monkeypatch.setattr(ablate, "ensure_runs", no_training)
    res = CliRunner().invoke(app, ["occlusion-report", "--preset", "smoke", "--seeds", "2"])
    assert res.exit_code == 1
    assert "shared-0/smoke/seed1, shared-0/smoke/seed2" in res.output
    assert "--train-missing" in res.output and "make occlusion-runs" in res.output
    assert not (project / "data").exists()
    _finished_run(project, "shared-0", "smoke", 1)
    assert plans.missing_report_runs(["shared-0"], "smoke", 2, project) == ["shared-0/smoke/seed2"]
    with pytest.raises(ablate.MissingRuns, match="seed2"):
        ablate.occlusion_report("smoke", 2, project)
    res = CliRunner().invoke(
        app,
        ["occlusion-report", "--preset", "smoke", "--seeds", "2", "--train-missing", "--dry-run"],
    )
    assert res.exit_code == 0, res.output
    assert "plan: occlusion report smoke" in res.output


def test_summary_explains_the_symmetry_column(capsys):
    from cloudpose.cli import _print_summary

    _print_summary({"test/ads_auc": 0.5, "test/rot_sym_lt_10deg": 0.2})
    out = capsys.readouterr().out
    assert "rot<10deg*" in out
    assert "* rot<10deg*: rotation error < 10 deg modulo the object's symmetries" in out


def test_next_step_says_how_many_runs(capsys):
    from cloudpose.cli import _next_steps

    _next_steps("smoke")
    n = len(get_group("shared").members) * 3
    out = capsys.readouterr().out
    assert re.search(rf"{n} runs \(every variant x 3 seeds\) x ~\d+ min = ~[\d.]+ h", out)


def test_smoke_icp_warning_is_marked_expected_once(monkeypatch):
    from cloudpose import cli

    monkeypatch.setattr(warnings, "formatwarning", lambda m, *a, **k: f"warning: {m}\n")
    cli._mark_expected(*cli.EXPECTED_WARNINGS["smoke"])
    first = warnings.formatwarning("ICP kept the network's pose for 3 of 9", UserWarning, "f", 1)
    second = warnings.formatwarning("ICP kept the network's pose for 2 of 9", UserWarning, "f", 1)
    other = warnings.formatwarning("something else", UserWarning, "f", 1)
    assert "expected on the smoke preset" in first
    assert "expected" not in second and "expected" not in other


def test_ablate_help_lists_every_group_and_is_not_cut_when_piped(monkeypatch):
    monkeypatch.delenv("COLUMNS", raising=False)
    monkeypatch.delenv("TERMINAL_WIDTH", raising=False)
    res = CliRunner().invoke(app, ["ablate", "--help"])
    assert res.exit_code == 0, res.output
    for g in groups():
        assert g in res.output
    assert "…" not in res.output
    assert "cloudpose/resources/registry/presets.toml" in res.output


def test_flags_show_no_value_type():
    res = CliRunner().invoke(app, ["--help"])
    line = next(x for x in res.output.splitlines() if "--debug" in x)
    assert "<bool>" not in line
    res = CliRunner().invoke(app, ["ablate", "--help"])
    assert "<bool>" not in res.output and "<int>" in res.output


def test_variants_rows_align():
    res = CliRunner().invoke(app, ["variants"])
    lines = res.output.splitlines()
    header, rows = lines[0], lines[2:]
    col = header.index("parameters") + len("parameters")  # right-aligned column ends here
    for row in rows:
        assert re.match(r"[\d,]+$", row[:col].split()[-1]), row
        assert row[col : col + 2] == "  ", row


def test_the_documented_variant_table_groups_match_the_registry():
    text = VARIANTS_DOC.read_text()
    rows = re.findall(r"^\| `([^`|]+)`[^|]*\| ([a-z, ]+) \|", text, re.M)
    found = {name: [g.strip() for g in gs.split(",")] for name, gs in rows}
    assert "shared-0" in found
    for name, gs in found.items():
        if name in ("shared-1",):  # "shared-1 .. shared-5" on one row
            continue
        assert gs == groups_of(name), name


def test_reports_of_uncommitted_presets_stay_out_of_committed_reports(tmp_path):
    from cloudpose.report.build import default_out_dir

    assert default_out_dir(tmp_path, "smoke") == tmp_path / "reports" / "smoke"  # no checkout
    (tmp_path / "reports" / "cpu").mkdir(parents=True)
    (tmp_path / "reports" / "cpu" / "table1_overall.md").write_text("x\n")
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run([*git, "add", "reports"], cwd=tmp_path, check=True)
    subprocess.run([*git, "commit", "-qm", "reports"], cwd=tmp_path, check=True)
    assert default_out_dir(tmp_path, "cpu") == tmp_path / "reports" / "cpu"
    assert default_out_dir(tmp_path, "smoke") == tmp_path / "runs" / "reports" / "smoke"


def test_seed_list():
    assert plans.seed_list(3) == [1, 2, 3]
    assert plans.seed_list([3, 1, 3]) == [1, 3]
    with pytest.raises(ValueError, match="seeds"):
        plans.seed_list(0)


def test_a_plan_says_what_the_chunk_store_holds_for_each_seed(tmp_path, monkeypatch):
    from cloudpose.conventions import packaged_classes
    from cloudpose.data.synth.chunks import ChunkStore
    from cloudpose.suite.plan import chunk_lines
    from cloudpose.train.loop import ONLINE_STORE_ENV, online_chunks

    monkeypatch.setenv(ONLINE_STORE_ENV, str(tmp_path / "store"))
    online = {"data": {"train_source": "online", "online_epoch_segments": 64}}
    todo = [resolve("shared-0", "smoke", seed=s, overrides=online) for s in (1, 2, 3)]
    settings, chunk_size, n_chunks = online_chunks(todo[0], packaged_classes())
    store = ChunkStore(tmp_path / "store", settings, chunk_size)
    for j in range(n_chunks + 2):  # chunks past the run's are not its own
        store.path(1, j).parent.mkdir(parents=True, exist_ok=True)
        store.path(1, j).write_bytes(b"")
    store.path(2, 0).parent.mkdir(parents=True)
    store.path(2, 0).write_bytes(b"")
    lines = chunk_lines([*todo, todo[0]], tmp_path)
    assert lines == [
        f"chunks: seed 1: {n_chunks:,} of {n_chunks:,} stored (read, none synthesized)",
        f"chunks: seed 2: 1 of {n_chunks:,} stored (the rest synthesized by the run's 1 worker)",
        f"chunks: seed 3: 0 of {n_chunks:,} stored (the rest synthesized by the run's 1 worker)",
    ]
    in_process = resolve(
        "shared-0",
        "smoke",
        seed=2,
        overrides={**online, "data": {**online["data"], "online_workers": 0}},
    )
    assert "in the training process" in chunk_lines([in_process], tmp_path)[0]
    assert chunk_lines([resolve("shared-0", "smoke")], tmp_path) == []  # rendered frames
    monkeypatch.setenv(ONLINE_STORE_ENV, "0")
    assert chunk_lines(todo, tmp_path) == []
