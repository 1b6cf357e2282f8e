"""Segment tails: how far do segment points lie from the object posed at the ground truth, on
real depth and on its synthetic twins, over all points and over the first 256 FPS points?

Hypothesis under test: real segments carry flying pixels / mixed depth at object boundaries
(points trailing behind or in front of the object along the viewing ray) that the renderer does
not make, and farthest point sampling over-samples them. For every instance of the frames
(default: the 61 of ``cloudpose/resources/real_dev``) and the conditions ``real``,
``twin-clean``, ``twin-v1`` and ``twin-v2`` of ``real_twins.py`` (its ``_conditions``: same GT
poses, our renderer, sensor model v1 / v2, noise seed 0), the segment is cut as
:func:`cloudpose.data.segments.extract_segments` cuts it (label mask, depth > 0, 0.2 m outlier
filter, FPS to 1024 with the segment cache's starts; asserted equal to it). Each point's distance
is the exact distance to the surface mesh the renderer casts (version 1, built from the 2,621
``points.xyz``, 1.7 mm apart: nearest-point distances would add a floor) posed at the GT. Its sign is
that of (point - nearest surface point) along the viewing ray: behind (+) or in front (-).
"Off-silhouette" = the pixel is not the instance's in the clean rendering (the ray misses it).
"Edge" = pixels from the point's pixel to the nearest pixel of another label.

Statistics weight every instance equally (each point of instance i weighs 1/n_i)::

    nice -n 19 python reports/diagnostics/segment_tails.py > reports/diagnostics/segment_tails.md
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import warnings
import zlib
from pathlib import Path

import numpy as np
import open3d as o3d
import pandas as pd
from scipy.spatial import cKDTree

from cloudpose.conventions import resource_path
from cloudpose.data.cache import FPS_SEED
from cloudpose.data.layout import open_dataset
from cloudpose.data.segments import extract_segments, farthest_point_sampling, instance_streams
from cloudpose.data.synth.render import Renderer
from cloudpose.data.synth.sensor import edge_distance
from cloudpose.store.tracking import shown_path

sys.path.insert(0, str(Path(__file__).parent))
from real_twins import _conditions, _markdown

CONDS = ("real", "twin-clean", "twin-v1", "twin-v2")
N_FPS, RADIUS, N_NET = 1024, 0.2, 256  # DataConfig.n_fps, .outlier_radius, TrainConfig.n_points


def _scene(renderer: Renderer, c: int) -> o3d.t.geometry.RaycastingScene:
    V, F = renderer._mesh_arrays(c)
    s = o3d.t.geometry.RaycastingScene()
    s.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F))
    return s


def _instance_points(frame, depth, label, own, edge, renderer, scenes, streams, i):
    """(signed distance m (+ behind), off-silhouette bool, pixels to the label edge) of the
    filtered points, the FPS order and the points; None without a usable point."""
    c = int(frame.cls_ids[i])
    v, u = np.nonzero((label == c) & (depth > 0))
    if not len(v):
        return None
    z = depth[v, u].astype(np.float64)
    p = (np.stack([u, v, np.ones_like(u)], 1) @ np.linalg.inv(frame.K).T) * z[:, None]
    keep = np.linalg.norm(p - p.mean(0), axis=1) <= RADIUS
    p, v, u = p[keep], v[keep], u[keep]
    order = farthest_point_sampling(p, N_FPS, streams[i])
    R, t = frame.poses[i, :, :3], frame.poses[i, :, 3]
    if c not in scenes:
        scenes[c] = _scene(renderer, c)
    pm = ((p - t) @ R).astype(np.float32)  # camera -> model frame
    q = scenes[c].compute_closest_points(o3d.core.Tensor(pm))["points"].numpy() @ R.T + t
    ray = p / np.linalg.norm(p, axis=1, keepdims=True)
    d = np.linalg.norm(p - q, axis=1)
    sign = np.sign(np.einsum("ij,ij->i", p - q, ray))
    return d * np.where(sign == 0, 1, sign), own[v, u] != c, edge[v, u], order, p


def _wq(x, w, q):
    o = np.argsort(x)
    cw = np.cumsum(w[o])
    return float(x[o][np.searchsorted(cw, q * cw[-1])])


def _stats(recs: list[dict], key: str) -> dict:
    d = np.concatenate([r[key][0] for r in recs])
    off = np.concatenate([r[key][1] for r in recs])
    edge = np.concatenate([r[key][2] for r in recs])
    w = np.concatenate([np.full(len(r[key][0]), 1 / len(r[key][0])) for r in recs])
    a = np.abs(d)
    far = a > 0.01
    wf = w * far
    share = lambda m: 100 * float((w * m).sum() / w.sum())  # noqa: E731
    return {
        "instances": len(recs),
        "median mm": 1000 * _wq(a, w, 0.5),
        "p90 mm": 1000 * _wq(a, w, 0.9),
        "p99 mm": 1000 * _wq(a, w, 0.99),
        "> 1 cm %": share(far),
        "> 2 cm %": share(a > 0.02),
        "far: behind %": 100 * float((wf * (d > 0)).sum() / max(wf.sum(), 1e-12)),
        "far: in front %": 100 * float((wf * (d < 0)).sum() / max(wf.sum(), 1e-12)),
        "far: off-silh. %": 100 * float((wf * off).sum() / max(wf.sum(), 1e-12)),
        "far: <= 2 px from edge %": 100 * float((wf * (edge <= 2)).sum() / max(wf.sum(), 1e-12)),
        "inst. > 5% beyond 2 cm": int(sum(np.mean(np.abs(r[key][0]) > 0.02) > 0.05 for r in recs)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(resource_path("real_dev")))
    ap.add_argument("--seed", type=int, default=0, help="seed of the sensor noise")
    ap.add_argument("--surface-version", type=int, default=1)
    args = ap.parse_args()
    dataset = open_dataset(args.data)
    models = dataset.models()
    renderer = Renderer(
        {c: p.copy() for c, p in models.items()}, surface_version=args.surface_version
    )
    scenes: dict = {}
    recs = []
    for fid in dataset.image_set("all"):
        frame = dataset.frame(fid)
        conds = _conditions(
            frame, renderer, np.random.default_rng([args.seed, zlib.crc32(fid.encode())])
        )
        own = conds["twin-clean"][1]
        for name in CONDS:
            depth, label = conds[name][0].astype(np.float32), conds[name][1]
            seed = [FPS_SEED, zlib.crc32(fid.encode())]
            edge = edge_distance(label)
            streams = instance_streams(np.random.default_rng(seed), frame.cls_ids)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ref = extract_segments(
                    dataclasses.replace(frame, depth=depth, label=label),
                    n_fps=N_FPS, outlier_radius=RADIUS, rng=np.random.default_rng(seed),
                )  # fmt: skip
            for i in range(len(frame.cls_ids)):
                got = _instance_points(frame, depth, label, own, edge, renderer, scenes, streams, i)
                if got is None:
                    continue
                sd, off, ed, order, p = got
                assert ref[i].count == len(p) and np.allclose(ref[i].points, p[order], atol=1e-6)
                k = order[: min(N_NET, len(p))]
                recs.append({
                    "cond": name, "video": fid.split("/")[0],
                    "class": dataset.classes[int(frame.cls_ids[i]) - 1],
                    "all": (sd, off, ed), "fps": (sd[k], off[k], ed[k]),
                })  # fmt: skip
    df = pd.DataFrame(recs)
    videos = sorted(df["video"].unique())
    cmd = "nice -n 19 python reports/diagnostics/segment_tails.py " + " ".join(sys.argv[1:])
    print("# Segment tails: distance of segment points to the model at the ground truth\n")
    print(
        f"_made by `{cmd.strip()} > reports/diagnostics/segment_tails.md`; data {shown_path(args.data)}; "
        f"surface version {args.surface_version}, noise seed {args.seed}; instances weighted "
        "equally; distances to the posed surface mesh; far = beyond 1 cm; behind/in front: "
        "sign along the viewing ray; off-silh.: the ray misses the instance in the clean "
        "rendering (0 for twins by construction); edge: pixels to the nearest pixel of another "
        "label (sensor.edge_distance)._\n"
    )
    spacing = np.median([np.median(cKDTree(m).query(m, k=2)[0][:, 1]) for m in models.values()])
    for key, title in (("all", "All segment points (after the 0.2 m filter)"),
                       ("fps", f"First {N_NET} FPS points (what the network sees)")):  # fmt: skip
        rows = [
            {"video": g, "condition": c, **_stats(sub.to_dict("records"), key)}
            for g in ["pooled", *videos]
            for c in CONDS
            if len(sub := df[(df["cond"] == c) & ((df["video"] == g) | (g == "pooled"))])
        ]
        print(f"## {title}\n\n{_markdown(pd.DataFrame(rows))}\n")
    rows = []
    for cls, sub in df.groupby("class"):
        row = {"class": cls, "instances": int((sub["cond"] == "real").sum())}
        for key in ("all", "fps"):
            for c in ("real", "twin-v1", "twin-v2"):
                r = sub[sub["cond"] == c].to_dict("records")
                row[f"{key} {c} >1cm %"] = _stats(r, key)["> 1 cm %"]
        rows.append(row)
    tab = pd.DataFrame(rows).sort_values("fps real >1cm %", ascending=False)
    print(f"## Per class, pooled over videos: share of points beyond 1 cm\n\n{_markdown(tab)}\n")
    print(f"_(median nearest-neighbour spacing of the points.xyz models: {1000 * spacing:.1f} mm)_")


if __name__ == "__main__":
    main()
