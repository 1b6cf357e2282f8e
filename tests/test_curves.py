"""`cloudpose curves`: per-epoch histories of named runs from MLflow, plotted and saved as CSV."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from cloudpose.cli import app
from cloudpose.registry import resolve
from cloudpose.report.curves import curves_csv, fetch_curves, plot_curves
from cloudpose.store import tracking

ROT = {"cpu": [1.9, 1.7, 1.6], "smoke": [2.0, 1.2, 0.8, 0.5, 0.4]}
SEGMENTS = {"cpu": 3550, "smoke": 447}


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A throwaway store with two runs, ``a`` (3 epochs) and ``b`` (5 epochs)."""
    root = tmp_path_factory.mktemp("curves")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{root / 'mlflow.db'}")
        mp.chdir(root)
        client = tracking.setup(root)
        exp = tracking.experiment_id(client, "loss", root)
        for name, rot in ROT.items():
            tags = {
                "variant": "shared-0",
                "preset": name,
                "seed": "1",
                "data": "d" * 16,
                "config": resolve("shared-0", name, 1).fingerprint(),
                "git_commit": "c0ffee",
            }
            run = client.create_run(exp, tags=tags, run_name=f"shared-0/{name}/seed1")
            rid = run.info.run_id
            client.log_param(rid, "data.train_segments", str(SEGMENTS[name]))
            client.log_param(rid, "train.batch_size", "32")
            for epoch, v in enumerate(rot, 1):
                client.log_metric(rid, "train/loss_rot", v, step=epoch)
                client.log_metric(rid, "val/rot_err_median_deg", 100.0 - epoch, step=epoch)
            client.set_terminated(rid, "FINISHED")
    return root


@pytest.fixture
def client(store, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{store / 'mlflow.db'}")
    monkeypatch.chdir(store)
    return tracking.setup(store)


METRICS = ["train/loss_rot", "val/rot_err_median_deg"]


def test_fetch_returns_the_logged_histories(client):
    got = fetch_curves(client, ["shared-0/cpu/seed1", "shared-0/smoke/seed1"], METRICS)
    assert [c.label for c in got] == ["shared-0/cpu/seed1", "shared-0/smoke/seed1"]
    for c, name in zip(got, ROT, strict=True):
        s = c.series["train/loss_rot"]
        assert list(s.index) == list(range(1, len(ROT[name]) + 1))
        np.testing.assert_allclose(s.to_numpy(), ROT[name])
        assert c.steps_per_epoch == SEGMENTS[name] // 32
        assert c.config == resolve("shared-0", name, 1).fingerprint() and c.commit == "c0ffee"
    # by run id too
    again = fetch_curves(client, [got[1].run_id], METRICS)
    assert again[0].label == "shared-0/smoke/seed1"


def test_unknown_run_or_metric_is_a_clear_error(client):
    with pytest.raises(ValueError, match="no finished run named"):
        fetch_curves(client, ["shared-0/nope/seed1"], METRICS)
    with pytest.raises(ValueError, match=r"val/nothing.*was not logged"):
        fetch_curves(client, ["shared-0/cpu/seed1"], ["val/nothing"])


def test_plot_and_csv(client, tmp_path):
    got = fetch_curves(client, ["shared-0/cpu/seed1", "shared-0/smoke/seed1"], METRICS)
    for x in ("epoch", "step"):
        png = plot_curves(
            got,
            METRICS,
            tmp_path / f"c_{x}.png",
            command="test",
            x=x,
            mark_epoch=2,
            mark_label="here",
        )
        assert png.stat().st_size > 10_000
    with pytest.raises(ValueError, match="x must be"):
        plot_curves(got, METRICS, tmp_path / "bad.png", command="test", x="time")
    csv = curves_csv(got, METRICS, tmp_path / "c.csv", command="cloudpose curves ...")
    assert csv.read_text().startswith("# made by cloudpose curves ...")
    df = pd.read_csv(csv, comment="#")
    assert len(df) == sum(len(v) for v in ROT.values())
    b = df[df["run"] == "shared-0/smoke/seed1"]
    np.testing.assert_allclose(b["train/loss_rot"], ROT["smoke"])
    assert list(b["step"]) == [e * (SEGMENTS["smoke"] // 32) for e in range(1, 6)]


def test_cli_writes_png_and_csv(client, store):
    out = store / "out" / "rot.png"
    res = CliRunner().invoke(
        app,
        [
            "curves",
            "--run",
            "shared-0/cpu/seed1",
            "--run",
            "shared-0/smoke/seed1",
            "--out",
            str(out),
            "--x",
            "step",
        ],
    )
    assert res.exit_code == 0, res.output
    assert out.is_file() and out.with_suffix(".csv").is_file()
    assert "--x step" in out.with_suffix(".csv").read_text().splitlines()[0]
    bad = CliRunner().invoke(app, ["curves", "--run", "shared-0/zzz/seed1", "--out", str(out)])
    assert bad.exit_code == 2 and "no finished run" in bad.output
