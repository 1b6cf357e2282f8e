"""What limits the cpu-online network: rotation accuracy against Adam steps and against distinct
training segments, from the experiment log of the preset's runs.

Reads the CSV that ``cloudpose experiments --group shared --group diagnostics --preset
cpu-online --against cpu-online --out reports/diagnostics/cpu_online_experiments.md`` writes
beside its Markdown, and draws the share of instances under 10 degrees modulo symmetry (test
set and real development frames, without ICP) against the steps and against the distinct
segments a run drew (steps x batch / ``data.online_reuse``). Runs with changes other than
``train.epochs``, ``data.online_reuse`` and ``model.width`` are left out::

    python reports/diagnostics/online_budget.py reports/diagnostics/cpu_online_experiments.csv \\
        --out reports/diagnostics/online_budget.png
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pandas as pd

from cloudpose.registry import resolve

_PRESET = resolve("shared-0", "cpu-online")
BATCH, REUSE = _PRESET.train.batch_size, _PRESET.data.online_reuse
KEPT = ("train.epochs", "data.online_reuse", "model.width")


def budget_table(log: pd.DataFrame) -> pd.DataFrame:
    """One row per kept run: its changes parsed, steps, distinct segments and accuracies."""
    rows = []
    for _, r in log.iterrows():
        changes = (
            {}
            if r["changes"] == "(none)"
            else dict(kv.split("=", 1) for kv in re.split(r",\s*", r["changes"]))
        )
        if set(changes) - set(KEPT):
            continue
        reuse = int(changes.get("data.online_reuse", REUSE))
        rows.append(
            {
                "run": r["run"],
                "reuse": reuse,
                "width": float(changes.get("model.width", 1.0)),
                "steps": int(r["Adam steps"]),
                "segments": int(r["Adam steps"]) * BATCH // reuse,
                "test": r["test < 10° mod sym (%)"],
                "test_icp": r["test + ICP < 10° mod sym (%)"],
                "real": r["real < 10° mod sym (%)"],
                "real_icp": r["real + ICP < 10° mod sym (%)"],
            }
        )
    return pd.DataFrame(rows)


def plot(t: pd.DataFrame, out: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, x, label in (
        (axes[0], "steps", "Adam steps"),
        (axes[1], "segments", "distinct training segments"),
    ):
        for (reuse, width), g in t.groupby(["reuse", "width"]):
            g = g.sort_values(x)
            name = f"reuse {reuse}" + (f", width x{width:g}" if width != 1.0 else "")
            line = ax.plot(g[x], g["test"], "o-", label=f"test, {name}")[0]
            ax.plot(
                g[x], g["real"], "s--", color=line.get_color(), alpha=0.6, label=f"real, {name}"
            )
        ax.set_xscale("log", base=2)
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("rotation < 10° mod sym, no ICP (%)")
    axes[1].legend(fontsize=7, loc="lower right")
    fig.suptitle("cpu-online shared-0 (seed 1-3): accuracy against steps and fresh data")
    fig.tight_layout()
    fig.savefig(out, dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path, help="CSV of the cpu-online experiment log")
    ap.add_argument(
        "--out", type=Path, required=True, help="PNG to write (the table beside it as .csv)"
    )
    a = ap.parse_args()
    t = budget_table(pd.read_csv(a.log))
    t.to_csv(a.out.with_suffix(".csv"), index=False, float_format="%.1f")
    plot(t, a.out)
    print(t.to_string(index=False))


if __name__ == "__main__":
    main()
