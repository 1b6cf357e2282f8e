"""Ordinary mistakes of a new user against the real CLI on the smoke preset: each gives a clear
one-line error or a correct result, never a silent wrong number or a traceback. The mistakes
caught before any work are fast; the ones against a trained run are marked slow."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cloudpose.store import tracking
from tests.conftest import cli, one_line_error

DATA = Path(__file__).parent / "data"


@pytest.fixture
def project(smoke_project):
    return smoke_project


@pytest.mark.slow
@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["train", "--variant", "nope", "--preset", "smoke"], ["unknown variant", "shared-0"]),
        (["run", "--preset", "zzz"], ["unknown preset", "smoke", "cpu"]),
        (["train", "--preset", "smoke", "--epochs", "0"], ["train.epochs must be >= 1"]),
        (["train", "--preset", "smoke", "--epochs", "-3"], ["train.epochs must be >= 1"]),
        (["train", "--preset", "smoke", "--set", "train.epochs"], ["section.field=value"]),
    ],
)
def test_bad_names_and_settings_are_one_line(project, args, needles):
    one_line_error(cli(*args), *needles)


@pytest.mark.slow
def test_debug_shows_the_traceback(project):
    res = cli("--debug", "train", "--variant", "nope", "--preset", "smoke")
    assert res.exit_code != 0 and isinstance(res.exception, ValueError)


@pytest.mark.slow
def test_a_file_that_is_not_a_checkpoint(project, tmp_path):
    text = tmp_path / "notes.pt"
    text.write_text("these are my notes, not a model\n" * 10)
    for bad in (text, DATA / "demo_no_gt" / "depth.png"):
        res = cli(
            "predict",
            "--depth",
            str(DATA / "demo_no_gt" / "depth.png"),
            "--label",
            str(DATA / "demo_no_gt" / "label.png"),
            "--checkpoint",
            str(bad),
        )
        one_line_error(res, str(bad), "not a cloudpose checkpoint")


@pytest.mark.slow
def test_a_malicious_pickle_is_refused_in_one_line(project, tmp_path):
    import pickle

    class Evil:
        def __reduce__(self):
            return (print, ("owned",))

    path = tmp_path / "evil.pt"
    path.write_bytes(pickle.dumps({"model": Evil(), "config": {}}))
    res = cli("evaluate", "--run", str(tmp_path), "--no-progress")  # not a run folder either
    one_line_error(res)
    from cloudpose.infer import load_checkpoint

    with pytest.raises(ValueError, match="not a cloudpose checkpoint"):
        load_checkpoint(path)


@pytest.mark.slow
def test_evaluating_another_folder_named_test_keeps_the_runs_own_results(project, tmp_path):
    proj, out = project
    client = tracking.setup(proj)
    res = cli("evaluate", "--run", str(out.run_dir), "--no-progress")
    assert res.exit_code == 0, res.output
    own = client.get_run(out.run_id).data.metrics["test/ads_auc"]
    # the real annotated frame, copied to a folder called "test", twice (same basename)
    for i, frames in enumerate(("all", "all")):
        folder = tmp_path / f"copy{i}" / "test"
        shutil.copytree(DATA / "ycb_real", folder)
        if i == 1:  # another folder of one basename with other content
            (folder / "keyframe.txt").write_text("0000/000001\n")
            meta = folder / "data" / "0000" / "000001-label.png"
            lab = np.array(Image.open(meta))
            lab[lab == 21] = 0  # drop the foam brick
            Image.fromarray(lab).save(meta)
        res = cli(
            "evaluate",
            "--run",
            str(out.run_dir),
            "--data",
            str(folder),
            "--frames",
            frames,
            "--no-progress",
        )
        assert res.exit_code == 0, res.output
        assert "checkpoint" in res.output and str(folder) in res.output
    metrics = client.get_run(out.run_id).data.metrics
    assert metrics["test/ads_auc"] == own  # untouched
    names = {k.split("/")[0] for k in metrics if k.startswith("test-all-")} - {
        k.split("/")[0] for k in metrics if k.split("/")[0].endswith("_icp")
    }
    assert len(names) == 2  # one per distinct dataset, neither named "test"
    # (other tests evaluate the shared smoke run under other masks: eval/test-degraded-...)
    arts = {a.path for a in client.list_artifacts(out.run_id, "eval")}
    assert {a for a in arts if a == "eval/test" or a.startswith("eval/test-all-")} == {
        "eval/test"
    } | {f"eval/{n}" for n in names}
    # the reserved name cannot be taken by other data
    res = cli(
        "evaluate",
        "--run",
        str(out.run_dir),
        "--data",
        str(folder),
        "--frames",
        "all",
        "--name",
        "test",
        "--no-progress",
    )
    one_line_error(res, "reserved")
    # a name already holding other data is not overwritten; the same bytes may be re-evaluated
    codes = []
    for name in sorted(names):
        res = cli(
            "evaluate",
            "--run",
            str(out.run_dir),
            "--data",
            str(DATA / "ycb_real"),
            "--frames",
            "all",
            "--name",
            name,
            "--no-progress",
        )
        codes.append(res.exit_code)
        if res.exit_code:
            one_line_error(res, "other data")
    assert sorted(codes) == [0, 2]


@pytest.mark.slow
def test_an_empty_frame_list_is_an_error(project, tmp_path):
    _, out = project
    folder = tmp_path / "empty"
    shutil.copytree(DATA / "ycb_real", folder)
    (folder / "keyframe.txt").write_text("")
    res = cli("evaluate", "--run", str(out.run_dir), "--data", str(folder), "--no-progress")
    one_line_error(res, "keyframe", "empty")


@pytest.mark.slow
def test_a_run_name_resolves_to_the_presets_own_config(project):
    proj, out = project
    name = "shared-0/smoke/seed1"
    from cloudpose.store.runs import resolve_run_id

    client = tracking.setup(proj)
    assert resolve_run_id(client, name) == out.run_id
    # an override (fewer epochs) is another config: its own run, never taken for the name
    res = cli("train", "--preset", "smoke", "--set", "train.epochs=1", "--no-progress")
    assert res.exit_code == 0, res.output
    assert resolve_run_id(client, name) == out.run_id
    # the name train prints (with +CONFIG) names that run, for --run as for the library
    printed, run_id = re.search(r"^run (\S+) \(MLflow run (\w+),", res.output, re.M).groups()
    assert printed.startswith(name + "+") and resolve_run_id(client, printed) == run_id
    res = cli("evaluate", "--run", printed, "--refine", "none", "--no-progress")
    assert res.exit_code == 0 and f"run {run_id}" in res.output, res.output
    names = {r.info.run_name for r in tracking.find_runs(client, variant="shared-0", seed=1)}
    assert name in names and any(n.startswith(name + "+") for n in names)  # never one name
    # two finished runs of the preset's own config (here: the same run tagged again)
    twin = client.create_run(
        client.get_run(out.run_id).info.experiment_id,
        tags=dict(client.get_run(out.run_id).data.tags),
        run_name=name,
    )
    client.log_param(twin.info.run_id, "data.root", "")
    client.set_terminated(twin.info.run_id, "FINISHED")
    with pytest.raises(ValueError, match=r"2 finished runs .*Pass the run id") as info:
        resolve_run_id(client, name)
    assert out.run_id in str(info.value) and twin.info.run_id in str(info.value)
    client.delete_run(twin.info.run_id)


@pytest.mark.slow
def test_depth_in_millimetres_is_caught(project, tmp_path):
    _, out = project
    depth = np.array(Image.open(DATA / "demo_no_gt" / "depth.png")).astype(np.uint32)
    mm = tmp_path / "depth_mm.png"
    Image.fromarray((depth // 10).astype(np.uint16)).save(mm)  # 0.1 mm -> mm
    args = [
        "predict",
        "--depth",
        str(mm),
        "--label",
        str(DATA / "demo_no_gt" / "label.png"),
        "--checkpoint",
        str(out.checkpoint),
        "--overlay",
        str(tmp_path / "o.png"),
    ]
    one_line_error(cli(*args), str(mm), "10 times too small", "--depth-factor")
    res = cli(*args, "--depth-factor", "1000")
    assert res.exit_code == 0, res.output


@pytest.mark.slow
def test_device_is_one_choice(project):
    import torch

    _, out = project
    from cloudpose.infer import load_checkpoint

    model, _ = load_checkpoint(out.checkpoint, "auto")
    want = "cuda" if torch.cuda.is_available() else "cpu"
    assert next(model.buffers()).device.type == want
    if not torch.cuda.is_available():
        res = cli("evaluate", "--run", str(out.run_dir), "--device", "cuda", "--no-progress")
        one_line_error(res, "CUDA is not available")


# --- caught before any work: no data made, no run folder, no MLflow run -----------------------


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["--set", 'train.epochs="two"'], ["train.epochs='two'", "expected int"]),
        (["--set", "train.epochs=2.5"], ["train.epochs=2.5", "expected int"]),
        (["--set", "train.n_points=0"], ["train.n_points must be >= 1"]),
        (["--set", "train.lr=-1"], ["train.lr must be > 0"]),
        (["--group", "../../x"], ["group '../../x'", "letters, digits"]),
        (["--group", "/tmp/elsewhere"], ["group '/tmp/elsewhere'"]),
    ],
)
@pytest.mark.parametrize("command", ["train", "run"])
def test_bad_settings_and_groups_stop_before_anything_is_written(command, args, needles):
    one_line_error(cli(command, "--preset", "smoke", "--no-progress", *args), *needles)
    assert list(Path.cwd().iterdir()) == []  # no data/, runs/, mlartifacts/ nor mlflow.db


@pytest.mark.parametrize(
    ("name", "needles"),
    [
        ("val", ["'val' is a metric prefix of training"]),
        ("fit", ["'fit' is a metric prefix of training"]),
        ("train", ["metric prefix of training"]),
        ("time", ["metric prefix of training"]),
        ("mine_icp", ["ending in _icp"]),
        ("../../x", ["--name '../../x'", "letters, digits"]),
        ("a/b", ["--name 'a/b'"]),
        ("real", ["reserved for the packaged real development frames"]),
    ],
)
def test_evaluation_names_that_collide_are_refused(name, needles):
    res = cli("evaluate", "--run", "any", "--data", str(DATA / "ycb_real"), "--name", name)
    one_line_error(res, *needles)


@pytest.mark.parametrize(
    "command", [["evaluate", "--run", "any"], ["baseline", "--method", "fpfh"]]
)
def test_icp_starts_outside_the_rotation_groups_are_refused(command):
    res = cli(*command, "--refine", "starts=6")
    one_line_error(res, "--refine starts=6: expected one of 1, 12, 24, 60")
    assert list(Path.cwd().iterdir()) == []


@pytest.mark.parametrize(
    "command", [["evaluate", "--run", "any"], ["baseline", "--method", "fpfh"]]
)
def test_an_icp_radius_outside_the_schedules_range_is_refused(command):
    res = cli(*command, "--refine", "radius=0.002")
    one_line_error(res, "--refine radius=0.002: ICP radius 0.002 m: expected from the paper's 0.01")
    assert list(Path.cwd().iterdir()) == []


def test_an_existing_bop_csv_is_not_overwritten(tmp_path):
    mine = tmp_path / "mine.csv"
    mine.write_text("my results\n")
    res = cli("evaluate", "--run", "any", "--bop-csv", str(mine))
    one_line_error(res, str(mine), "exists; pass --force")
    assert mine.read_text() == "my results\n"
    one_line_error(cli("evaluate", "--run", "any", "--bop-csv", str(tmp_path)), "is a folder")
    # with --force the command goes on (here to the unknown run)
    one_line_error(cli("evaluate", "--run", "any", "--bop-csv", str(mine), "--force"), "'any'")


def test_export_onto_a_file_is_one_line(tmp_path):
    out = tmp_path / "out.txt"
    out.write_text("keep me\n")
    res = cli("export", "--data", str(DATA / "ycb_real"), "--out", str(out), "--no-progress")
    one_line_error(res, str(out), "is a file")
    assert out.read_text() == "keep me\n"


@pytest.mark.parametrize(
    "command",
    [
        ["synth"],
        ["showcase"],
        ["ship", "--run", "any"],
        ["report"],
        ["real-report"],
        ["stress"],
        ["ablate", "--dry-run"],
        ["compare"],
    ],
)
def test_an_output_folder_that_is_a_file_is_refused_before_any_work(command, tmp_path):
    """Every option that names a folder to write refuses an existing file, naming the option,
    and leaves the file as it was."""
    out = tmp_path / "out.txt"
    out.write_text("keep me\n")
    res = cli(*command, "--out", str(out))
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert "'--out'" in res.output and "is a file" in res.output
    assert out.read_text() == "keep me\n" and sorted(tmp_path.iterdir()) == [out]


@pytest.mark.parametrize(
    "command",
    [
        ["evaluate", "--run", "pretrained"],
        ["predict", "--depth", "d.png", "--label", "l.png", "--checkpoint", "pretrained"],
    ],
)
def test_icp_fields_beside_no_icp_are_refused(command):
    """An ICP field that --refine none would ignore is an error naming both, before any work."""
    res = cli(*command, "--refine", "none,starts=24,radius=0.18")
    one_line_error(res, "--refine none,starts=24,radius=0.18: none is no ICP")


def test_a_service_that_cannot_be_reached_is_one_line(monkeypatch):
    import cloudpose.suite.ablate

    def unreachable(*args, **kwargs):
        raise ConnectionError("Could not find any running Ray instance. Please specify ...")

    monkeypatch.setattr(cloudpose.suite.ablate, "run_group", unreachable)
    res = cli("ablate", "--group", "shared", "--preset", "smoke", "--executor", "ray")
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    last = res.output.strip().splitlines()[-1]  # after the sweep's plan
    assert last.startswith("error: Could not find any running Ray instance"), res.output


# --- runs that fail, and runs started twice ------------------------------------------------------


@pytest.mark.slow
def test_a_run_that_fails_is_marked_failed_and_resumes(tmp_path, smoke_data, monkeypatch):
    import cloudpose.train.step
    from cloudpose.registry import resolve
    from cloudpose.suite.pipeline import train_run
    from tests.conftest import make_project

    proj = make_project(tmp_path / "proj", smoke_data, monkeypatch)
    cfg = resolve("shared-0", "smoke", 1, {"train": {"epochs": 1}})

    def nan_loss(*args, **kwargs):
        terms = real_loss(*args, **kwargs)
        return type(terms)(*(t * float("nan") for t in terms))

    real_loss = cloudpose.train.step.pose_loss
    monkeypatch.setattr(cloudpose.train.step, "pose_loss", nan_loss)
    with pytest.raises(FloatingPointError, match="loss became nan"):
        train_run(cfg, project_dir=proj, progress=False)
    client = tracking.setup(proj)
    (run,) = tracking.find_runs(client, variant="shared-0", status=None)
    assert run.info.status == "FAILED"
    monkeypatch.setattr(cloudpose.train.step, "pose_loss", real_loss)
    out = train_run(cfg, project_dir=proj, progress=False)  # the same command again
    assert out.run_id == run.info.run_id
    assert client.get_run(out.run_id).info.status == "FINISHED"


@pytest.mark.slow
def test_two_identical_trains_started_together_make_one_run(tmp_path, smoke_data, monkeypatch):
    from tests.conftest import make_project

    proj = make_project(tmp_path / "proj", smoke_data, monkeypatch)
    argv = [sys.executable, "-m", "cloudpose.cli", "train", "--preset", "smoke", "--no-progress"]
    argv += ["--set", "train.epochs=1"]
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    procs = [
        subprocess.Popen(argv, cwd=proj, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        for _ in range(2)
    ]
    outputs = [p.communicate(timeout=600)[0].decode() for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outputs
    ids = {re.search(r"\(MLflow run (\w+),", o).group(1) for o in outputs}
    client = tracking.setup(proj)
    runs = tracking.find_runs(client, variant="shared-0", status=None)
    assert len(ids) == 1 and [r.info.run_id for r in runs] == list(ids), outputs
    folders = [p for p in (proj / "runs" / "shared-0" / "smoke").iterdir() if p.is_dir()]
    assert len(folders) == 1


def test_a_report_preset_that_is_a_path_is_refused():
    res = cli("report", "--preset", "../../elsewhere", "--no-mlflow")
    one_line_error(res, "--preset '../../elsewhere'", "letters, digits")
    assert list(Path.cwd().iterdir()) == []


@pytest.mark.parametrize(
    "command", [["evaluate", "--run", "pretrained"], ["baseline", "--method", "fpfh"]]
)
def test_an_unknown_icp_selection_is_one_line_listing_the_known(command):
    res = cli(*command, "--refine", "select=closest")
    one_line_error(res, "--refine select=closest", "fitness, depth")
