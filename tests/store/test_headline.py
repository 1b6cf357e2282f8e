"""Headline metrics of a run and the MLflow UI view that compares variants by them."""

from __future__ import annotations

import json

import pandas as pd
import pytest
from typer.testing import CliRunner

from cloudpose.evaluate import OWN_TEST, log_evaluation
from cloudpose.store import headline, tracking

DETAIL = {
    "test/ads_auc": 0.9,
    "test_icp/ads_auc": 0.95,
    "test/rot_sym_lt_10deg": 0.3,
    "test/trans_lt_1cm": 0.6,
    "test/class/025_mug/ads_auc": 0.8,
}


def _store(tmp_path):
    client = tracking.setup(tmp_path)
    return client, tracking.experiment_id(client, "shared", tmp_path)


def _run(client, exp, variant="shared-1", seed=1, metrics=None):
    run = client.create_run(exp, tags={"variant": variant, "preset": "smoke", "seed": str(seed)})
    if metrics:
        client.log_batch(run.info.run_id, metrics=tracking.metric_batch(metrics))
    client.set_terminated(run.info.run_id, "FINISHED")
    return run.info.run_id


def test_headline_copies_the_detailed_keys_and_skips_missing_or_nan():
    assert headline.headline(DETAIL) == {
        "ads_auc": 0.9,
        "ads_auc_icp": 0.95,
        "rot_sym_lt_10deg": 0.3,
        "trans_lt_1cm": 0.6,
    }
    assert headline.headline({"test/ads_auc": float("nan"), "test/trans_lt_1cm": 0.5}) == {
        "trans_lt_1cm": 0.5
    }


def test_own_test_evaluation_logs_headline_keys_beside_the_detail(tmp_path):
    client, exp = _store(tmp_path)
    run_id = _run(client, exp)
    table = pd.DataFrame({"frame_id": ["0000/000001"], "net_ads": [0.01]})
    log_evaluation(client, run_id, OWN_TEST, table, dict(DETAIL))
    metrics = client.get_run(run_id).data.metrics
    assert {k: metrics[k] for k in headline.HEADLINE} == headline.headline(DETAIL)
    assert {k: metrics[k] for k in DETAIL} == DETAIL  # the detail stays as it was
    # an evaluation on other data is no headline of the run
    other = _run(client, exp, seed=2)
    log_evaluation(client, other, "real", table, {"real/ads_auc": 0.5, "real_icp/ads_auc": 0.6})
    assert not set(headline.HEADLINE) & set(client.get_run(other).data.metrics)


def test_backfill_logs_runs_stored_before_headlines_once(tmp_path):
    client, exp = _store(tmp_path)
    old = _run(client, exp, metrics=DETAIL)
    _run(client, exp, variant="shared-2", metrics={"val/ads_auc": 0.5})  # never evaluated
    runs, changed = headline.backfill(client, exp)
    assert [r.info.run_id for r in runs] == [old] and changed == 1
    assert client.get_run(old).data.metrics["ads_auc_icp"] == 0.95
    runs, changed = headline.backfill(client, exp)
    assert len(runs) == 1 and changed == 0
    assert len(client.get_metric_history(old, "ads_auc")) == 1
    # a re-evaluation that changed the detail brings the headline along
    client.log_batch(old, metrics=tracking.metric_batch({"test/ads_auc": 0.7}))
    assert headline.backfill(client, exp)[1] == 1
    assert client.get_run(old).data.metrics["ads_auc"] == 0.7


def test_saved_view_groups_by_variant_with_headline_columns_and_is_written_once(tmp_path):
    client, exp = _store(tmp_path)
    _run(client, exp, metrics=DETAIL)
    _run(client, exp, seed=2, metrics=DETAIL)
    prepared = headline.prepare_ui(client)
    assert [(p.name, p.runs, p.backfilled) for p in prepared] == [("cloudpose-shared", 2, 2)]
    tags = client.get_experiment(exp).tags
    envelope = json.loads(tags["mlflow.sharedViewState." + headline.VIEW_KEY])
    assert envelope["name"] == headline.VIEW_NAME
    state = json.loads(envelope["state"])
    assert state["selectedColumns"] == [f"metrics.`{k}`" for k in headline.HEADLINE]
    assert state["groupBy"]["aggregateFunction"] == "average"
    assert [k["groupByData"] for k in state["groupBy"]["groupByKeys"]] == ["variant", "preset"]
    assert state["groupsExpanded"] == {"tag.variant.shared-1,tag.preset.smoke": False}
    assert tags["mlflow.experimentKind"] == "custom_model_development"
    assert not headline.install_view(
        client, client.get_experiment(exp), [("shared-1", "smoke")]
    )  # current: nothing written
    url = headline.view_url("http://127.0.0.1:5000", exp)
    assert url == (
        f"http://127.0.0.1:5000/#/experiments/{exp}/runs?viewStateShareKey=variants"
        "&workflowType=machine_learning"
    )


def test_mlflow_ui_no_serve_prints_each_experiments_view(tmp_path, monkeypatch):
    from cloudpose.cli import app

    client, exp = _store(tmp_path)
    _run(client, exp, metrics=DETAIL)
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, ["mlflow-ui", "--no-serve", "--port", "5123"])
    assert res.exit_code == 0, res.output
    assert "logged now for 1 runs" in res.output
    assert headline.view_url("http://127.0.0.1:5123", exp) in res.output
    again = CliRunner().invoke(app, ["mlflow-ui", "--no-serve"])
    assert "logged now" not in again.output


def test_experiment_description_starts_with_one_plain_line(tmp_path):
    from cloudpose.report.build import _summary_note

    table = tmp_path / "table3_shared_layers.md"
    table.write_text("# Table III: sharing layers (%)\n\n| a | b |\n|---|---|\n| 1 | 2 |\n")

    class Prov:
        def line(self):
            return "made by `cloudpose report`"

    note = _summary_note("shared", "cpu", [table], Prov())
    first, rest = note.split("\n", 1)
    assert first.startswith("shared (cpu preset): Table III: sharing layers (%)")
    assert not set(first) & set("*`#|")
    assert "| 1 | 2 |" in rest and "made by" in rest


@pytest.mark.slow
def test_a_trained_and_evaluated_run_has_its_headline_metrics(smoke_project):
    from cloudpose.evaluate import evaluate

    proj, out = smoke_project
    ev = evaluate(str(out.run_dir), project_dir=proj, progress=False)
    metrics = tracking.setup(proj).get_run(out.run_id).data.metrics
    assert metrics["ads_auc"] == pytest.approx(ev.metrics["test/ads_auc"])
    assert metrics["ads_auc_icp"] == pytest.approx(ev.metrics["test_icp/ads_auc"])
    assert set(headline.HEADLINE) <= set(metrics)
