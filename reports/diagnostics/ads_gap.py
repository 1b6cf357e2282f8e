"""Where does the network lose ADS AUC to a classical baseline? The gap split over the test
instances by how far off each method's rotation is, and over classes.

The YCB-Video toolbox's AUC (:func:`cloudpose.metrics.summaries.voc_ap_auc`) integrates the
accuracy curve over 0-10 cm; for ``n`` instances with distances ``d_i`` it equals
``100 * (1 - mean_i min(d_i, 10 cm) / 10 cm)`` up to ``100 / n`` pp (the staircase counts each
instance from its own distance on). So the AUC gap of two methods on the same instances is,
to that precision, the mean over instances of ``100 * (min(d_other, 10 cm) - min(d_net, 10
cm)) / 10 cm``: additive, and each instance's share of it can be summed over any group of
instances. This script sums it over cells of (the network's rotation error modulo symmetry,
the baseline's) in bins < 10, 10-30 and >= 30 degrees, and over classes; a positive number is
AUC the network loses. The network's runs are pooled: every figure is the mean over them.

Runs are read by MLflow run name from the store of the current folder (the newest run of a
name), e.g. in the project that holds the default's sweep::

    python reports/diagnostics/ads_gap.py --baseline baseline-fpfh/cpu-online/seed1 \\
        --run shared-0/cpu-online/seed1 ... --run shared-0/cpu-online/seed5 \\
        > reports/diagnostics/ads_gap.md

With a baseline evaluated on a subsample of the test set (point-pair features' 250 instances)
only the instances both hold are compared.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from cloudpose.metrics.summaries import AUC_MAX_THRESHOLD, voc_ap_auc
from cloudpose.store import instances as instance_tables
from cloudpose.store import tracking

BINS = (0.0, 10.0, 30.0, np.inf)
LABELS = ("< 10", "10-30", ">= 30")
KEY = ["frame_id", "instance"]
STAGES = {"net": "without ICP", "icp": "with ICP"}


def instances(client, name: str) -> pd.DataFrame:
    """``eval/test/instances.csv`` of the newest finished run named ``name``."""
    run = tracking.newest_run_named(client, name)
    if run is None:
        raise SystemExit(f"no finished run named {name!r} in the MLflow store of {Path.cwd()}")
    return instance_tables.read_artifact_table(client, run, "eval/test/instances.csv")


def auc_loss(ads: pd.Series) -> np.ndarray:
    """Each instance's share of ``100 - AUC``, pp (misses count as the full 10 cm)."""
    d = np.nan_to_num(ads.to_numpy(dtype=np.float64), nan=np.inf)
    return 100.0 * np.minimum(d, AUC_MAX_THRESHOLD) / AUC_MAX_THRESHOLD


def gap_table(net: list[pd.DataFrame], base: pd.DataFrame, stage: str) -> pd.DataFrame:
    """One row per network run: the AUCs, the gap and its split over the rotation-bin cells."""
    rows = []
    for k, df in enumerate(net):
        m = df.merge(base, on=KEY, suffixes=("", "_b"))
        gap = auc_loss(m[f"{stage}_ads"]) - auc_loss(m[f"{stage}_ads_b"])
        bn = pd.cut(m[f"{stage}_rot_sym_err_deg"], BINS, right=False, labels=LABELS)
        bb = pd.cut(m[f"{stage}_rot_sym_err_deg_b"], BINS, right=False, labels=LABELS)
        row = {
            "run": k,
            "n": len(m),
            "auc_net": 100 * voc_ap_auc(m[f"{stage}_ads"].to_numpy()),
            "auc_base": 100 * voc_ap_auc(m[f"{stage}_ads_b"].to_numpy()),
            "gap": gap.mean(),
        }
        for a in LABELS:
            for b in LABELS:
                cell = (bn == a).to_numpy() & (bb == b).to_numpy()
                row[(a, b, "share")] = 100 * cell.mean()
                row[(a, b, "gap")] = gap[cell].sum() / len(m)
        both = (bn == LABELS[0]).to_numpy() & (bb == LABELS[0]).to_numpy()
        for col, out in ((f"{stage}_trans_err", "t"), (f"{stage}_ads", "ads")):
            row[f"{out}_net"] = 1000 * m.loc[both, col].median()
            row[f"{out}_base"] = 1000 * m.loc[both, f"{col}_b"].median()
        rows.append(row)
    return pd.DataFrame(rows)


def class_gaps(net: list[pd.DataFrame], base: pd.DataFrame, stage: str) -> pd.DataFrame:
    """Per class: instances, the gap each class adds to the whole (pp), its own AUC gap."""
    parts = []
    for df in net:
        m = df.merge(base, on=KEY, suffixes=("", "_b"))
        gap = auc_loss(m[f"{stage}_ads"]) - auc_loss(m[f"{stage}_ads_b"])
        parts.append(
            pd.DataFrame({"class": m["class"], "gap": gap, "n_all": len(m)})
            .groupby("class")
            .agg(n=("gap", "size"), total=("gap", "sum"), n_all=("n_all", "first"))
        )
    per = pd.concat(parts).groupby("class").mean()
    per["adds"] = per.total / per.n_all
    per["own"] = per.total / per.n
    return per.sort_values("adds", ascending=False)


def markdown(net: list[pd.DataFrame], base: pd.DataFrame, baseline: str) -> str:
    out = []
    for stage, title in STAGES.items():
        t = gap_table(net, base, stage)
        mean = t.mean(numeric_only=True)
        out.append(f"## {title}\n")
        out.append(
            f"{int(mean.n)} instances; ADS AUC network {mean.auc_net:.1f} (runs "
            f"{t.auc_net.min():.1f}-{t.auc_net.max():.1f}), {baseline} {mean.auc_base:.1f}; "
            f"gap {mean.gap:+.2f} pp (runs {t.gap.min():+.2f} to {t.gap.max():+.2f}; "
            f"positive: the network behind).\n"
        )
        out.append(
            "Share of instances / gap each cell adds (pp), by rotation error modulo "
            "symmetry (deg), mean over the network's runs:\n"
        )
        out.append(f"| network \\ {baseline} | " + " | ".join(LABELS) + " | row total |")
        out.append("|---|" + "---:|" * (len(LABELS) + 1))
        for a in LABELS:
            cells = [f"{mean[(a, b, 'share')]:.1f}% / {mean[(a, b, 'gap')]:+.2f}" for b in LABELS]
            share = sum(mean[(a, b, "share")] for b in LABELS)
            gap = sum(mean[(a, b, "gap")] for b in LABELS)
            out.append(f"| {a} | " + " | ".join(cells) + f" | {share:.1f}% / {gap:+.2f} |")
        out.append(
            f"\nWhere both are under 10 degrees: median translation error {mean.t_net:.1f} mm "
            f"(network) against {mean.t_base:.1f} mm, median ADS {mean.ads_net:.2f} against "
            f"{mean.ads_base:.2f} mm.\n"
        )
        err = pd.concat([df[f"{stage}_rot_sym_err_deg"] for df in net])
        gross = err[err >= BINS[2]]
        split = pd.cut(gross, [BINS[2], 90.0, 150.0, np.inf], right=False).value_counts(sort=False)
        shares = ", ".join(
            f"{100 * v / len(gross):.0f}% in {iv.left:.0f}-{min(iv.right, 180.0):.0f}"
            for iv, v in split.items()
        )
        out.append(
            f"The network's rotations >= {BINS[2]:.0f} degrees off (modulo symmetry, on all "
            f"{len(net[0])} test instances of each run): {shares} degrees (near half turns: "
            f">= 150).\n"
        )
        per = class_gaps(net, base, stage)
        out.append(
            "Classes adding the most to the gap (pp of the whole; own: the class's AUC gap):\n"
        )
        out.append("| class | instances | adds | own |")
        out.append("|---|---:|---:|---:|")
        for cls, r in per.head(8).iterrows():
            out.append(f"| {cls} | {r.n:.0f} | {r.adds:+.2f} | {r.own:+.1f} |")
        rest = per.iloc[8:]
        out.append(f"| the other {len(rest)} | {rest.n.sum():.0f} | {rest.adds.sum():+.2f} | |\n")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", required=True, help="network run name (repeatable)")
    ap.add_argument("--baseline", required=True, help="baseline run name")
    args = ap.parse_args()
    client = tracking.setup(Path.cwd())
    net = [instances(client, n) for n in args.run]
    base = instances(client, args.baseline)
    cmd = shlex.join(["python", "reports/diagnostics/ads_gap.py", *sys.argv[1:]])
    label = args.baseline.split("/")[0].removeprefix("baseline-").upper()
    print(f"# Where the network loses ADS AUC to {label}\n")
    print(f"_made by `{cmd}`; network runs: {', '.join(args.run)}._\n")
    print(markdown(net, base, label))


if __name__ == "__main__":
    main()
