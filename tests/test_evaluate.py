"""Evaluation: the run's own test set and the real YCB-Video frame."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cloudpose.evaluate import evaluate
from cloudpose.metrics import SUMMARY_KEYS

DATA = Path(__file__).parent / "data"


@pytest.fixture
def project(smoke_project):
    return smoke_project


@pytest.mark.slow
def test_evaluate_own_test_set_logs_table_and_metrics(project):
    proj, out = project
    ev = evaluate(str(out.run_dir), project_dir=proj, progress=False)
    df = ev.table
    assert len(df) > 0
    for method in ("net", "icp"):
        for key in ("ad", "ads", "rot_err_deg", "trans_err"):
            col = df[f"{method}_{key}"]
            assert np.all(np.isinf(col[df.miss])) and np.all(np.isfinite(col[~df.miss]))
        assert np.all(df[f"{method}_ads"] <= df[f"{method}_ad"] + 1e-12)
    for prefix in ("test", "test_icp"):
        for key in SUMMARY_KEYS:
            assert 0.0 <= ev.metrics[f"{prefix}/{key}"] <= 1.0
            assert 0.0 <= ev.metrics[f"{prefix}/class_mean/{key}"] <= 1.0

    from cloudpose.store import tracking

    client = tracking.setup(proj)
    run = client.get_run(out.run_id)
    assert run.data.metrics["test/ads_auc"] == pytest.approx(ev.metrics["test/ads_auc"])
    arts = [a.path for a in client.list_artifacts(out.run_id, "eval/test")]
    assert arts == ["eval/test/instances.parquet", "eval/test/per_class.csv"]
    # the per-class detail is the table, read back as the keys it was computed as
    from cloudpose.report.runs import RunRecord
    from cloudpose.store.metric_names import detail_kind

    assert not [k for k in run.data.metrics if detail_kind(k)]
    info = (out.run_id, "shared-0", 1, "smoke", "d", "c", 0, {}, dict(run.data.metrics))
    record = RunRecord(*info, artifact_uri=run.info.artifact_uri, client=client)
    per_class = {k: v for k, v in ev.metrics.items() if detail_kind(k) == "class"}
    assert per_class and all(
        record.metric(k) == pytest.approx(v, rel=1e-12) for k, v in per_class.items()
    )


NEW_RUN_METRICS = 120
"""The most metric keys a new run has, trained and evaluated on its test set and on the real
frames: training's curves (train/, val/, fit/, time/), the pooled and class-mean summaries of
each evaluation without and with ICP, the headline keys; per-class and per-video detail are
tables (``eval/NAME/per_class.csv``, ``per_video.csv``)."""


@pytest.mark.slow
def test_a_new_run_logs_at_most_a_hundred_and_twenty_metric_keys(tmp_path, smoke_data):
    from cloudpose.evaluate import evaluate_real
    from tests.conftest import train_smoke_project

    proj, out = train_smoke_project(tmp_path, smoke_data)
    evaluate(str(out.run_dir), project_dir=proj, progress=False)
    real = evaluate_real(str(out.run_dir), project_dir=proj, progress=False)
    assert any("/video/" in k for k in real.metrics)  # computed, and logged as a table
    from cloudpose.store import tracking

    client = tracking.setup(proj)
    keys = client.get_run(out.run_id).data.metrics
    assert 0 < len(keys) <= NEW_RUN_METRICS, sorted(keys)
    assert not [k for k in keys if "/class/" in k or "/video/" in k]
    arts = {a.path for a in client.list_artifacts(out.run_id, "eval/real")}
    assert {"eval/real/per_class.csv", "eval/real/per_video.csv"} <= arts


@pytest.mark.slow
def test_evaluate_on_the_real_ycb_frame(project):
    proj, out = project
    ev = evaluate(
        str(out.run_dir),
        data=str(DATA / "ycb_real"),
        frames="all",
        project_dir=proj,
        progress=False,
    )
    df = ev.table
    assert sorted(df["class"]) == ["009_gelatin_box", "025_mug", "061_foam_brick"]
    assert not df.miss.any()
    assert np.all(np.isfinite(df[["net_ad", "net_ads", "icp_ad", "icp_ads"]].to_numpy()))
    assert ev.name.startswith("ycb_real-all-") and f"{ev.name}_icp/ads_auc" in ev.metrics
    # The mug is partly hidden by the foam brick in this frame (docs/design.md occlusion factor).
    occ = dict(zip(df["class"], df["occlusion"], strict=True))
    assert occ["025_mug"] > 0.1 and occ["009_gelatin_box"] < 0.05


@pytest.mark.slow
def test_other_icp_settings_log_beside_the_runs_own(project):
    """``icp_overrides`` evaluates under its own name: the network's estimates are the same,
    and from 12 starts each object's fit is at least the one-start fit."""
    proj, out = project
    own = evaluate(str(out.run_dir), project_dir=proj, progress=False, log=False)
    many = evaluate(
        str(out.run_dir),
        project_dir=proj,
        progress=False,
        icp_overrides={"starts": 12},
        log=False,
    )
    assert (own.name, many.name) == ("test", "test-starts12")
    np.testing.assert_array_equal(many.table["net_ads"], own.table["net_ads"])
    fit, fit_own = many.table["icp_fitness"], own.table["icp_fitness"]
    ok = fit_own.notna()
    assert (fit[ok] >= fit_own[ok]).all()


def test_icp_label_names_how_settings_differ():
    from cloudpose.evaluate import icp_label
    from cloudpose.refine import ICPSettings, schedule_for

    own = ICPSettings()
    assert icp_label(ICPSettings(fallback=True), own) == "fallback"
    assert icp_label(own, ICPSettings(fallback=True)) == "nofallback"
    assert icp_label(ICPSettings(starts=24), own) == "starts24"
    assert icp_label(ICPSettings(fallback=True, starts=60), own) == "fallback-starts60"
    assert icp_label(ICPSettings(iterations=3), own) == "other"
    wide = ICPSettings(**schedule_for(0.05))
    assert icp_label(wide, own) == "radius50mm"
    assert icp_label(dataclasses.replace(wide, starts=24, select="depth"), own) == (
        "starts24-selectdepth-radius50mm"
    )
    assert icp_label(own, wide) == "radius10mm"
    assert icp_label(ICPSettings(max_distance=0.05), own) == "other"  # not schedule_for's
    assert icp_label(ICPSettings(max_distance=0.002), own) == "other"


@pytest.mark.slow
def test_a_downloaded_checkpoint_is_removed_after_the_evaluation(project, tmp_path, monkeypatch):
    """A run whose folder lacks model.pt is evaluated from its MLflow artifact: the download
    goes into a temporary folder that is removed afterwards (it was left in /tmp, 6.5 MB a call)."""
    import tempfile

    proj, out = project
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    model = out.run_dir / "model.pt"
    aside = out.run_dir / "model.pt.aside"
    model.rename(aside)
    try:
        ev = evaluate(out.run_id, project_dir=proj, progress=False, icp=False, log=False)
    finally:
        aside.rename(model)
    assert len(ev.table) > 0 and "downloaded" in ev.source
    assert list(tmp.iterdir()) == []


def test_a_torn_model_of_a_run_folder_says_how_to_rewrite_it(smoke_run, tmp_path, monkeypatch):
    import shutil

    src, ref = smoke_run
    proj = tmp_path / "copy"
    shutil.copytree(src, proj, symlinks=True)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    run_dir = proj / ref.run_dir.relative_to(src)
    (run_dir / "model.pt").write_bytes(b"")
    with pytest.raises(ValueError, match=r"model\.pt is not .*rerun the run's train command"):
        evaluate(str(run_dir), project_dir=proj, progress=False, log=False)


def test_metric_names_import_without_torch_and_name_each_method():
    """The reports read the evaluation names at the top of their modules: the module of the
    names loads neither torch nor the evaluation."""
    import subprocess
    import sys

    code = (
        "import sys; import cloudpose.store.metric_names; "
        "print(sorted(m for m in ('torch', 'cloudpose.evaluate') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    from cloudpose.store import metric_names as names

    assert names.method_prefixes("real") == {"net": "real", "icp": "real_icp"}
    assert names.own_test_name() == names.OWN_TEST == "test"
    assert names.own_test_name("degraded-medium") == "test-degraded-medium"
    name = names.data_evaluation_name(DATA / "ycb_real", "all", "0123456789abcdef0123")
    assert name == "ycb_real-all-0123456789"


@pytest.mark.slow
def test_an_ensemble_keeps_one_members_refinement_per_object(tmp_path, smoke_data):
    """Two seeds of the smoke preset: each object's result after ICP is one member's own
    one-start refinement, the one with the best score (fitness: never below the other's);
    logged under its own name with the members' run ids; a network of another preset and a
    run given twice are refused."""
    from cloudpose.evaluate import evaluate_real
    from cloudpose.registry import resolve
    from cloudpose.store import tracking
    from cloudpose.suite.pipeline import train_run
    from tests.conftest import make_project

    mp = pytest.MonkeyPatch()
    try:
        proj = make_project(tmp_path / "proj", smoke_data, mp)
        a, b = (train_run(resolve("shared-0", "smoke", seed=s), project_dir=proj, progress=False)
                for s in (1, 2))  # fmt: skip
    finally:
        mp.undo()
    kw = dict(project_dir=proj, progress=False)
    one = [evaluate_real(r.run_id, log=False, **kw).table for r in (a, b)]
    ens = evaluate_real(a.run_id, ensemble=[b.run_id], **kw)
    assert ens.name == "real-ensemble2" and f"{ens.name}_icp/ads_auc" in ens.metrics
    t = ens.table
    member = t["ensemble_member"].to_numpy()
    assert set(member[~t.miss]) == {0, 1} and (member[t.miss] == -1).all()  # both chosen
    for k in (0, 1):
        rows = member == k
        np.testing.assert_allclose(t.loc[rows, "icp_ads"], one[k].loc[rows, "icp_ads"], atol=1e-12)
        np.testing.assert_allclose(t.loc[rows, "net_ads"], one[k].loc[rows, "net_ads"], atol=1e-12)
    valid = ~t.miss.to_numpy()
    fits = np.stack([one[0]["icp_fitness"], one[1]["icp_fitness"]])[:, valid]
    assert (t["icp_fitness"].to_numpy()[valid] >= fits.max(axis=0) - 1e-12).all()
    tags = tracking.setup(proj).get_run(a.run_id).data.tags
    assert tags[f"eval/{ens.name}/ensemble"] == f"{a.run_id},{b.run_id}"
    with pytest.raises(ValueError, match="in the ensemble already"):
        evaluate_real(a.run_id, ensemble=[a.run_id], log=False, **kw)
    with pytest.raises(ValueError, match=r"differs from the first network's in data\."):
        evaluate_real(a.run_id, ensemble=["pretrained"], log=False, **kw)
    with pytest.raises(ValueError, match="drop --refine none"):
        evaluate_real(a.run_id, ensemble=[b.run_id], icp=False, log=False, **kw)


def test_an_ensemble_refuses_a_network_twice_by_any_name():
    """The shipped network and the MLflow run it came from are one network: named together, or
    one of them twice, they are refused, and the option that named the second is in the
    message; another run of the same preset joins, and a network of other data does not."""
    from cloudpose.infer import load_checkpoint
    from cloudpose.methods import LoadedNetwork, check_ensemble
    from cloudpose.store.pretrained import PRETRAINED, shipped

    model, cfg = load_checkpoint(shipped().path)
    run_id = shipped().info["run_id"]

    def nets(names, loaded):
        return [
            LoadedNetwork(n, rid, m, c, "") for n, (rid, m, c) in zip(names, loaded, strict=True)
        ]

    ids = check_ensemble(
        nets([PRETRAINED, "other"], [(None, model, cfg), ("f" * 32, model, cfg)]), "--run"
    )
    assert ids[0] == f"{run_id}:{shipped().info['sha256'][:12]}" and ids[1] == "f" * 32
    pairs = {  # the shipped network, then its run; the run, then the shipped network
        "--run": ([PRETRAINED, "second"], [(None, model, cfg), (run_id, model, cfg)]),
        "--ensemble": (["first", PRETRAINED], [(run_id, model, cfg), (None, model, cfg)]),
    }
    for option, (names, loaded) in pairs.items():
        with pytest.raises(ValueError, match=rf"^{option} {names[1]}: run {run_id} is in the en"):
            check_ensemble(nets(names, loaded), option)
    other = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, n_fps=2 * cfg.data.n_fps))
    with pytest.raises(ValueError, match=r"^--run second: .* differs .* in data\.n_fps"):
        check_ensemble(
            nets([PRETRAINED, "second"], [(None, model, cfg), ("f" * 32, model, other)]), "--run"
        )
