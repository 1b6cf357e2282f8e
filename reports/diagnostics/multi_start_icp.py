"""Are the network's coarse rotation misses within reach of a verification step? ICP from the
network's estimate turned by every element of a rotation group, the best fit kept
(``icp.starts``, :mod:`cloudpose.refine`), against ICP from the estimate alone, for the network
and for the classical baselines alike.

Every estimate is read from a logged evaluation (the ``net_R`` / ``net_t`` columns of
``eval/{split}/instances.csv``), so no network runs here: only the refinement is redone, on
the same segments the evaluation used (the preset's test set, or the real development frames).
The one-start rows are recomputed the same way, and a check asserts that they equal the logged
``icp_*`` columns, so both rows differ only in the starts.

Runs are read by MLflow run name from the store of the current folder (the newest run of a
name), e.g. in the project that holds the default's sweep::

    python reports/diagnostics/multi_start_icp.py --split real --starts 24 \\
        --run shared-0/cpu-online/seed1 ... --run shared-0/cpu-online/seed7 \\
        --baseline baseline-fpfh/cpu-online/seed1+real-6b1ea2e9 \\
        > reports/diagnostics/multi_start_icp_real.md

A baseline evaluated on a subsample of the test set (``--limit``) is compared with the
network on the instances both hold.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from cloudpose.methods import instance_table
from cloudpose.refine import Estimates, ICPSettings, refine_poses
from cloudpose.registry import resolve
from cloudpose.report.real import METRICS, table_metrics, versus_baseline
from cloudpose.store import instances, tracking
from cloudpose.studies.baseline_runs import split_segments

KEY = ["frame_id", "instance"]


def logged(client, name: str, split: str) -> tuple[pd.DataFrame, dict]:
    """The instance table ``eval/{split}/instances.csv`` and the tags of the newest finished
    run named ``name``."""
    run = tracking.newest_run_named(client, name)
    if run is None:
        raise SystemExit(f"no finished run named {name!r} in the MLflow store of {Path.cwd()}")
    table = instances.read_artifact_table(client, run, f"eval/{split}/instances.csv")
    return table, run.data.tags


def poses(table: pd.DataFrame, prefix: str) -> Estimates:
    """The logged poses of one method (``net`` / ``icp``); identity and zero for a miss."""
    n = len(table)
    R, t = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
    for i, (r, s) in enumerate(zip(table[f"{prefix}_R"], table[f"{prefix}_t"], strict=True)):
        if isinstance(r, str) and r:
            R[i] = np.array(r.split(), dtype=float).reshape(3, 3)
            t[i] = np.array(s.split(), dtype=float)
    return Estimates(R, t)


class Segments:
    """The segments an evaluation of ``split`` used, built once per preset."""

    def __init__(self, split: str, project: Path):
        self.split, self.project, self._cache = split, project, {}

    def of(self, preset: str, seed: int):
        if preset not in self._cache:
            cfg = resolve("shared-0", preset, seed)
            _, dataset, pool = split_segments(cfg, self.split, self.project, progress=False)
            self._cache[preset] = (dataset, pool, cfg.loss.symmetry_table)
        return self._cache[preset]


def same_refinement(name: str, recomputed: pd.DataFrame, table: pd.DataFrame) -> None:
    """Exit unless the one-start ICP redone here is the logged one: ADS within 0.1 mm on all
    but 2% of the instances (ICP's float rounding differs between CPUs, and a few refinements
    end elsewhere for it)."""
    a, b = recomputed["icp_ads"].to_numpy(float), table["icp_ads"].to_numpy(float)
    both = np.isfinite(a) & np.isfinite(b)  # a miss has no ADS on either side
    diff = np.where(both, np.abs(np.where(both, a, 0.0) - np.where(both, b, 0.0)), 0.0)
    off = diff > 1e-4
    if off.mean() > 0.02:
        raise SystemExit(
            f"{name}: the one-start refinement differs from the logged one on {off.sum()} of "
            f"{len(off)} instances (ADS by up to {1000 * diff[off].max():.2f} mm)"
        )


def logged_segments(client, name: str, split: str, segments: Segments):
    """``(table, segs, dataset, symmetry table)``: the logged instance table of the run named
    ``name`` and the segments its evaluation used, row for row (a logged miss stays one)."""
    table, tags = logged(client, name, split)
    dataset, pool, sym = segments.of(tags["preset"], int(tags.get("seed", 1)))
    keys = pd.Index(
        pd.Series(pool.frame_id).astype(str) + "#" + pd.Series(pool.instance).astype(str)
    )
    where = keys.get_indexer(table["frame_id"].astype(str) + "#" + table["instance"].astype(str))
    if (where < 0).any():
        raise SystemExit(f"{name}: {int((where < 0).sum())} logged instances not in the segments")
    segs = pool.subset(where)
    segs.valid = ~table["miss"].to_numpy(dtype=bool)
    return table, segs, dataset, sym


def refined(client, name: str, split: str, starts: int, segments: Segments) -> dict:
    """The run's logged table (``one``: its own one-start ICP) and the same estimates refined
    from ``starts`` starts (``many``), with the share of objects another start won and the
    refinement's milliseconds per object."""
    table, segs, dataset, sym = logged_segments(client, name, split, segments)
    models = dataset.models()
    est = poses(table, "net")
    one, _ = refine_poses(segs, est, models)
    check = instance_table(segs, {"icp": one}, models, dataset.classes, sym)
    same_refinement(name, check, table)
    t0 = time.perf_counter()
    many, _stats = refine_poses(segs, est, models, ICPSettings(starts=starts))
    ms = 1000 * (time.perf_counter() - t0) / max(int(segs.valid.sum()), 1)
    moved = np.abs(many.R - one.R).max(axis=(1, 2)) > 1e-6
    out = instance_table(segs, {"net": est, "icp": many}, models, dataset.classes, sym)
    near_one = table["icp_rot_sym_err_deg"].to_numpy(float) < 10  # NaN (a miss): not near
    near_many = out["icp_rot_sym_err_deg"].to_numpy(float) < 10
    return {
        "name": name,
        "one": table,
        "many": out,
        "moved": float(moved[segs.valid].mean()),
        "gained": float(np.mean(near_many & ~near_one)),
        "lost": float(np.mean(near_one & ~near_many)),
        "ms": ms,
    }


def cells(results: list[dict], keep: pd.Index | None = None) -> dict[tuple, list[float]]:
    """(refinement, video, metric) -> values over runs, in percent."""
    out: dict[tuple, list[float]] = {}
    for r in results:
        for label, table, prefixes in (
            ("none", r["one"], ("net",)),
            ("1 start", r["one"], ("icp",)),
            ("many", r["many"], ("icp",)),
        ):
            if keep is not None:
                table = table.set_index(KEY).loc[keep].reset_index()
            for (col, video, metric), v in table_metrics(table).items():
                if col in prefixes:
                    out.setdefault((label, video, metric), []).append(100 * v)
    return out


def fmt(values: list[float]) -> str:
    v = np.asarray(values)
    return f"{v.mean():.1f}" if len(v) == 1 else f"{v.mean():.1f} ± {v.std(ddof=1):.1f}"


def section(title: str, groups: list[tuple[str, list[dict]]], starts: int, keep=None) -> list[str]:
    lines = [f"## {title}", ""]
    values = {method: cells(results, keep) for method, results in groups}
    videos = [*sorted({v for _, v, _ in values[groups[0][0]] if v != "pooled"}), "pooled"]
    if len(videos) == 2:  # one video: the pooled column says it all
        videos = ["pooled"]
    for metric, label in METRICS.items():
        rows = []
        for method, _ in groups:
            names = {
                "none": method,
                "1 start": f"{method} + ICP",
                "many": f"{method} + ICP from {starts} starts",
            }
            for ref, name in names.items():
                rows.append([name] + [fmt(values[method][(ref, v, metric)]) for v in videos])
        lines += [f"**{label} (%)**", "", "| method | " + " | ".join(videos) + " |"]
        lines += ["|---|" + "---:|" * len(videos)] + ["| " + " | ".join(r) + " |" for r in rows]
        lines.append("")
    lines += [
        "| method (each run's own instances) | runs | objects another start won | now within 10° "
        "| no longer within 10° "
        "| ms / object, ICP from all starts |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for method, results in groups:
        share = {k: 100 * np.mean([r[k] for r in results]) for k in ("moved", "gained", "lost")}
        ms = np.mean([r["ms"] for r in results])
        lines.append(
            f"| {method} | {len(results)} | {share['moved']:.1f}% | {share['gained']:.1f}% "
            f"| {share['lost']:.1f}% | {ms:.1f} |"
        )
    return [*lines, ""]


def by_class(results: list[dict], starts: int) -> list[str]:
    """Rotation < 10 degrees modulo symmetry per class, after ICP from one start and from all,
    mean over the runs; the classes that gain most first."""
    rows = []
    for cls in sorted(set(results[0]["one"]["class"])):
        share = {}
        for key in ("one", "many"):
            share[key] = np.mean(
                [
                    100 * np.mean(r[key].loc[r[key]["class"] == cls, "icp_rot_sym_err_deg"] < 10)
                    for r in results
                ]
            )
        n = int((results[0]["one"]["class"] == cls).sum())
        rows.append((share["many"] - share["one"], cls, n, share["one"], share["many"]))
    lines = [
        f"**Rotation < 10° mod sym per class, the network + ICP (%), 1 and {starts} starts**",
        "",
        f"| class | instances | 1 start | {starts} starts |",
        "|---|---:|---:|---:|",
    ]
    for _, cls, n, one, many in sorted(rows, key=lambda r: (-r[0], r[1])):
        lines.append(f"| {cls} | {n} | {one:.1f} | {many:.1f} |")
    return [*lines, ""]


def verdict(low: float, high: float) -> str:
    """A paired difference's 95% interval in words."""
    return "network ahead" if low > 0 else "baseline ahead" if high < 0 else "not resolved"


def difference_cells(d: dict) -> str:
    """A paired difference (:func:`cloudpose.report.real.versus_baseline`, fractions) as three
    table cells: points, 95% interval, verdict."""
    lo, hi = 100 * d["low"], 100 * d["high"]
    return f"{100 * d['diff']:+.1f} | [{lo:+.1f}, {hi:+.1f}] | {verdict(lo, hi)}"


def arguments(description: str, split: str) -> argparse.ArgumentParser:
    """The options every diagnostic of logged runs takes: the networks, the baselines, the
    split (default ``split``)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--run", action="append", required=True, help="network run name (repeat)")
    ap.add_argument("--baseline", action="append", default=[], help="baseline run name (repeat)")
    ap.add_argument("--split", choices=("test", "real"), default=split)
    return ap


def paired(net: list[dict], base: dict, starts: int) -> list[str]:
    """Network minus baseline on the real frames, bootstrap over object poses."""
    lines = [
        "| metric | ICP | network − baseline (pp) | 95% interval | |",
        "|---|---|---:|---:|---|",
    ]
    for metric, label in METRICS.items():
        for ref, key in (("1 start", "one"), (f"{starts} starts", "many")):
            d = versus_baseline([r[key] for r in net], base[key], metric, "icp")
            lines.append(f"| {label} | {ref} | {difference_cells(d)} |")
    return [*lines, ""]


def main(argv: list[str] | None = None) -> None:
    ap = arguments(__doc__.split("\n\n")[0], "test")
    ap.add_argument("--starts", type=int, default=24)
    args = ap.parse_args(argv)
    client = tracking.setup(Path.cwd())
    segments = Segments(args.split, Path.cwd())
    net = [refined(client, n, args.split, args.starts, segments) for n in args.run]
    bases = [refined(client, n, args.split, args.starts, segments) for n in args.baseline]
    where = "the real development frames" if args.split == "real" else "the preset's test set"
    cmd = " ".join(
        shlex.quote(a)
        for a in ["python", "reports/diagnostics/multi_start_icp.py", *(argv or sys.argv[1:])]
    )
    lines = [
        f"# ICP from {args.starts} starts on {where}",
        "",
        f"_made by `{cmd}` in the project folder that holds the runs; the estimates are the logged ones, only ICP is redone; milliseconds on the machine that ran it, beside whatever else it ran._",
        "",
        f"ICP from {args.starts} starts: the paper's schedule from the estimate turned by each element of the rotation group of that order (the identity first), the refinement with the highest fitness kept unless it beats the estimate's own by no more than 0.02 (`cloudpose evaluate --icp-starts {args.starts}`, `icp.starts`). Cells: mean ± sample SD over the network's runs; one value for a baseline.",
        "",
    ]
    lines += section("All instances of the network", [("network", net)], args.starts)
    lines += by_class(net, args.starts)
    for b in bases:
        keep = b["one"].set_index(KEY).index
        lines += section(
            f"On the instances of {b['name']} ({len(keep)})",
            [("network", net), (b["name"], [b])],
            args.starts,
            keep,
        )
        if args.split == "real":
            lines += [
                f"Paired on the same instances, network (mean over its runs) − {b['name']}, 95% interval from a bootstrap over object poses and the network's runs:",
                "",
            ]
            lines += paired(net, b, args.starts)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
