"""The real-frame report: the 61 packaged real development frames, per video and pooled.

Rows: the network (shared-0 of a preset, every seed found), FPFH + RANSAC and point-pair
features (``cloudpose baseline --split real``), each without and with ICP, and with ICP and its
fallback guard where such an evaluation exists (``cloudpose evaluate --real --icp-fallback``).
Columns: per video (0000-0003) and pooled, ADS AUC, rotation error < 10 degrees modulo the
object's symmetries, translation error < 1 cm (percent of instances), and milliseconds per
object (the method, plus ICP in the ICP rows). Over several seeds a cell is the mean over seeds
(± the sample standard deviation).

How far the network is from FPFH + RANSAC is measured paired, on the same instances, with a
95% interval from a bootstrap over *object poses* (:func:`versus_baseline`): an object stands
still in a video while the camera moves, so its 20 instances are one pose seen 20 times, and
the 264 instances are 17 poses. An interval over instances would treat them as 264
independent draws and be several times too narrow.

Only reads: every figure comes from an evaluation's logged instance table
(``eval/real/instances.csv``) and its timing metrics; a missing evaluation is listed with the
command that makes it, never computed here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from cloudpose.baselines import load_settings
from cloudpose.baselines.base import settings_fingerprint
from cloudpose.data.keys import canonical_key
from cloudpose.methods import summary_metrics, video_metrics
from cloudpose.report.committed import refuse_empty, report_folder
from cloudpose.report.formats import write_text
from cloudpose.report.stats import auc_of_rows, share_below
from cloudpose.store import tracking
from cloudpose.store.instances import run_instance_table
from cloudpose.store.metric_names import (
    ICP_SUFFIX,
    OWN_TEST,
    REAL_DEV,
    method_prefixes,
)
from cloudpose.store.runs import is_preset_config

NETWORK = "shared-0"
BASELINES = {"fpfh": "FPFH + RANSAC", "ppf": "point-pair features"}
METRICS = {
    "ads_auc": "ADS AUC",
    "rot_sym_lt_10deg": "rotation < 10° mod sym",
    "trans_lt_1cm": "translation < 1 cm",
}
REFERENCE = "fpfh"
"""The baseline the network is compared with, paired by instance (:func:`versus_baseline`)."""
BOOTSTRAP_REPLICATES = 4000
CLAIM_HALF_WIDTH = {"ads_auc": 0.01, "rot_sym_lt_10deg": 0.05, "trans_lt_1cm": 0.05}
"""Half-width of the 95% interval on a difference between two settings that
:func:`seed_spread` sizes the seeds for, per metric: 1 point of ADS AUC (the size of the
differences the claims weigh), 5 points of the two accuracies."""
MAX_SEEDS = 100
"""Beyond this many seeds a setting :func:`seeds_for` gives up (shown as more)."""


@dataclass(frozen=True)
class Evaluation:
    """One logged evaluation on the real frames: its instance table and timings."""

    method: str  # shared-0, fpfh, ppf
    seed: int
    name: str  # real or real-fallback
    table: pd.DataFrame
    net_ms: float
    icp_ms: float
    run_id: str
    test: dict[str, float] = field(default_factory=dict)
    """The same run's pooled figures on its own synthetic test set (``test/KEY``,
    ``test_icp/KEY`` of :data:`METRICS`; the network's runs only)."""


@dataclass
class RealReport:
    """The report's rows (long form: one row per method, ICP setting, video, metric) and what
    is missing."""

    rows: pd.DataFrame
    missing: list[str] = field(default_factory=list)
    seeds: dict[str, list[int]] = field(default_factory=dict)
    versus: pd.DataFrame = field(default_factory=pd.DataFrame)
    borrowed: dict[str, list[str]] = field(default_factory=dict)
    """Baseline -> the other presets whose runs it took (:func:`find_evaluations`)."""
    misses: pd.DataFrame = field(default_factory=pd.DataFrame)
    """Per video: instances and misses (:func:`misses`)."""
    spread: pd.DataFrame = field(default_factory=pd.DataFrame)
    """The network's spread over seeds, real frames against the test set (:func:`seed_spread`)."""


def misses(evaluations: list[Evaluation]) -> pd.DataFrame:
    """Per video: its instances and the classes of its misses, the instances whose
    ground-truth mask leaves no usable point (the ``miss`` column of an instance table). Every
    method sees the same segments, so a miss is a failure for all of them and caps what any
    reaches on that video; read from the first evaluation of the real frames. Columns: video,
    instances, misses, classes (comma-separated); empty when there is no evaluation."""
    tables = [ev.table for ev in evaluations if ev.name == REAL_DEV]
    if not tables:
        return pd.DataFrame(columns=["video", "instances", "misses", "classes"])
    t = tables[0].assign(video=video_of(tables[0]["frame_id"]))
    if "miss" not in t:  # a table logged before the column existed
        t["miss"] = False
    rows = []
    for video, g in t.groupby("video", sort=True):
        missed = g[g["miss"].astype(bool)]
        rows.append(
            {
                "video": video,
                "instances": len(g),
                "misses": len(missed),
                "classes": ", ".join(sorted(set(missed["class"].astype(str)))),
            }
        )
    return pd.DataFrame(rows)


def video_of(frame_id: pd.Series) -> pd.Series:
    """``0001/000004`` -> ``0001``."""
    return frame_id.astype(str).str.split("/").str[0]


def table_metrics(table: pd.DataFrame) -> dict[tuple[str, str, str], float]:
    """``(method column prefix, video or "pooled", metric) -> value`` (0..1) of an instance
    table of :func:`cloudpose.methods.instance_table` (``net_*``, ``icp_*`` columns)."""
    out: dict[tuple[str, str, str], float] = {}
    name = "x"
    metrics = {**summary_metrics(table, name), **video_metrics(table, name)}
    for method, prefix in method_prefixes(name).items():
        for key in METRICS:
            if f"{prefix}/{key}" not in metrics:
                continue
            out[(method, "pooled", key)] = metrics[f"{prefix}/{key}"]
            for video in sorted(set(video_of(table["frame_id"]))):
                out[(method, video, key)] = metrics[f"{prefix}/video/{video}/{key}"]
    return out


def _load(client, run, method: str, name: str) -> Evaluation | None:
    from mlflow.exceptions import MlflowException

    try:
        table = run_instance_table(client, run, name)  # checked: whole, every row
    except (FileNotFoundError, MlflowException):  # no such evaluation
        return None
    m = run.data.metrics
    test = {
        f"{prefix}/{key}": float(m[f"{prefix}/{key}"])
        for prefix in (OWN_TEST, OWN_TEST + ICP_SUFFIX)
        for key in METRICS
        if method == NETWORK and f"{prefix}/{key}" in m
    }
    return Evaluation(
        method,
        int(run.data.tags.get("seed", 0)),
        name,
        table,
        float(m.get(f"{name}/net_ms_per_object", math.nan)),
        float(m.get(f"{name}/icp_ms_per_object", math.nan)),
        run.info.run_id,
        test,
    )


def find_evaluations(
    client, preset: str, seeds: int = 3
) -> tuple[list[Evaluation], list[str], dict[str, list[int]], dict[str, list[str]]]:
    """Every real-frame evaluation of ``preset``'s network and baselines in the store.

    The network: the newest FINISHED ``shared-0`` run per seed trained with the preset's own
    config (:func:`cloudpose.store.runs.is_preset_config`). Baselines: the newest FINISHED run per
    seed of ``baseline-{method}`` on split ``real`` with the method's default settings; a
    baseline that ``preset`` has not run is taken from another preset's runs on the same data
    as the network's runs (a baseline sees only the segments, which the data key fixes), as
    :func:`cloudpose.report.runs.load_runs` does for the test set.

    Returns:
        The evaluations; what is missing, each with the command that makes it (seeds
        ``1..seeds`` of the network and seed 1 of each baseline are expected); the seeds found
        per method; the other presets each borrowed baseline came from.
    """
    found: list[Evaluation] = []
    missing: list[str] = []
    seeds_found: dict[str, list[int]] = {}
    newest: dict[int, object] = {}
    for run in tracking.find_runs(client, variant=NETWORK, preset=preset):
        seed = int(run.data.tags.get("seed", 0))
        if seed not in newest and is_preset_config(run):
            newest[seed] = run
    for seed in sorted(set(range(1, seeds + 1)) | set(newest)):
        run = newest.get(seed)
        if run is None:
            missing.append(
                f"{NETWORK}/{preset}/seed{seed}: no run "
                f"(`cloudpose run --variant {NETWORK} --preset {preset} --seed {seed}`)"
            )
            continue
        ev = _load(client, run, NETWORK, REAL_DEV)
        if ev is None:
            missing.append(
                f"{NETWORK}/{preset}/seed{seed}: not evaluated on the real frames "
                f"(`cloudpose evaluate --run {NETWORK}/{preset}/seed{seed} --real`; needs the "
                "run's checkpoint)"
            )
            continue
        found.append(ev)
        seeds_found.setdefault(NETWORK, []).append(seed)
        guarded = _load(client, run, NETWORK, f"{REAL_DEV}-fallback")
        if guarded is not None:
            found.append(guarded)
    data_keys = sorted(
        {canonical_key(r.data.tags["data"]) for r in newest.values() if r.data.tags.get("data")}
    )
    borrowed: dict[str, list[str]] = {}
    for method in BASELINES:
        fp = settings_fingerprint(load_settings(method))
        extra = (
            f"tags.kind = 'baseline' and tags.split = '{REAL_DEV}' and tags.subsample = 'all' "
            f"and tags.config = '{fp}'"
        )
        runs = tracking.find_runs(
            client, variant=f"baseline-{method}", preset=preset, extra_filter=extra
        )
        for key in [] if runs else data_keys:
            runs += tracking.find_runs(
                client, variant=f"baseline-{method}", data=key, extra_filter=extra
            )
        others = sorted({r.data.tags.get("preset", "?") for r in runs} - {preset})
        if others:
            borrowed[method] = others
        per_seed: dict[int, object] = {}
        for run in runs:
            per_seed.setdefault(int(run.data.tags.get("seed", 0)), run)
        for seed, run in sorted(per_seed.items()):
            ev = _load(client, run, method, REAL_DEV)
            if ev is not None:
                found.append(ev)
                seeds_found.setdefault(method, []).append(seed)
        if method not in seeds_found:
            missing.append(
                f"baseline-{method}/{preset}: not run on the real frames "
                f"(`cloudpose baseline --method {method} --preset {preset} --split real`)"
            )
    return found, missing, seeds_found, borrowed


def _label(method: str, icp: str) -> str:
    base = "network (shared-0)" if method == NETWORK else BASELINES[method]
    return {"net": base, "icp": f"{base} + ICP", "icp_fallback": f"{base} + ICP + fallback"}[icp]


def build(evaluations: list[Evaluation]) -> pd.DataFrame:
    """Long-form rows: method, icp (net / icp / icp_fallback), label, video, metric, mean,
    std (over seeds; NaN for one), seeds, instances, ms_per_object."""
    cells: dict[tuple, list[float]] = {}
    ms: dict[tuple, list[float]] = {}
    counts: dict[tuple, int] = {}
    for ev in evaluations:
        fallback = ev.name.endswith("-fallback")
        videos = video_of(ev.table["frame_id"])
        for (col, video, key), value in table_metrics(ev.table).items():
            if fallback and col == "net":
                continue  # the same estimates as the run's own evaluation
            icp = "icp_fallback" if fallback else col
            cells.setdefault((ev.method, icp, video, key), []).append(value)
            n = len(ev.table) if video == "pooled" else int((videos == video).sum())
            counts[(ev.method, icp, video)] = n
        for icp in ("icp_fallback",) if fallback else ("net", "icp"):
            t = ev.net_ms + (ev.icp_ms if icp != "net" else 0.0)
            ms.setdefault((ev.method, icp), []).append(t)
    order = {NETWORK: 0, **{m: i + 1 for i, m in enumerate(BASELINES)}}
    icp_order = {"net": 0, "icp": 1, "icp_fallback": 2}
    rows = []
    for (method, icp, video, key), values in cells.items():
        v = np.asarray(values, dtype=float)
        rows.append(
            {
                "method": method,
                "icp": icp,
                "label": _label(method, icp),
                "video": video,
                "metric": key,
                "mean": float(v.mean()),
                "std": float(v.std(ddof=1)) if len(v) > 1 else math.nan,
                "seeds": len(v),
                "instances": counts[(method, icp, video)],
                "ms_per_object": float(np.nanmean(ms[(method, icp)])),
            }
        )
    df = pd.DataFrame(rows)
    if df.empty:
        return df
    df["_m"] = df["method"].map(order)
    df["_i"] = df["icp"].map(icp_order)
    df["_v"] = df["video"].map(lambda v: "~" if v == "pooled" else v)
    df = df.sort_values(["_m", "_i", "metric", "_v"]).drop(columns=["_m", "_i", "_v"])
    return df.reset_index(drop=True)


def object_pose(table: pd.DataFrame) -> np.ndarray:
    """``VIDEO/CLASS`` of each instance: one object that stays put while the camera moves (a
    class appears once per scene), the unit :func:`versus_baseline` resamples."""
    return (video_of(table["frame_id"]) + "/" + table["class"].astype(str)).to_numpy()


def _stat(metric: str):
    """(column suffix, stat over an (R, N) array of per-instance values) of a metric."""
    return {
        "ads_auc": ("ads", auc_of_rows),
        "rot_sym_lt_10deg": ("rot_sym_err_deg", share_below(10.0)),
        "trans_lt_1cm": ("trans_err", share_below(0.01)),
    }[metric]


def versus_baseline(
    network: list[pd.DataFrame],
    baseline: pd.DataFrame,
    metric: str,
    icp: str,
    replicates: int = BOOTSTRAP_REPLICATES,
    seed: int = 0,
) -> dict[str, float]:
    """The network's metric minus the baseline's on the same instances, with a 95% interval.

    Args:
        network: instance tables of the network, one per seed.
        baseline: the baseline's instance table (the same frames).
        metric: a key of :data:`METRICS`.
        icp: "net" (without ICP) or "icp" (both refined by ICP).

    Returns:
        ``diff`` (mean over seeds of network minus baseline, pooled), ``low``, ``high`` (the
        2.5 and 97.5 percentiles of bootstrap replicates that draw object poses
        (:func:`object_pose`) with replacement, every instance of a drawn pose, and the seeds
        with replacement), ``poses`` (how many) and ``instances``.
    """
    col, stat = _stat(metric)
    key = ["frame_id", "instance"]
    base = baseline.set_index(key)
    order = base.index
    xb = base[f"{icp}_{col}"].to_numpy(float)
    xa = np.stack([t.set_index(key).loc[order, f"{icp}_{col}"].to_numpy(float) for t in network])
    poses = object_pose(baseline)
    units = [np.flatnonzero(poses == p) for p in sorted(set(poses))]
    diff = float(np.mean(stat(xa) - stat(xb[None])))
    rng = np.random.default_rng(seed)
    draws = np.empty(replicates)
    for r in range(replicates):
        idx = np.concatenate([units[i] for i in rng.integers(0, len(units), len(units))])
        seeds = rng.integers(0, len(xa), len(xa))
        draws[r] = float(np.mean(stat(xa[seeds][:, idx]) - stat(xb[None, idx])))
    low, high = np.quantile(draws, [0.025, 0.975])
    return {
        "diff": diff,
        "low": float(low),
        "high": float(high),
        "poses": len(units),
        "instances": len(order),
    }


def comparison(evaluations: list[Evaluation], reference: str = REFERENCE) -> pd.DataFrame:
    """:func:`versus_baseline` for every metric, without and with ICP: the network's seeds
    against the reference baseline's lowest seed; empty when either is missing."""
    nets = [ev.table for ev in evaluations if ev.method == NETWORK and ev.name == REAL_DEV]
    refs = [ev for ev in evaluations if ev.method == reference and ev.name == REAL_DEV]
    if not nets or not refs:
        return pd.DataFrame()
    ref = min(refs, key=lambda ev: ev.seed).table
    rows = [
        {"metric": m, "icp": icp, **versus_baseline(nets, ref, m, icp)}
        for m in METRICS
        for icp in ("net", "icp")
    ]
    return pd.DataFrame(rows)


def seeds_for(
    sd: float, half_width: float, level: float = 0.95, cap: int = MAX_SEEDS
) -> int | None:
    """Seeds each of two settings needs for the ``level`` interval on the difference of their
    means over seeds to be at most ``± half_width``, when one seed's figure spreads by ``sd``
    (two independent samples of seeds): the smallest ``n >= 2`` with
    ``t(2n - 2) * sd * sqrt(2 / n) <= half_width``, Student's t quantile. None beyond ``cap``
    or for an unknown ``sd``."""
    from scipy.stats import t

    if not np.isfinite(sd):
        return None
    q = 0.5 + level / 2
    for n in range(2, cap + 1):
        if t.ppf(q, 2 * n - 2) * sd * math.sqrt(2 / n) <= half_width:
            return n
    return None


def seed_spread(evaluations: list[Evaluation]) -> pd.DataFrame:
    """How far one seed's pooled figure moves from seed to seed, on the real frames and on the
    same runs' synthetic test set, and the seeds a difference of ``± half_width``
    (:data:`CLAIM_HALF_WIDTH`) needs on each (:func:`seeds_for`): one row per metric and ICP
    setting (``metric``, ``icp``, ``seeds``, ``half_width``, ``real_sd``, ``test_sd``,
    ``real_seeds``, ``test_seeds``; None: more than :data:`MAX_SEEDS`). Empty with fewer than
    two of the network's seeds."""
    nets = [ev for ev in evaluations if ev.method == NETWORK and ev.name == REAL_DEV]
    if len(nets) < 2:
        return pd.DataFrame()
    per_run = [table_metrics(ev.table) for ev in nets]
    rows = []
    for key in METRICS:
        for icp in ("net", "icp"):
            prefix = OWN_TEST + (ICP_SUFFIX if icp == "icp" else "")
            real = np.array([m[(icp, "pooled", key)] for m in per_run])
            test = np.array([ev.test.get(f"{prefix}/{key}", math.nan) for ev in nets])
            test_sd = float(test.std(ddof=1)) if np.isfinite(test).all() else math.nan
            real_sd, h = float(real.std(ddof=1)), CLAIM_HALF_WIDTH[key]
            rows.append(
                {
                    "metric": key,
                    "icp": icp,
                    "seeds": len(nets),
                    "half_width": h,
                    "real_sd": real_sd,
                    "test_sd": test_sd,
                    "real_seeds": seeds_for(real_sd, h),
                    "test_seeds": seeds_for(test_sd, h),
                }
            )
    return pd.DataFrame(rows)


def _verdict(low: float, high: float) -> str:
    if low > 0:
        return "network ahead"
    if high < 0:
        return "network behind"
    return "not resolved"


def _cell(mean: float, std: float) -> str:
    if math.isnan(std):
        return f"{100 * mean:.1f}"
    return f"{100 * mean:.1f} ± {100 * std:.1f}"


def markdown(report: RealReport, preset: str, command: str, store: str = "the store") -> str:
    """The report as Markdown: one table per metric (rows: methods; columns: videos, pooled),
    the command and settings beside it, and what is missing."""
    df = report.rows
    lines = [
        f"# Real development frames ({preset} preset)",
        "",
        f"Made by `{command}` from the logged evaluations (it never trains or evaluates). "
        "Data: the 61 real YCB-Video frames with ground truth that ship in the package "
        "(`cloudpose/resources/real_dev`: frames 000001-000020 of training videos 0000-0002 "
        "and 0003/000138; 14 classes, 4 scenes). Network: shared-0 of the "
        f"{preset} preset, trained on synthetic frames only, evaluated by `cloudpose evaluate "
        "--real` (ICP + fallback: `--icp-fallback`, the guard of `icp.fallback`). Baselines: "
        f"`cloudpose baseline --method fpfh|ppf --preset {preset} --split real` (default "
        "settings of cloudpose/resources/registry/baselines.toml). ICP: the paper's schedule (10 iterations, "
        "1 cm shrinking by 10%). Percent of instances (ADS AUC: area under the ADS accuracy "
        "curve up to 10 cm); a miss counts as a failure. Several seeds: mean ± sample std over "
        "seeds. ms per object: the method (+ ICP), on the machine that ran it.",
        "",
    ]
    seeds = "; ".join(f"{m} seed {', '.join(map(str, s))}" for m, s in report.seeds.items())
    lines += [f"Runs found in {store}: {seeds or 'none'}.", ""]
    for method, others in report.borrowed.items():
        lines += [
            f"{BASELINES[method]}: the runs of preset {', '.join(others)} on the same data "
            f"({preset} has none of its own; a baseline sees only the segments).",
            "",
        ]
    if df.empty:
        lines += ["No evaluation on the real frames was found.", ""]
    else:
        videos = [v for v in sorted(set(df["video"])) if v != "pooled"] + ["pooled"]
        n = df[(df["method"] == df["method"].iloc[0]) & (df["icp"] == "net")]
        n = n.drop_duplicates("video").set_index("video")["instances"]
        header = [f"{v} ({n.get(v, '?')})" for v in videos]
        for key, title in METRICS.items():
            sub = df[df["metric"] == key]
            lines += [f"## {title} (%)", ""]
            lines += ["| method | " + " | ".join(header) + " | ms / object |"]
            lines += ["|---|" + "---:|" * (len(videos) + 1)]
            for label, g in sub.groupby("label", sort=False):
                g = g.set_index("video")
                cells = [
                    _cell(g.loc[v, "mean"], g.loc[v, "std"]) if v in g.index else "" for v in videos
                ]
                ms = g["ms_per_object"].iloc[0]
                lines += [f"| {label} | " + " | ".join(cells) + f" | {ms:.1f} |"]
            lines += [""]
        lines += ["Column headers: video (instances). Video 0003 holds one frame.", ""]
        missed = report.misses[report.misses["misses"] > 0] if len(report.misses) else []
        if len(missed):
            parts = [
                f"{r.video}: {r.misses} of {r.instances} ({r.classes}), at most "
                f"{100 * (1 - r.misses / r.instances):.1f}%"
                for r in missed.itertuples()
            ]
            lines += [
                "Misses, instances whose ground-truth mask leaves no usable point (listed in "
                "the frame's meta, no labelled pixel with depth): a failure for every method, "
                "so they cap every row of their video: " + "; ".join(parts) + ".",
                "",
            ]
    vs = report.versus
    if not vs.empty:
        n_poses, n_inst = int(vs["poses"].iloc[0]), int(vs["instances"].iloc[0])
        lines += [
            f"## The network against {BASELINES[REFERENCE]}, paired (percentage points)",
            "",
            f"Pooled difference network minus {BASELINES[REFERENCE]} on the same {n_inst} "
            f"instances (network: mean over its seeds), and its 95% interval from "
            f"{BOOTSTRAP_REPLICATES} bootstrap replicates over the {n_poses} object poses "
            "(video/class: an object stands still while the camera moves, so its instances "
            "are one pose seen again and again) and the seeds. Not resolved: the interval "
            "holds 0; these frames cannot tell the two apart on that metric.",
            "",
            "| metric | without ICP | 95% interval | | with ICP (both) | 95% interval | |",
            "|---|---:|---:|---|---:|---:|---|",
        ]
        for key, title in METRICS.items():
            cells = []
            for icp in ("net", "icp"):
                r = vs[(vs["metric"] == key) & (vs["icp"] == icp)].iloc[0]
                cells += [
                    f"{100 * r['diff']:+.1f}",
                    f"[{100 * r['low']:+.1f}, {100 * r['high']:+.1f}]",
                    _verdict(r["low"], r["high"]),
                ]
            lines += [f"| {title} | " + " | ".join(cells) + " |"]
        lines += [""]
    lines += _spread_markdown(report.spread)
    if report.missing:
        lines += ["## Missing", ""]
        lines += [f"- {m}" for m in report.missing]
        lines += [""]
    return "\n".join(lines)


def _spread_markdown(spread: pd.DataFrame) -> list[str]:
    """The seed-spread section (:func:`seed_spread`); nothing without it."""
    if spread.empty:
        return []
    n = int(spread["seeds"].iloc[0])
    lines = [
        "## How many seeds a difference on these frames needs",
        "",
        f"Sample std over the network's {n} seeds of its pooled figure on these frames and on "
        "the same runs' synthetic test set, and the seeds each of two settings needs for a "
        "95% interval of ± the half-width on their difference (two independent samples of "
        "seeds, Student's t; the std estimated from these seeds, itself uncertain). Seeds only "
        "narrow the draw of training: the object poses of these frames are a sample of their "
        "own, and no number of seeds narrows that part (the paired interval above holds both).",
        "",
        "| metric | half-width | std over seeds, real | std, test set | seeds, real | "
        "seeds, test set |",
        "|---|---:|---:|---:|---:|---:|",
    ]

    def seeds(v) -> str:
        return f"> {MAX_SEEDS}" if v is None or pd.isna(v) else str(int(v))

    for r in spread.itertuples():
        label = METRICS[r.metric] + (" + ICP" if r.icp == "icp" else "")
        test = "" if math.isnan(r.test_sd) else f"{100 * r.test_sd:.1f}"
        lines += [
            f"| {label} | ±{100 * r.half_width:g} | {100 * r.real_sd:.1f} | {test} | "
            f"{seeds(r.real_seeds)} | " + (seeds(r.test_seeds) if test else "") + " |"
        ]
    return [*lines, ""]


def render_real_report(
    preset: str,
    project_dir: Path,
    out_dir: Path | None = None,
    command: str = "",
    seeds: int = 3,
    echo=print,
) -> tuple[RealReport, list[Path]]:
    """Write ``real_frames.md`` and ``real_frames.csv`` into ``out_dir`` (default
    ``{project_dir}/reports/{preset}``) from the evaluations in the project's store.

    Refuses (:class:`~cloudpose.report.committed.NoRunsError`, nothing written) a store with no
    real-frame evaluation of the preset's network; renders into ``runs/reports/PRESET`` rather
    than over committed reports whose runs it lacks
    (:func:`~cloudpose.report.committed.report_folder`)."""
    client = tracking.setup(project_dir)
    evaluations, missing, found, borrowed = find_evaluations(client, preset, seeds)
    refuse_empty(len(found.get(NETWORK, [])), preset, project_dir, "real-report")
    report = RealReport(
        build(evaluations),
        missing,
        found,
        comparison(evaluations),
        borrowed,
        misses(evaluations),
        seed_spread(evaluations),
    )
    pairs = {
        (m if m == NETWORK else f"baseline-{m}", seed) for m, ss in found.items() for seed in ss
    }
    out_dir = report_folder(
        preset,
        project_dir,
        out_dir,
        Path(project_dir) / "reports" / preset,
        pairs,
        echo,
        variants={NETWORK, *(f"baseline-{m}" for m in BASELINES)},
        split=REAL_DEV,
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    command = command or f"cloudpose real-report --preset {preset}"
    md, csv = out_dir / "real_frames.md", out_dir / "real_frames.csv"
    store = "the project's MLflow store"
    write_text(md, markdown(report, preset, command, store))
    report.rows.to_csv(csv, index=False, float_format="%.6g")
    files = [md, csv]
    if not report.versus.empty:
        files.append(out_dir / f"real_frames_vs_{REFERENCE}.csv")
        report.versus.to_csv(files[-1], index=False, float_format="%.6g")
    if not report.spread.empty:
        files.append(out_dir / "real_frames_seeds.csv")
        report.spread.to_csv(files[-1], index=False, float_format="%.6g")
    return report, files
