"""Segmentation quality as an ablation: shared-0 under each test-time mask source.

The report is checked on a throwaway MLflow store of constructed per-instance tables (every
expected number computed here with NumPy), the runner end to end on the smoke preset.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cloudpose.registry import resolve
from cloudpose.report.segmentation import SOURCES
from tests.conftest import make_project

PRESET = "smoke"
SEEDS = (1, 2)
MISSES = {"gt": 0, "degraded-mild": 2, "degraded-medium": 5, "degraded-strong": 12}
"""Constructed misses per source (of 60 instances)."""
M = 60


def _instances(rng: np.random.Generator, misses: int) -> pd.DataFrame:
    occ = np.linspace(0.0, 0.95, M)
    miss = np.zeros(M, bool)
    miss[rng.choice(M, misses, replace=False)] = True
    df = pd.DataFrame(
        {
            "frame_id": [f"0048/{i // 4:06d}" for i in range(M)],
            "instance": np.arange(M) % 4,
            "cls_id": 1 + np.arange(M) % 21,
            "occlusion": occ,
            "miss": miss,
        }
    )
    for method, scale in (("net", 0.02), ("icp", 0.008)):
        ads = rng.exponential(scale, M)
        df[f"{method}_ad"] = ads * 2
        df[f"{method}_ads"] = ads
        df[f"{method}_rot_err_deg"] = rng.gamma(2.0, 8.0, M)
        df[f"{method}_rot_sym_err_deg"] = df[f"{method}_rot_err_deg"] * 0.5
        df[f"{method}_trans_err"] = ads
        df.loc[miss, [c for c in df if c.startswith(method)]] = np.inf
    return df


def _store(root: Path, sources) -> dict:
    """shared-0 runs of two seeds, each with one evaluation per source in ``sources``."""
    from cloudpose.report.segmentation import mask_source_evaluation_name
    from cloudpose.store import tracking

    client = tracking.setup(root)
    exp = tracking.experiment_id(client, "shared", root)
    rng = np.random.default_rng(7)
    logged = {}
    for seed in SEEDS:
        tags = {
            "variant": "shared-0",
            "preset": PRESET,
            "seed": str(seed),
            "data": "f00dfeed12345",
            "git_commit": "abc1234",
            "config": resolve("shared-0", PRESET, seed).fingerprint(),
        }
        rid = client.create_run(exp, tags=tags).info.run_id
        client.log_param(rid, "data.root", "")
        client.log_metric(rid, "test/ads_auc", 0.5)
        for source in sources:
            df = _instances(rng, MISSES[source])
            name = mask_source_evaluation_name(source)
            path = root / "logged" / rid / name / "instances.csv"
            path.parent.mkdir(parents=True)
            df.to_csv(path, index=False)
            client.log_artifact(rid, str(path), artifact_path=f"eval/{name}")
            logged[(source, seed)] = df
        client.set_terminated(rid, "FINISHED")
    return logged


def _render(root: Path, monkeypatch):
    """``cloudpose report --all``, with the variant groups' own reports left out (they are
    test_report's business, and the slow part of a render)."""
    from cloudpose.report import build, render_reports

    monkeypatch.chdir(root)
    monkeypatch.setattr(build, "groups", dict)
    return render_reports(PRESET, None, project_dir=root, command="cloudpose report --all")


def test_masks_report_from_constructed_runs(tmp_path, monkeypatch):
    """One row per source (the paper's PoseCNN row first); every figure is the mean over seeds
    of the instance tables' values, misses included as failures; the occlusion plot has one
    series per source and method; the report is logged to MLflow as report/masks/smoke."""
    from cloudpose.metrics import voc_ap_auc
    from cloudpose.store import tracking

    logged = _store(tmp_path, SOURCES)
    res = _render(tmp_path, monkeypatch)
    out = tmp_path / "reports" / PRESET
    table = pd.read_csv(out / "table_masks.csv", comment="#")
    assert list(table["source"]) == ["paper: PoseCNN", *SOURCES]
    paper = table.iloc[0]
    assert paper["ads_auc_net_mean"] == 91.3 and paper["ads_auc_icp_mean"] == 94.7
    assert paper["ad_auc_net_mean"] == 76.0 and paper["ad_auc_icp_mean"] == 82.7
    for _, row in table.iloc[1:].iterrows():
        s = row["source"]
        dfs = [logged[(s, seed)] for seed in SEEDS]
        assert row["misses_mean"] == MISSES[s] and row["instances"] == M
        for method in ("net", "icp"):
            below = [100 * np.mean(d[f"{method}_ads"].to_numpy() < 0.02) for d in dfs]
            auc = [100 * voc_ap_auc(d[f"{method}_ads"].to_numpy()) for d in dfs]
            rot = [100 * np.mean(d[f"{method}_rot_sym_err_deg"].to_numpy() < 10) for d in dfs]
            assert row[f"ads_lt_2cm_{method}_mean"] == pytest.approx(np.mean(below), abs=1e-3)
            assert row[f"ads_lt_2cm_{method}_std"] == pytest.approx(np.std(below, ddof=1), 1e-3)
            assert row[f"ads_auc_{method}_mean"] == pytest.approx(np.mean(auc), abs=1e-3)
            assert row[f"rot_sym_lt_10deg_{method}_mean"] == pytest.approx(np.mean(rot), 1e-3)
    md = (out / "table_masks.md").read_text()
    assert "| degraded-strong | boundary ±8 px, bleeding 8 px, 10% missed |" in md
    assert "12 of 60" in md and "cloudpose report --all" in md
    assert "\\begin{tabular}" in (out / "table_masks.tex").read_text()

    occ = pd.read_csv(out / "occlusion_masks.csv", comment="#")
    expected = {f"{s}, network alone" for s in SOURCES} | {f"{s} + ICP" for s in SOURCES}
    assert set(occ["series"]) == expected
    # a miss is a failure in its bin: the strong masks' bins hold every instance
    strong = occ[occ["series"] == "degraded-strong + ICP"]
    assert strong["count"].sum() == M
    first = [logged[("degraded-strong", s)].query("occlusion < 0.1") for s in SEEDS]
    assert first[0]["miss"].any()  # the bin holds a miss, counted as a failure
    hits = [100 * np.mean(d["icp_ads"].to_numpy() < 0.01) for d in first]
    assert strong.iloc[0]["count"] == len(first[0])
    assert strong.iloc[0]["accuracy_mean_pct"] == pytest.approx(np.mean(hits), abs=1e-2)
    assert (out / "occlusion_masks.png").stat().st_size > 10_000
    assert "table_masks.md" in (out / "README.md").read_text()

    client = tracking.setup(tmp_path)
    arts = {a.path for a in client.list_artifacts(res.mlflow_runs["masks"])}
    assert {"table_masks.md", "occlusion_masks.png", "occlusion_masks.csv"} <= arts
    assert client.get_run(res.mlflow_runs["masks"]).info.run_name == f"report/masks/{PRESET}"


def test_report_all_without_mask_evaluations_has_no_masks_table(tmp_path, monkeypatch):
    _store(tmp_path, ["gt"])
    res = _render(tmp_path, monkeypatch)
    assert not (tmp_path / "reports" / PRESET / "table_masks.csv").exists()
    assert res.mlflow_runs == {}
    assert (tmp_path / "reports" / PRESET / "table1_overall.md").exists()


def test_an_unknown_mask_source_fails_before_training(tmp_path):
    from cloudpose.suite.masks import mask_ablation

    with pytest.raises(ValueError, match="degraded-medium"):
        mask_ablation(PRESET, 1, tmp_path, False, sources=["gt", "degraded-typo"])
    assert not (tmp_path / "runs").exists()


@pytest.mark.slow
def test_ablate_masks_on_smoke_trains_once_then_skips(tmp_path, smoke_data, monkeypatch):
    """The command trains shared-0 once, evaluates it under each degraded source (ground truth
    is its own evaluation), renders the table and plot; a second call does nothing new."""
    from typer.testing import CliRunner

    from cloudpose.cli import app
    from cloudpose.store import tracking
    from cloudpose.suite.masks import mask_ablation

    proj = make_project(tmp_path / "proj", smoke_data, monkeypatch)
    monkeypatch.chdir(proj)
    res = mask_ablation(PRESET, 1, proj, progress=False, echo=lambda s: None)
    assert [r.status for r in res.runs] == ["trained"]
    assert [(e.source, e.status) for e in res.evaluations] == [
        ("gt", "logged"),
        *((s, "evaluated") for s in SOURCES[1:]),
    ]
    metrics = tracking.setup(proj).get_run(res.runs[0].run_id).data.metrics
    for s in SOURCES[1:]:
        assert f"test-{s}/ads_auc" in metrics and f"test-{s}_icp/ads_auc" in metrics

    out = proj / "reports" / PRESET
    table = pd.read_csv(out / "table_masks.csv", comment="#").set_index("source")
    misses = [table.loc[s, "misses_mean"] for s in SOURCES]
    assert misses == sorted(misses) and misses[-1] > misses[0]
    occ = pd.read_csv(out / "occlusion_masks.csv", comment="#")
    assert {f"{s} + ICP" for s in SOURCES} <= set(occ["series"])
    assert (out / "occlusion_masks.png").exists()

    again = CliRunner().invoke(app, ["ablate-masks", "--preset", PRESET, "--seeds", "1"])
    assert again.exit_code == 0, again.output
    assert "shared-0 0 trained, 1 found; 0 evaluations made, 4 logged before" in again.output
    log = (proj / "runs" / f"ablate-masks-{PRESET}.log").read_text().splitlines()
    assert [line.split("\t")[4] for line in log[4:]] == ["logged"] * 4
