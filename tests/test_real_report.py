"""The real-frame report from a throwaway store: per video and pooled, network and baselines,
without and with ICP; what is missing is named with its command; nothing is computed."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cloudpose.registry import resolve

PRESET = "smoke"
DATA = "f00dfeed1234567890"
VIDEOS = {"0000": 6, "0001": 4}


def _instances(rng: np.random.Generator, fallback: bool = False) -> pd.DataFrame:
    """Ten instances in two videos; rotation and translation errors on both sides of the
    thresholds, ADS up to 10 cm."""
    frame_id = [f"{v}/{i:06d}" for v, n in VIDEOS.items() for i in range(n)]
    m = len(frame_id)
    df = pd.DataFrame(
        {
            "frame_id": frame_id,
            "instance": np.zeros(m, dtype=int),
            "cls_id": np.full(m, 2),
            "class": ["003_cracker_box"] * m,
            "occlusion": np.zeros(m),
            "points": np.full(m, 500),
            "miss": np.zeros(m, dtype=bool),
        }
    )
    for method in ("net", "icp"):
        ads = rng.uniform(0.0, 0.05, m)
        df[f"{method}_ad"] = ads * 1.5
        df[f"{method}_ads"] = ads
        df[f"{method}_rot_err_deg"] = rng.uniform(0, 30, m)
        df[f"{method}_rot_sym_err_deg"] = rng.uniform(0, 20, m)
        df[f"{method}_trans_err"] = rng.uniform(0, 0.02, m)
    return df


def _log(client, exp, tags, name, evaluations: dict[str, pd.DataFrame], ms=(2.0, 5.0)) -> None:
    from cloudpose.evaluate import log_evaluation

    run = client.create_run(exp, tags=tags, run_name=name)
    for ev_name, table in evaluations.items():
        metrics = {f"{ev_name}/net_ms_per_object": ms[0], f"{ev_name}/icp_ms_per_object": ms[1]}
        log_evaluation(client, run.info.run_id, ev_name, table, metrics)
    client.set_terminated(run.info.run_id, "FINISHED")


def _store(root: Path, seeds=(1, 2), baselines=("fpfh",)) -> dict:
    from cloudpose.baselines import load_settings
    from cloudpose.baselines.base import settings_fingerprint
    from cloudpose.store import tracking

    client = tracking.setup(root)
    rng = np.random.default_rng(5)
    logged: dict = {}
    exp = tracking.experiment_id(client, "shared", root)
    for seed in seeds:
        tags = {
            "variant": "shared-0",
            "group": "shared",
            "preset": PRESET,
            "seed": str(seed),
            "data": DATA,
            "config": resolve("shared-0", PRESET, seed).fingerprint(),
        }
        evs = {"real": _instances(rng)}
        if seed == 1:
            evs["real-fallback"] = _instances(rng)
        logged[("shared-0", seed)] = evs
        _log(client, exp, tags, f"shared-0/{PRESET}/seed{seed}", evs)
    # a run of another config (an override) is not the preset's network
    other = dict(tags, seed="1", config="0123456789abcdef")
    _log(client, exp, other, f"shared-0/{PRESET}/seed1+x", {"real": _instances(rng)})
    exp_b = tracking.experiment_id(client, "baselines", root)
    for method in baselines:
        tags = {
            "variant": f"baseline-{method}",
            "group": "baselines",
            "preset": PRESET,
            "seed": "1",
            "data": DATA,
            "config": settings_fingerprint(load_settings(method)),
            "kind": "baseline",
            "subsample": "all",
            "split": "real",
        }
        evs = {"real": _instances(rng)}
        logged[(method, 1)] = evs
        _log(client, exp_b, tags, f"baseline-{method}/{PRESET}/seed1+real", evs, ms=(90.0, 5.0))
    return logged


def _baseline_run(client, root: Path, method: str, preset: str, data: str, rng) -> pd.DataFrame:
    """A baseline's evaluation on the real frames, logged as a run of ``preset`` on ``data``."""
    from cloudpose.baselines import load_settings
    from cloudpose.baselines.base import settings_fingerprint
    from cloudpose.store import tracking

    tags = {
        "variant": f"baseline-{method}",
        "group": "baselines",
        "preset": preset,
        "seed": "1",
        "data": data,
        "config": settings_fingerprint(load_settings(method)),
        "kind": "baseline",
        "subsample": "all",
        "split": "real",
    }
    table = _instances(rng)
    exp = tracking.experiment_id(client, "baselines", root)
    _log(client, exp, tags, f"baseline-{method}/{preset}/seed1+real", {"real": table})
    return table


def _share(table: pd.DataFrame, col: str, limit: float, video: str | None) -> float:
    sel = table if video is None else table[table["frame_id"].str.startswith(video + "/")]
    return float((sel[col] < limit).mean())


@pytest.mark.slow  # a fresh MLflow store: ~40 s on 2 shared cores
def test_real_report_per_video_and_pooled(tmp_path):
    from cloudpose.report.real import render_real_report
    from cloudpose.store import tracking

    logged = _store(tmp_path)
    client = tracking.setup(tmp_path)
    tags = {
        "variant": "shared-0",
        "group": "shared",
        "preset": PRESET,
        "seed": "3",
        "data": DATA,
        "config": resolve("shared-0", PRESET, 3).fingerprint(),
    }
    exp = tracking.experiment_id(client, "shared", tmp_path)
    _log(client, exp, tags, f"shared-0/{PRESET}/seed3", {})  # trained, never on real frames
    report, files = render_real_report(PRESET, tmp_path, command="cloudpose real-report", seeds=4)
    assert [f.name for f in files] == [
        "real_frames.md",
        "real_frames.csv",
        "real_frames_vs_fpfh.csv",
        "real_frames_seeds.csv",
    ]
    assert all(f.parent == tmp_path / "reports" / PRESET for f in files)
    rows = pd.read_csv(files[1], dtype={"video": str})
    assert report.seeds == {"shared-0": [1, 2], "fpfh": [1]}

    def cell(method, icp, video, metric):
        r = rows[
            (rows.method == method)
            & (rows.icp == icp)
            & (rows.video == video)
            & (rows.metric == metric)
        ]
        assert len(r) == 1, (method, icp, video, metric)
        return r.iloc[0]

    # network: mean (and sample std) over its two seeds, per video and pooled, both sides of ICP
    for icp, prefix in (("net", "net"), ("icp", "icp")):
        for video in ("0000", "0001", None):
            per_seed = [
                _share(logged[("shared-0", s)]["real"], f"{prefix}_trans_err", 0.01, video)
                for s in (1, 2)
            ]
            r = cell("shared-0", icp, video or "pooled", "trans_lt_1cm")
            assert r["mean"] == pytest.approx(np.mean(per_seed), abs=1e-6)
            assert r["std"] == pytest.approx(np.std(per_seed, ddof=1), abs=1e-6)
            assert r["seeds"] == 2
    rot = _share(logged[("shared-0", 1)]["real-fallback"], "icp_rot_sym_err_deg", 10, "0001")
    r = cell("shared-0", "icp_fallback", "0001", "rot_sym_lt_10deg")
    assert r["mean"] == pytest.approx(rot, abs=1e-6) and r["seeds"] == 1 and math.isnan(r["std"])
    # baseline: its own table; ms per object = method (+ ICP)
    b = cell("fpfh", "icp", "pooled", "trans_lt_1cm")
    assert b["mean"] == pytest.approx(
        _share(logged[("fpfh", 1)]["real"], "icp_trans_err", 0.01, None)
    )
    assert b["ms_per_object"] == pytest.approx(95.0)
    assert cell("fpfh", "net", "0000", "ads_auc")["ms_per_object"] == pytest.approx(90.0)
    assert cell("shared-0", "net", "0000", "ads_auc")["instances"] == VIDEOS["0000"]
    # the Markdown: every row label, the command, and what is missing with its command
    md = files[0].read_text()
    assert "made by `cloudpose real-report`" in md.lower()
    for label in ("network (shared-0) + ICP + fallback", "FPFH + RANSAC + ICP", "0001 (4)"):
        assert label in md
    text = "\n".join(report.missing)
    assert len(report.missing) == 3
    assert f"`cloudpose evaluate --run shared-0/{PRESET}/seed3 --real`" in text
    assert f"`cloudpose run --variant shared-0 --preset {PRESET} --seed 4`" in text
    assert f"`cloudpose baseline --method ppf --preset {PRESET} --split real`" in text
    assert "--method ppf" in md and "--method fpfh" not in text
    # the paired comparison with FPFH: one row per metric and ICP setting, over 2 object poses
    vs = pd.read_csv(files[2])
    assert len(vs) == 6 and set(vs["poses"]) == {2} and set(vs["instances"]) == {10}
    assert "The network against FPFH + RANSAC, paired" in md
    spread = pd.read_csv(files[3])  # the network's two seeds: no test set logged here
    assert len(spread) == 6 and set(spread["seeds"]) == {2} and spread["test_sd"].isna().all()
    assert "How many seeds a difference on these frames needs" in md


def _poses(successes: dict[str, list[bool]]) -> pd.DataFrame:
    """An instance table with one object pose per key (``VIDEO/CLASS``), rotation errors of 1
    (success) or 50 deg per instance, the same for ICP."""
    rows = []
    for pose, ok in successes.items():
        video, cls = pose.split("/")
        for i, good in enumerate(ok):
            err = 1.0 if good else 50.0
            rows.append(
                {
                    "frame_id": f"{video}/{i:06d}",
                    "instance": cls,
                    "class": cls,
                    "net_rot_sym_err_deg": err,
                    "icp_rot_sym_err_deg": err,
                }
            )
    return pd.DataFrame(rows)


def test_versus_baseline_resamples_object_poses_not_instances():
    from cloudpose.report.real import versus_baseline

    poses = ["0000/a", "0000/b", "0001/c", "0001/d"]
    base = _poses({p: [False] * 10 for p in poses})
    # ahead on every pose: the interval excludes 0
    better = _poses({p: [True] * 5 + [False] * 5 for p in poses})
    r = versus_baseline([better], base, "rot_sym_lt_10deg", "net", replicates=500)
    assert r["diff"] == pytest.approx(0.5) and r["low"] > 0 and r["poses"] == 4
    # ahead on one pose only (10 of 40 instances): resampling instances would call that a
    # difference; over 4 poses, a replicate without that pose is common, so the interval holds 0
    one = _poses({p: [p == "0000/a"] * 10 for p in poses})
    r = versus_baseline([one], base, "rot_sym_lt_10deg", "icp", replicates=500)
    assert r["diff"] == pytest.approx(0.25) and r["low"] == 0.0 and r["high"] > 0.25
    # the network's rows are matched to the baseline's by instance, not by order; seeds averaged
    shuffled = better.sample(frac=1.0, random_state=0)
    r2 = versus_baseline([shuffled, one], base, "rot_sym_lt_10deg", "net", replicates=200)
    assert r2["diff"] == pytest.approx((0.5 + 0.25) / 2)


@pytest.mark.slow  # a fresh MLflow store: ~40 s on 2 shared cores
def test_a_baseline_the_preset_lacks_comes_from_another_preset_on_the_same_data(tmp_path):
    from cloudpose.report.real import render_real_report
    from cloudpose.store import tracking

    _store(tmp_path, seeds=(1,), baselines=())
    client = tracking.setup(tmp_path)
    rng = np.random.default_rng(9)
    fpfh = _baseline_run(client, tmp_path, "fpfh", "cpu-online", DATA, rng)
    _baseline_run(client, tmp_path, "ppf", "cpu", "0ther0data0key0000", rng)  # other data
    report, files = render_real_report(PRESET, tmp_path, command="cloudpose real-report", seeds=1)
    assert report.seeds == {"shared-0": [1], "fpfh": [1]}
    assert report.borrowed == {"fpfh": ["cpu-online"]}
    rows = pd.read_csv(files[1], dtype={"video": str})
    r = rows[
        (rows.method == "fpfh")
        & (rows.icp == "icp")
        & (rows.video == "pooled")
        & (rows.metric == "trans_lt_1cm")
    ]
    assert r["mean"].tolist() == pytest.approx([_share(fpfh, "icp_trans_err", 0.01, None)])
    assert [m for m in report.missing if "ppf" in m] == [
        f"baseline-ppf/{PRESET}: not run on the real frames "
        f"(`cloudpose baseline --method ppf --preset {PRESET} --split real`)"
    ]
    md = files[0].read_text()
    assert "FPFH + RANSAC: the runs of preset cpu-online on the same data" in md


def test_misses_cap_their_video_and_are_named():
    """An instance whose mask leaves no usable point fails for every method: the report counts
    them per video, names their classes and says how far they cap the video's rows."""
    from cloudpose.report.real import Evaluation, RealReport, build, markdown, misses

    table = _instances(np.random.default_rng(3))
    first_0001 = int(np.flatnonzero(table["frame_id"].str.startswith("0001"))[0])
    table.loc[first_0001, ["miss", "class"]] = True, "025_mug"
    evs = [Evaluation("shared-0", 1, "real", table, 2.0, 5.0, "r1")]
    got = misses(evs)
    assert got.to_dict("records") == [
        {"video": "0000", "instances": 6, "misses": 0, "classes": ""},
        {"video": "0001", "instances": 4, "misses": 1, "classes": "025_mug"},
    ]
    md = markdown(RealReport(build(evs), misses=got), PRESET, "cloudpose real-report")
    assert "0001: 1 of 4 (025_mug), at most 75.0%" in md
    assert "0000: 0 of" not in md
    # without a miss, no such line
    clean = [Evaluation("shared-0", 1, "real", _instances(np.random.default_rng(3)), 2.0, 5.0, "r")]
    assert "Misses," not in markdown(RealReport(build(clean), misses=misses(clean)), PRESET, "c")
    assert misses([]).empty


def test_seeds_for_is_the_fewest_whose_interval_fits():
    """The count returned meets t(2n - 2) * sd * sqrt(2 / n) <= half-width and one fewer does
    not; no spread needs the least (2), an unknown one or a huge one gives None."""
    from scipy.stats import t

    from cloudpose.report.real import MAX_SEEDS, seeds_for

    def width(n, sd):
        return t.ppf(0.975, 2 * n - 2) * sd * math.sqrt(2 / n)

    for sd, h in ((0.069, 0.05), (0.006, 0.01), (0.02, 0.05), (0.092, 0.05)):
        n = seeds_for(sd, h)
        assert n is not None and width(n, sd) <= h and (n == 2 or width(n - 1, sd) > h)
    assert seeds_for(0.069, 0.05) > seeds_for(0.027, 0.05)  # more spread, more seeds
    assert seeds_for(0.0, 0.05) == 2
    assert seeds_for(float("nan"), 0.05) is None
    assert seeds_for(0.2, 0.01) is None and seeds_for(0.2, 0.01, cap=MAX_SEEDS * 100) > MAX_SEEDS


def test_seed_spread_reads_each_seed_on_the_real_frames_and_its_test_set():
    from cloudpose.report.real import Evaluation, RealReport, markdown, seed_spread, table_metrics

    rng = np.random.default_rng(11)
    tables = [_instances(rng) for _ in range(3)]
    test_rot = [0.50, 0.52, 0.55]
    evs = [
        Evaluation(
            "shared-0",
            s + 1,
            "real",
            t,
            2.0,
            5.0,
            f"r{s}",
            {"test_icp/rot_sym_lt_10deg": test_rot[s]},
        )
        for s, t in enumerate(tables)
    ]
    evs.append(Evaluation("fpfh", 1, "real", _instances(rng), 90.0, 5.0, "b"))  # not the network
    spread = seed_spread(evs).set_index(["metric", "icp"])
    real = [table_metrics(t)[("icp", "pooled", "rot_sym_lt_10deg")] for t in tables]
    row = spread.loc[("rot_sym_lt_10deg", "icp")]
    assert row["seeds"] == 3 and row["half_width"] == 0.05
    assert row["real_sd"] == pytest.approx(np.std(real, ddof=1))
    assert row["test_sd"] == pytest.approx(np.std(test_rot, ddof=1))
    assert math.isnan(spread.loc[("ads_auc", "net"), "test_sd"])  # the test set not logged
    assert seed_spread(evs[:1] + evs[3:]).empty  # one seed has no spread
    md = markdown(RealReport(pd.DataFrame(), spread=seed_spread(evs)), PRESET, "c")
    assert "## How many seeds a difference on these frames needs" in md
    assert "| rotation < 10° mod sym + ICP | ±5 |" in md
