"""Segment tails at test time: does removing the points that lie off the object before farthest
point sampling help a trained network, and which filter without the ground truth comes close?

FPS over-samples a segment's tail: on the real development frames 2.0% of the points lie more
than 1 cm off the posed model, but 6.1% of the first 256 FPS points, the rotation network's
input (``segment_tails.md``). Here every instance is cut as the project cuts it (label mask,
depth > 0, the 0.2 m outlier filter) and then, before FPS to 1024, one filter of :data:`FILTERS`:

- ``none``: the project's segment;
- ``oracle``: drop the points more than 2 cm off the model posed at the ground truth (an upper
  bound: it needs the answer);
- ``components``: keep the mask pixels connected to the largest depth-continuous region (4-
  neighbours whose depths differ by < 1 cm are joined; every region of at least a quarter of
  the largest is kept);
- ``statistical``: Open3D's ``remove_statistical_outlier`` (20 neighbours, 2 standard
  deviations).

The networks are trained runs as they are (nothing retrained), each followed by its own ICP.
Every figure is on the same instances::

    python reports/diagnostics/tail_filters.py --run shared-0/cpu-online/seed1 \\
        --run shared-0/cpu-online/seed8 --synth-instances 240 \\
        --out reports/diagnostics/tail_filters.md

Run it in the project folder that holds the runs.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from cloudpose.data.segment_set import SegmentSet
from cloudpose.files import atomic_text
from cloudpose.studies.perturbations import (
    instance_rngs,
    open_source,
    sampled_segment,
    segment_points,
)
from cloudpose.studies.stress import SweepMethod, run_method, summary_of

FILTERS = ("none", "oracle", "components", "statistical")
ORACLE_MM = 20.0
STEP_M = 0.01
"""Depth step that separates two regions of a mask (``components``)."""


def depth_components(mask: np.ndarray, depth: np.ndarray, step: float = STEP_M) -> np.ndarray:
    """The pixels of ``mask`` (with depth) in a depth-continuous region of at least a quarter
    of the largest: 4-neighbours are joined when their depths differ by less than ``step``."""
    ok = mask & (depth > 0)
    idx = -np.ones(mask.shape, dtype=np.int64)
    n = int(ok.sum())
    if n == 0:
        return ok
    idx[ok] = np.arange(n)
    rows, cols = [], []
    pairs = (  # (ids, ids of the right / lower neighbour, their depths)
        (idx[:, :-1], idx[:, 1:], depth[:, :-1], depth[:, 1:]),
        (idx[:-1, :], idx[1:, :], depth[:-1, :], depth[1:, :]),
    )
    for a, b, da, db in pairs:
        join = (a >= 0) & (b >= 0) & (np.abs(da - db) < step)
        rows.append(a[join])
        cols.append(b[join])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n))
    k, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels, minlength=k)
    keep_label = sizes >= 0.25 * sizes.max()
    out = np.zeros_like(mask)
    out[ok] = keep_label[labels]
    return out


def statistical(points: np.ndarray) -> np.ndarray:
    """Open3D's statistical outlier removal (20 neighbours, 2 standard deviations)."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    _, kept = pcd.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)
    return points[np.asarray(kept, dtype=np.int64)]


def cut(fd, i: int, how: str, *, trees, source: str, seed: int, n_fps: int = 1024):
    """Instance ``i`` of a frame cut as the project cuts it, filtered by ``how`` before FPS
    (the FPS stream of :func:`cloudpose.studies.stress.instance_rngs`: the same for every filter)."""
    f = fd.frame
    c = int(f.cls_ids[i])
    _, frng = instance_rngs(seed, source, fd.index, i)
    mask = f.label == c
    if how == "components":
        mask = depth_components(mask, f.depth)
    pts = segment_points(f, f.depth, mask, 0.2)
    if how == "oracle" and len(pts):
        R = f.poses[i, :, :3].astype(np.float64)
        t = f.poses[i, :, 3].astype(np.float64)
        d, _ = trees[c].query((pts - t) @ R)
        pts = pts[d <= ORACLE_MM / 1000]
    elif how == "statistical" and len(pts) > 20:
        pts = statistical(pts)
    return sampled_segment(fd, i, pts, frng, n_fps)


def off_model_share(segs: SegmentSet, trees, n: int = 256) -> float:
    """Mean over instances of the share of the first ``n`` FPS points more than 1 cm off the
    posed model."""
    shares = []
    for j in np.flatnonzero(segs.valid):
        k = int(min(segs.count[j], n))
        p = segs.points[j, :k].astype(np.float64)
        d, _ = trees[int(segs.cls_id[j])].query((p - segs.t[j]) @ segs.R[j].astype(np.float64))
        shares.append(np.mean(d > 0.01))
    return float(np.mean(shares))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", action="append", required=True, help="a trained run (repeatable)")
    p.add_argument("--synth-instances", type=int, default=240)
    p.add_argument("--filter", action="append", choices=FILTERS, help="default: all")
    p.add_argument("--work", type=Path, default=Path("runs/tail_filters"), help="scratch")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    from cloudpose.infer import load_checkpoint
    from cloudpose.store import tracking
    from cloudpose.store.runs import resolve_run

    client = tracking.setup()
    methods = []
    for r in args.run:
        path = resolve_run(client, r)[1]
        _, cfg = load_checkpoint(path, "cpu")
        methods.append(SweepMethod(f"net-seed{cfg.seed}", Path(path)))
    filters = args.filter or list(FILTERS)
    rows, cache = [], {}
    for name, limit in (("real", None), ("synth", args.synth_instances)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            src = open_source(
                name, cfg, args.work, instances=limit, synth_frames=60, progress=False
            )
        models = src.dataset.models()
        trees = {c: cKDTree(m) for c, m in models.items()}
        for how in filters:
            segs = SegmentSet.from_segments(
                [
                    cut(src.frames[fp], i, how, trees=trees, source=name, seed=1)
                    for fp, i in src.instances
                ],
                1024,
            )
            tails = off_model_share(segs, trees)
            for m in methods:
                table = run_method(m, segs, src.dataset, 1, cache)
                for stage in ("net", "icp"):
                    rows.append(
                        dict(
                            source=name,
                            filter=how,
                            method=m.name,
                            stage=stage,
                            off_model_256=tails,
                            points=float(np.median(segs.count[segs.valid])),
                            **summary_of(table, stage),
                        )
                    )
            print(f"{name} {how}: done", file=sys.stderr)
    df = pd.DataFrame(rows)
    atomic_text(args.out.with_suffix(".csv"), df.to_csv(index=False, float_format="%.5f"))
    atomic_text(args.out, markdown(df, ["reports/diagnostics/tail_filters.py", *argv]))
    print(markdown(df, ["reports/diagnostics/tail_filters.py", *argv]))
    return 0


def markdown(df: pd.DataFrame, argv: list[str]) -> str:
    cmd = " ".join(shlex.quote(a) for a in argv)
    lines = [
        "# Segment tails at test time: filters before FPS, trained networks as they are",
        "",
        f"_made by `python {cmd}` in the project folder that holds the runs; see the "
        "script's docstring for the filters._",
        "",
        "Cells: mean over the networks' seeds; ADS AUC and shares in %, median translation in "
        "mm. 'tail in FPS 256': the share of the first 256 FPS points more than 1 cm off the "
        "posed model; 'points': the median segment size after the filter.",
    ]
    for source, part in df.groupby("source", sort=False):
        n = int(part["count"].iloc[0])
        seeds = ", ".join(sorted(part["method"].unique()))
        lines += [
            "",
            f"## {source} ({n} instances; {seeds})",
            "",
            "| filter | tail in FPS 256 | points | ADS AUC | + ICP | rot < 10 deg mod sym | "
            "+ ICP | translation < 1 cm | + ICP | median translation | + ICP |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for how, g in part.groupby("filter", sort=False):
            net = g[g["stage"] == "net"].mean(numeric_only=True)
            icp = g[g["stage"] == "icp"].mean(numeric_only=True)
            lines.append(
                f"| {how} | {100 * net['off_model_256']:.1f} | {net['points']:.0f} | "
                f"{100 * net['ads_auc']:.1f} | {100 * icp['ads_auc']:.1f} | "
                f"{100 * net['rot_sym_lt_10deg']:.1f} | {100 * icp['rot_sym_lt_10deg']:.1f} | "
                f"{100 * net['trans_lt_1cm']:.1f} | {100 * icp['trans_lt_1cm']:.1f} | "
                f"{net['trans_median_mm']:.1f} | {icp['trans_median_mm']:.1f} |"
            )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
