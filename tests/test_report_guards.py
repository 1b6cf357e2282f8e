"""Report commands never render from an empty store nor over committed reports they lack runs of."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cloudpose.cli import app
from cloudpose.failures import file_system_message
from cloudpose.report.committed import (
    NoRunsError,
    committed_pairs,
    refuse_empty,
    report_folder,
)


def _committed(project: Path, preset: str, runs: list[tuple[str, int]]) -> None:
    """A compact store's run folders of baseline runs (their pairs need no config fingerprint)."""
    for i, (variant, seed) in enumerate(runs):
        folder = project / "reports" / preset / "mlflow-store" / "runs" / f"run{i}"
        folder.mkdir(parents=True)
        row = {
            "run": {"status": "FINISHED"},
            "tags": {
                "preset": preset,
                "variant": variant,
                "seed": str(seed),
                "kind": "baseline",
                "split": "test",
            },
            "params": {},
        }
        (folder / "run.json").write_text(json.dumps(row))


def _unpacked_here(project: Path, monkeypatch) -> Path:
    """Where the committed cpu-online store is "unpacked": committed_store replaced by one that
    makes an empty stores/cpu-online/mlflow.db (the real one unpacks the compact store)."""
    from cloudpose.report import committed

    unpacked = project / "stores" / "cpu-online"

    def unpack(preset, project_dir):
        unpacked.mkdir(parents=True, exist_ok=True)
        (unpacked / "mlflow.db").touch()
        return unpacked

    monkeypatch.setattr(committed, "committed_store", unpack)
    return unpacked


def test_refuse_empty_names_the_store_and_the_preset(tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'EMPTY.db'}")
    with pytest.raises(NoRunsError, match=r"EMPTY\.db: no finished, evaluated run of preset 'p1'"):
        refuse_empty(0, "p1", tmp_path, "the report")
    refuse_empty(3, "p1", tmp_path, "the report")  # runs found: nothing raised


def test_committed_pairs_reads_the_compact_store(tmp_path):
    _committed(tmp_path, "p1", [("baseline-fpfh", 1), ("baseline-fpfh", 2)])
    assert committed_pairs("p1", tmp_path) == {("baseline-fpfh", 1), ("baseline-fpfh", 2)}
    assert committed_pairs("p1", tmp_path, split="real") == set()
    assert committed_pairs("p2", tmp_path) is None


def test_a_smaller_sweep_renders_beside_the_committed_reports(tmp_path):
    _committed(tmp_path, "p1", [("baseline-fpfh", s) for s in (1, 2, 3)])
    said: list[str] = []
    committed = tmp_path / "reports" / "p1"
    fewer = {("baseline-fpfh", 1)}
    assert report_folder("p1", tmp_path, None, committed, fewer, said.append) == (
        tmp_path / "runs" / "reports" / "p1"
    )
    assert "count 3 runs" in said[-1] and "lack 2" in said[-1]
    more = {("baseline-fpfh", s) for s in (1, 2, 3, 4)}
    assert report_folder("p1", tmp_path, None, committed, more, said.append) == committed
    assert "3 committed runs and 1 more" in said[-1]
    # named by the user: written as asked, the counts said first
    assert report_folder("p1", tmp_path, committed, committed, fewer, said.append) == committed
    assert said[-1].startswith("warning: replacing reports/p1/")
    # another folder: no question
    other = tmp_path / "mine"
    assert report_folder("p1", tmp_path, other, committed, fewer, said.append) == other


def test_a_sweep_on_other_data_renders_beside_the_committed_reports(tmp_path):
    """Committed runs of data ``aaaa`` only: a store's runs of data ``bbbb``, however many,
    include none of them (before, the empty set of committed runs on ``bbbb`` let them render
    over the committed reports without a word)."""
    _committed(tmp_path, "p1", [("baseline-fpfh", 1)])
    row = tmp_path / "reports" / "p1" / "mlflow-store" / "runs" / "run0" / "run.json"
    run = json.loads(row.read_text())
    run["tags"]["data"] = "aaaa"
    row.write_text(json.dumps(run))
    said: list[str] = []
    committed = tmp_path / "reports" / "p1"
    mine = {("baseline-fpfh", s) for s in (1, 2, 3)}
    assert report_folder("p1", tmp_path, None, committed, mine, said.append, data_key="bbbb") == (
        tmp_path / "runs" / "reports" / "p1"
    )
    assert "of other data than this store's 3 runs (data bbbb)" in said[-1]
    # on the committed runs' data, the superset renders over them as before
    assert report_folder("p1", tmp_path, None, committed, mine, said.append, data_key="aaaa") == (
        committed
    )


@pytest.mark.parametrize("command", [["report", "--no-mlflow"], ["real-report"]])
def test_report_commands_refuse_an_empty_store(tmp_path, monkeypatch, command):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'EMPTY.db'}")
    out = tmp_path / "out"
    res = CliRunner().invoke(app, [*command, "--preset", "cpu-online", "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert "no finished, evaluated run of preset 'cpu-online'" in res.output
    assert not out.exists()


@pytest.mark.parametrize(
    ("code", "words"),
    [
        (errno.ENOTDIR, "a part of the path is a file"),
        (errno.EACCES, "no permission"),
        (errno.EROFS, "read-only file system"),
        (errno.ENOSPC, "no space left"),
    ],
)
def test_file_system_errors_are_one_line_naming_the_path(code, words):
    exc = OSError(code, "said", "/some/where/out")
    message = file_system_message(exc)
    assert message.startswith("/some/where/out: said (") and words in message
    assert "\n" not in message


def test_a_file_system_error_in_a_command_is_one_line(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    blocker = tmp_path / "afile"
    blocker.write_text("")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'EMPTY.db'}")
    res = CliRunner().invoke(app, ["curves", "--run", "x", "--out", str(blocker / "c.png")])
    assert res.exit_code != 0
    assert "Traceback" not in res.output


def test_a_sweep_reuses_the_committed_store_unless_fresh(tmp_path, monkeypatch):
    from cloudpose.report import committed

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    _committed(tmp_path, "cpu-online", [("baseline-fpfh", 1)])
    unpacked = _unpacked_here(tmp_path, monkeypatch)
    said: list[str] = []
    shown = committed.sweep_store("cpu-online", tmp_path, False, said.append)
    assert shown == "stores/cpu-online/mlflow.db"
    assert "MLFLOW_TRACKING_URI" in os.environ
    assert str(unpacked.resolve()) in os.environ["MLFLOW_TRACKING_URI"]
    assert "unpacked now" in said[0] and "FRESH=1" in said[0]

    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    said.clear()
    assert committed.sweep_store("cpu-online", tmp_path, True, said.append) == "./mlflow.db"
    assert "MLFLOW_TRACKING_URI" not in os.environ and "--fresh" in said[0]
    # a store the user named is used as named
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "sqlite:///mine.db")
    assert committed.sweep_store("cpu-online", tmp_path, False, said.append) == "sqlite:///mine.db"
    # a preset the checkout commits no store of trains into the project's own
    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    assert committed.sweep_store("smoke", tmp_path, False, said.append) == "./mlflow.db"


def test_a_render_of_the_same_numbers_leaves_the_files_as_they_are(tmp_path):
    import matplotlib.pyplot as plt

    from cloudpose.report import plots
    from cloudpose.report.formats import Provenance, write_text

    def prov(command: str) -> Provenance:
        return Provenance(command, "cpu-online", "synthetic", (1, 2), ("abc123",))

    text = tmp_path / "t.md"
    write_text(text, f"_{prov('cloudpose report').line()}_\n| a | 1.0 |\n")
    before = text.stat().st_mtime_ns
    write_text(text, f"_{prov('cloudpose ablate --group shared').line()}_\n| a | 1.0 |\n")
    assert text.stat().st_mtime_ns == before and "cloudpose report" in text.read_text()
    write_text(text, f"_{prov('cloudpose ablate').line()}_\n| a | 2.0 |\n")
    assert "2.0" in text.read_text() and "cloudpose ablate" in text.read_text()

    def figure(command: str, y: float):
        fig, ax = plt.subplots()
        ax.plot([0, 1], [0, y])
        plots._footer(fig, prov(command))
        return fig

    png = tmp_path / "f.png"
    plots._save(figure("cloudpose report", 1.0), png)
    first = png.read_bytes()
    plots._save(figure("cloudpose occlusion-report", 1.0), png)
    assert png.read_bytes() == first
    plots._save(figure("cloudpose occlusion-report", 2.0), png)
    assert png.read_bytes() != first


@pytest.mark.parametrize("fresh", [False, True])
def test_a_baseline_reuses_the_committed_store_unless_fresh(tmp_path, monkeypatch, fresh):
    import cloudpose.studies.baseline_runs

    monkeypatch.chdir(tmp_path)
    _committed(tmp_path, "cpu-online", [("baseline-fpfh", 1)])
    unpacked = _unpacked_here(tmp_path, monkeypatch)
    seen = {}

    def fake(method, preset, seed, **kw):  # the store the run would be looked up and logged in
        seen["store"] = os.environ.get("MLFLOW_TRACKING_URI")
        raise ValueError("stop here")

    monkeypatch.setattr(cloudpose.studies.baseline_runs, "run_baseline", fake)
    args = ["baseline", "--method", "fpfh", "--preset", "cpu-online", "--no-progress"]
    res = CliRunner().invoke(app, args + (["--fresh"] if fresh else []))
    assert "stop here" in res.output
    if fresh:
        assert seen["store"] is None and "store: ./mlflow.db (--fresh" in res.output
    else:
        assert seen["store"] == f"sqlite:///{(unpacked / 'mlflow.db').resolve()}"
        assert "store: stores/cpu-online/mlflow.db (unpacked now" in res.output


def _stress_results(folder: Path, names: list[str]) -> Path:
    for name in names:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text("{}\n" if name.endswith(".json") else "x\n")
    return folder


STRESS_FILES = ["sweep.json", "results/real/bias/10/fpfh.csv", "results/real/bias/20/fpfh.csv"]


@pytest.fixture
def committed_stress(tmp_path) -> Path:
    """A project whose reports/cpu-online keeps a stress report's packed results (3 files)."""
    import tarfile

    project = tmp_path / "project"
    committed = project / "reports" / "cpu-online"
    committed.mkdir(parents=True)
    src = _stress_results(tmp_path / "src", STRESS_FILES)
    with tarfile.open(committed / "stress-results.tar.xz", "w:xz") as tar:
        for name in STRESS_FILES:
            tar.add(src / name, arcname=name)
    return project


@pytest.mark.parametrize(
    ("names", "where", "said"),
    [
        (STRESS_FILES[:2], "runs/reports/cpu-online", "count 3 result files; these 2 lack 1"),
        (STRESS_FILES, "reports/cpu-online", None),
        ([*STRESS_FILES, "results/real/cut/1/fpfh.csv"], "reports/cpu-online", "and 1 more"),
    ],
)
def test_a_stress_report_of_fewer_results_renders_beside_the_committed_one(
    committed_stress, tmp_path, monkeypatch, names, where, said
):
    """`cloudpose stress --steps report` of results lacking some of those the committed report
    was rendered from (reports/PRESET/stress-results.tar.xz) writes into runs/reports/PRESET,
    saying so with the counts; results holding them all render over it."""
    from cloudpose.report import stress as report_stress

    rendered: list[Path] = []
    monkeypatch.setattr(
        report_stress, "render_stress_report", lambda run, out, **kw: rendered.append(out) or []
    )
    monkeypatch.chdir(committed_stress)
    results = _stress_results(tmp_path / "mine", names)
    res = CliRunner().invoke(app, ["stress", "--steps", "report", "--results", str(results)])
    assert res.exit_code == 0, res.output
    assert rendered == [committed_stress / where]
    if said is None:
        assert res.output.strip() == ""
    else:
        assert said in res.output and len(res.output.strip().splitlines()) == 1


def test_a_stress_report_named_by_out_over_committed_results_says_the_counts_first(
    committed_stress, tmp_path, monkeypatch
):
    from cloudpose.report import stress as report_stress

    rendered: list[Path] = []
    monkeypatch.setattr(
        report_stress, "render_stress_report", lambda run, out, **kw: rendered.append(out) or []
    )
    monkeypatch.chdir(committed_stress)
    results = _stress_results(tmp_path / "mine", STRESS_FILES[:1])
    out = committed_stress / "reports" / "cpu-online"
    res = CliRunner().invoke(
        app, ["stress", "--steps", "report", "--results", str(results), "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    assert rendered == [out]
    assert res.output.startswith("warning: replacing reports/cpu-online/ by --out: ")
    assert "count 3 result files; these 1 lack 2" in res.output
