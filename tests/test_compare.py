"""``cloudpose compare``: the network and a classical method on the same segments, refined by the
same ICPs; the figures are those of ``evaluate`` and ``baseline`` on the same frames, a call
resumes from its folder, and a folder of another comparison is refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.conftest import DATA, cli, one_line_error

REAL = DATA / "ycb_real"  # one real annotated frame
QUICK = ["--refine", "starts=1,select=fitness,radius=0.05"]


def test_ray_split_separates_depth_from_a_sideways_centre():
    from cloudpose.studies.compare import ray_split

    t_gt = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.0, 2.0]])
    err = np.array([[0.0, 0.0, -0.01], [0.0, 0.02, 0.0], [0.003, 0.004, 0.012]])
    along, across = ray_split(t_gt + err, t_gt)
    np.testing.assert_allclose(along, [0.01, 0.0, 0.012], atol=1e-12)
    np.testing.assert_allclose(across, [0.0, 0.02, 0.005], atol=1e-12)
    np.testing.assert_allclose(np.hypot(along, across), np.linalg.norm(err, axis=1), atol=1e-12)


def test_refinements_are_the_papers_and_the_recipe():
    from cloudpose.refine import ICPSettings
    from cloudpose.studies.compare import refinements

    paper, wide = refinements(24, "depth", 0.18)
    assert paper.settings == ICPSettings() and paper.name == "icp"
    assert (wide.settings.starts, wide.settings.select) == (24, "depth")
    assert wide.settings.max_distance == pytest.approx(0.18)
    assert wide.name == "icp-starts24-selectdepth-radius180mm"
    assert [r.name for r in refinements(1, "fitness", 0.01)] == ["icp"]  # the paper's only
    # one start of one network has nothing to select among: the paper's, not a second copy
    assert [r.name for r in refinements(1, "depth", 0.01)] == ["icp"]
    # an ensemble's selection chooses among its networks
    assert [r.name for r in refinements(1, "depth", 0.01, networks=2)] == ["icp", "icp-selectdepth"]


def test_the_plan_counts_each_network_of_an_ensemble():
    """The refinements' time in the plan grows with the networks refined, the methods' not."""
    import re

    from cloudpose.studies.compare import CONTROL, ICP_SECONDS, NETWORK, plan, refinements

    class Segs:
        valid = np.ones(1000, dtype=bool)

        def __len__(self):
            return 1000

    wide = refinements(24, "depth", 0.18)[1]
    todo = {NETWORK: [wide], CONTROL: [wide]}
    one_ref = 1000 * ICP_SECONDS * wide.settings.starts * wide.settings.iterations
    for networks in (1, 4):
        minutes = re.search(r"about (\d+) min", plan(Segs(), {}, todo, {NETWORK: networks}))
        assert minutes and int(minutes[1]) == round((networks + 1) * one_ref / 60)


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    """(project folder, comparison folder, CLI output) of the shipped network against FPFH +
    RANSAC and the control of no estimate on the one real frame."""
    proj = tmp_path_factory.mktemp("compare")
    out = proj / "cmp"
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(proj)
        args = ["--data", str(REAL), "--frames", "all", "--method", "fpfh", "--method", "none"]
        res = cli("compare", *args, *QUICK, "--out", str(out), "--no-progress")
    assert res.exit_code == 0, res.output
    return proj, out, res.output


def _table(out: Path, name: str) -> pd.DataFrame:
    return pd.read_csv(out / "tables" / f"{name}.csv", dtype={"frame_id": str})


def test_report_holds_every_method_and_stage(compared):
    _, out, output = compared
    plan = "compare: 3 instances; fpfh estimates: 3 of 3 to compute; 6 refinement(s) to compute"
    assert output.splitlines()[0] == plan  # the plan, before any work
    assert f"report: {out / 'compare.md'}" in output
    text = (out / "compare.md").read_text()
    assert "`cloudpose compare --data" in text and "--method fpfh" in text
    rows = [line for line in text.splitlines() if line.startswith("| network")]
    assert rows[0].startswith("| network |") and len(rows) >= 3
    for label in ("FPFH + RANSAC + ICP (paper)", "FPFH + RANSAC + ICP (1 start, by fitness, 5 cm)"):
        assert f"| {label} |" in text
    assert "## Paired: the network against each method" in text
    summary = pd.read_csv(out / "compare.csv")
    assert len(summary) == 9  # 3 methods x (estimate + 2 refinements)
    assert "| no estimate + ICP (paper) |" in text
    assert summary[["ads_auc", "rot_sym_lt_10deg", "trans_lt_1cm"]].notna().all().all()
    done = summary[summary["method"] != "none"]
    assert (done["ads_auc"] > 0.5).all()  # a real frame the shipped network and FPFH can do
    assert (out / "compare.png").stat().st_size > 10_000
    diffs = pd.read_csv(out / "compare_paired.csv")
    assert len(diffs) == 2 * 3 * 3  # (fpfh, none) x stages x metrics
    d = diffs.set_index(["against", "stage", "metric"])["diff"]
    s = summary.set_index(["method", "stage"])["ads_auc"]
    for stage in ("estimate", "icp", "icp-radius50mm"):  # the paired difference is the pooled one
        want = s[("network", stage)] - s[("fpfh", stage)]
        assert d[("fpfh", stage, "ads_auc")] == pytest.approx(want, abs=1e-9)
    methods = ("network", "fpfh", "none")
    tables = [_table(out, f"{m}-{r}") for m in methods for r in ("icp", "icp-radius50mm")]
    keys = [list(zip(t["frame_id"], t["instance"], strict=True)) for t in tables]
    assert all(k == keys[0] for k in keys)  # every method on the same segments


def test_figures_are_evaluates_and_the_baselines(compared):
    """The network after the paper's ICP is ``evaluate``'s, FPFH + RANSAC's estimate and its
    refinement are ``baseline``'s, on the same frames."""
    from cloudpose.evaluate import evaluate
    from cloudpose.infer import load_checkpoint
    from cloudpose.store.pretrained import shipped
    from cloudpose.studies.baseline_runs import run_baseline

    proj, out, _ = compared
    ours = evaluate("pretrained", data=str(REAL), frames="all", project_dir=proj, log=False,
                    progress=False).table  # fmt: skip
    mine = _table(out, "network-icp")
    for col in ("net_ads", "icp_ads", "icp_rot_sym_err_deg", "icp_trans_err"):
        np.testing.assert_allclose(mine[col], ours[col], rtol=0, atol=1e-6, err_msg=col)
    _, cfg = load_checkpoint(shipped().path)
    theirs = run_baseline("fpfh", cfg.preset, seed=1, project_dir=proj, data=REAL, frames="all",
                          log=False, progress=False).table  # fmt: skip
    fpfh = _table(out, "fpfh-icp")
    for col in ("net_ads", "net_rot_sym_err_deg", "icp_ads", "icp_trans_err"):
        np.testing.assert_allclose(fpfh[col], theirs[col], rtol=0, atol=1e-6, err_msg=col)
    # the translation error's two parts make it whole
    for t in (mine, fpfh):
        ok = np.isfinite(t["icp_trans_err"])
        np.testing.assert_allclose(np.hypot(t["icp_trans_along"], t["icp_trans_across"])[ok],
                                   t["icp_trans_err"][ok], rtol=1e-6)  # fmt: skip


def test_a_second_call_reads_what_the_first_computed(compared, monkeypatch):
    import cloudpose.methods as methods
    import cloudpose.studies.compare as compare

    proj, out, _ = compared
    before = (out / "compare.csv").read_text()

    def fail(*args, **kwargs):
        raise AssertionError("computed again")

    monkeypatch.setattr(compare, "_refine", fail)
    monkeypatch.setattr(methods, "estimate_all", fail)
    monkeypatch.chdir(proj)
    done = compare.run_compare(out, data=REAL, frames="all", methods=["fpfh", "none"], starts=1,
                               select="fitness", radius=0.05, progress=False)  # fmt: skip
    from cloudpose.report.compare import render

    render(done, "cloudpose compare")
    assert (out / "compare.csv").read_text() == before
    assert len(done.tables) == 6
    # another folder on the same frames computes its own tables, and reuses FPFH's estimates
    monkeypatch.undo()
    monkeypatch.setattr(methods, "estimate_all", fail)
    monkeypatch.chdir(proj)
    other = compare.run_compare(proj / "other", data=REAL, frames="all", methods=["fpfh"],
                                starts=1, select="fitness", radius=0.05, progress=False)  # fmt: skip
    pd.testing.assert_frame_equal(
        other.tables[("fpfh", "icp")], done.tables[("fpfh", "icp")], check_dtype=False
    )


def test_unreadable_timings_are_computed_again(compared, tmp_path, monkeypatch, capsys):
    import shutil

    import cloudpose.studies.compare as compare

    proj, out, _ = compared
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    (copy / "tables" / "icp_ms.json").write_text('{"network-icp": 1.')  # a torn write
    monkeypatch.chdir(proj)
    done = compare.run_compare(copy, data=REAL, frames="all", methods=["fpfh"], starts=1,
                               select="fitness", radius=0.05, progress=False)  # fmt: skip
    assert "warning:" in capsys.readouterr().out
    timing = json.loads((copy / "tables" / "icp_ms.json").read_text())
    assert {"network-icp", "fpfh-icp-radius50mm", "fpfh-estimate"} <= set(timing)
    first = _table(out, "network-icp")
    np.testing.assert_allclose(done.tables[("network", "icp")]["icp_ads"], first["icp_ads"])


def test_the_default_folder_is_one_per_data_and_networks(compared, monkeypatch):
    proj = compared[0]
    monkeypatch.chdir(proj)
    res = cli("compare", "--data", str(REAL), "--frames", "all", "--method", "none", *QUICK,
              "--no-progress")  # fmt: skip
    assert res.exit_code == 0, res.output
    made = sorted((proj / "runs" / "compare").glob("*/*/compare.md"))
    assert len(made) == 1 and made[0].parent.parent.name.startswith("ycb_real-all-")


def test_a_folder_of_another_comparison_is_refused(compared, monkeypatch):
    proj, out, _ = compared
    monkeypatch.chdir(proj)
    args = ["--data", str(REAL), "--frames", "all", "--method", "fpfh", "--seed", "2", *QUICK]
    one_line_error(cli("compare", *args, "--out", str(out), "--no-progress"), "seed", str(out))


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["--method", "sift"], ["--method 'sift'", "fpfh"]),
        (["--refine", "starts=5"], ["--refine starts=5"]),
        (["--refine", "radius=2"], ["--refine radius=2", "0.5 m"]),
        (["--run", "pretrained", "--run", "pretrained"], ["each at most once"]),
    ],
)
def test_bad_options_are_one_line(args, needles):
    one_line_error(cli("compare", "--data", str(REAL), *args, "--no-progress"), *needles)


def test_an_ensemble_of_one_network_twice_is_that_network(compared, tmp_path, monkeypatch):
    """Two copies of the shipped network as an ensemble: estimates cached per member, and the
    refinement kept per object is the one network's own."""
    import cloudpose.infer as infer
    import cloudpose.studies.compare as compare
    from cloudpose.data.dataset import folder_segments
    from cloudpose.data.layout import open_dataset
    from cloudpose.methods import LoadedNetwork, Network
    from cloudpose.store.pretrained import shipped

    proj, out, _ = compared
    net = LoadedNetwork.from_checkpoint(shipped().path)
    cfg = net.config
    dataset = open_dataset(REAL)
    segs = folder_segments(dataset, "all", cfg.data, proj, progress=False)
    pair = compare._network(segs, Network((net, net)), tmp_path / "n.npz")
    assert len(pair.estimates) == 2 and pair.label == "network (2 networks)"
    monkeypatch.setattr(infer, "estimate_poses", lambda *a, **k: pytest.fail("estimated again"))
    again = compare._network(segs, Network((net, net)), tmp_path / "n.npz")
    np.testing.assert_array_equal(again.estimates[1].R, pair.estimates[1].R)  # read back
    paper = compare.refinements(1, "fitness", 0.01)[0]
    table, _ = compare._refine(
        pair, segs, dataset, dataset.models(), paper, cfg.loss.symmetry_table
    )
    one = _table(out, "network-icp")
    np.testing.assert_allclose(table["icp_ads"], one["icp_ads"], rtol=0, atol=1e-6)


class _Segments:
    """What :func:`cloudpose.methods.no_estimate` reads of a segment set: its length, validity and
    observed points."""

    def __init__(self, points: np.ndarray, valid: np.ndarray):
        self.points, self.valid = points, valid

    def __len__(self) -> int:
        return len(self.points)

    def observed(self, i: int) -> np.ndarray:
        return self.points[i]


def test_the_control_is_the_identity_at_each_segments_mean():
    from cloudpose.methods import no_estimate

    points = np.random.default_rng(0).normal(size=(3, 8, 3))
    est = no_estimate(_Segments(points, np.array([True, False, True])))
    np.testing.assert_array_equal(est.R, np.tile(np.eye(3), (3, 1, 1)))
    np.testing.assert_allclose(est.t[[0, 2]], points[[0, 2]].mean(axis=1))
    np.testing.assert_array_equal(est.t[1], np.zeros(3))  # a miss stays at the origin


def test_a_method_that_cannot_register_a_segment_scores_it_as_a_miss(compared):
    """A segment the method gave no pose for: a miss for that method only, every error
    infinite, along and across the ray too; the other rows are refined as usual."""
    import cloudpose.studies.compare as compare
    from cloudpose.data.dataset import folder_segments
    from cloudpose.data.layout import open_dataset
    from cloudpose.infer import load_checkpoint
    from cloudpose.methods import Estimated, no_estimate
    from cloudpose.store.pretrained import shipped

    proj, out, _ = compared
    _, cfg = load_checkpoint(shipped().path)
    dataset = open_dataset(REAL)
    segs = folder_segments(dataset, "all", cfg.data, proj, progress=False)
    ok = np.ones(len(segs), dtype=bool)
    ok[1] = False
    stub = Estimated("stub", "a stub", (no_estimate(segs),), ok, 0.0)
    paper = compare.refinements(1, "fitness", 0.01)[0]
    table, _ = compare._refine(
        stub, segs, dataset, dataset.models(), paper, cfg.loss.symmetry_table
    )
    assert table["miss"].tolist() == [False, True, False]
    for col in ("net_ads", "icp_ads", "icp_trans_err", "icp_trans_along", "icp_trans_across"):
        assert np.isinf(table[col][1]) and np.isfinite(table[col][[0, 2]]).all(), col
    assert segs.valid.all()  # the caller's segments are left as they were
    control = _table(out, "none-icp")  # the same estimates with every row registered
    np.testing.assert_allclose(table["icp_ads"][[0, 2]], control["icp_ads"][[0, 2]], atol=1e-9)


def test_a_folder_is_refused_for_other_frames_or_other_baseline_settings(compared, tmp_path,
                                                                        monkeypatch):  # fmt: skip
    import shutil

    proj, out, _ = compared
    monkeypatch.chdir(proj)
    data = tmp_path / "real"
    shutil.copytree(REAL, data)
    (data / "image_sets").mkdir()
    (data / "image_sets" / "one.txt").write_text("0000/000001\n")  # the frame, another list
    args = ["--method", "fpfh", *QUICK, "--out", str(out), "--no-progress"]
    res = cli("compare", "--data", str(data), "--frames", "one", *args)
    one_line_error(res, "holds a comparison of another", "'one'")
    record = json.loads((out / "compare.json").read_text())
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    record["settings"]["fpfh"] = "0" * 16  # as if baselines.toml had changed since
    (copy / "compare.json").write_text(json.dumps(record))
    args = ["--data", str(REAL), "--frames", "all", "--method", "fpfh", *QUICK]
    res = cli("compare", *args, "--out", str(copy), "--no-progress")
    one_line_error(res, "fpfh's results with other settings", "0" * 16)


def test_the_commands_defaults_are_the_recipe():
    import typer.main

    from cloudpose.cli import app
    from cloudpose.cli.app import parse_refine
    from cloudpose.config import PRODUCT_REFINEMENT, REFINEMENTS
    from cloudpose.studies.compare import RECIPE

    command = typer.main.get_command(app).commands["compare"]
    defaults = {p.name: p.default for p in command.params}
    assert defaults["refine"] is None and REFINEMENTS[PRODUCT_REFINEMENT] == RECIPE
    assert parse_refine("compare", None).fields == RECIPE  # --refine not given: the recipe


def test_a_combination_keeps_one_of_its_methods_refinements_per_object(compared, tmp_path,
                                                                        monkeypatch):  # fmt: skip
    """``--combine network+fpfh`` in a folder that holds both methods' tables: their estimates
    are read back (FPFH's from the project's cache, none computed), each object keeps one of
    the two methods' own refinements, and the report sets the combination against each
    method."""
    import shutil

    import cloudpose.methods as methods

    proj, out, _ = compared
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    monkeypatch.setattr(methods, "estimate_all", lambda *a, **k: pytest.fail("estimated"))
    monkeypatch.chdir(proj)
    args = ["--data", str(REAL), "--frames", "all", "--method", "fpfh", "--method", "none"]
    res = cli("compare", *args, "--combine", "fpfh+network", *QUICK, "--out", str(copy),
              "--no-progress")  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "fpfh estimates: kept; 2 refinement(s) to compute" in res.output.splitlines()[0]
    # 12 starts kept by ICP's fitness: each member refined as on its own, the depth choosing
    many = ["--refine", "starts=12,select=fitness,radius=0.05"]
    res = cli("compare", *args, "--combine", "fpfh+network", *many, "--out", str(copy),
              "--no-progress")  # fmt: skip
    assert res.exit_code == 0, res.output
    for ref in ("icp", "icp-radius50mm", "icp-starts12-radius50mm"):
        both = _table(copy, f"network+fpfh-{ref}")
        own = [_table(copy, f"{m}-{ref}")["icp_ads"].to_numpy() for m in ("network", "fpfh")]
        for i, ads in enumerate(both["icp_ads"]):
            assert min(abs(ads - o[i]) for o in own) < 1e-9, (ref, i)
    text = (copy / "compare.md").read_text()
    label = "network or FPFH + RANSAC, by the depth"
    assert f"| {label} + ICP (paper) |" in text and f"| {label} | no estimate | estimates |" in text
    diffs = pd.read_csv(copy / "compare_paired.csv")
    assert set(diffs["stage"]) == {"estimate", "icp", "icp-starts12-radius50mm"}
    pairs = {("network", "fpfh"), ("network", "none")}
    pairs |= {("network+fpfh", m) for m in ("network", "fpfh", "none")}
    assert set(zip(diffs["method"], diffs["against"], strict=True)) == pairs
    assert len(diffs) == len(pairs) * 3 * 3  # pairs x stages x metrics


def test_combinations_fill_a_members_miss_and_refuse_what_the_call_lacks():
    from cloudpose.methods import Estimated, combine
    from cloudpose.refine import Estimates
    from cloudpose.studies.compare import combination

    names = ["network", "fpfh", "none"]
    assert combination("none+network", names) == ("network", "none")
    for bad in ("network", "network+network", "network+ppf", "network+"):
        with pytest.raises(ValueError, match=r"^--combine"):
            combination(bad, names)
    n = 3
    a = Estimates(np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)))
    b = Estimates(-np.tile(np.eye(3), (n, 1, 1)), np.ones((n, 3)))
    first = Estimated("fpfh", "F", (a,), np.array([True, False, False]), 2.0)
    second = Estimated("ppf", "P", (b,), np.array([False, True, False]), 3.0)
    both = combine(("fpfh", "ppf"), [first, second])
    assert both.ok.tolist() == [True, True, False] and both.ms_per_object == 5.0
    assert both.label == "F or P, by the depth" and both.parts == ("fpfh", "ppf")
    np.testing.assert_array_equal(both.estimates[0].t[1], b.t[1])  # fpfh's miss: ppf's estimate
    np.testing.assert_array_equal(both.estimates[1].t[0], a.t[0])  # ppf's miss: fpfh's estimate


def test_a_combination_chooses_by_the_depth_and_refines_by_the_refinements_own_score(
    compared, monkeypatch
):
    """The starts of each estimate are scored as the refinement says (here ICP's fitness); only
    the choice among the combination's methods is the depth's."""
    import cloudpose.refine as refinement
    import cloudpose.studies.compare as compare
    from cloudpose.data.dataset import folder_segments
    from cloudpose.data.layout import open_dataset
    from cloudpose.infer import load_checkpoint
    from cloudpose.methods import Estimated, combine, no_estimate
    from cloudpose.store.pretrained import shipped

    proj, _, _ = compared
    _, cfg = load_checkpoint(shipped().path)
    dataset = open_dataset(REAL)
    segs = folder_segments(dataset, "all", cfg.data, proj, progress=False)
    ok = np.ones(len(segs), dtype=bool)
    members = [Estimated(m, m, (no_estimate(segs),), ok, 0.0) for m in ("a", "b")]
    both = combine(("a", "b"), members)
    seen = {"starts": set(), "choice": []}
    refine, select = refinement.refine_poses, refinement.select_refinements

    def refine_spy(segs, est, models, settings, *args, **kwargs):
        seen["starts"].add(settings.select)
        return refine(segs, est, models, settings, *args, **kwargs)

    def select_spy(segs, poses, stats, models, how, views):
        seen["choice"].append(how)
        return select(segs, poses, stats, models, how, views)

    monkeypatch.setattr(refinement, "refine_poses", refine_spy)
    monkeypatch.setattr(refinement, "select_refinements", select_spy)
    ref = compare.refinements(12, "fitness", 0.05)[1]
    compare._refine(both, segs, dataset, dataset.models(), ref, cfg.loss.symmetry_table)
    assert seen == {"starts": {"fitness"}, "choice": ["depth"]}
