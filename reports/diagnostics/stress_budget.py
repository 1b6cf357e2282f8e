"""Stress perturbations at several training budgets, paired on the instances a classical
baseline ran on.

Each ``--net LABEL=DIR`` is the results folder of a ``cloudpose stress`` sweep that evaluated
one network (method ``--method``, e.g. ``net-seed1``); ``--baseline`` is the folder whose sweep
also ran FPFH + RANSAC (method ``fpfh``) on a subsample. Every network is scored on the
baseline's instances only (matched by frame and instance), so the rows compare the same
segments; a network whose sweep lacks a perturbation is left out of that perturbation's rows::

    python reports/diagnostics/stress_budget.py --perturbation dilate --perturbation bias \\
        --perturbation points --method net-seed1 \\
        --net cpu-online=runs/stress/x1 --net cpu-online-4x=runs/stress/x4 \\
        --net gpu=runs/stress/gpu1 --baseline runs/stress/gpu1 \\
        --out reports/diagnostics/stress_budget.md

Writes the Markdown (per perturbation: where the real development frames sit, then ADS AUC,
rotation < 10 deg modulo symmetry and median translation per level, without / with ICP), a
CSV beside it and a plot (``.png``: ADS AUC after ICP and the median translation without it,
the real frames' level marked).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from cloudpose.files import atomic_write
from cloudpose.studies.perturbations import PERTURBATIONS
from cloudpose.studies.stress import (
    collect_stats,
    level_result_path,
    real_level,
    summary_of,
)

BASELINE = "fpfh"
FIGURES = (  # column, scale, heading
    ("ads_auc", 100.0, "ADS AUC"),
    ("rot_sym_lt_10deg", 100.0, "rot < 10 deg mod sym (%)"),
    ("trans_median_mm", 1.0, "median translation (mm)"),
)


def _sweep(folder: Path) -> dict:
    """The ``sweep.json`` of the stress sweep in ``folder``."""
    return json.loads((folder / "sweep.json").read_text())


def _levels(folder: Path, perturbation: str) -> list[float]:
    """Levels of ``perturbation`` in the sweep of ``folder``."""
    perturbations = _sweep(folder)["perturbations"]
    if perturbation not in perturbations:
        raise ValueError(f"{folder}/sweep.json: no {perturbation!r} in its perturbations")
    return sorted(float(lv) for lv in perturbations[perturbation])


def _table(folder: Path, source: str, perturbation: str, level: float, method: str) -> Path:
    """The result file of ``method`` at ``level``."""
    path = level_result_path(folder, source, perturbation, level, method)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no result of {method} (run its stress sweep first)")
    return path


def paired(nets: dict[str, Path], baseline: Path, perturbation: str, method: str) -> pd.DataFrame:
    """One row per (source, level, method, stage) of ``perturbation``: the summary on the
    baseline's instances. A network whose sweep lacks the perturbation is left out."""
    sources = _sweep(baseline)["sources"]
    levels = _levels(baseline, perturbation)
    nets = {k: v for k, v in nets.items() if perturbation in _sweep(v)["perturbations"]}
    rows = []
    for src in sources:
        for lv in levels:
            base = pd.read_csv(_table(baseline, src, perturbation, lv, BASELINE))
            keys = base[["frame_id", "instance"]]
            tables = {BASELINE: base}
            for label, folder in nets.items():
                net = pd.read_csv(_table(folder, src, perturbation, lv, method))
                tables[label] = net.merge(keys, on=["frame_id", "instance"])
                if len(tables[label]) != len(base):
                    raise ValueError(
                        f"{folder}: {method} at {src} {perturbation}={lv} lacks some of "
                        f"{BASELINE}'s {len(base)} instances (has {len(tables[label])})"
                    )
            for label, table in tables.items():
                for stage in ("net", "icp"):
                    rows.append(
                        {
                            "perturbation": perturbation,
                            "source": src,
                            "level": lv,
                            "method": label,
                            "stage": stage,
                            **summary_of(table, stage),
                        }
                    )
    return pd.DataFrame(rows)


def real_levels(baseline: Path, perturbations: list[str]) -> dict[str, float]:
    """Where the real development frames sit on each perturbation's axis
    (:func:`cloudpose.studies.stress.real_level` from the baseline sweep's segment statistics)."""
    stats = collect_stats(baseline)
    return {p: float(real_level(PERTURBATIONS[p], stats)[0]) for p in perturbations}


def markdown(df: pd.DataFrame, levels: dict[str, float], command: str) -> str:
    n = sorted({int(c) for c in df["count"]})
    lines = [
        "# Stress curves of networks at several budgets against FPFH + RANSAC",
        "",
        f"Made by `{command}`. Every method on the same instances ({', '.join(map(str, n))} "
        "per source, FPFH + RANSAC's subsample of the stress sweep): read the differences, "
        "not the decimals. Cells: without ICP / with ICP (each method's own ICP). The real "
        "development frames' level on each axis is `cloudpose.studies.stress.real_level`'s.",
        "",
    ]
    for pert, part in df.groupby("perturbation", sort=False):
        p = PERTURBATIONS[pert]
        methods = list(dict.fromkeys(part["method"]))
        real = levels.get(pert, float("nan"))
        where = f"{real:.3g} {p.unit}" if np.isfinite(real) else "not placed"
        lines += [f"## {pert}: {p.what} [{p.unit}]", "", f"Real frames' level: {where}.", ""]
        for col, scale, head in FIGURES:
            lines += [f"### {head}", "", "| source | level | " + " | ".join(methods) + " |"]
            lines.append("|---|---:|" + "---:|" * len(methods))
            for (src, lv), g in part.groupby(["source", "level"], sort=False):
                cells = []
                for m in methods:
                    v = g[g["method"] == m].set_index("stage")[col] * scale
                    cells.append(f"{v['net']:.1f} / {v['icp']:.1f}")
                lines.append(f"| {src} | {lv:g} | " + " | ".join(cells) + " |")
            lines.append("")
    return "\n".join(lines)


def plot(df: pd.DataFrame, levels: dict[str, float], out: Path) -> None:
    perts = list(dict.fromkeys(df["perturbation"]))
    sources = list(dict.fromkeys(df["source"]))
    shown = (
        ("ads_auc", 100.0, "icp", "ADS AUC + ICP"),
        ("trans_median_mm", 1.0, "net", "median translation, no ICP (mm)"),
    )
    cols = [(src, s) for s in shown for src in sources]
    nets = [m for m in dict.fromkeys(df["method"]) if m != BASELINE]
    colour = {m: f"C{k}" for k, m in enumerate(nets)}  # one colour a network in every panel
    fig, axes = plt.subplots(
        len(perts), len(cols), figsize=(4.2 * len(cols), 3.3 * len(perts)), squeeze=False
    )
    for i, pert in enumerate(perts):
        for j, (src, (col, scale, stage, title)) in enumerate(cols):
            ax = axes[i][j]
            sub = df[(df["perturbation"] == pert) & (df["source"] == src) & (df["stage"] == stage)]
            for m, g in sub.groupby("method", sort=False):
                g = g.sort_values("level")
                if m == BASELINE:
                    ax.plot(g["level"], g[col] * scale, "k--", label=m)
                else:
                    ax.plot(g["level"], g[col] * scale, "-o", color=colour[m], label=m, ms=4)
            real = levels.get(pert, float("nan"))
            if np.isfinite(real):
                ax.axvline(real, color="tab:red", lw=0.8, ls=":", label="real frames' level")
            ax.set_title(f"{src}: {title}", fontsize=9)
            ax.set_xlabel(f"{pert} [{PERTURBATIONS[pert].unit}]", fontsize=8)
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    atomic_write(out, lambda tmp: fig.savefig(tmp, dpi=100), suffix=".png")
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--perturbation", action="append", required=True, choices=sorted(PERTURBATIONS))
    ap.add_argument("--method", default="net-seed1", help="the network's method in each sweep")
    ap.add_argument("--net", action="append", required=True, metavar="LABEL=DIR")
    ap.add_argument("--baseline", required=True, type=Path, help="sweep that ran fpfh")
    ap.add_argument("--out", required=True, type=Path, help="Markdown; .csv and .png beside")
    args = ap.parse_args(argv)
    nets = {}
    for item in args.net:
        label, sep, folder = item.partition("=")
        if not sep:
            ap.error(f"--net {item!r}: expected LABEL=DIR")
        nets[label] = Path(folder)
    df = pd.concat([paired(nets, args.baseline, p, args.method) for p in args.perturbation])
    levels = real_levels(args.baseline, args.perturbation)
    command = "python " + shlex.join(
        ["reports/diagnostics/stress_budget.py", *(argv or sys.argv[1:])]
    )
    out = args.out
    text = markdown(df, levels, command)
    atomic_write(out, lambda tmp: Path(tmp).write_text(text), suffix=".md")
    atomic_write(out.with_suffix(".csv"), lambda tmp: df.to_csv(tmp, index=False), suffix=".csv")
    plot(df, levels, out.with_suffix(".png"))
    print(f"wrote {out}, {out.with_suffix('.csv')}, {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
