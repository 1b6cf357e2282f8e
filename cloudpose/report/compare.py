"""The report of ``cloudpose compare`` (:mod:`cloudpose.studies.compare`): ``compare.md``, its summary
``compare.csv``, the paired differences ``compare_paired.csv`` and the figure ``compare.png``,
from the comparison's instance tables only.

Sections: every method and stage pooled (ADS AUC, AD AUC, rotation < 10 deg modulo symmetry,
translation < 1 cm, median translation and its parts along and across the viewing ray,
milliseconds per object); the network minus each method at each stage (and each combination
minus each method), paired over object poses with a 95% bootstrap interval
(:func:`cloudpose.report.real.versus_baseline`); ADS AUC per
video; rotation < 10 deg per object pose. The figure: ADS AUC and rotation < 10 deg per object
pose, each method after each refinement.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from cloudpose.files import atomic_text, atomic_write
from cloudpose.metrics.summaries import voc_ap_auc
from cloudpose.report.formats import write_png
from cloudpose.report.real import object_pose, versus_baseline, video_of
from cloudpose.studies.compare import (
    MACHINE,
    NETWORK,
    STAGE_ESTIMATE,
    MethodComparison,
    rows,
    table_problem,
)

METRICS = {
    "ads_auc": "ADS AUC",
    "rot_sym_lt_10deg": "rot < 10° mod sym",
    "trans_lt_1cm": "trans < 1 cm",
}
"""What the paired differences are taken on (:func:`cloudpose.report.real.versus_baseline`)."""


def _pct(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{100 * x:.1f}"


def _mm(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{x:.1f}"


def _signed(x: float) -> str:
    """Points with a sign and one decimal; two where one would round a non-zero value to 0
    (an interval's bound just below 0 must not read as 0)."""
    if x != 0 and round(100 * x, 1) == 0:
        return f"{100 * x:+.2f}"
    return f"{100 * x:+.1f}"


def _machines(machines) -> str:
    return "on " + "; ".join(machines) if machines else "on the machine that computed them"


def _stages(refs) -> list[tuple[str, str, str]]:
    """``(stage, table's refinement, column prefix)`` of every stage: the estimate (read from
    the paper's refinement's table), then each refinement."""
    return [(STAGE_ESTIMATE, refs[0].name, "net")] + [(r.name, r.name, "icp") for r in refs]


def pooled_markdown(pooled: pd.DataFrame) -> list[str]:
    """The pooled table: a row per method and stage of :func:`rows`, with its
    milliseconds per object."""
    lines = [
        "| method | ADS AUC | AD AUC | rot < 10° mod sym | trans < 1 cm | median trans (mm) "
        "| across the ray | along the ray | ms / object |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for _, r in pooled.iterrows():
        lines.append(
            f"| {r['label']} | {_pct(r['ads_auc'])} | {_pct(r['ad_auc'])} "
            f"| {_pct(r['rot_sym_lt_10deg'])} | {_pct(r['trans_lt_1cm'])} "
            f"| {_mm(r['trans_median_mm'])} | {_mm(r['across_median_mm'])} "
            f"| {_mm(r['along_median_mm'])} | {_mm(r['ms_per_object'])} |"
        )
    return lines


def pairs(contenders) -> list[tuple[str, str]]:
    """``(method, against)`` of every paired difference: the network against each other single
    method, then each combination against each single method (one of its own: what the others
    add to it)."""
    singles = [c.name for c in contenders if not c.parts]
    out = [(NETWORK, other) for other in singles if other != NETWORK]
    return out + [(c.name, other) for c in contenders if c.parts for other in singles]


def paired(tables: dict, contenders, refs) -> pd.DataFrame:
    """Each method of :func:`pairs` minus the other at each stage, per metric of
    :data:`METRICS`: ``method``, ``against``, ``stage``, ``metric``, ``diff``, ``low``,
    ``high``, ``poses``, ``instances`` (fractions)."""
    out = []
    for method, against in pairs(contenders):
        for stage, ref, prefix in _stages(refs):
            for metric in METRICS:
                d = versus_baseline([tables[(method, ref)]], tables[(against, ref)], metric, prefix)
                out.append(
                    {"method": method, "against": against, "stage": stage, "metric": metric, **d}
                )
    return pd.DataFrame(out)


def _paired_markdown(diffs: pd.DataFrame, contenders, refs) -> list[str]:
    labels = {c.name: c.label for c in contenders}
    stage_label = {STAGE_ESTIMATE: "estimates", **{r.name: r.label.lstrip("+ ") for r in refs}}
    head = " | ".join(METRICS.values())
    lines = [f"| method | against | stage | {head} |", "|---|---|---|" + "---:|" * len(METRICS)]
    for (method, against, stage), g in diffs.groupby(["method", "against", "stage"], sort=False):
        cells = []
        for metric in METRICS:
            r = g[g["metric"] == metric].iloc[0]
            word = " ahead" if r["low"] > 0 else " behind" if r["high"] < 0 else ""
            cells.append(f"{_signed(r['diff'])} [{_signed(r['low'])}, {_signed(r['high'])}]{word}")
        row = f"{labels[method]} | {labels[against]} | {stage_label[stage]}"
        lines.append(f"| {row} | {' | '.join(cells)} |")
    return lines


def _columns(contenders, refs) -> list[tuple[str, str, str, str]]:
    """``(method, table's refinement, column prefix, heading)`` of every method and stage, the
    method named at its estimate, each refinement after it by its own label."""
    return [
        (c.name, ref, prefix, c.label if stage == STAGE_ESTIMATE else _ref_label(refs, stage))
        for c in contenders
        for stage, ref, prefix in _stages(refs)
    ]


def _ref_label(refs, name: str) -> str:
    return next(r.label for r in refs if r.name == name)


def _ads_auc(table: pd.DataFrame, prefix: str) -> float:
    return voc_ap_auc(table[f"{prefix}_ads"].to_numpy(float))


def _rot10(table: pd.DataFrame, prefix: str) -> float:
    return float(np.mean(table[f"{prefix}_rot_sym_err_deg"].to_numpy(float) < 10.0))


def by_group(tables: dict, contenders, refs, group: pd.Series, stat) -> pd.DataFrame:
    """``stat`` (of an instance table and a column prefix) per value of ``group`` (aligned with
    every table's rows), a row each, with its instance count; one column per method and stage,
    numbered in the order of :func:`_columns`."""
    cols = _columns(contenders, refs)
    keys = sorted(set(group))
    out = pd.DataFrame({"instances": [int((group == k).sum()) for k in keys]}, index=keys)
    for i, (method, ref, prefix, _) in enumerate(cols):
        table = tables[(method, ref)]
        out[i] = [stat(table[group.to_numpy() == k], prefix) for k in keys]
    return out


def _grouped_markdown(df: pd.DataFrame, contenders, refs, what: str, zeros: bool) -> list[str]:
    """``df`` of :func:`by_group` as a table, a row per group; ``zeros``: a last row counting
    the groups at 0."""
    heads = [h for *_, h in _columns(contenders, refs)]
    cols = [c for c in df.columns if c != "instances"]
    lines = [
        f"| {what} | instances | " + " | ".join(heads) + " |",
        "|---|---:|" + "---:|" * len(heads),
    ]
    for key, r in df.iterrows():
        lines.append(
            f"| {key} | {int(r['instances'])} | " + " | ".join(_pct(r[c]) for c in cols) + " |"
        )
    if zeros:
        counts = [f"{int((df[c] == 0).sum())} of {len(df)}" for c in cols]
        lines.append("| at 0% | | " + " | ".join(counts) + " |")
    return lines


def figure(tables: dict, contenders, refs, poses: pd.Series, path: Path) -> Path:
    """ADS AUC and rotation < 10 deg per object pose, each method (a colour) after each
    refinement (lighter: the paper's ICP)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = sorted(set(poses))
    bars = [(i, c, j, r) for i, c in enumerate(contenders) for j, r in enumerate(refs)]
    fig, axes = plt.subplots(2, 1, figsize=(max(8.0, 0.7 * len(keys) + 2), 7.5), sharex=True)
    width = 0.8 / len(bars)
    x = np.arange(len(keys))
    lowest = 100.0
    for k, (i, c, j, r) in enumerate(bars):
        table = tables[(c.name, r.name)]
        alpha = 0.45 + 0.55 * j / max(len(refs) - 1, 1)
        for ax, stat in zip(axes, (_ads_auc, _rot10), strict=True):
            values = np.array([100 * stat(table[poses.to_numpy() == p], "icp") for p in keys])
            if stat is _ads_auc:
                lowest = min(lowest, float(np.min(values[values > 0], initial=100.0)))
            ax.bar(x + (k - (len(bars) - 1) / 2) * width, values, width, color=f"C{i}",
                   alpha=alpha, label=f"{c.label} {r.label}")  # fmt: skip
    axes[0].set_ylim(max(0.0, 5 * np.floor(lowest / 5) - 5), 100)
    axes[0].set_ylabel("ADS AUC")
    axes[1].set_ylabel("rotation < 10° mod sym (%)")
    axes[1].set_xticks(x, keys, rotation=60, ha="right", fontsize=8)
    for ax in axes:
        ax.grid(axis="y", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=len(refs), fontsize=8, frameon=False)
    axes[0].set_title("per object pose, after each refinement", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.03 * len(contenders)))
    return write_png(fig, path, 110)


def render(comparison: MethodComparison, command: str) -> tuple[Path, Path]:
    """Write ``compare.md`` (naming ``command``, the command line that made it),
    ``compare.csv``, ``compare_paired.csv`` and ``compare.png`` into the comparison's folder;
    the report's and the figure's paths; ``ValueError`` naming a table that lacks a column
    the report reads (:func:`cloudpose.studies.compare.table_problem`)."""
    out_dir, tables = comparison.out_dir, comparison.tables
    contenders, refs = comparison.contenders, comparison.refinements
    icp_ms, described, source = comparison.timing, comparison.described, comparison.source
    combined = [c for c in contenders if c.parts]

    for (method, ref), table in tables.items():
        problem = table_problem(table)
        if problem is not None:
            path = out_dir / "tables" / f"{method}-{ref}.csv"
            raise ValueError(f"{path}: {problem}; run the comparison again to compute it")
    keys = [(t["frame_id"].astype(str).tolist(), t["instance"].tolist()) for t in tables.values()]
    if any(k != keys[0] for k in keys):  # the per-video and per-pose tables read rows by position
        raise ValueError(f"{out_dir}: its instance tables do not list the same instances")
    pooled = rows(tables, contenders, refs)
    pooled["ms_per_object"] = [
        icp_ms.get(f"{m}-{s}", np.nan)
        for m, s in zip(pooled["method"], pooled["stage"], strict=True)
    ]
    atomic_write(out_dir / "compare.csv", lambda tmp: pooled.to_csv(tmp, index=False), ".csv")
    diffs = paired(tables, contenders, refs)
    atomic_write(out_dir / "compare_paired.csv", lambda tmp: diffs.to_csv(tmp, index=False), ".csv")
    first = tables[(NETWORK, refs[0].name)]
    videos = video_of(first["frame_id"])
    poses = pd.Series(object_pose(first), index=first.index)
    misses = int(first["miss"].astype(bool).sum())
    settings = "; ".join(
        f"{r.label.lstrip('+ ')}: first radius {1000 * r.settings.max_distance:g} mm, "
        f"{r.settings.iterations} iterations shrinking by {1 - r.settings.shrink:.0%}, "
        f"{r.settings.starts} start(s) kept by {r.settings.select}"
        for r in refs
    )
    lines = [
        "# Like for like: the network against classical registration",
        "",
        f"Made by `{command}` (cloudpose/studies/compare.py). Data: {described}; "
        f"{videos.nunique()} video(s), {poses.nunique()} object poses "
        f"({misses} instance(s) without a usable segment point: a miss for every method). "
        f"Network: {source}. Every method estimates the pose of the same segments once; each "
        f"estimate is then refined by each ICP: {settings}. ms / object: the method's own "
        f"(the estimate rows) or the refinement's, {_machines(icp_ms.get(MACHINE))}."
        + (
            " For several networks the estimate rows hold, per object, the network whose "
            "refinement the paper's ICP kept by its fitness (an ensemble is a choice among "
            "refinements)."
            if contenders[0].label != NETWORK
            else ""
        )
        + (
            " A combination (`--combine`) refines every estimate of each of its methods by "
            "each ICP and keeps, per object, the refinement that agrees best with the depth "
            "(`cloudpose.refine.depth_score`: fitness and coverage of the segment against "
            "free-space violations; for the paper's ICP too); its estimate rows are the "
            "estimate whose refinement the paper's ICP kept, its ms the methods' together."
            if combined
            else ""
        ),
        "",
        "## Pooled",
        "",
        *pooled_markdown(pooled),
        "",
        "## Paired: the network against each method"
        + (", each combination against each method" if combined else ""),
        "",
        "The method minus the one it is set against, on the same instances at the same stage, "
        "points, with a 95% interval from a bootstrap over object poses (an object stands "
        "still in a video while the camera moves: its instances are one pose seen many "
        "times). *ahead* / *behind*: the interval excludes 0.",
        "",
        *_paired_markdown(diffs, contenders, refs),
        "",
        "## ADS AUC per video",
        "",
        *_grouped_markdown(
            by_group(tables, contenders, refs, videos, _ads_auc), contenders, refs, "video", False
        ),
        "",
        "## Rotation < 10° modulo symmetry per object pose",
        "",
        *_grouped_markdown(
            by_group(tables, contenders, refs, poses, _rot10), contenders, refs, "pose", True
        ),
        "",
        "![ADS AUC and rotation per object pose](compare.png)",
        "",
    ]
    fig = figure(tables, contenders, refs, poses, out_dir / "compare.png")
    report = atomic_text(out_dir / "compare.md", "\n".join(lines))
    return report, fig
