"""The command line: errors of predict and evaluate, the registry listing.

Every user mistake the CLI must answer in one line is in test_cli_misuse.py.
"""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from cloudpose.cli import app


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
    from cloudpose.config import variants

    res = CliRunner().invoke(app, ["variants"])
    assert res.exit_code == 0, res.output
    for name in variants():
        assert name in res.output
