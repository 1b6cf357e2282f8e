"""The stress report (``cloudpose stress``, :mod:`cloudpose.studies.stress`): ``stress.md``, ``stress.csv``
and two figures (``stress.png``: ADS AUC; ``stress_translation.png``: median translation error)
per perturbation level, real development frames and synthetic test frames side by side, the
real frames' own level marked, drawn from a sweep's result folder only.
"""

from __future__ import annotations

import json
import tarfile
from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from cloudpose.config import PAPER_RADIUS
from cloudpose.refine import schedule_for
from cloudpose.report.committed import guarded_folder
from cloudpose.report.formats import write_png
from cloudpose.studies.perturbations import PERTURBATIONS, STATISTICS, identity_level
from cloudpose.studies.stress import (
    collect,
    collect_stats,
    real_level,
    result_files,
    result_path,
    summary_of,
)

PACKED_RESULTS = "stress-results.tar.xz"
"""The results a committed stress report was rendered from, packed beside it (``stress
--pack``): a folder holding it is rendered over only by results that hold each of its files
(:func:`report_folder`)."""

NETWORK = "network"
"""Label of the mean over the sweep's checkpoints (``net-*`` methods)."""

CURVES = (
    (NETWORK, "net", "network", "C0", "--"),
    (NETWORK, "icp", "network + ICP", "C0", "-"),
    ("ensemble", "icp", "ensemble + ICP", "C3", "-"),
    ("fpfh", "net", "FPFH + RANSAC", "C1", "--"),
    ("fpfh", "icp", "FPFH + RANSAC + ICP", "C1", "-"),
    ("ppf", "net", "point-pair features", "C2", "--"),
    ("ppf", "icp", "point-pair features + ICP", "C2", "-"),
)
"""(method, stage, label, colour, line style) of every curve and table column."""

FRAGILE_PP = 3.0
"""A perturbation counts as one the network is fragile to where, at its largest level, network
+ ICP loses this many points of ADS AUC more than FPFH + RANSAC + ICP loses on the same
instances (FPFH's subsample; point-pair features run on too few instances here to decide)."""


AT_OR_ABOVE_PP = 0.05
"""ADS AUC points below FPFH + RANSAC + ICP that still count as at its level in the tally of
the fragility section: the cells are printed to one decimal, and a tie printed as +0.0 is one."""

FRAGILE_MM = 2.0
"""Translation-fragile: at the real frames' level on synthetic segments, the network's median
translation error grows by this many millimetres more than FPFH + RANSAC + ICP's."""


def with_network_mean(summary: pd.DataFrame) -> pd.DataFrame:
    """``summary`` with rows of method :data:`NETWORK`: the mean over the ``net-*`` methods."""
    nets = summary[summary.method.str.startswith("net-")].copy()
    if nets.empty:
        return summary
    at = nets.method.str.partition("@")[2]
    nets["method"] = np.where(at == "", NETWORK, NETWORK + "@" + at)
    keys = ["source", "perturbation", "level", "stage", "method"]
    mean = nets.groupby(keys, as_index=False).mean(numeric_only=True)
    return pd.concat([summary, mean], ignore_index=True)


def _curve(summary, source, pert, method, stage) -> pd.DataFrame:
    """The rows of one curve: ``method`` at ``stage`` on ``source`` under ``pert``."""
    return summary[
        (summary.source == source)
        & (summary.perturbation == pert)
        & (summary.method == method)
        & (summary.stage == stage)
    ]


def _value(summary, source, pert, level, method, stage, col) -> float:
    curve = _curve(summary, source, pert, method, stage)
    row = curve[np.isclose(curve.level, level)]
    return float(row[col].iloc[0]) if len(row) else np.nan


def _interp(summary, source, pert, level, method, stage, col) -> float:
    sub = _curve(summary, source, pert, method, stage).sort_values("level")
    if sub.empty or not np.isfinite(level):
        return np.nan
    return float(np.interp(level, sub.level, sub[col]))


def _cell(summary, source, pert, level, method, stage) -> str:
    v = [_value(summary, source, pert, level, method, stage, c) for c in
         ("ads_auc", "rot_sym_lt_10deg", "trans_lt_1cm", "trans_median_mm")]  # fmt: skip
    if not np.isfinite(v[0]):
        return ""
    return f"{100 * v[0]:.1f} / {100 * v[1]:.0f}% / {100 * v[2]:.0f}% / {v[3]:.1f}"


def fragility(summary: pd.DataFrame, levels: dict[str, float]) -> pd.DataFrame:
    """Per (source, perturbation): ADS AUC lost from the identity to the real frames' level and
    to the largest level, by network + ICP and by each registration + ICP (points)."""
    rows = []
    for source in sorted(summary.source.unique()):
        for name, p in PERTURBATIONS.items():
            if name not in set(summary.perturbation):
                continue
            ident = identity_level(p)
            far = max(p.levels, key=lambda lv: abs(lv - ident))
            row = {"source": source, "perturbation": name, "real_level": levels.get(name)}
            for method in (NETWORK, f"{NETWORK}@fpfh", "fpfh", f"{NETWORK}@ppf", "ppf",
                           "ensemble@fpfh"):  # fmt: skip
                base = _value(summary, source, name, ident, method, "icp", "ads_auc")
                at_real = _interp(summary, source, name, levels.get(name, np.nan), method, "icp",
                                  "ads_auc")  # fmt: skip
                at_far = _value(summary, source, name, far, method, "icp", "ads_auc")
                row[f"{method}_loss_real"] = 100 * (base - at_real)
                row[f"{method}_loss_far"] = 100 * (base - at_far)
                row[f"{method}_at_real"] = 100 * at_real
            lv = levels.get(name, np.nan)
            for method, stage in (
                (NETWORK, "net"), (NETWORK, "icp"), (f"{NETWORK}@fpfh", "net"), ("fpfh", "icp"),
            ):  # fmt: skip
                col = "trans_median_mm"
                row[f"{method}_{stage}_t0"] = _value(
                    summary, source, name, ident, method, stage, col
                )
                row[f"{method}_{stage}_treal"] = _interp(
                    summary, source, name, lv, method, stage, col
                )
            gap = row[f"{NETWORK}@fpfh_loss_far"] - row["fpfh_loss_far"]
            row["fragile"] = bool(np.isfinite(gap) and gap > FRAGILE_PP)
            rows.append(row)
    return pd.DataFrame(rows)


def plot_metric(summary, levels, col, path: Path, ylabel: str, footer: str, scale=1.0) -> Path:
    """One panel per (perturbation, source): ``col`` against the level for every curve of
    :data:`CURVES`, the real frames' level as a dotted line."""
    perts = [n for n in PERTURBATIONS if n in set(summary.perturbation)]
    sources = [s for s in ("real", "synth") if s in set(summary.source)]
    ncols = 2 * len(sources)
    nrows = int(np.ceil(len(perts) / 2))
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.0 * ncols, 3.0 * nrows), squeeze=False)
    for k, name in enumerate(perts):
        p = PERTURBATIONS[name]
        for j, source in enumerate(sources):
            ax = axes[k // 2, (k % 2) * len(sources) + j]
            for method, stage, label, colour, style in CURVES:
                sub = _curve(summary, source, name, method, stage).sort_values("level")
                if len(sub):
                    ax.plot(sub.level, scale * sub[col], style, color=colour, marker=".",
                            label=label)  # fmt: skip
            lv = levels.get(name, np.nan)
            if np.isfinite(lv):
                ax.axvline(lv, color="0.3", linestyle=":", label="real frames' level")
            ax.set_title(f"{name} ({source})", fontsize=9)
            ax.set_xlabel(f"{p.what} [{p.unit}]", fontsize=7)
            ax.set_ylabel(ylabel, fontsize=7)
            ax.tick_params(labelsize=7)
    for ax in axes.flat[len(perts) * len(sources) :]:
        ax.set_visible(False)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=len(labels), fontsize=8)
    fig.text(0.01, 0.003, footer, fontsize=6, color="0.35")
    fig.tight_layout(rect=(0, 0.02, 1, 0.97))
    return write_png(fig, path, 90)


def _schedule(radius: float) -> str:
    """The ICP schedule of a sweep in words (after "the same ICP")."""
    if radius == PAPER_RADIUS:
        return ", the paper's schedule from a 1 cm radius"
    n = schedule_for(radius)["iterations"]
    return (
        f", from a first radius of {100 * radius:g} cm ({n} iterations down to the paper's last "
        "radius; cloudpose.refine.schedule_for, `--icp-radius`)"
    )


def markdown(
    meta: dict, summary: pd.DataFrame, stats: pd.DataFrame, levels: dict, how: dict,
    frag: pd.DataFrame, command: str, extra: str = "",
) -> str:  # fmt: skip
    """The report's text."""
    methods = ", ".join(
        f"`{m}`" + (f" ({v['limit']} evenly spaced instances)" if v["limit"] else "")
        for m, v in meta["methods"].items()
    )
    out = [
        f"# Stress curves: preset {meta['preset']}",
        "",
        f"Made by `{command}` from the sweep's results (cloudpose/studies/stress.py, seed "
        f"{meta['seed']}). Sources: "
        + "; ".join(f"**{s}**: {d}" for s, d in meta["sources"].items())
        + f". Methods: {methods}; `{NETWORK}` is their checkpoints' mean"
        + (
            "; `ensemble` is the checkpoints as one (each estimate refined by ICP, per object "
            "the refinement of best ICP fitness kept; cloudpose evaluate --ensemble)"
            if "ensemble" in meta["methods"]
            else ""
        )
        + ". Every method is followed by the same ICP (the network by its run's own)"
        + _schedule(meta.get("icp_radius", PAPER_RADIUS))
        + ".",
        "",
        "Each perturbation acts on the frame's mask and depth before segmentation ("
        + ", ".join(p.name for p in PERTURBATIONS.values() if p.stage == "pixels")
        + ") or on the back-projected points before FPS (the others); level "
        f"{identity_level(PERTURBATIONS['dilate']):g} (x1 for points) is the unperturbed "
        "segment. Cells: ADS AUC / rotation < 10 deg modulo symmetry / translation < 1 cm / "
        "median translation error (mm).",
        "",
    ]
    out += _levels_section(levels, how)
    fragility, t_fragile = _fragility_section(frag)
    out += fragility
    fragile = sorted(set(frag[frag.fragile].perturbation))
    out += [
        "",
        "Fragile on ADS AUC (either source): " + (", ".join(fragile) or "none") + ". "
        "Translation-fragile at the real frames' level: " + (", ".join(t_fragile) or "none") + ".",
        "",
        "![ADS AUC per level](stress.png)",
        "",
        "![median translation per level](stress_translation.png)",
        "",
    ]
    out += _per_perturbation_section(summary, meta)
    out += _statistics_section(stats)
    if extra:
        out += ["", extra]
    return "\n".join(out) + "\n"


def _levels_section(levels: dict, how: dict) -> list[str]:
    """Where the real frames sit on each perturbation's scale."""
    out = [
        "## Where the real frames sit",
        "",
        "The real segments' statistic against the synthetic ones' at each level "
        "(cloudpose.studies.stress.real_level); the level is marked on the figures.",
        "",
        "| perturbation | real frames' level | how |",
        "|---|---:|---|",
    ]
    for name, p in PERTURBATIONS.items():
        if name not in levels:
            continue
        lv = levels[name]
        cell = f"{lv:.3g} {p.unit}" if np.isfinite(lv) else "not placed"
        out.append(f"| {name}: {p.what} | {cell} | {how[name]} |")
    return out


def _fragility_section(frag: pd.DataFrame) -> tuple[list[str], list[str]]:
    """The fragility tables (ADS AUC lost; translation at the real frames' level) and the
    perturbations the network's translation is fragile to."""
    ensemble = "ensemble@fpfh_at_real" in frag and bool(frag["ensemble@fpfh_at_real"].notna().any())
    out = ["", "## Fragility", ""]
    out += [
        "ADS AUC (after ICP) lost from the unperturbed segments to the real frames' level and to "
        "the largest level, in points (real level unplaced: the largest only). Paired: the "
        "network on the instances FPFH + RANSAC ran on, and on those point-pair features ran "
        f"on. **fragile** = on FPFH's instances the network loses more than {FRAGILE_PP:g} "
        "points more than FPFH + RANSAC at the largest level. Last column: network + ICP minus "
        "FPFH + RANSAC + ICP at the real frames' level, same instances"
        + (", and the same for the ensemble + ICP." if ensemble else "."),
        "",
        "| source | perturbation | real level | network (all) | network (FPFH's) | FPFH "
        "| network (PPF's) | PPF | network - FPFH at real | "
        + ("ensemble - FPFH at real | " if ensemble else "")
        + "fragile |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|" + ("---:|" if ensemble else "") + "---|",
    ]

    def pair(r, m):
        return f"{r[f'{m}_loss_real']:.1f} / {r[f'{m}_loss_far']:.1f}"

    for _, r in frag.iterrows():
        lv = r.real_level
        gap = r[f"{NETWORK}@fpfh_at_real"] - r["fpfh_at_real"]
        ens = f"{r['ensemble@fpfh_at_real'] - r['fpfh_at_real']:+.1f} | " if ensemble else ""
        out.append(
            f"| {r.source} | {r.perturbation} | {lv:.3g} | {pair(r, NETWORK)} | "
            f"{pair(r, NETWORK + '@fpfh')} | {pair(r, 'fpfh')} | {pair(r, NETWORK + '@ppf')} | "
            f"{pair(r, 'ppf')} | {gap:+.1f} | {ens}{'**fragile**' if r.fragile else ''} |"
        )
    placed = frag[np.isfinite(frag.real_level.astype(float))]
    tally = [("network + ICP", placed[f"{NETWORK}@fpfh_at_real"])]
    if ensemble:
        tally.append(("the ensemble + ICP", placed["ensemble@fpfh_at_real"]))
    at_or_above = "; ".join(
        f"{label} on {int((at >= placed['fpfh_at_real'] - AT_OR_ABOVE_PP).sum())}"
        for label, at in tally
    )
    out += [
        "",
        f"At the real frames' level, on FPFH's instances, at or above FPFH + RANSAC + ICP "
        f"(within {AT_OR_ABOVE_PP:g} point) on ADS AUC, of the {len(placed)} placed "
        f"(source, perturbation) pairs: {at_or_above}.",
    ]
    out += [
        "",
        "Synthetic segments brought to the real frames' level: median translation error (mm) "
        "at the identity -> at that level (interpolated between the levels on each side). "
        "**translation-fragile** = on FPFH's instances the network alone grows by more than "
        f"{FRAGILE_MM:g} mm more than FPFH + RANSAC + ICP does.",
        "",
        "| perturbation | real level | network | network + ICP | FPFH + RANSAC + ICP | |",
        "|---|---:|---:|---:|---:|---|",
    ]
    t_fragile = []
    for _, r in frag.iterrows():
        if r.source != "synth" or not np.isfinite(r.real_level):
            continue
        grow = (r[f"{NETWORK}@fpfh_net_treal"] - r[f"{NETWORK}@fpfh_net_t0"]) - (
            r["fpfh_icp_treal"] - r["fpfh_icp_t0"]
        )
        flag = bool(np.isfinite(grow) and grow > FRAGILE_MM)
        if flag:
            t_fragile.append(r.perturbation)
        cells = [
            f"{r[f'{m}_{s}_t0']:.1f} -> {r[f'{m}_{s}_treal']:.1f}"
            for m, s in ((NETWORK, "net"), (NETWORK, "icp"), ("fpfh", "icp"))
        ]
        out.append(
            f"| {r.perturbation} | {r.real_level:.3g} | " + " | ".join(cells)
            + f" | {'**translation-fragile**' if flag else ''} |"
        )  # fmt: skip
    return out, t_fragile


def _per_perturbation_section(summary: pd.DataFrame, meta: dict) -> list[str]:
    """One table per perturbation: every curve's cell at every level of each source."""
    out = ["## Per perturbation"]
    cols = [(m, s, label) for m, s, label, *_ in CURVES if m in set(summary.method)]
    for name, p in PERTURBATIONS.items():
        if name not in set(summary.perturbation):
            continue
        out += ["", f"### {name}: {p.what} [{p.unit}]", ""]
        out.append("| source | level | " + " | ".join(label for *_, label in cols) + " |")
        out.append("|---|---:|" + "---:|" * len(cols))
        for source in meta["sources"]:
            for lv in sorted(p.levels):
                cells = [_cell(summary, source, name, lv, m, s) for m, s, _ in cols]
                out.append(f"| {source} | {lv:g} | " + " | ".join(cells) + " |")
    return out


def _statistics_section(stats: pd.DataFrame) -> list[str]:
    """The segment statistics at each level, and what each is."""
    out: list[str] = []
    out += ["", "## Segment statistics per level", ""]
    keys = list(STATISTICS)
    out.append("| source | perturbation | level | " + " | ".join(keys) + " |")
    out.append("|---|---|---:|" + "---:|" * len(keys))
    for _, r in stats.iterrows():
        out.append(
            f"| {r.source} | {r.perturbation} | {r.level:g} | "
            + " | ".join(f"{r[k]:.3g}" for k in keys)
            + " |"
        )
    out += ["", *(f"- {k}: {v}" for k, v in STATISTICS.items())]
    return out


def per_pose_markdown(run_dir: Path) -> str:
    """Per object pose of the real frames (video/class) in the sweep: the network + ICP and FPFH
    + RANSAC + ICP at the identity, and which segment statistic lies farthest outside the
    synthetic segments' range (its percentile among the synthetic identity's), naming the
    perturbation that moves it: the candidate cause of a miss. "" without the results."""
    ident = ("dilate", 0.0)
    real_stats = result_path(run_dir, "real", *ident, "stats")
    syn_stats = result_path(run_dir, "synth", *ident, "stats")
    nets = sorted(result_path(run_dir, "real", *ident, "x").parent.glob("net-*.csv"))
    fpfh = result_path(run_dir, "real", *ident, "fpfh")
    if not (real_stats.is_file() and syn_stats.is_file() and nets and fpfh.is_file()):
        return ""
    rs, ss = pd.read_csv(real_stats), pd.read_csv(syn_stats)
    net = pd.concat([pd.read_csv(p) for p in nets])
    net = net.groupby(["frame_id", "instance"], as_index=False).mean(numeric_only=True)
    fp = pd.read_csv(fpfh)
    by_stat: dict[str, list[str]] = {}  # a statistic can place several perturbations
    for name, p in PERTURBATIONS.items():
        by_stat.setdefault(p.stat, []).append(name)
    stats = [k for k in by_stat if k in rs and k != "occlusion"]
    df = rs.merge(net, on=["frame_id", "instance"])
    df["pose"] = df.frame_id.str.split("/").str[0] + "/" + df["cls_id"].astype(int).astype(str)
    out = [
        "## Per object pose of the real frames: the candidate cause of each miss",
        "",
        "Real object poses (video/class id) among the sweep's real instances at the identity: "
        "network + ICP (mean over its checkpoints) and FPFH + RANSAC + ICP (on its subsample), "
        "rotation error modulo symmetry (deg) / translation error (mm), medians over the "
        "pose's instances; and the segment statistic whose median lies farthest towards more "
        "of its perturbation among the synthetic segments' (its percentile among them, 0-100; "
        "fewer points for count, either sign for bias), with that perturbation. A miss: "
        "rotation >= 10 deg or translation >= 1 cm. A few instances per pose: a pointer, not "
        "a measurement.",
        "",
        "| pose | instances | network + ICP | FPFH + ICP | miss | most atypical statistic "
        "(percentile among synthetic) | perturbation |",
        "|---|---:|---:|---:|---|---|---|",
    ]
    for pose, g in df.groupby("pose", sort=True):
        rot, tr = float(g.icp_rot_sym_err_deg.median()), 1000 * float(g.icp_trans_err.median())
        f = fp.merge(g[["frame_id", "instance"]], on=["frame_id", "instance"])
        fcell = (
            f"{f.icp_rot_sym_err_deg.median():.1f} / {1000 * f.icp_trans_err.median():.1f}"
            if len(f)
            else ""
        )
        pct = {}
        for k in stats:
            ref = ss[k].to_numpy(dtype=float)
            ref = ref[np.isfinite(ref)]
            v = float(g[k].median())
            if len(ref) and np.isfinite(v):
                pct[k] = 100 * float(np.mean(ref < v))
        k = max(pct, key=lambda k: _more_perturbed(k, pct[k])) if pct else None
        miss = "miss" if rot >= 10 or tr >= 10 else ""
        out.append(
            f"| {pose} | {len(g)} | {rot:.1f} / {tr:.1f} | {fcell} | {miss} | "
            + (f"{k} ({pct[k]:.0f})" if k else "")
            + f" | {' or '.join(by_stat.get(k, []))} |"
        )
    return "\n".join(out)


def _more_perturbed(stat: str, percentile: float) -> float:
    """How far a percentile among synthetic segments lies towards more of the perturbation:
    fewer points for ``count``, either sign for ``bias``, more of the others."""
    if stat == "count":
        return 100 - percentile
    if stat == "bias":
        return 50 + abs(percentile - 50)
    return percentile


ICP_SELECTIONS = ("starts1", "starts24-fitness", "starts24-depth", "starts60-fitness",
                  "starts60-depth")  # fmt: skip
"""The ICP settings of a sweep's comparison of start selections (``OUT/icp_select/``, one
table per source, setting and network): the run's own (one start), and 24 / 60 starts scored
by fitness alone or by the depth. The study that computed them (``cloudpose stress
--icp-selection``) is retired, answered since by ``cloudpose compare --refine select=``; its
results, where a sweep folder holds them (the committed ``cpu-online`` sweep does), are still
reported."""


def collect_icp_selection(out_dir: Path) -> pd.DataFrame:
    """One row per (source, setting, network) of a sweep's start-selection results: the
    summary after ICP (:func:`cloudpose.studies.stress.summary_of`) and the instance count."""
    rows = []
    for path in sorted((out_dir / "icp_select").glob("*/*/*.csv")):
        table = pd.read_csv(path)
        rows.append(
            {
                "source": path.parent.parent.name,
                "setting": path.parent.name,
                "method": path.stem,
                **summary_of(table, "icp"),
                "seconds_per_instance": float(table["seconds"].iloc[0]) / max(len(table), 1),
            }
        )
    return pd.DataFrame(rows)


def icp_selection_markdown(run_dir: Path) -> str:
    """The section comparing how ICP starts are chosen (:data:`ICP_SELECTIONS`), or "" without
    its results."""
    df = collect_icp_selection(run_dir)
    if df.empty:
        return ""
    order = list(ICP_SELECTIONS)
    out = [
        "## Choosing among ICP starts: fitness or agreement with the depth",
        "",
        "The network's estimate refined by ICP from one start (the run's own), or from 24 / 60 "
        "turned starts keeping the best by ICP's fitness alone (`icp.select = fitness`) or by "
        "(fitness + coverage) / 2 - free-space violations against the observed depth "
        "(`icp.select = depth`, cloudpose.refine.depth_score), on the unperturbed segments. "
        "Cells: ADS AUC / rotation < 10 deg modulo symmetry / translation < 1 cm / median "
        "translation (mm); ms: ICP time per object.",
        "",
        "| source | network | instances | " + " | ".join(order) + " |",
        "|---|---|---:|" + "---:|" * len(order),
    ]
    for (source, method), g in df.groupby(["source", "method"], sort=True):
        cells = []
        for name in order:
            r = g[g.setting == name]
            if r.empty:
                cells.append("")
                continue
            r = r.iloc[0]
            cells.append(
                f"{100 * r.ads_auc:.1f} / {100 * r.rot_sym_lt_10deg:.0f}% / "
                f"{100 * r.trans_lt_1cm:.0f}% / {r.trans_median_mm:.1f} "
                f"({1000 * r.seconds_per_instance:.0f} ms)"
            )
        n = int(g["count"].iloc[0])
        out.append(f"| {source} | {method} | {n} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def report_folder(
    preset: str,
    project_dir: Path,
    out_dir: Path | None,
    default: Path,
    run_dir: Path,
    echo: Callable[[str], object],
) -> Path:
    """Where the stress report of the sweep in ``run_dir`` may be written: ``out_dir``, else
    ``default``; a folder that keeps the results its report was rendered from
    (:data:`PACKED_RESULTS`) is rendered over only by results holding each of those files,
    else into ``runs/reports/PRESET`` (:func:`cloudpose.report.committed.guarded_folder`)."""
    target = Path(out_dir) if out_dir is not None else Path(default)
    packed = target / PACKED_RESULTS
    if not packed.is_file():
        return target
    with tarfile.open(packed, "r:*") as tar:
        theirs = {m.name for m in tar.getmembers() if m.isfile()}
    ours = {f.relative_to(run_dir).as_posix() for f in result_files(run_dir)}
    named = out_dir is not None
    return guarded_folder(preset, project_dir, target, named, theirs, ours, "result files", echo)


def render_stress_report(run_dir: Path, out_dir: Path, command: str, extra: str = "") -> list[Path]:
    """``stress.md``, ``stress.csv``, ``stress.png`` and ``stress_translation.png`` in
    ``out_dir`` from the sweep in ``run_dir`` (:func:`cloudpose.studies.stress.run_sweep`);
    ``extra`` is appended to the text (a further section in markdown)."""
    meta = json.loads((run_dir / "sweep.json").read_text())
    summary = with_network_mean(collect(run_dir))
    if summary.empty:
        raise ValueError(f"{run_dir}: no stress result yet (run `cloudpose stress` first)")
    stats = collect_stats(run_dir)
    levels, how = {}, {}
    for name in meta["perturbations"]:
        levels[name], how[name] = real_level(PERTURBATIONS[name], stats)
    frag = fragility(summary, levels)
    out_dir.mkdir(parents=True, exist_ok=True)
    footer = f"made by {command}; preset {meta['preset']}; seed {meta['seed']}"
    files = [
        plot_metric(summary, levels, "ads_auc", out_dir / "stress.png", "ADS AUC (%)", footer,
                    100.0),
        plot_metric(summary, levels, "trans_median_mm", out_dir / "stress_translation.png",
                    "median translation error (mm)", footer),
    ]  # fmt: skip
    csv = out_dir / "stress.csv"
    summary.round(5).to_csv(csv, index=False)
    md = out_dir / "stress.md"
    sections = (icp_selection_markdown(run_dir), per_pose_markdown(run_dir), extra)
    extra = "\n\n".join(x for x in sections if x)
    md.write_text(markdown(meta, summary, stats, levels, how, frag, command, extra))
    return [md, csv, *files]
