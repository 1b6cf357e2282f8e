"""Headline metrics of a run, and the MLflow UI prepared to compare variants by them
(cloudpose.store.headline): the runs that count, the statistics columns, the views, the
descriptions, dead runs and paths."""

from __future__ import annotations

import json
import math
import re

import pandas as pd
import pytest
from typer.testing import CliRunner

from cloudpose.evaluate import OWN_TEST, log_evaluation
from cloudpose.registry import resolve
from cloudpose.report import ui
from cloudpose.report.stats import format_mean_std, mean_std
from cloudpose.store import liveness, metric_names, tracking

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
    assert ui.headline(DETAIL) == {
        "ads_auc": 0.9,
        "ads_auc_icp": 0.95,
        "rot_sym_lt_10deg": 0.3,
        "trans_lt_1cm": 0.6,
    }
    assert ui.headline({"test/ads_auc": float("nan"), "test/trans_lt_1cm": 0.5}) == {
        "trans_lt_1cm": 0.5
    }


def test_own_test_evaluation_logs_headline_keys_beside_the_detail(tmp_path):
    client, exp = _store(tmp_path)
    run_id = _run(client, exp)
    table = pd.DataFrame({"frame_id": ["0000/000001"], "net_ads": [0.01]})
    log_evaluation(client, run_id, OWN_TEST, table, dict(DETAIL))
    metrics = client.get_run(run_id).data.metrics
    assert {k: metrics[k] for k in ui.HEADLINE} == ui.headline(DETAIL)
    # the summary detail stays as it was; the per-class key moves to the run's detail table
    summary, _ = metric_names.split_detail(dict(DETAIL))
    assert {k: metrics[k] for k in summary} == summary
    assert "test/class/025_mug/ads_auc" not in metrics
    run = client.get_run(run_id)
    reader = metric_names.DetailReader(client, run_id, run.info.artifact_uri, metrics)
    assert reader.get("test/class/025_mug/ads_auc") == pytest.approx(0.8)
    # an evaluation on other data is no headline of the run
    other = _run(client, exp, seed=2)
    log_evaluation(client, other, "real", table, {"real/ads_auc": 0.5, "real_icp/ads_auc": 0.6})
    assert not set(ui.HEADLINE) & set(client.get_run(other).data.metrics)


def test_backfill_logs_runs_stored_before_headlines_once(tmp_path):
    client, exp = _store(tmp_path)
    old = _run(client, exp, metrics=DETAIL)

    def runs():
        return client.search_runs([exp], "")

    assert ui.backfill(client, runs()) == 1
    assert client.get_run(old).data.metrics["ads_auc_icp"] == 0.95
    assert ui.backfill(client, runs()) == 0
    assert len(client.get_metric_history(old, "ads_auc")) == 1
    # a re-evaluation that changed the detail brings the headline along
    client.log_batch(old, metrics=tracking.metric_batch({"test/ads_auc": 0.7}))
    assert ui.backfill(client, runs()) == 1
    assert client.get_run(old).data.metrics["ads_auc"] == 0.7


# -- statistics columns --------------------------------------------------------------------


@pytest.mark.parametrize(
    "values",
    [
        [0.91234, 0.91311, 0.9142],
        [0.45949999, 0.46051, 0.41],  # means and sds near a rounding edge
        [0.125, 0.375],
        [0.3],  # one seed: no sd
        [0.2, float("nan"), 0.4],  # a seed without the figure
    ],
)
def test_statistics_are_the_reports_mean_and_sd_in_percent_as_it_prints_them(values):
    stats = ui.variant_stats({"ads_auc": values}, seeds=len(values))
    assert stats["seeds"] == len(values)
    text = format_mean_std(mean_std(values))
    assert ui.format_stat(stats, "ADS AUC") == text
    mean, *sd = text.split(" ± ")
    assert stats["ADS AUC mean"] == float(mean)
    assert stats.get("ADS AUC sd") == (float(sd[0]) if sd else None)
    assert "ADS AUC ICP mean" not in stats  # no values, no column
    assert ui.format_stat(stats, "ADS AUC ICP") == "–"


def test_statistic_keys_are_mlflow_keys_and_the_chart_filter_matches_only_them():
    keys = ui.stat_keys()
    assert keys[-1] == "seeds" and len(keys) == 2 * len(ui.HEADLINE) + 1
    assert all(re.fullmatch(r"[A-Za-z0-9_\-./ ]+", k) for k in keys)
    comp = ui.GroupComparison("rotation", "smoke", "aaaa", (), None)
    pattern = re.compile(ui.comparison_view(comp)["chartsSearchFilter"])
    assert all(pattern.search(k) for k in keys)
    others = ["ads_auc", "test/ads_auc", "ADS AUC mean/x", "train/loss", "seeds2"]
    assert not any(pattern.search(k) for k in others)


# -- views ----------------------------------------------------------------------------------


def _comparison():
    rows = (
        ui.Row("shared-0", "axis-angle", ("a", "b"), {"ADS AUC mean": 91.3}),
        ui.Row("quaternion", "quaternion", ("c",), {"ADS AUC mean": 91.4}),
        ui.Row("rot6d", "6D"),  # no run yet
    )
    return ui.GroupComparison(
        "rotation", "smoke", "aaaa", rows, "r", report_experiment="4", experiments=("1", "4")
    )


def test_a_comparison_view_groups_by_its_tag_with_the_statistics_by_maximum():
    comp = _comparison()
    state = ui.comparison_view(comp)
    assert state["searchFilter"] == "tags.`rotation.smoke` != ''"
    assert state["groupBy"] == {
        "aggregateFunction": "max",
        "groupByKeys": [{"mode": "tag", "groupByData": "rotation.smoke"}],
    }
    cols = [f"metrics.`{k}`" for k in ui.stat_keys()]
    assert state["selectedColumns"] == cols
    assert state["columnOrder"][1:-1] == cols
    # rotation groups sort by the rotation share, best first
    assert state["orderByKey"] == "metrics.`rot lt 10deg sym mean`" and not state["orderByAsc"]
    # one row per variant with runs, closed; the report run's row open (its name is a link)
    assert state["groupsExpanded"] == {
        "tag.rotation.smoke.shared-0, axis-angle": False,
        "tag.rotation.smoke.quaternion": False,
        f"tag.rotation.smoke.{ui.REPORT_ROW}": True,
    }
    assert ui.Row("quaternion", "quaternion").value == "quaternion"


def test_a_view_over_several_experiments_opens_in_the_multi_experiment_table():
    one = ui.view_path(["4"], "loss.smoke")
    assert one == "#/experiments/4/runs?viewStateShareKey=loss.smoke&workflowType=machine_learning"
    several = ui.view_url("http://h:1/", ["4", "12", "1"], "loss.smoke")
    assert several == (
        "http://h:1/#/compare-experiments/s?experiments=%5B%221%22%2C%2212%22%2C%224%22%5D"
        "&viewStateShareKey=loss.smoke&workflowType=machine_learning"
    )  # sorted as the UI sorts them (as strings)


def test_the_description_starts_with_the_title_and_holds_the_grids_numbers():
    comp = _comparison()
    text = ui.description("Rotation representation: x", [comp], [], "report note")
    first, rest = text.split("\n", 1)
    assert first == "Rotation representation: x"
    assert "| shared-0 | axis-angle | 91.3 | – | – | – | 2 |" in rest
    assert "| rot6d | 6D | – | – | – | – | no run |" in rest
    assert "(#/experiments/4/runs/r/artifacts)" in rest  # the report run's tables and plots
    assert ui.view_path(comp.experiments, comp.key) in rest
    assert rest.endswith("report note")
    assert len(ui.description("t", [comp], [], "x" * 30000)) < 20000  # MLflow's limit


def test_group_titles_differ_in_the_characters_the_experiments_list_shows():
    starts = [t[:25] for t in ui.TITLES.values()]
    assert len(set(starts)) == len(starts)
    assert ui.group_title("newgroup", [ui.Row("a", "A")]) == "Newgroup: A"


# -- dead runs and paths ----------------------------------------------------------------------

H = 3600 * 1000


def test_a_running_run_is_dead_when_stale_or_abandoned_and_never_while_its_folder_is_held():
    now = 100 * H
    assert liveness.dead_reason(now - 1 * H, now) is None  # logged an hour ago
    assert "nothing logged" in liveness.dead_reason(now - 7 * H, now)
    assert "later run" in liveness.dead_reason(now - 1 * H, now, later_start_ms=now - H // 2)
    assert liveness.dead_reason(now - 1 * H, now, later_start_ms=now - 2 * H) is None
    assert liveness.dead_reason(now - 70 * H, now, now - H, folder_locked=True) is None


def test_a_run_folder_held_by_a_process_is_alive(tmp_path):
    from filelock import FileLock

    from cloudpose.store.runs import lock_path

    folder = tmp_path / "runs" / "shared-0" / "smoke" / "seed1-aaaa-bbbb"
    folder.mkdir(parents=True)
    assert not ui._folder_locked(str(folder))
    held = FileLock(str(lock_path(folder)))
    with held:
        assert ui._folder_locked(str(folder))
    assert not ui._folder_locked(str(folder))
    assert not ui._folder_locked(str(tmp_path / "elsewhere"))


def test_run_dir_paths_become_the_projects(tmp_path):
    proj = tmp_path / "proj"
    inside = proj / "runs" / "l2" / "cpu" / "seed1-aa-bb"
    assert ui.relative_run_dir(str(inside), proj) == "runs/l2/cpu/seed1-aa-bb"
    foreign = "/tmp/exp/runs/l2/cpu/seed1-aa-bb"
    assert ui.relative_run_dir(foreign, proj, exists=lambda p: False) == ("runs/l2/cpu/seed1-aa-bb")
    assert ui.relative_run_dir(foreign, proj, exists=lambda p: True) is None  # here
    assert ui.relative_run_dir("runs/l2/cpu/seed1-aa-bb", proj) is None
    assert ui.relative_run_dir("", proj) is None


# -- the whole preparation, on a store ----------------------------------------------------------


@pytest.fixture
def sweep(tmp_path):
    """A store as a sweep leaves it: shared-0 trained in the shared group's experiment, the
    rotation group's variants and a report run in its own, reruns and dead runs."""
    client = tracking.setup(tmp_path)
    exps = {g: tracking.experiment_id(client, g, tmp_path) for g in ("shared", "rotation")}
    clock = iter(range(1_000, 10**9, 1_000))

    def add(group, variant, seed, ads, status="FINISHED", config=None, data="aaaa", run_dir=""):
        fp = config or resolve(variant, "smoke", seed).fingerprint()
        tags = {"variant": variant, "seed": str(seed), "preset": "smoke", "data": data}
        tags.update(config=fp, group=group, run_dir=run_dir)
        run = client.create_run(exps[group], start_time=next(clock), tags=tags)
        metrics = {"test/ads_auc": ads, "test_icp/ads_auc": ads + 0.02}
        metrics.update({"test/rot_sym_lt_10deg": ads / 2, "test/trans_lt_1cm": 0.5})
        if status != "RUNNING":
            client.log_batch(run.info.run_id, metrics=tracking.metric_batch(metrics))
            client.set_terminated(run.info.run_id, status)
        return run.info.run_id

    ids = {
        "s0-1-old": add("shared", "shared-0", 1, 0.80),
        "s0-1": add("shared", "shared-0", 1, 0.90),
        "s0-2": add("shared", "shared-0", 2, 0.92),
        "s0-other": add("shared", "shared-0", 3, 0.99, config="0123456789abcdef"),
        "q-1": add("rotation", "quaternion", 1, 0.85),
        "q-2": add("rotation", "quaternion", 2, 0.89),
        "dead": add("rotation", "quaternion", 3, 0, "RUNNING", run_dir="/gone/runs/q/smoke/s3"),
    }
    report = client.create_run(
        exps["rotation"],
        tags={"kind": "report", "report_group": "rotation", "report_preset": "smoke"},
        run_name="report/rotation/smoke",
    )
    client.set_tag(report.info.run_id, "mlflow.note.content", "rotation (smoke preset): Table IV")
    client.set_terminated(report.info.run_id, "FINISHED")
    ids["report"] = report.info.run_id
    return client, exps, ids, add


def _prepare(client, hours_later=10):
    return ui.prepare_ui(client, now_ms=int(1e6) + hours_later * H)


def test_prepare_ui_builds_each_comparison_from_the_reports_runs(sweep, tmp_path):
    client, exps, ids, _ = sweep
    prepared = _prepare(client)
    comps = {c.key: c for c in prepared.comparisons}
    assert set(comps) == {
        "shared.smoke",
        "rotation.smoke",
        "loss.smoke",
        "symmetry.smoke",
        "centre.smoke",
    }
    rot = comps["rotation.smoke"]
    rows = {r.variant: r for r in rot.rows}
    # the reference, logged in another experiment, is in the rotation view; newest run per seed
    assert set(rows["shared-0"].run_ids) == {ids["s0-1"], ids["s0-2"]}
    assert set(rows["quaternion"].run_ids) == {ids["q-1"], ids["q-2"]}
    assert rows["rot6d"].run_ids == ()
    assert rot.experiments == tuple(sorted(exps.values())) and rot.report_run == ids["report"]
    # the statistics are the report's: mean and sample std of the newest runs, in percent
    want = format_mean_std(mean_std([0.90, 0.92]))
    assert ui.format_stat(rows["shared-0"].stats, "ADS AUC") == want
    run = client.get_run(ids["s0-1"]).data
    assert run.metrics["ADS AUC mean"] == float(want.split(" ± ")[0])
    assert run.metrics["seeds"] == 2
    assert run.tags["rotation.smoke"] == "shared-0, axis-angle"
    assert run.tags["shared.smoke"] == "shared-0, none"
    # the view's filter finds the counted runs and the report run, nothing else
    found = client.search_runs(list(exps.values()), "tags.`rotation.smoke` != ''")
    assert {r.info.run_id for r in found} == {
        *rot.rows[0].run_ids,
        *rot.rows[1].run_ids,
        ids["report"],
    }
    assert client.get_run(ids["report"]).data.tags["rotation.smoke"] == ui.REPORT_ROW
    # the view is on every experiment the multi-experiment table may read it from
    for exp in exps.values():
        state = json.loads(
            json.loads(client.get_experiment(exp).tags["mlflow.sharedViewState.rotation.smoke"])[
                "state"
            ]
        )
        assert state == json.loads(json.dumps(ui.comparison_view(rot)))
    # the description: a title in words, the grid's numbers, the report's note
    note = client.get_experiment(exps["rotation"]).tags["mlflow.note.content"]
    assert note.split("\n", 1)[0] == ui.TITLES["rotation"]
    assert f"| shared-0 | axis-angle | {want} |" in note
    assert note.endswith("rotation (smoke preset): Table IV")


def test_prepare_ui_tags_superseded_runs_and_leaves_them_out(sweep):
    client, _, ids, add = sweep
    prepared = _prepare(client)
    assert prepared.superseded == 2
    old = client.get_run(ids["s0-1-old"]).data.tags
    assert old["superseded"].startswith("a newer run of shared-0 seed 1 counts instead: ")
    assert ids["s0-1"] in old["superseded"]
    assert "another config" in client.get_run(ids["s0-other"]).data.tags["superseded"]
    assert not {k for k in old if k.endswith(".smoke")}
    # a newer rerun of a counted seed: the earlier one leaves the view, its statistics NaN
    newer = add("rotation", "quaternion", 1, 0.95)
    _prepare(client)
    was = client.get_run(ids["q-1"]).data
    assert "rotation.smoke" not in was.tags and "newer run" in was.tags["superseded"]
    assert math.isnan(was.metrics["ADS AUC mean"])
    now = client.get_run(newer).data
    assert now.tags["rotation.smoke"] == "quaternion" and "superseded" not in now.tags
    assert now.metrics["ADS AUC mean"] == float(
        format_mean_std(mean_std([0.95, 0.89])).split(" ± ")[0]
    )


def test_prepare_ui_marks_dead_runs_killed_and_writes_nothing_the_second_time(sweep):
    client, _, ids, _ = sweep
    assert _prepare(client, hours_later=1).killed == []  # it may still be training
    prepared = _prepare(client, hours_later=10)
    assert [name for name, _ in prepared.killed] == [client.get_run(ids["dead"]).info.run_name]
    dead = client.get_run(ids["dead"])
    assert dead.info.status == "KILLED" and dead.info.end_time == dead.info.start_time
    assert "nothing logged" in dead.data.tags[liveness.KILLED_TAG]
    assert dead.data.tags["run_dir"] == "runs/q/smoke/s3"  # not this machine's folder
    again = _prepare(client, hours_later=20)
    assert again.written == 0 and again.killed == []


def test_mlflow_ui_no_serve_prints_each_comparison_view(sweep, tmp_path, monkeypatch):
    from cloudpose.cli import app

    client, exps, ids, _ = sweep
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, ["mlflow-ui", "--no-serve", "--port", "5123"])
    assert res.exit_code == 0, res.output
    url = ui.view_url("http://127.0.0.1:5123", sorted(exps.values()), "rotation.smoke")
    assert re.search(r"rotation\.smoke\s+2 variants\s+4 runs\s+" + re.escape(url), res.output)
    assert "2 evaluated runs that the report does not count" in res.output
    # started in 1970 by the test's clock, never logged since
    assert f"marked KILLED: {client.get_run(ids['dead']).info.run_name} (" in res.output


def test_the_report_notes_first_line_is_plain_text(tmp_path):
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
    assert set(ui.HEADLINE) <= set(metrics)
