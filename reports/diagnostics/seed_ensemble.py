"""Do networks of different seeds miss different object poses, and can the depth tell which
one is right? An ensemble over seeds: every network's estimate of an instance refined by the
run's ICP, the refinement kept that agrees best with the observed depth (``depth``:
:func:`cloudpose.refine.depth_score`, the score of ``icp.select = depth``) or with the segment
alone (``fitness``), against each network on its own and against the best of them per
instance (``oracle``, which reads the ground truth: the ceiling a selection could reach).

Every estimate is read from a logged evaluation (``net_R`` / ``net_t`` of
``eval/{split}/instances.csv``), so no network runs here; the one-start refinement is redone
on the same segments and checked against the logged one (``multi_start_icp.same_refinement``).
Subsets of ``k`` seeds: every combination of the runs given (up to ``--combinations`` of them,
evenly spaced), mean ± sample SD over the combinations. Runs are read by MLflow run name from
the store of the current folder, e.g. in the project that holds the default's sweep::

    python reports/diagnostics/seed_ensemble.py --split real \\
        --run shared-0/cpu-online/seed1 ... --run shared-0/cpu-online/seed8 \\
        --baseline baseline-fpfh/cpu-online/seed1+real-6b1ea2e9 \\
        > reports/diagnostics/seed_ensemble_real.md
"""

from __future__ import annotations

import itertools
import shlex
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from cloudpose.config import PAPER_RADIUS
from cloudpose.methods import instance_table, no_estimate
from cloudpose.refine import (
    Estimates,
    ICPSettings,
    refine_poses,
    refinement_scores,
    schedule_for,
    segment_views,
)
from cloudpose.report.real import METRICS, table_metrics, versus_baseline
from cloudpose.store import tracking

sys.path.insert(0, str(Path(__file__).parent))
from multi_start_icp import (
    KEY,
    Segments,
    arguments,
    logged,
    logged_segments,
    poses,
    same_refinement,
)

SELECTIONS = ("fitness", "depth", "oracle")


def hypotheses(
    client,
    name: str,
    split: str,
    segments: Segments,
    starts: int = 1,
    radius: float = PAPER_RADIUS,
    scores: bool = True,
    control: bool = False,
) -> dict:
    """One run's estimates refined by ICP on the segments its evaluation used (one start, or
    ``starts`` turned starts kept by the depth, ``icp.starts`` / ``icp.select = depth``; from
    the first radius ``radius``, :func:`cloudpose.refine.schedule_for`), each refinement's
    fitness and depth score (:func:`cloudpose.refine.refinement_scores`; not with ``scores``
    off, for a table alone), and the instance table of the refined poses. ``control``: the
    run's segments with no estimate instead of its own (:func:`cloudpose.methods.no_estimate`),
    refined the same way."""
    table, segs, dataset, sym = logged_segments(client, name, split, segments)
    models = dataset.models()
    est = no_estimate(segs) if control else poses(table, "net")
    if not control:
        refined, stats = refine_poses(segs, est, models)
        out = instance_table(segs, {"icp": refined}, models, dataset.classes, sym)
        same_refinement(name, out, table)
    views = segment_views(dataset, segs)
    if control or starts > 1 or radius != PAPER_RADIUS:
        many = ICPSettings(starts=starts, select="depth", **schedule_for(radius))
        refined, stats = refine_poses(segs, est, models, many, views=views)
        out = instance_table(segs, {"icp": refined}, models, dataset.classes, sym)
    score = {
        select: refinement_scores(segs, refined, stats, models, select, views)
        for select in (("fitness", "depth") if scores else ())
    }
    return {
        "name": name,
        "table": out,
        "segs": segs,
        "models": models,
        "classes": dataset.classes,
        "sym": sym,
        "poses": refined,
        "score": score,
    }


def ensemble(runs: list[dict], select: str) -> pd.DataFrame:
    """The instance table of the refinement each instance keeps among ``runs``: the highest
    score of ``select``, or the smallest rotation error modulo symmetry (``oracle``), the
    first run's on a tie."""
    if select == "oracle":
        err = np.stack([r["table"]["icp_rot_sym_err_deg"].to_numpy(float) for r in runs])
        pick = np.argmin(np.where(np.isfinite(err), err, np.inf), axis=0)
    else:
        pick = np.argmax(np.stack([r["score"][select] for r in runs]), axis=0)
    first = runs[0]
    kept = Estimates.kept([r["poses"] for r in runs], pick)
    return instance_table(
        first["segs"], {"icp": kept}, first["models"], first["classes"], first["sym"]
    )


def pooled(table: pd.DataFrame) -> dict[str, float]:
    """Pooled metrics after ICP (percent) and the median translation error (mm)."""
    m = {key: 100 * v for (col, video, key), v in table_metrics(table).items()
         if col == "icp" and video == "pooled"}  # fmt: skip
    m["trans_median_mm"] = 1000 * float(np.nanmedian(table["icp_trans_err"].to_numpy(float)))
    return m


def combinations(n: int, k: int, limit: int) -> list[tuple[int, ...]]:
    """Up to ``limit`` of the k-subsets of ``range(n)``, evenly spaced in lexicographic order."""
    every = list(itertools.combinations(range(n), k))
    if len(every) <= limit:
        return every
    return [every[i] for i in np.linspace(0, len(every) - 1, limit).round().astype(int)]


def fmt(values: list[float]) -> str:
    v = np.asarray(values, dtype=float)
    return f"{v.mean():.1f}" if len(v) == 1 else f"{v.mean():.1f} ± {v.std(ddof=1):.1f}"


COLUMNS = {**{k: f"{v} (%)" for k, v in METRICS.items()}, "trans_median_mm": "median trans. (mm)"}


def size_table(runs: list[dict], sizes: list[int], limit: int, keep=None) -> list[str]:
    """Rows: each selection at each ensemble size (1: the networks alone)."""
    lines = [
        "| seeds | selection | combinations | " + " | ".join(COLUMNS.values()) + " |",
        "|---:|---|---:|" + "---:|" * len(COLUMNS),
    ]
    for k in sizes:
        combos = combinations(len(runs), k, limit)
        for select in ("icp",) if k == 1 else SELECTIONS:
            vals: dict[str, list[float]] = {c: [] for c in COLUMNS}
            for combo in combos:
                chosen = [runs[i] for i in combo]
                table = chosen[0]["table"] if k == 1 else ensemble(chosen, select)
                if keep is not None:
                    table = table.set_index(KEY).loc[keep].reset_index()
                for c, v in pooled(table).items():
                    vals[c].append(v)
            name = "one network + ICP" if k == 1 else select
            lines.append(
                f"| {k} | {name} | {len(combos)} | "
                + " | ".join(fmt(vals[c]) for c in COLUMNS)
                + " |"
            )
    return [*lines, ""]


def per_pose(runs: list[dict]) -> list[str]:
    """Per object pose (video/class) of the real frames: the share of its instances within 10
    degrees modulo symmetry after ICP for each run and for the ensemble of all by depth."""
    from cloudpose.report.real import object_pose

    ens = ensemble(runs, "depth")
    pose = object_pose(runs[0]["table"])
    cols = {r["name"].rsplit("/", 1)[-1]: r["table"] for r in runs}
    cols[f"ensemble ({len(runs)}, depth)"] = ens
    share = (
        pd.DataFrame({k: (t["icp_rot_sym_err_deg"].to_numpy(float) < 10) for k, t in cols.items()})
        .groupby(pose)
        .mean()
    )
    seeds = share.iloc[:, :-1]
    split = int(((seeds.max(axis=1) >= 0.5) & (seeds.min(axis=1) == 0)).sum())
    lines = [
        "## Per object pose",
        "",
        "Share of each pose's instances within 10° mod sym after ICP (%), per run and for the "
        f"ensemble of all by depth. Poses that one run gets for half or more of their instances "
        f"and another for none: {split} of {len(share)}.",
        "",
        "| pose | instances | " + " | ".join(share.columns) + " |",
        "|---|---:|" + "---:|" * len(share.columns),
    ]
    counts = pd.Series(pose).value_counts()
    for p, row in share.iterrows():
        lines.append(f"| {p} | {counts[p]} | " + " | ".join(f"{100 * v:.0f}" for v in row) + " |")
    return [*lines, ""]


def baseline_table(
    client, name: str, split: str, segments: Segments, starts: int = 1, radius: float = PAPER_RADIUS
):
    """A baseline's instance table: the logged one (its ICP columns are its one-start
    refinement), or its logged estimates refined from ``starts`` turned starts kept by the
    depth and from the first radius ``radius``, as each network's are (``hypotheses``)."""
    if starts == 1 and radius == PAPER_RADIUS:
        return logged(client, name, split)[0]
    return hypotheses(client, name, split, segments, starts, radius, scores=False)["table"]


def paired(runs: list[dict], base: pd.DataFrame) -> list[str]:
    """The networks alone (mean over them) and the ensemble of every run by each selection
    minus the baseline + ICP on the same instances, 95% interval over object poses."""
    groups = {"one network (mean)": [r["table"] for r in runs]}
    for select in ("fitness", "depth"):
        groups[f"ensemble of {len(runs)}, {select}"] = [ensemble(runs, select)]
    lines = [
        "| metric | " + " | ".join(f"{g} | 95% interval" for g in groups) + " |",
        "|---|" + "---:|---:|" * len(groups),
    ]
    for metric, label in METRICS.items():
        cells = []
        for nets in groups.values():
            d = versus_baseline(nets, base, metric, "icp")
            cells += [f"{100 * d['diff']:+.1f}", f"[{100 * d['low']:+.1f}, {100 * d['high']:+.1f}]"]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def main(argv: list[str] | None = None) -> None:
    ap = arguments(__doc__.split("\n\n")[0], "real")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--combinations", type=int, default=28, help="most subsets per size")
    ap.add_argument(
        "--starts", type=int, default=1, help="ICP starts per network, kept by the depth (1: one)"
    )
    ap.add_argument(
        "--baseline-starts",
        type=int,
        default=1,
        help="ICP starts per baseline estimate, kept by the depth (1: the logged refinement)",
    )
    ap.add_argument(
        "--icp-radius",
        type=float,
        default=PAPER_RADIUS,
        help="ICP's first radius for every method, metres (0.01: the paper's schedule)",
    )
    ap.add_argument(
        "--control",
        action="store_true",
        help="also refine no estimate (identity at the segment mean) the same way",
    )
    args = ap.parse_args(argv)
    sizes = [k for k in args.sizes if 1 <= k <= len(args.run)]
    client = tracking.setup(Path.cwd())
    segments = Segments(args.split, Path.cwd())
    radius = args.icp_radius
    runs = [hypotheses(client, n, args.split, segments, args.starts, radius) for n in args.run]
    schedule = (
        "the paper's schedule"
        if radius == PAPER_RADIUS
        else f"the schedule from a first radius of {100 * radius:g} cm (`--icp-radius`)"
    )
    where = "the real development frames" if args.split == "real" else "the preset's test set"
    cmd = " ".join(
        shlex.quote(a)
        for a in ["python", "reports/diagnostics/seed_ensemble.py", *(argv or sys.argv[1:])]
    )
    lines = [
        f"# An ensemble over seeds on {where}",
        "",
        f"_made by `{cmd}` in the project folder that holds the runs; the estimates are the "
        "logged ones, only ICP and the scores are computed here._",
        "",
        (
            f"Each network's estimate refined by its run's ICP (one start, {schedule}); "
            if args.starts == 1
            else f"Each network's estimate refined by ICP from {args.starts} starts, the "
            "refinement that agrees best with the depth kept (`icp.starts`, `icp.select = "
            f"depth`; {schedule} from each); "
        )
        + "per instance the refinement kept with the highest ICP fitness (`fitness`), the "
        "highest depth score, (fitness + coverage) / 2 − free-space violations "
        "(`depth`, cloudpose.refine.depth_score), or the smallest rotation error (`oracle`: "
        "reads the ground truth, the ceiling of any selection among these hypotheses). "
        f"Runs: {', '.join(args.run)}. Cells: mean ± sample SD over the subsets of that many "
        f"seeds (every subset, or {args.combinations} evenly spaced).",
        "",
        f"## All {len(runs[0]['table'])} instances",
        "",
    ]
    lines += size_table(runs, sizes, args.combinations)
    if args.split == "real":
        lines += per_pose(runs)
    for b in args.baseline:
        base = baseline_table(client, b, args.split, segments, args.baseline_starts, radius)
        keep = base.set_index(KEY).index
        base_row = pooled(base)
        refined_from = (
            "ICP"
            if args.baseline_starts == 1
            else f"ICP from {args.baseline_starts} starts, kept by the depth"
        ) + ("" if radius == PAPER_RADIUS else f" ({100 * radius:g} cm first radius)")
        lines += [
            f"## Against {b}, on its {len(keep)} instances",
            "",
            f"The baseline + {refined_from}: "
            + ", ".join(f"{COLUMNS[c]} {base_row[c]:.1f}" for c in COLUMNS)
            + ".",
            "",
        ]
        if len(keep) < len(runs[0]["table"]):
            lines += size_table(runs, sizes, args.combinations, keep)
        if args.split == "real":
            lines += [
                f"Paired, network + ICP − the baseline + {refined_from} on the same instances "
                "(percentage points), 95% interval from a bootstrap over object poses (and the networks' "
                "runs):",
                "",
            ]
            lines += paired(runs, base)
    if args.control:
        base = hypotheses(
            client, args.run[0], args.split, segments, args.starts, radius, False, control=True
        )["table"]
        lines += [
            "## Against no estimate at all, refined the same way",
            "",
            f"The control: ICP from {args.starts} start(s) turned about the identity rotation at "
            "the mean of each segment's points, kept by the depth, as each network's estimate "
            "is (what the refinement finds with nothing to start from): "
            + ", ".join(f"{COLUMNS[c]} {pooled(base)[c]:.1f}" for c in COLUMNS)
            + ".",
            "",
        ]
        if args.split == "real":
            lines += [
                "Paired, network + ICP − the control on the same instances (percentage points), "
                "95% interval from a bootstrap over object poses (and the networks' runs):",
                "",
            ]
            lines += paired(runs, base)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
