"""How far off can an estimate be for ICP to bring it home? The paper's schedule starts at a
1 cm correspondence radius; a wider first radius (``icp.radius``,
:func:`cloudpose.refine.schedule_for`: more iterations at the same 10% shrink, ending at the
paper's last radius) against it, for the network and the classical baselines alike.

Every estimate is read from a logged evaluation (``net_R`` / ``net_t`` of
``eval/{split}/instances.csv``), so no network and no registration runs here: only ICP, from
the estimate alone (one start), on the same segments the evaluation used; as a control, ICP
from no estimate (the identity rotation at the segment's mean) shows what the refinement finds
alone. The paper's radius is checked against the logged refinement
(``multi_start_icp.same_refinement``). Runs are read
by MLflow run name from the store of the current folder, e.g. in the project that holds the
default's sweep::

    python reports/diagnostics/icp_radius.py --split test \\
        --run shared-0/cpu-online/seed1 ... --run shared-0/cpu-online/seed8 \\
        --baseline baseline-fpfh/cpu-online/seed1 --baseline baseline-ppf/cpu-online/seed1 \\
        > reports/diagnostics/icp_radius_test.md

The radius a user should take is chosen on the synthetic test set by the rule of
:func:`choose` (never on the real development frames, which only check it).
"""

from __future__ import annotations

import shlex
import sys
import time
from pathlib import Path

import numpy as np

from cloudpose.config import PAPER_RADIUS
from cloudpose.methods import instance_table, no_estimate
from cloudpose.refine import ICPSettings, refine_poses, schedule_for
from cloudpose.report.real import METRICS, table_metrics, versus_baseline
from cloudpose.store import tracking

sys.path.insert(0, str(Path(__file__).parent))
from multi_start_icp import (
    KEY,
    Segments,
    arguments,
    difference_cells,
    fmt,
    logged_segments,
    poses,
    same_refinement,
)

RADII = (PAPER_RADIUS, 0.02, 0.03, 0.05, 0.08, 0.12, 0.18, 0.25)
CHOOSE_WITHIN = 0.1  # points of the networks' mean ADS AUC: the smallest radius this near the best


def radius_label(radius: float) -> str:
    return f"{100 * radius:g} cm" + (" (paper)" if radius == PAPER_RADIUS else "")


def refined(
    client, name: str, split: str, radii, segments: Segments, control: bool = False
) -> dict:
    """The run's estimates refined from one start with each first radius: ``{radius: instance
    table}`` (``net_*``: the estimate, ``icp_*``: the refinement) and ICP's milliseconds per
    object at each radius. ``control``: no estimate instead (identity rotation at the segment
    mean, :func:`cloudpose.methods.no_estimate`) on the same segments."""
    table, segs, dataset, sym = logged_segments(client, name, split, segments)
    models = dataset.models()
    est = no_estimate(segs) if control else poses(table, "net")
    tables, ms = {}, {}
    n = max(int(segs.valid.sum()), 1)
    for radius in radii:
        t0 = time.perf_counter()
        ref, _ = refine_poses(segs, est, models, ICPSettings(**schedule_for(radius)))
        ms[radius] = 1000 * (time.perf_counter() - t0) / n
        out = instance_table(segs, {"net": est, "icp": ref}, models, dataset.classes, sym)
        if radius == PAPER_RADIUS and not control:
            same_refinement(name, out, table)
        tables[radius] = out
    return {"name": name, "tables": tables, "ms": ms}


def _values(results: list[dict], radius, keep) -> dict[str, list[float]]:
    """metric -> values over runs (percent; median translation in mm) after ICP at ``radius``
    (``None``: the estimate without ICP), on the instances ``keep`` (None: all)."""
    out: dict[str, list[float]] = {}
    for r in results:
        table = r["tables"][radius or PAPER_RADIUS]
        if keep is not None:
            table = table.set_index(KEY).loc[keep].reset_index()
        col = "net" if radius is None else "icp"
        m = table_metrics(table)
        for metric in METRICS:
            out.setdefault(metric, []).append(100 * m[(col, "pooled", metric)])
        out.setdefault("median_mm", []).append(1000 * np.nanmedian(table[f"{col}_trans_err"]))
    return out


def section(title: str, groups: list[tuple[str, list[dict]]], radii, keep=None) -> list[str]:
    cols = [None, *radii]
    heads = ["no ICP", *(radius_label(r) for r in radii)]
    lines = [f"## {title}", ""]
    labels = {**METRICS, "median_mm": "median translation error (mm)"}
    for metric, label in labels.items():
        lines += [f"**{label}{'' if metric == 'median_mm' else ' (%)'}**", ""]
        lines += [
            "| method | runs | " + " | ".join(heads) + " |",
            "|---|---:|" + "---:|" * len(cols),
        ]
        for method, results in groups:
            cells = [fmt(_values(results, c, keep)[metric]) for c in cols]
            lines.append(f"| {method} | {len(results)} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["**ICP, ms per object**", ""]
    lines += ["| method | " + " | ".join(heads[1:]) + " |", "|---|" + "---:|" * len(radii)]
    for method, results in groups:
        ms = [f"{np.mean([r['ms'][c] for r in results]):.1f}" for c in radii]
        lines.append(f"| {method} | " + " | ".join(ms) + " |")
    return [*lines, ""]


def choose(net: list[dict], radii) -> tuple[float, list[float]]:
    """The smallest radius whose networks' mean ADS AUC after ICP is within
    :data:`CHOOSE_WITHIN` points of the best radius's, and those means."""
    means = [float(np.mean(_values(net, r, None)["ads_auc"])) for r in radii]
    best = max(means)
    return next(r for r, m in zip(radii, means, strict=True) if m >= best - CHOOSE_WITHIN), means


def paired(net: list[dict], base: dict, radii) -> list[str]:
    """Network (mean over runs) minus baseline on the real frames, both refined with the same
    radius, and the network at each radius against the baseline with the paper's; a bootstrap
    over object poses and the network's runs."""
    lines = [
        "| metric | network's radius | baseline's radius | network − baseline (pp) | 95% interval | |",
        "|---|---|---|---:|---:|---|",
    ]
    for metric, label in METRICS.items():
        for radius in radii:
            pairs = [(radius, radius)] + (
                [(radius, PAPER_RADIUS)] if radius != PAPER_RADIUS else []
            )
            for mine, theirs in pairs:
                d = versus_baseline(
                    [r["tables"][mine] for r in net], base["tables"][theirs], metric, "icp"
                )
                lines.append(
                    f"| {label} | {radius_label(mine)} | {radius_label(theirs)} "
                    f"| {difference_cells(d)} |"
                )
    return [*lines, ""]


def main(argv: list[str] | None = None) -> None:
    ap = arguments(__doc__.split("\n\n")[0], "test")
    ap.add_argument("--radii", type=float, nargs="+", default=list(RADII), help="metres")
    args = ap.parse_args(argv)
    radii = sorted(set(args.radii) | {PAPER_RADIUS})
    client = tracking.setup(Path.cwd())
    segments = Segments(args.split, Path.cwd())
    net = [refined(client, n, args.split, radii, segments) for n in args.run]
    bases = [refined(client, n, args.split, radii, segments) for n in args.baseline]
    where = "the real development frames" if args.split == "real" else "the preset's test set"
    cmd = " ".join(
        shlex.quote(a)
        for a in ["python", "reports/diagnostics/icp_radius.py", *(argv or sys.argv[1:])]
    )
    chosen, means = choose(net, radii)
    at = ", ".join(f"{radius_label(r)} {m:.2f}" for r, m in zip(radii, means, strict=True))
    if args.split == "test":
        rule = (
            f"The rule, fixed before the runs and applied to the synthetic test set only: the "
            f"smallest radius whose networks' mean ADS AUC after ICP is within {CHOOSE_WITHIN} "
            f"point of the best radius's. Here (the networks' mean ADS AUC at each radius: "
            f"{at}): **{radius_label(chosen)}**."
        )
    else:
        rule = (
            f"The networks' mean ADS AUC after ICP at each radius: {at}. The radius a user "
            "should take is chosen on the synthetic test set (icp_radius_test.md); these frames "
            "only check it."
        )
    lines = [
        f"# ICP's first radius on {where}",
        "",
        f"_made by `{cmd}` in the project folder that holds the runs; the estimates are the logged ones, only ICP is redone; milliseconds on the machine that ran it, beside whatever else it ran._",
        "",
        "ICP from the estimate alone (one start). Each column's schedule starts at that correspondence radius and shrinks it by 10% an iteration, with as many iterations as bring it to the paper's last radius (3.9 mm, within 5%): "
        + ", ".join(f"{100 * r:g} cm x {schedule_for(r)['iterations']}" for r in radii)
        + " iterations (`cloudpose evaluate --icp-radius R`, `icp.radius`). Cells: mean ± sample SD over the network's runs; one value for a baseline.",
        "",
        rule,
        "",
    ]
    control = refined(client, args.run[0], args.split, radii, segments, control=True)
    lines += section(
        "All instances of the networks",
        [("network", net), ("no estimate (identity at the segment mean)", [control])],
        radii,
    )
    for b in bases:
        keep = b["tables"][PAPER_RADIUS].set_index(KEY).index
        lines += section(
            f"On the instances of {b['name']} ({len(keep)})",
            [("network", net), (b["name"], [b])],
            radii,
            keep,
        )
        if args.split == "real":
            lines += [
                f"Paired on the same instances, network (mean over its runs) − {b['name']}, 95% interval from a bootstrap over object poses and the network's runs:",
                "",
            ]
            lines += paired(net, b, radii)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
