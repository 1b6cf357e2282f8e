"""One perturbation of the stress curves at several training budgets, paired on the instances
a classical baseline ran on.

Each ``--net LABEL=DIR`` is the results folder of a ``cloudpose stress`` sweep that evaluated
one network (method ``--method``, e.g. ``net-seed1``) under ``--perturbation``; ``--baseline``
is the folder whose sweep also ran FPFH + RANSAC (method ``fpfh``) on a subsample. Every
network is scored on the baseline's instances only (matched by frame and instance), so the
rows compare the same segments::

    python reports/diagnostics/stress_budget.py --perturbation dilate --method net-seed1 \\
        --net cpu-online=runs/stress/x1 --net cpu-online-4x=runs/stress/x4 \\
        --net gpu=runs/stress/gpu1 --baseline runs/stress/gpu1 \\
        --out reports/diagnostics/stress_budget.md

Writes the Markdown (ADS AUC, rotation < 10 deg modulo symmetry and median translation per
level, without / with ICP), a CSV beside it and a plot (``.png``).
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
import pandas as pd

from cloudpose.files import atomic_write
from cloudpose.stress import PERTURBATIONS, identity_level, result_path, summary_of

BASELINE = "fpfh"
FIGURES = (  # column, scale, heading
    ("ads_auc", 100.0, "ADS AUC"),
    ("rot_sym_lt_10deg", 100.0, "rot < 10 deg mod sym (%)"),
    ("trans_median_mm", 1.0, "median translation (mm)"),
)


def _levels(folder: Path, perturbation: str) -> list[float]:
    """Levels of ``perturbation`` in the sweep of ``folder`` (its ``sweep.json``)."""
    meta = json.loads((folder / "sweep.json").read_text())
    if perturbation not in meta["perturbations"]:
        raise ValueError(f"{folder}/sweep.json: no {perturbation!r} in its perturbations")
    return [float(lv) for lv in meta["perturbations"][perturbation]]


def _table(folder: Path, source: str, perturbation: str, level: float, method: str) -> Path:
    """The result file of ``method`` at ``level`` (the identity is stored once, under dilate)."""
    p = PERTURBATIONS[perturbation]
    name, lv = ("dilate", 0.0) if level == identity_level(p) else (perturbation, level)
    path = result_path(folder, source, name, lv, method)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no result of {method} (run its stress sweep first)")
    return path


def paired(nets: dict[str, Path], baseline: Path, perturbation: str, method: str) -> pd.DataFrame:
    """One row per (source, level, method, stage): the summary on the baseline's instances."""
    sources = json.loads((baseline / "sweep.json").read_text())["sources"]
    rows = []
    for src in sources:
        for lv in _levels(baseline, perturbation):
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
                            "source": src,
                            "level": lv,
                            "method": label,
                            "stage": stage,
                            **summary_of(table, stage),
                        }
                    )
    return pd.DataFrame(rows)


def markdown(df: pd.DataFrame, perturbation: str, command: str) -> str:
    p = PERTURBATIONS[perturbation]
    methods = list(dict.fromkeys(df["method"]))
    n = sorted({int(c) for c in df["count"]})
    lines = [
        f"# {perturbation}: {p.what} [{p.unit}], networks at several budgets against FPFH + RANSAC",
        "",
        f"Made by `{command}`. Every method on the same instances ({', '.join(map(str, n))} "
        "per source, FPFH + RANSAC's subsample of the stress sweep): read the differences, "
        "not the decimals. Cells: without ICP / with ICP (each method's own ICP).",
        "",
    ]
    for col, scale, head in FIGURES:
        lines += [f"## {head}", "", "| source | level | " + " | ".join(methods) + " |"]
        lines.append("|---|---:|" + "---:|" * len(methods))
        for (src, lv), g in df.groupby(["source", "level"], sort=False):
            cells = []
            for m in methods:
                v = g[g["method"] == m].set_index("stage")[col] * scale
                cells.append(f"{v['net']:.1f} / {v['icp']:.1f}")
            lines.append(f"| {src} | {lv:g} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def plot(df: pd.DataFrame, perturbation: str, out: Path) -> None:
    sources = list(dict.fromkeys(df["source"]))
    shown = (
        ("ads_auc", 100.0, "icp", "ADS AUC + ICP"),
        ("trans_median_mm", 1.0, "net", "median translation, no ICP (mm)"),
    )
    fig, axes = plt.subplots(len(shown), len(sources), figsize=(5 * len(sources), 7), squeeze=False)
    for j, src in enumerate(sources):
        for i, (col, scale, stage, title) in enumerate(shown):
            ax = axes[i][j]
            for m, g in df[(df["source"] == src) & (df["stage"] == stage)].groupby(
                "method", sort=False
            ):
                style = "k--" if m == BASELINE else "-o"
                ax.plot(g["level"], g[col] * scale, style, label=m, markersize=4)
            ax.set_title(f"{src}: {title}")
            ax.set_xlabel(f"{perturbation} [{PERTURBATIONS[perturbation].unit}]")
            ax.grid(alpha=0.3)
    axes[0][0].legend()
    fig.tight_layout()
    atomic_write(out, lambda tmp: fig.savefig(tmp, dpi=110), suffix=".png")
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--perturbation", required=True, choices=sorted(PERTURBATIONS))
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
    df = paired(nets, args.baseline, args.perturbation, args.method)
    command = "python " + shlex.join(
        ["reports/diagnostics/stress_budget.py", *(argv or sys.argv[1:])]
    )
    out = args.out
    atomic_write(
        out,
        lambda tmp: Path(tmp).write_text(markdown(df, args.perturbation, command)),
        suffix=".md",
    )
    atomic_write(out.with_suffix(".csv"), lambda tmp: df.to_csv(tmp, index=False), suffix=".csv")
    plot(df, args.perturbation, out.with_suffix(".png"))
    print(f"wrote {out}, {out.with_suffix('.csv')}, {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
