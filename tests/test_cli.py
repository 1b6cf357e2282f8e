"""The command line: errors of predict and evaluate, the registry listing.

Every user mistake the CLI must answer in one line is in test_cli_misuse.py.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from cloudpose.cli import app, recorded_command


@pytest.mark.slow
def test_cli_predict_and_evaluate_errors(smoke_project, tmp_path):
    _, out = smoke_project
    runner = CliRunner()
    res = runner.invoke(app, ["evaluate", "--run", "no-such-run", "--no-progress"])
    assert res.exit_code == 2 and "no-such-run" in res.output
    res = runner.invoke(
        app,
        [
            "predict",
            "--depth",
            str(tmp_path / "missing.png"),
            "--label",
            str(tmp_path / "x.png"),
            "--checkpoint",
            str(out.checkpoint),
        ],
    )
    assert res.exit_code == 2 and "missing.png" in res.output


def test_cli_variants_lists_the_registry():
    from cloudpose.registry import variants

    res = CliRunner().invoke(app, ["variants"])
    assert res.exit_code == 0, res.output
    for name in variants():
        assert name in res.output


def test_recorded_command_writes_paths_in_the_working_folder_relative(tmp_path, monkeypatch):
    """A provenance line names the project's files, not the folder of the machine it ran on; a
    path outside the working folder stays as given."""
    demo = typer.Typer()
    seen: list[str] = []

    @demo.command()
    def make(ctx: typer.Context, out: Path = typer.Option(...), seed: int = 1) -> None:
        seen.append(recorded_command(ctx))

    project = tmp_path / "project"
    (project / "reports").mkdir(parents=True)
    monkeypatch.chdir(project)
    runner = CliRunner()
    for out, shown in [
        (project / "reports" / "log.md", "reports/log.md"),
        (tmp_path / "elsewhere.md", str(tmp_path / "elsewhere.md")),
    ]:
        res = runner.invoke(demo, ["--out", str(out), "--seed", "3"])
        assert res.exit_code == 0, res.output
        assert seen[-1] == f"cloudpose --out {shown} --seed 3"
