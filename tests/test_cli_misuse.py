"""Ordinary mistakes of a new user against the real CLI on the smoke preset: each gives a clear
one-line error or a correct result, never a silent wrong number or a traceback."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from cloudpose import tracking
from cloudpose.cli import app

DATA = Path(__file__).parent / "data"
pytestmark = pytest.mark.slow


@pytest.fixture
def project(smoke_project):
    return smoke_project


def cli(*args: str):
    return CliRunner().invoke(app, list(args))


def one_line_error(res, *needles: str) -> str:
    """The error of a failed command: exit 2, one line on stderr, no traceback."""
    assert res.exit_code == 2, res.output
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    assert "Traceback" not in res.output
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


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


def test_debug_shows_the_traceback(project):
    res = cli("--debug", "train", "--variant", "nope", "--preset", "smoke")
    assert res.exit_code != 0 and isinstance(res.exception, ValueError)


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


def test_an_empty_frame_list_is_an_error(project, tmp_path):
    _, out = project
    folder = tmp_path / "empty"
    shutil.copytree(DATA / "ycb_real", folder)
    (folder / "keyframe.txt").write_text("")
    res = cli("evaluate", "--run", str(out.run_dir), "--data", str(folder), "--no-progress")
    one_line_error(res, "keyframe", "empty")


def test_a_run_name_resolves_to_the_presets_own_config(project):
    proj, out = project
    name = "shared-0/smoke/seed1"
    from cloudpose.runs import resolve_run_id

    client = tracking.setup(proj)
    assert resolve_run_id(client, name) == out.run_id
    # an override (fewer epochs) is another config: its own run, never taken for the name
    res = cli("train", "--preset", "smoke", "--set", "train.epochs=1", "--no-progress")
    assert res.exit_code == 0, res.output
    assert resolve_run_id(client, name) == out.run_id
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
