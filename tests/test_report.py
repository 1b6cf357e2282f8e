"""Reports from a throwaway MLflow store holding synthetic runs (numbers from a seeded generator).

Every expected number is computed here from the generated values, independently of
cloudpose.report; the verdicts are checked on constructed cases.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image
from scipy import stats as sps

from cloudpose.registry import get_group, resolve
from cloudpose.report import stats
from cloudpose.report.claims import claims_frame, evaluate_claims

PRESET = "smoke"
DATA = "f00dfeed1234567890"
COMMIT = "abc1234def"
COMMAND = "cloudpose report --all --preset smoke"
SEEDS = (1, 2, 3)
METRICS = (
    "ad_auc",
    "ads_auc",
    "ads_lt_1cm",
    "rot_lt_10deg",
    "rot_lt_15deg",
    "rot_lt_20deg",
    "trans_lt_1cm",
)
CLASSES = [
    line.strip()
    for line in (Path(__file__).parents[1] / "cloudpose/resources/classes.txt").read_text().split()
    if line.strip()
]

# Constructed per-seed offsets of each variant's test metrics from shared-0 (fractions):
#   shared-1: clearly worse than shared-0 -> "separate beats shared 1" supported;
#   l2: clearly better -> "geodesic beats L2" contradicted;
#   quaternion: differences +0.01, -0.01, +0.002 -> CI contains 0 -> not resolved;
#   shared-all-2x: one seed only -> not resolved.
OFFSETS = {
    "shared-1": (-0.10, -0.11, -0.09),
    "l2": (0.10, 0.12, 0.11),
    "quaternion": (0.01, -0.01, 0.002),
}


def _test_set(m: int = 240) -> pd.DataFrame:
    """The test instances every run is evaluated on: occlusion, class, misses."""
    rng = np.random.default_rng(99)
    occ = rng.uniform(0.0, 1.0, m)
    occ[:3] = [0.0, 0.999, 1.0]  # the edges: first bin, last bin, last bin (1.0 included)
    return pd.DataFrame(
        {"occlusion": occ, "miss": rng.uniform(size=m) < 0.05, "cls_id": rng.integers(1, 22, m)}
    )


TEST_SET = _test_set()


def _instances(rng: np.random.Generator) -> pd.DataFrame:
    m = len(TEST_SET)
    occ, miss, cls = (TEST_SET[c].to_numpy() for c in ("occlusion", "miss", "cls_id"))
    net_ads = rng.exponential(0.012, m) * (1 + 2 * occ)
    icp_ads = net_ads * rng.uniform(0.2, 0.9, m)
    net_ad = net_ads * rng.uniform(1.0, 3.0, m)
    icp_ad = icp_ads * rng.uniform(1.0, 2.0, m)
    rot = rng.gamma(2.0, 6.0, m)
    df = pd.DataFrame(
        {
            "frame_id": [f"0048/{i // 5:06d}" for i in range(m)],
            "instance": np.arange(m) % 5,
            "cls_id": cls,
            "class": [CLASSES[c - 1] for c in cls],
            "occlusion": occ,
            "points": rng.integers(50, 2000, m),
            "miss": miss,
            "net_ad": net_ad,
            "net_ads": net_ads,
            "net_rot_err_deg": rot,
            "net_trans_err": net_ads * 0.8,
            "icp_ad": icp_ad,
            "icp_ads": icp_ads,
            "icp_rot_err_deg": rot * 0.7,
            "icp_trans_err": icp_ads * 0.8,
            "icp_fitness": rng.uniform(0.5, 1, m),
        }
    )
    for c in (
        "net_ad",
        "net_ads",
        "net_rot_err_deg",
        "net_trans_err",
        "icp_ad",
        "icp_ads",
        "icp_rot_err_deg",
        "icp_trans_err",
    ):
        df.loc[miss, c] = np.inf
    return df


def _stray_run(client, exp: str, data: str, commit: str, config: str | None, finished=True):
    """A shared-0 seed-1 run with test ADS AUC 0 that the report must leave out: on ``data``,
    of ``config`` (None: no tag), left RUNNING unless ``finished``."""
    tags = {"variant": "shared-0", "preset": PRESET, "seed": "1", "data": data}
    tags |= {"git_commit": commit} | ({"config": config} if config is not None else {})
    run = client.create_run(exp, tags=tags)
    client.log_metric(run.info.run_id, "test/ads_auc", 0.0)
    if finished:
        client.set_terminated(run.info.run_id, "FINISHED")


def _make_store(root: Path) -> dict:
    """Synthetic runs of every variant of every group; returns what was logged."""
    from mlflow.entities import Metric, Param

    from cloudpose.store import tracking

    client = tracking.setup(root)
    rng = np.random.default_rng(1234)
    logged: dict = {"metrics": {}, "instances": {}, "params": {}, "history": {}}
    base = {m: rng.uniform(0.4, 0.8, len(SEEDS)) for m in METRICS}
    seen = set()
    for gname in ("shared", "rotation", "loss"):
        for variant in get_group(gname).members:
            if variant in seen:
                continue
            seen.add(variant)
            seeds = (1,) if variant == "shared-all-2x" else SEEDS
            exp = tracking.experiment_id(client, gname, root)
            n_params = int(rng.integers(1_000_000, 4_000_000))
            logged["params"][variant] = n_params
            for i, seed in enumerate(seeds):
                tags = {
                    "variant": variant,
                    "group": gname,
                    "preset": PRESET,
                    "seed": str(seed),
                    "data": DATA,
                    "git_commit": COMMIT,
                    "run_dir": str(root / variant),
                    "config": resolve(variant, PRESET, seed).fingerprint(),
                }
                run = client.create_run(exp, tags=tags, run_name=f"{variant}/{PRESET}/seed{seed}")
                rid = run.info.run_id
                params = [
                    Param("model.parameters", str(n_params)),
                    Param("data.root", ""),
                    Param("data.synth_seed", "0"),
                ]
                ms = {}
                for m in METRICS:
                    if variant in OFFSETS:
                        v = base[m][i] + OFFSETS[variant][i]
                    elif variant == "shared-0":
                        v = base[m][i]
                    else:
                        v = base[m][i] + rng.normal(0, 0.03)
                    ms[f"test/{m}"] = v
                    ms[f"test_icp/{m}"] = v + 0.1 + rng.normal(0, 0.005)  # ICP clearly better
                    ms[f"test_icp/class_mean/{m}"] = v + 0.05
                if variant == "shared-0":
                    for c in CLASSES[:-1]:  # the last class has no test instance
                        for m in ("ad_auc", "ads_auc", "ads_lt_1cm"):
                            ms[f"test_icp/class/{c}/{m}"] = rng.uniform(0.5, 1.0)
                hist = {
                    "train/loss": np.exp(-np.arange(1, 6) / 3) + rng.uniform(0, 0.1, 5),
                    "val/ads_auc": np.linspace(0.2, 0.7, 5) + rng.uniform(0, 0.05, 5),
                }
                metrics = [Metric(k, v, 0, 0) for k, v in ms.items()]
                metrics += [
                    Metric(k, float(v), e, e + 1)
                    for k, vals in hist.items()
                    for e, v in enumerate(vals)
                ]
                client.log_batch(rid, metrics=metrics, params=params)
                df = _instances(rng)
                path = root / "logged" / rid / "instances.csv"
                path.parent.mkdir(parents=True)
                df.to_csv(path, index=False)
                client.log_artifact(rid, str(path), artifact_path="eval/test")
                client.set_terminated(rid, "FINISHED")
                logged["metrics"][(variant, seed)] = ms
                logged["instances"][(variant, seed)] = df
                logged["history"][(variant, seed)] = hist
    # the FPFH baseline (today's settings), and one made with other settings (left out)
    from cloudpose.baselines.base import load_settings, settings_fingerprint

    bexp = tracking.experiment_id(client, "baselines", root)
    current = settings_fingerprint(load_settings("fpfh"))
    for seed, config in ((1, current), (2, current), (3, current), (1, "0ldsettings00000")):
        tags = {
            "variant": "baseline-fpfh",
            "group": "baselines",
            "preset": PRESET,
            "seed": str(seed),
            "data": DATA,
            "git_commit": COMMIT,
            "config": config,
            "kind": "baseline",
        }
        run = client.create_run(bexp, tags=tags, run_name=f"baseline-fpfh/{PRESET}/seed{seed}")
        ms = {
            "test/ads_auc": 0.9 + 0.01 * seed,
            "test_icp/ads_auc": 0.95,
            "test/ad_auc": 0.5,
            "test_icp/ad_auc": 0.55,
            "test/ads_lt_1cm": 0.8,
            "test_icp/ads_lt_1cm": 0.85,
            "test/net_ms_per_object": 300.0,
            "test/icp_ms_per_object": 2.0,
        }
        if config != current:
            ms["test/ads_auc"] = 0.0
        client.log_batch(
            run.info.run_id,
            metrics=[Metric(k, v, 0, 0) for k, v in ms.items()],
            params=[Param("data.root", ""), Param("data.synth_seed", "0")],
        )
        client.set_terminated(run.info.run_id, "FINISHED")
        if config == current:
            logged["metrics"][("baseline-fpfh", seed)] = ms
    # a run on other data and an unfinished run: both must stay out of the report
    exp = tracking.experiment_id(client, "shared", root)
    own = resolve("shared-0", PRESET, 1).fingerprint()
    _stray_run(client, exp, "0therdata00", "zzz", own)
    _stray_run(client, exp, DATA, "yyy", None, finished=False)
    # a finished run of the same name, data and preset, trained with an override (the newest)
    edited = resolve("shared-0", PRESET, 1, {"train": {"epochs": 1}}).fingerprint()
    _stray_run(client, exp, DATA, "xxx", edited)
    return logged


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    root = tmp_path_factory.mktemp("store")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{root / 'mlflow.db'}")
        mp.chdir(root)
        logged = _make_store(root)
        from cloudpose.report import render_reports

        with pytest.warns(UserWarning) as caught:
            result = render_reports(PRESET, None, project_dir=root, command=COMMAND)
        said = " ".join(str(w.message) for w in caught)
        assert "other data" in said and "1 finished run(s)" in said and "another config" in said
        yield root, logged, result


def _read_csv(path: Path) -> pd.DataFrame:
    return pd.read_csv(path, comment="#")


def _ms(values) -> tuple[float, float]:
    v = np.asarray(values, float)
    return 100 * v.mean(), 100 * v.std(ddof=1)


# ---------------------------------------------------------------- stats


def test_difference_paired_matches_scipy_ttest_rel():
    rng = np.random.default_rng(7)
    a = rng.normal(0.7, 0.02, 5)
    b = a - rng.normal(0.03, 0.01, 5)
    d = stats.difference(dict(enumerate(a)), dict(enumerate(b)))
    ci = sps.ttest_rel(a, b).confidence_interval(0.95)
    assert d.paired and d.n == 5
    assert d.mean == pytest.approx(np.mean(a - b))
    assert (d.low, d.high) == pytest.approx((ci.low, ci.high))


def test_difference_unpaired_is_welch():
    a = {1: 0.70, 2: 0.72, 3: 0.69}
    b = {4: 0.60, 5: 0.66, 6: 0.61, 7: 0.64}
    d = stats.difference(a, b)
    ci = sps.ttest_ind(list(a.values()), list(b.values()), equal_var=False).confidence_interval()
    assert not d.paired
    assert (d.low, d.high) == pytest.approx((ci.low, ci.high))


@pytest.mark.parametrize(
    ("a", "b", "expect", "verdict"),
    [
        ({1: 0.80, 2: 0.82, 3: 0.81}, {1: 0.70, 2: 0.71, 3: 0.69}, 1, stats.SUPPORTED),
        ({1: 0.60, 2: 0.62, 3: 0.61}, {1: 0.70, 2: 0.71, 3: 0.69}, 1, stats.CONTRADICTED),
        ({1: 0.71, 2: 0.69, 3: 0.705}, {1: 0.70, 2: 0.70, 3: 0.70}, 1, stats.UNRESOLVED),
        ({1: 0.99}, {1: 0.10}, 1, stats.UNRESOLVED),  # one seed: never resolved
        ({}, {1: 0.1, 2: 0.2}, 1, stats.UNRESOLVED),
        # errors, smaller is better: a clearly smaller supports the claim
        ({1: 1.0, 2: 1.1, 3: 0.9}, {1: 2.0, 2: 2.1, 3: 2.05}, -1, stats.SUPPORTED),
    ],
)
def test_verdicts_on_constructed_cases(a, b, expect, verdict):
    assert stats.difference(a, b, expect=expect).verdict == verdict


def test_verdict_needs_three_seeds():
    # a clear difference on two seeds: the interval is printed, the verdict waits for a third seed
    a, b = {1: 0.800, 2: 0.812}, {1: 0.700, 2: 0.710}
    two = stats.difference(a, b)
    ci = sps.ttest_rel([0.800, 0.812], [0.700, 0.710]).confidence_interval(0.95)
    assert two.n == 2 and (two.low, two.high) == pytest.approx((ci.low, ci.high))
    assert two.low > 0 and two.verdict == stats.UNRESOLVED
    assert stats.difference(a, b, min_seeds=2).verdict == stats.SUPPORTED
    three = stats.difference({**a, 3: 0.81}, {**b, 3: 0.70})
    assert three.verdict == stats.SUPPORTED
    with pytest.raises(ValueError, match="min_seeds"):
        stats.difference(a, b, min_seeds=1)


@pytest.mark.parametrize(
    ("low", "high", "expect", "paper", "outcome"),
    [
        (0.01, 0.03, 1, 0.02, stats.SUPPORTED),  # holds the paper's size
        (0.01, 0.03, 1, math.nan, stats.SUPPORTED),  # no paper figure
        (0.01, 0.03, 1, 0.10, stats.SMALLER),  # direction yes, size no
        (0.05, 0.08, 1, 0.02, stats.LARGER),
        (-0.03, -0.01, 1, 0.02, stats.CONTRADICTED),
        (-0.005, 0.008, 1, 0.02, stats.EQUIVALENT),  # inside +-1 pp
        (-0.02, 0.03, 1, 0.10, stats.SMALLER),  # contains 0, excludes the paper's +10 pp
        (-0.02, 0.03, 1, 0.02, stats.UNRESOLVED),  # contains 0 and the paper's size
        (-0.02, 0.03, 1, math.nan, stats.UNRESOLVED),
        (-0.03, -0.01, -1, -0.02, stats.SUPPORTED),  # errors: smaller is better
        (0.01, 0.03, -1, -0.02, stats.CONTRADICTED),
    ],
)
def test_classify_names_every_outcome(low, high, expect, paper, outcome):
    verdict, why = stats.classify(low, high, expect, paper, margin=0.01)
    assert verdict == outcome
    assert verdict in stats.OUTCOMES
    if verdict in (stats.SMALLER, stats.LARGER, stats.EQUIVALENT, stats.UNRESOLVED):
        assert why  # the reader is told which bound decided it


def test_pooled_spread_floors_a_chance_agreement():
    # three seeds whose differences agree to the last digit, among variants whose paired
    # differences spread by ~1 pp: the interval is the pooled floor, not a point
    base = {1: 0.50, 2: 0.60, 3: 0.55}
    lucky = {s: v + 0.004 for s, v in base.items()}
    noisy = [{1: 0.51, 2: 0.59, 3: 0.57}, {1: 0.49, 2: 0.62, 3: 0.54}, base, lucky]
    pooled = stats.pooled_sd(noisy)
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    var = [np.var([noisy[i][s] - noisy[j][s] for s in (1, 2, 3)], ddof=1) for i, j in pairs]
    assert pooled.sd == pytest.approx(np.sqrt(np.mean(var)))
    assert pooled.dof == 4 * 2
    d = stats.difference(lucky, base, floor=pooled, margin=0.01)
    half = stats.floor_halfwidth(pooled, 3)
    assert half > 0.005
    assert (d.low, d.high) == pytest.approx((0.004 - half, 0.004 + half))
    assert d.method == "t+floor"
    assert d.verdict != stats.SUPPORTED  # the lucky zero spread is not evidence


def test_bootstrap_difference_over_seeds_and_instances():
    rng = np.random.default_rng(3)
    n = 400
    truth = rng.exponential(8.0, n)  # rotation errors, degrees

    def runs(shift):
        return {s: truth * shift * rng.uniform(0.8, 1.2, n) for s in (1, 2, 3, 4)}

    better, worse = runs(0.6), runs(1.0)
    stat = stats.share_below(10.0)
    d = stats.bootstrap_difference(better, worse, stat, replicates=300, margin=0.02)
    per_seed = [np.mean(better[s] < 10) - np.mean(worse[s] < 10) for s in (1, 2, 3, 4)]
    assert d.mean == pytest.approx(np.mean(per_seed))
    assert d.low < d.mean < d.high and d.low > 0
    assert d.verdict == stats.SUPPORTED and d.method == "bootstrap" and d.n == 4
    again = stats.bootstrap_difference(better, worse, stat, replicates=300, margin=0.02)
    assert again == d  # the report is deterministic
    # the instance level: one seed each way but many instances still leaves test-set spread
    same = stats.bootstrap_difference(worse, worse, stat, replicates=300, margin=0.02)
    assert same.low == same.high == 0.0 and same.verdict == stats.UNRESOLVED
    auc = stats.bootstrap_difference(
        {s: v / 100 for s, v in better.items()},
        {s: v / 100 for s, v in worse.items()},
        stats.auc_of_rows,
        replicates=100,
    )
    assert auc.mean > 0


def test_identical_paired_differences_are_not_a_verdict():
    # every seed one test instance (1/740) apart: std 0, a zero-width interval, no verdict
    step = 1 / 740
    a = {s: v + step for s, v in {1: 0.004, 2: 0.011, 3: 0.007}.items()}
    b = {1: 0.004, 2: 0.011, 3: 0.007}
    d = stats.difference(a, b)
    assert d.mean == pytest.approx(step)
    assert d.low == pytest.approx(d.high)
    assert d.verdict == stats.UNRESOLVED


def test_mean_std_and_format():
    ms = stats.mean_std([0.5, 0.7, np.nan, None])
    assert ms == pytest.approx((0.6, np.std([0.5, 0.7], ddof=1), 2))
    assert stats.format_mean_std(ms) == "60.0 ± 14.1"
    assert stats.format_mean_std(stats.mean_std([0.123])) == "12.3"
    assert stats.format_mean_std(stats.mean_std([])) == "–"


# ---------------------------------------------------------------- tables


def test_table3_mean_std_and_paper_beside(rendered):
    _root, logged, result = rendered
    out = result.out_dir
    df = _read_csv(out / "table3_shared_layers.csv").set_index("variant")
    paper = pd.read_csv(
        Path(__file__).parents[1] / "cloudpose/resources/paper/table3_shared_layers.csv"
    ).set_index("shared_layers")
    for variant in get_group("shared").members:
        seeds = [s for (v, s) in logged["metrics"] if v == variant]
        for m in ("ad_auc", "ads_auc", "rot_lt_10deg", "trans_lt_1cm"):
            vals = [logged["metrics"][(variant, s)][f"test/{m}"] for s in seeds]
            assert df.loc[variant, f"{m}_mean"] == pytest.approx(100 * np.mean(vals), abs=1e-3)
            if len(vals) > 1:
                assert df.loc[variant, f"{m}_std"] == pytest.approx(_ms(vals)[1], abs=1e-3)
            else:
                assert math.isnan(df.loc[variant, f"{m}_std"])
        assert df.loc[variant, "seeds"] == len(seeds)
        assert df.loc[variant, "parameters"] == logged["params"][variant]
    assert df.loc["shared-0", "paper_ad_auc"] == pytest.approx(paper.loc["none", "AD_auc"])
    assert df.loc["shared-all", "paper_rot_lt_10deg"] == pytest.approx(
        paper.loc["all", "rot_err_lt_10deg"]
    )
    # Markdown: the formatted mean ± std of ours next to the paper's figure in the same row
    md = (out / "table3_shared_layers.md").read_text()
    vals = [logged["metrics"][("shared-0", s)]["test/ad_auc"] for s in SEEDS]
    mean, std = _ms(vals)
    row = next(line for line in md.splitlines() if "| shared-0 |" in line)
    assert f"{mean:.1f} ± {std:.1f} | {paper.loc['none', 'AD_auc']:.1f}" in row
    assert f"{logged['params']['shared-0']:,}" in row
    tex = (out / "table3_shared_layers.tex").read_text()
    assert "\\toprule" in tex and "\\bottomrule" in tex and "$\\pm$" in tex


def test_table1_ours_and_paper_rows(rendered):
    _, logged, result = rendered
    md = (result.out_dir / "table1_overall.md").read_text()
    assert "paper, real YCB-Video" in md and "synthetic" in md and DATA[:10] in md
    for paper_row in ("| Ours w/o ICP | paper", "| DF + ICP | paper", "| PC | paper"):
        assert paper_row in md
    assert "82.7" in md and "94.7" in md and "90.3" in md  # the paper's "Ours" row
    df = _read_csv(result.out_dir / "table1_overall.csv")
    ours = df[df["method"].str.contains("shared-0")].set_index("icp")
    for icp, prefix in ((0, "test"), (1, "test_icp")):
        for m in ("ad_auc", "ads_auc", "ads_lt_1cm"):
            vals = [logged["metrics"][("shared-0", s)][f"{prefix}/{m}"] for s in SEEDS]
            mean, std = _ms(vals)
            assert ours.loc[icp, f"{m}_mean"] == pytest.approx(mean, abs=1e-3)
            assert ours.loc[icp, f"{m}_std"] == pytest.approx(std, abs=1e-3)
            assert f"{mean:.1f} ± {std:.1f}" in md


def test_table1_has_the_baselines_with_their_time(rendered):
    _, logged, result = rendered
    md = (result.out_dir / "table1_overall.md").read_text()
    df = _read_csv(result.out_dir / "table1_overall.csv").set_index("method")
    row = df.loc["FPFH + RANSAC w/o ICP (baseline-fpfh)"]
    vals = [logged["metrics"][("baseline-fpfh", s)]["test/ads_auc"] for s in SEEDS]
    assert row["ads_auc_mean"] == pytest.approx(100 * np.mean(vals), abs=1e-3)  # stale run out
    assert row["seeds"] == 3 and row["ms_per_object"] == pytest.approx(300.0)
    assert df.loc["FPFH + RANSAC (baseline-fpfh + ICP)", "ms_per_object"] == pytest.approx(302.0)
    assert "| FPFH + RANSAC w/o ICP (baseline-fpfh) |" in md and "ms/object" in md
    t2 = (result.out_dir / "table2_per_class.md").read_text()
    assert "FPFH + RANSAC + ICP" in t2  # its per-class column ('–': no per-class metrics logged)
    assert "baseline-fpfh_ads_auc_mean" in _read_csv(result.out_dir / "table2_per_class.csv")


def test_table2_per_class(rendered):
    _, logged, result = rendered
    df = _read_csv(result.out_dir / "table2_per_class.csv").set_index("object")
    paper = pd.read_csv(
        Path(__file__).parents[1] / "cloudpose/resources/paper/table2_per_class.csv"
    ).set_index("object")
    cls = CLASSES[3]
    vals = [logged["metrics"][("shared-0", s)][f"test_icp/class/{cls}/ads_auc"] for s in SEEDS]
    assert df.loc[cls, "ads_auc_mean"] == pytest.approx(100 * np.mean(vals), abs=1e-3)
    assert df.loc[cls, "paper_ads_auc"] == pytest.approx(paper.loc[cls, "Ours_ADS"])
    assert math.isnan(df.loc[CLASSES[-1], "ads_auc_mean"])  # no test instance: no number
    md = (result.out_dir / "table2_per_class.md").read_text()
    row = next(line for line in md.splitlines() if line.startswith(f"| {CLASSES[-1]} "))
    assert "| – | – | – |" in row


def test_table4_rotation_and_loss(rendered):
    _, logged, result = rendered
    df = _read_csv(result.out_dir / "table4_rotation.csv")
    row = df[(df["ablation"] == "loss") & (df["variant"] == "l2")].iloc[0]
    vals = [logged["metrics"][("l2", s)]["test/rot_lt_15deg"] for s in SEEDS]
    assert row["rot_lt_15deg_mean"] == pytest.approx(100 * np.mean(vals), abs=1e-3)
    assert row["paper_rot_lt_15deg"] == pytest.approx(52.5)
    assert set(df["variant"]) == {"shared-0", "quaternion", "rot6d", "l2", "geodesic-plain"}
    assert set(df["ablation"]) == {"representation", "loss", "symmetry"}


def test_runs_on_other_data_or_unfinished_are_left_out(rendered):
    _, _, result = rendered
    assert result.runs.data_key == DATA
    assert {r.git_commit for r in result.runs.records} == {COMMIT}  # not xxx, yyy, zzz


# ---------------------------------------------------------------- claims


def test_claims_verdicts(rendered):
    _, logged, result = rendered
    # the logged metrics carry the constructed offsets (the instance tables are random draws)
    rows = claims_frame(evaluate_claims(result.runs, per_instance=False))

    def verdict(other, metric):
        return rows[(rows["other"] == other) & (rows["metric"] == metric)].iloc[0]

    # shared-1 is 9-11 pp worse on every seed; the paper printed +0.8 pp
    assert verdict("shared-1/test", "ad_auc")["verdict"] == stats.LARGER
    assert verdict("l2/test", "rot_lt_10deg")["verdict"] == stats.CONTRADICTED
    # quaternion differs by +1, -1, +0.2 pp: the interval holds 0 but not the paper's +4.2 pp
    quat = verdict("quaternion/test", "rot_lt_10deg")
    assert quat["verdict"] == stats.SMALLER and "contains 0" in quat["why"]
    one = verdict("shared-all-2x/test", "ads_auc")
    assert one["verdict"] == stats.UNRESOLVED and one["seeds"] == 1
    icp = verdict("shared-0/test", "ads_auc")  # ICP +10 pp against the paper's +3.4
    assert icp["verdict"] == stats.LARGER
    # the measured difference and interval, recomputed here: paired t over the three seeds,
    # widened to the floor of the pooled spread of every variant pair's differences
    a = [logged["metrics"][("shared-0", s)]["test/ad_auc"] for s in SEEDS]
    b = [logged["metrics"][("shared-1", s)]["test/ad_auc"] for s in SEEDS]
    ci = sps.ttest_rel(a, b).confidence_interval(0.95)
    pooled = stats.pooled_sd(
        [result.runs.values(v, "test/ad_auc") for v in result.runs.variants if "baseline" not in v]
    )
    half = stats.floor_halfwidth(pooled, 3)
    mean = np.mean(np.subtract(a, b))
    row = verdict("shared-1/test", "ad_auc")
    assert row["diff_pp"] == pytest.approx(100 * mean, abs=1e-3)
    assert (row["ci_low_pp"], row["ci_high_pp"]) == pytest.approx(
        (100 * min(ci.low, mean - half), 100 * max(ci.high, mean + half)), abs=1e-3
    )
    assert row["paper_diff_pp"] == pytest.approx(76.0 - 75.2)

    # the rendered claims use the per-instance tables: a bootstrap over seeds and instances
    df = _read_csv(result.out_dir / "claims.csv")
    boot = df[(df["metric"] == "ads_auc") & (df["seeds"] >= 3)]
    assert boot["interval"].str.startswith("bootstrap").all()
    assert set(df["verdict"]) <= set(stats.OUTCOMES)
    assert {"rot_asym_lt_10deg", "rot_asym_lt_15deg"} <= set(df["metric"])
    md = (result.out_dir / "claims.md").read_text()
    assert "separate (none) beats shared 1" in md and "**Verdict**" in md
    # the chance-level note counts the rows that have an interval (one-seed rows have none)
    n_ci = int(np.isfinite(df["ci_low_pp"]).sum())
    assert 0 < n_ci < len(df)
    assert f"{n_ci} intervals at 95% each" in md and f"about {0.05 * n_ci:.1f} of them" in md
    # at a glance: one row per claim, each cell the verdict of that claim's row in claims.csv
    glance = md.split("## At a glance")[1].split("\n## ")[0]
    rows = [r for r in glance.splitlines() if r.startswith("| ") and "---" not in r][1:]
    assert len(rows) == df.groupby(["topic", "claim"]).ngroups
    shared1 = next(r for r in rows if r.startswith("| separate (none) beats shared 1 |"))
    want = df[df["claim"] == "separate (none) beats shared 1"].iloc[0]
    cells = [c.strip() for c in shared1.strip("|").split("|")][1:]
    assert cells[0].replace("*", "").startswith(want["verdict"].split(" than")[0])
    assert f"[{want['paper_diff_pp']:+.1f}]" in cells[0]


def test_asymmetric_column_counts_only_classes_without_symmetry(rendered):
    _, logged, result = rendered
    from cloudpose.geometry.symmetry import load_symmetries

    asym = {c for c, s in load_symmetries().items() if s.kind == "none"}
    rows = claims_frame(evaluate_claims(result.runs, replicates=50))
    row = rows[(rows["other"] == "l2/test") & (rows["metric"] == "rot_asym_lt_10deg")].iloc[0]
    share = {}
    for v in ("shared-0", "l2"):
        share[v] = [
            np.mean(t.loc[t["class"].isin(asym), "net_rot_err_deg"] < 10)
            for t in (logged["instances"][(v, s)] for s in SEEDS)
        ]
    assert row["diff_pp"] == pytest.approx(100 * np.mean(np.subtract(*share.values())), abs=1e-6)


# ---------------------------------------------------------------- figures


def test_occlusion_bins_and_counts(rendered):
    _, logged, result = rendered
    df = _read_csv(result.out_dir / "occlusion.csv")
    for method in ("net", "icp"):
        sub = df[df["method"] == method].sort_values("bin_low_pct")
        accs, counts = [], None
        for s in SEEDS:
            t = logged["instances"][("shared-0", s)]
            b = np.minimum((t["occlusion"].to_numpy() * 10).astype(int), 9)
            counts = np.bincount(b, minlength=10)
            hit = t[f"{method}_ads"].to_numpy() < 0.01
            accs.append([100 * hit[b == i].mean() if (b == i).any() else np.nan for i in range(10)])
        np.testing.assert_array_equal(sub["count"].to_numpy(), counts)
        np.testing.assert_allclose(
            sub["accuracy_mean_pct"].to_numpy(), np.nanmean(accs, axis=0), atol=0.01
        )
        assert list(sub["bin_low_pct"]) == list(range(0, 100, 10))


def test_pngs_exist_and_are_not_blank(rendered):
    _, _, result = rendered
    names = ["occlusion.png"] + [
        f"{k}_{g}.png"
        for k in ("occlusion", "curves", "training", "rot_err")
        for g in ("shared", "rotation", "loss")
    ]
    for name in names:
        path = result.out_dir / name
        assert path.exists(), name
        img = Image.open(io.BytesIO(path.read_bytes())).convert("RGB")
        assert img.width >= 600 and img.height >= 300
        colours = len(np.unique(np.asarray(img.resize((200, 100))).reshape(-1, 3), axis=0))
        assert colours > 20, f"{name} looks blank ({colours} colours)"


# ---------------------------------------------------------------- provenance, index, MLflow


def test_every_report_names_command_preset_data_seeds_commit(rendered):
    _, _, result = rendered
    files = [p for p in result.out_dir.iterdir() if p.suffix in (".md", ".tex", ".csv")]
    assert len(files) >= 15
    for p in files:
        text = p.read_text()
        first = text.splitlines()[2] if p.suffix == ".md" and p.name != "README.md" else text
        for needle in (COMMAND, f"preset {PRESET}", DATA[:10], COMMIT):
            assert needle in text, (p.name, needle)
        if p.suffix in (".tex", ".csv"):
            assert text.startswith(("% made by", "# made by")), p.name
        elif p.name != "README.md":
            assert first.startswith("_made by"), p.name
    t3 = (result.out_dir / "table3_shared_layers.md").read_text()
    assert "seeds 1, 2, 3" in t3


def test_readme_index_lists_every_file(rendered):
    _, _, result = rendered
    readme = (result.out_dir / "README.md").read_text()
    for p in result.out_dir.iterdir():
        if p.name != "README.md":
            assert f"]({p.name})" in readme, p.name


def test_report_runs_logged_and_replaced(rendered):
    root, _, result = rendered
    from cloudpose.report import render_reports
    from cloudpose.store import tracking

    client = tracking.setup(root)
    exp = client.get_experiment_by_name("cloudpose-shared")
    first = result.mlflow_runs["shared"]
    arts = {a.path for a in client.list_artifacts(first)}
    assert {"table3_shared_layers.md", "claims.md", "occlusion.png", "curves_shared.png"} <= arts
    run = client.get_run(first)
    assert run.info.run_name == f"report/shared/{PRESET}"
    assert "variant" not in run.data.tags  # never mistaken for a training run
    # the group's table is the experiment's description: on its page without choosing columns
    note = client.get_experiment(exp.experiment_id).tags["mlflow.note.content"]
    assert "Table III" in note and "shared-all-2x" in note and COMMAND in note
    assert run.data.tags["mlflow.note.content"] == note
    with pytest.warns(UserWarning, match="other data"):
        again = render_reports(PRESET, ["shared"], project_dir=root, command=COMMAND)
    live = client.search_runs([exp.experiment_id], "tags.kind = 'report'")
    assert [r.info.run_id for r in live] == [again.mlflow_runs["shared"]]


def test_an_unresolved_difference_says_why():
    few = stats.difference({1: 0.9, 2: 0.8}, {1: 0.1, 2: 0.2})
    assert few.verdict == stats.UNRESOLVED and few.why == "2 seed(s) of 3 needed"
    same = stats.difference({1: 0.5, 2: 0.6, 3: 0.7}, {1: 0.4, 2: 0.5, 3: 0.6})
    assert same.verdict == stats.UNRESOLVED and "same difference" in same.why
    wide = stats.difference({1: 0.5, 2: 0.9, 3: 0.1}, {1: 0.5, 2: 0.5, 3: 0.5})
    assert wide.verdict == stats.UNRESOLVED and wide.why == "the interval contains 0"
    clear = stats.difference({1: 0.9, 2: 0.95, 3: 0.92}, {1: 0.1, 2: 0.12, 3: 0.2})
    assert clear.verdict == stats.SUPPORTED and clear.why == ""


def test_outlier_classes_flags_a_class_far_below_the_rest():
    from cloudpose.report.tables import outlier_classes

    values = {f"c{i}": 80.0 + i % 3 for i in range(20)} | {"002_master_chef_can": 55.8}
    assert outlier_classes(values) == {"002_master_chef_can": 55.8}
    assert outlier_classes({k: v for k, v in values.items() if k != "002_master_chef_can"}) == {}
    assert outlier_classes({"a": 1.0, "b": float("nan")}) == {}


def test_seeds_to_decide_projects_the_interval_at_the_same_mean():
    def undecided(mean, low, high, n=3):
        return stats.Difference(mean, low, high, n, True, stats.UNRESOLVED)

    # above 0 once the lower side (0.04 below the mean) shrinks below 0.03: 3 / 0.75^2 -> 6
    assert stats.seeds_to_decide(undecided(0.03, -0.01, 0.07)) == 6
    # halfway between 0 and the paper's +2 pp, 4 pp either side: only ~48 seeds would decide
    assert stats.seeds_to_decide(undecided(0.01, -0.03, 0.05), paper=0.02, margin=0.02) is None
    # equivalence inside +-2 pp: 0.05 * sqrt(3 / n) < 0.02 from n = 19; the pooled floor
    # (SD 5 pp, 20 dof) stays wider than the margin up to 25 seeds
    wide = undecided(0.0, -0.05, 0.05)
    assert stats.seeds_to_decide(wide, margin=0.02, cap=25) == 19
    assert stats.seeds_to_decide(wide, margin=0.02, cap=25, floor=stats.Pooled(0.05, 20)) is None
    assert stats.seeds_to_decide(wide, margin=0.02) is None  # the default cap is 10
    # too few seeds to project from: the minimum; decided: what it has
    assert stats.seeds_to_decide(undecided(0.03, -0.01, 0.07, n=2)) == stats.MIN_SEEDS
    done = stats.Difference(0.05, 0.02, 0.08, 4, True, stats.SUPPORTED)
    assert stats.seeds_to_decide(done) == 4


def test_seeds_wanted_asks_only_for_seeds_that_would_decide():
    from cloudpose.report.claims import Claim, ClaimResult, seeds_wanted

    def result(other, metric, mean, low, high, verdict=stats.UNRESOLVED, n=3, paper=math.nan):
        claim = Claim("t", "s", ("shared-0", "test"), (other, "test"), metric, paper)
        return ClaimResult(claim, stats.Difference(mean, low, high, n, True, verdict))

    results = [
        # decided above 0 at 6 seeds if the mean holds
        result("l2", "rot_lt_10deg", 0.03, -0.01, 0.07),
        # between 0 and the paper's +2 pp (given in pp): no count up to 10 decides it
        result("quaternion", "rot_lt_10deg", 0.01, -0.03, 0.05, paper=2.0),
        # decided: no more seeds
        result("shared-1", "ads_auc", 0.02, 0.01, 0.03, stats.SUPPORTED),
        # two seeds: the third first
        result("shared-2", "ads_auc", 0.0, -0.05, 0.05, n=2),
    ]
    assert seeds_wanted(results, cap=10) == {"l2": 6, "shared-0": 6, "shared-2": 3}
    assert seeds_wanted(results, cap=3) == {"shared-2": 3}  # 6 seeds are past the cap


def test_claims_md_says_whether_more_seeds_would_decide_an_open_row():
    from cloudpose.report.claims import Claim, ClaimResult, claims_frame, claims_markdown
    from cloudpose.report.formats import Provenance

    def result(metric, mean, low, high, n=3, paper=1.0):
        claim = Claim(
            "Topic", f"claim {metric}", ("shared-0", "test"), ("l2", "test"), metric, paper
        )
        return ClaimResult(claim, stats.Difference(mean, low, high, n, True, stats.UNRESOLVED))

    results = [
        result("rot_lt_10deg", 0.03, -0.01, 0.07),  # above 0 at 6 seeds
        result("rot_lt_20deg", 0.01, -0.03, 0.05, paper=2.0),  # between 0 and +2 pp for good
        result("ads_auc", 0.0, -0.05, 0.05, n=2),  # the third seed first
    ]
    md = claims_markdown(results, Provenance("cmd", "p", "d", (1, 2, 3), ("abc",)))
    # the per-topic rows (claim, metric, paper, ours, interval, floor, seeds, verdict) after
    # their header
    rows = [r for r in md.splitlines() if r.startswith("| claim ") and r.count("|") == 9][1:]
    assert "6 seeds would decide it" in rows[0]
    assert "no count up to 10 seeds would decide it" in rows[1]
    assert "would decide" not in rows[2]  # two seeds: nothing to project from
    assert (
        "Of the 3 not-resolved rows with a paper figure, 1 would stay so at 10 seeds at their "
        "present means, 1 could be decided by more seeds, and 1 have fewer than 3 seeds yet."
    ) in md
    to_decide = claims_frame(results)["seeds_to_decide"].tolist()  # claims.csv: blank if none
    assert to_decide[0] == 6 and math.isnan(to_decide[1]) and math.isnan(to_decide[2])


def test_table1_names_the_subsample_a_baseline_ran_on():
    from cloudpose.report.runs import RunRecord, RunSet
    from cloudpose.report.tables import table1_overall

    metrics = {
        f"{p}/{m}": v
        for p in ("test", "test_icp")
        for m, v in (("ad_auc", 0.5), ("ads_auc", 0.9), ("ads_lt_1cm", 0.8))
    }

    def record(variant: str, seed: int, subsample: str = "all") -> RunRecord:
        return RunRecord(
            f"{variant}{seed}", variant, seed, "p", "d", "c", 0, {}, metrics, subsample=subsample
        )

    runs = RunSet("p", "d", [record("shared-0", 1), record("baseline-ppf", 1, "250")])
    methods = [r[0] for r in table1_overall(runs).rows if r]
    assert "PPF (Drost) w/o ICP (baseline-ppf, 250 test instances)" in methods
    assert "Ours w/o ICP (shared-0)" in methods  # the full test set: no size named


def test_the_verdict_table_of_a_readme_is_replaced_between_its_markers(rendered, tmp_path):
    from cloudpose.report.claims import update_verdicts_block
    from cloudpose.report.formats import Provenance

    _, _, result = rendered
    prov = Provenance.of(result.runs, COMMAND, "abc")
    readme = tmp_path / "README.md"
    readme.write_text(
        f"# Prose\n\n<!-- verdicts {PRESET} -->\nold\n<!-- /verdicts {PRESET} -->\nafter\n"
    )
    update_verdicts_block(readme, PRESET, result.claims, prov)
    text = readme.read_text()
    assert text.startswith("# Prose\n\n") and text.endswith("\nafter\n") and "old" not in text
    assert "| separate (none) beats shared 1 |" in text and COMMAND in text
    update_verdicts_block(readme, PRESET, result.claims, prov)  # idempotent
    assert readme.read_text() == text
    readme.write_text("no markers\n")
    with pytest.raises(ValueError, match=f"<!-- verdicts {PRESET} -->"):
        update_verdicts_block(readme, PRESET, result.claims, prov)


def test_table2_reads_the_per_class_detail_from_keys_or_from_the_runs_table(tmp_path):
    """A run logged before the detail tables keeps its per-class keys as metrics; a new run
    keeps them in ``eval/test/per_class.csv``: Table II is the same from either."""
    from cloudpose.report.runs import RunRecord, RunSet
    from cloudpose.report.tables import paper_table, table2_per_class
    from cloudpose.store.metric_names import (
        detail_artifact,
        detail_table,
        split_detail,
        write_detail,
    )

    classes = list(paper_table("table2_per_class")["object"])
    rng = np.random.default_rng(0)
    stats = ("ad_auc", "ads_auc", "ads_lt_1cm", "count")

    def metrics(seed: int) -> dict[str, float]:
        out = {
            f"{p}/class_mean/{m}": 0.5 + 0.01 * seed
            for p in ("test", "test_icp")
            for m in stats[:3]
        }
        for p in ("test", "test_icp"):
            for c in classes[:-2]:  # two classes without a test instance: no keys
                out.update({f"{p}/class/{c}/{m}": float(rng.random()) for m in stats})
        return out

    old, new = [], []
    for seed in (1, 2, 3):
        m = metrics(seed)
        args = (f"r{seed}", "shared-0", seed, "p", "d", "c", 0, {})
        old.append(RunRecord(*args, m))
        summary, detail = split_detail(m)
        folder = tmp_path / f"r{seed}" / "artifacts"
        rel = Path(detail_artifact("test", "class"))
        (folder / rel.parent).mkdir(parents=True)
        write_detail(detail_table(detail["class"], "class"), folder / rel)
        new.append(RunRecord(*args, summary, artifact_uri=folder.as_uri()))
        assert not any("/class/" in k for k in summary)
    a, b = table2_per_class(RunSet("p", "d", old)), table2_per_class(RunSet("p", "d", new))
    assert a.rows == b.rows
    pd.testing.assert_frame_equal(a.data, b.data)
    assert sum(r is not None and r[4] != "–" for r in a.rows) == len(classes) - 2 + 1


def test_claims_across_two_budgets_hold_change_or_stay_undecided():
    from cloudpose.report.claims import (
        Claim,
        ClaimResult,
        across_budgets,
        budgets_frame,
        budgets_markdown,
    )

    def result(other, metric, verdict, mean=0.02, n=3):
        claim = Claim(
            "t", f"shared-0 beats {other}", ("shared-0", "test"), (other, "test"), metric, 1.0
        )
        return ClaimResult(
            claim, stats.Difference(mean, mean - 0.01, mean + 0.01, n, True, verdict)
        )

    small = [
        result("l2", "ads_auc", stats.SUPPORTED),
        result("quaternion", "ads_auc", stats.EQUIVALENT),
        result("shared-all", "ads_auc", stats.UNRESOLVED),
        result("geodesic-plain", "ads_auc", stats.SUPPORTED),
    ]
    large = [
        result("geodesic-plain", "ads_auc", stats.UNRESOLVED, n=0),  # not run at this budget
        result("l2", "ads_auc", stats.SUPPORTED, mean=0.03),
        result("quaternion", "ads_auc", stats.CONTRADICTED, mean=-0.02),
        result("shared-all", "ads_auc", stats.SUPPORTED),
    ]
    rows = across_budgets(large, small, ("big", "small"))
    words = {r.claim.statement: (r.word, r.how) for r in rows}
    assert words == {
        "shared-0 beats l2": ("holds", ""),
        "shared-0 beats quaternion": ("changes", "equivalent -> contradicted"),
        "shared-0 beats shared-all": ("undecided", "not resolved at small"),
        "shared-0 beats geodesic-plain": ("undecided", "not measured at big"),
    }
    md = budgets_markdown(rows, "big", "small", {"big": "4x", "small": "1x"})
    assert (
        "Summary: holds: 1; changes: 1; undecided: 2 (of 4); 1 of the undecided not measured at "
        "one budget." in md
    )
    assert "| shared-0 beats l2 | ADS AUC | supported: +2.0 [+1.0, +3.0], 3 seeds |" in md
    # a claim measured at one budget only is named once, not given a row
    assert "| shared-0 beats geodesic-plain |" not in md
    assert "Not measured at big, so *undecided* across budgets (1 claim-metric pair, " in md
    assert "measured at small only): shared-0 beats geodesic-plain." in md
    assert "Not measured at small" not in md
    df = budgets_frame(rows, "small")
    assert list(df["across_budgets"]) == ["holds", "changes", "undecided", "undecided"]
    assert df["verdict_at_small"].iloc[1] == stats.EQUIVALENT
    assert df["diff_pp_at_small"].iloc[0] == pytest.approx(2.0)


def _occlusion_only(root: Path, out_dir: Path, **kw):
    """render_reports of the group shared's occlusion plots only, from the store at ``root``."""
    from cloudpose.report import render_reports

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{root / 'mlflow.db'}")
        with pytest.warns(UserWarning):
            return render_reports(
                PRESET,
                ["shared"],
                project_dir=root,
                command=COMMAND,
                out_dir=out_dir,
                only_occlusion=True,
                log_mlflow=False,
                **kw,
            )


def test_occlusion_only_writes_the_occlusion_plots(rendered, tmp_path):
    root, _, _ = rendered
    res = _occlusion_only(root, tmp_path)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["occlusion.csv", "occlusion.png", "occlusion_shared.png"]
    assert sorted(p.name for p in res.files) == names
    first = (tmp_path / "occlusion.csv").read_text().splitlines()[0]
    assert f"made by `{COMMAND}`" in first and "seeds 1" in first


def test_a_run_without_its_instance_table_is_named_and_left_out_of_the_plots(
    rendered, tmp_path, monkeypatch
):
    from cloudpose.report.runs import RunRecord

    root, _, _ = rendered
    original = RunRecord.instances

    def lacking(self, name="test"):  # shared-0 seed 2's table is gone
        return None if (self.variant, self.seed) == ("shared-0", 2) else original(self, name)

    monkeypatch.setattr(RunRecord, "instances", lacking)
    said: list[str] = []
    res = _occlusion_only(root, tmp_path, echo=said.append)
    warning = [s for s in said if "lack their instance table" in s]
    assert len(warning) == 1 and "shared-0 seed 2 (" in warning[0]
    assert "baseline-fpfh seed 1 (" in warning[0]  # the fixture's baselines log none
    assert "cloudpose evaluate --run" in warning[0]
    first = (tmp_path / "occlusion.csv").read_text().splitlines()[0]
    assert "seeds 1, 3;" in first  # the provenance names the seeds drawn, not 1-3
    assert (tmp_path / "occlusion.png") in res.files
