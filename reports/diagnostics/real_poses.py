"""Do the real frames show poses the on-line scenes draw? Camera elevation and object resting
faces of the real development frames, against the scene sampler's ranges, beside the network's
rotation errors per class.

The scene sampler (:func:`cloudpose.data.synth.scenes.sample_table_scene`) puts every object on
one of its model's stable resting faces (:func:`cloudpose.data.synth.resting.resting_poses`) or
on another object, and looks at the table from an elevation of
:data:`~cloudpose.data.synth.scenes.CAMERA_ELEVATION_DEG` at a distance of
:data:`~cloudpose.data.synth.scenes.CAMERA_DISTANCE`. For each real frame this script fits the
table plane to the background depth (Open3D RANSAC plane on the pixels labelled 0, normal
towards the camera) and measures:

- the camera elevation: the angle between the optical axis and the table plane (90 deg: looking
  straight down), as the sampler's elevation is measured;
- for each annotated object, its "up" direction in the model frame (``R^T n`` with ``R`` the
  ground-truth model-to-camera rotation) and the angle to the nearest stable resting face's up
  direction (0 deg: it rests on a face the sampler draws; tens of degrees: leaning on something,
  or a face the sampler finds unstable), and its height above the plane.

With ``--run NAME`` (repeatable) the network's per-instance rotation errors modulo symmetry on
the real frames (``eval/real/instances.csv`` of that run's ``cloudpose evaluate --real``) and on
its synthetic test set (``eval/test/instances.csv``) are read from the MLflow store of the
current folder and pooled over the runs, per class. Run in the project folder that holds the
runs, e.g.::

    python reports/diagnostics/real_poses.py --run shared-0/cpu-online/seed2 \\
        --run shared-0/cpu-online/seed3 > reports/diagnostics/real_poses.md
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pandas as pd

from cloudpose.conventions import resource_path
from cloudpose.data.layout import open_dataset
from cloudpose.data.synth.resting import resting_poses
from cloudpose.data.synth.scenes import CAMERA_DISTANCE, CAMERA_ELEVATION_DEG
from cloudpose.store import instances, tracking

PLANE_DISTANCE = 0.01
"""RANSAC inlier distance of the table plane, metres."""

OFF_FACE_DEG = 15.0
"""An object whose up direction is further than this from every stable face's is counted as
not resting on a face the sampler draws."""


def table_plane(depth: np.ndarray, label: np.ndarray, K: np.ndarray) -> np.ndarray | None:
    """(4,) plane ``n . p + d = 0`` of the background (label 0) with ``n`` towards the camera;
    None when too few background points."""
    v, u = np.nonzero((label == 0) & (depth > 0))
    if len(v) < 1000:
        return None
    z = depth[v, u].astype(np.float64)
    pts = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[:: max(1, len(pts) // 50000)]))
    o3d.utility.random.seed(0)
    plane, _ = pcd.segment_plane(PLANE_DISTANCE, 3, 1000)
    plane = np.asarray(plane, dtype=np.float64)
    plane /= np.linalg.norm(plane[:3])
    return -plane if plane[3] < 0 else plane  # camera (origin) on the side n points to


def measure(root: Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(frames, instances) tables of the folder ``root``."""
    ds = open_dataset(root)
    up_of: dict[int, np.ndarray] = {}
    frames, inst = [], []
    for fid in ds.image_set("all"):
        f = ds.frame(fid)
        plane = table_plane(f.depth, f.label, f.K)
        if plane is None:
            continue
        n = plane[:3]
        elev = float(np.degrees(np.arcsin(abs(n[2]))))
        frames.append({"frame_id": fid, "video": fid[:4], "elevation_deg": elev})
        for c, P in zip(f.cls_ids, f.poses, strict=True):
            c = int(c)
            if c not in up_of:
                rest = resting_poses(ds.model_points(c))
                up_of[c] = rest.rotations.transpose(0, 2, 1) @ np.array([0.0, 0.0, 1.0])
            R, t = P[:, :3], P[:, 3]
            up = R.T @ n
            ang = np.degrees(np.arccos(np.clip(up_of[c] @ up, -1.0, 1.0)))
            centre = R @ ds.model_points(c).mean(axis=0) + t
            inst.append(
                {
                    "frame_id": fid,
                    "video": fid[:4],
                    "class": ds.classes[c - 1],
                    "distance_m": float(np.linalg.norm(centre)),
                    "off_face_deg": float(ang.min()),
                    "height_m": float(n @ centre + plane[3]),
                }
            )
    return pd.DataFrame(frames), pd.DataFrame(inst)


def network_errors(names: list[str]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Rotation errors mod symmetry of the runs ``names``, pooled over them: on the real frames
    per (video, class) and on the synthetic test set per class; columns ``lt10`` (percent
    under 10 deg) and ``median`` (deg)."""
    client = tracking.setup(Path.cwd())
    tables: dict[str, list[pd.DataFrame]] = {"real": [], "test": []}
    for name in names:
        run = tracking.newest_run_named(client, name)
        if run is None:
            raise SystemExit(f"no run named {name!r} in the MLflow store of {Path.cwd()}")
        for split, out in tables.items():
            out.append(instances.read_artifact_table(client, run, f"eval/{split}/instances.csv"))

    def summary(d: pd.DataFrame, by: list) -> pd.DataFrame:
        err = d.groupby(by).net_rot_sym_err_deg
        return pd.DataFrame(
            {"lt10": err.agg(lambda x: 100 * float(np.mean(x < 10))), "median": err.median()}
        )

    real = pd.concat(tables["real"])
    real["video"] = real["frame_id"].astype(str).str[:4]
    return summary(real, ["video", "class"]), summary(pd.concat(tables["test"]), ["class"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=resource_path("real_dev"))
    ap.add_argument("--run", action="append", default=[], help="MLflow run name (repeatable)")
    args = ap.parse_args()
    frames, inst = measure(args.data)
    cmd = shlex.join(["python", "reports/diagnostics/real_poses.py", *sys.argv[1:]])
    lo, hi = CAMERA_ELEVATION_DEG
    print("# Real frames: camera elevation and resting faces against the scene sampler\n")
    packaged = Path(args.data).resolve() == Path(resource_path("real_dev")).resolve()
    data = "the packaged real development frames (cloudpose/resources/real_dev)"
    data = data if packaged else str(args.data)
    print(f"_made by `{cmd}`; data: {data}, {len(frames)} frames with a table plane._\n")
    print(
        f"Sampler: elevation {lo:.0f}-{hi:.0f} deg, distance {CAMERA_DISTANCE[0]}-"
        f"{CAMERA_DISTANCE[1]} m to the scene centre; objects on a stable face or on another "
        f"object. Off face: angle from the object's up direction to the nearest stable face's "
        f"(> {OFF_FACE_DEG:.0f} deg: a pose the sampler draws only by stacking, if at all).\n"
    )
    print("## Camera elevation per video (deg)\n")
    print("| video | frames | min | median | max | frames outside the sampler's range |")
    print("|---|---:|---:|---:|---:|---:|")
    for v, g in frames.groupby("video"):
        e = g.elevation_deg
        out = int(((e < lo) | (e > hi)).sum())
        print(f"| {v} | {len(g)} | {e.min():.1f} | {e.median():.1f} | {e.max():.1f} | {out} |")
    per = inst.groupby(["video", "class"]).agg(
        n=("off_face_deg", "size"),
        off_face=("off_face_deg", "median"),
        height=("height_m", "median"),
        distance=("distance_m", "median"),
    )
    if args.run:
        real, test = network_errors(args.run)
        per = per.join(real.add_suffix("_real")).join(test.add_suffix("_test"), on="class")
    print("\n## Objects per video and class (medians over the frames)\n")
    head = "| video | class | instances | off face (deg) | centre above table (mm) | distance (m) |"
    rule = "|---|---|---:|---:|---:|---:|"
    if args.run:
        head += " rot < 10 deg real % | synthetic test % | median real (deg) | synthetic (deg) |"
        rule += "---:|---:|---:|---:|"
        print(f"Network: {', '.join(args.run)}, pooled; rotation error modulo symmetry.\n")
    print(head)
    print(rule)
    for (v, c), r in per.iterrows():
        line = f"| {v} | {c} | {int(r.n)} | {r.off_face:.1f} | {1000 * r.height:.0f} | {r.distance:.2f} |"
        if args.run:
            line += (
                f" {r.lt10_real:.1f} | {r.lt10_test:.1f} | {r.median_real:.1f} | "
                f"{r.median_test:.1f} |"
            )
        print(line)


if __name__ == "__main__":
    main()
