"""About which axis the network's large rotation errors turn, per class, beside the baselines.

For each test instance of a class, the error rotation ``R_gt^T R_est`` (model frame) of
shared-0 (newest finished run of the seed asked for) is split into its angle and its axis; an
error over 20 degrees counts as "about the long axis" when its axis is within 25 degrees of the
model's principal (longest) axis. The baselines' rotation errors modulo symmetry come from their
logged instance tables, as counts under 10 degrees and over 135 degrees (the other pose of a
near-symmetry, a half turn).

Run in a project folder whose MLflow store holds the network's ``model.pt``: a store where the
runs were trained (``make ablations PRESET=cpu SEEDS=3`` and ``make baselines``); the cpu
sweep's archive (``reports/cpu/mlflow-store.tar.xz`` in commit b200bde) leaves the checkpoints
out::

    for s in 1 2 3; do python reports/diagnostics/near_symmetry.py --seed $s; echo; done \
        > reports/diagnostics/near_symmetry.md
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from scipy.spatial.transform import Rotation

from cloudpose.data.dataset import prepare_data
from cloudpose.infer import estimate_poses, load_checkpoint
from cloudpose.registry import resolve
from cloudpose.store import instances, tracking

CLASSES = (
    "021_bleach_cleanser",
    "019_pitcher_base",
    "035_power_drill",
    "011_banana",
    "037_scissors",
    "006_mustard_bottle",
)
BIG_DEG, AXIS_DEG = 20.0, 25.0


def _newest(client, name: str):
    runs = tracking.find_runs(client, extra_filter=f"attributes.run_name = '{name}'")
    if not runs:
        raise SystemExit(f"no finished run named {name} in {tracking.tracking_uri(Path.cwd())}")
    return runs[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--run", help="MLflow run name of the network (default shared-0/PRESET/seedS)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    client = tracking.setup(Path.cwd())
    run = _newest(client, args.run or f"shared-0/{args.preset}/seed{args.seed}")
    ckpt = tracking.local_artifact(run.info.artifact_uri, "model.pt")
    if ckpt is None or not ckpt.is_file():
        raise SystemExit(f"run {run.info.run_id} has no local model.pt (see this script's doc)")
    model, cfg = load_checkpoint(ckpt)
    data = prepare_data(
        resolve("shared-0", args.preset, args.seed).data, Path.cwd(), progress=False
    )
    dataset = data.dataset
    models, classes, segs = dataset.models(), dataset.classes, data.test
    est = estimate_poses(model, segs, cfg.train.n_points)
    base = {
        m: instances.read_artifact_table(
            client, _newest(client, f"baseline-{m}/{args.preset}/seed1"), "eval/test/instances.csv"
        )
        for m in ("ppf", "fpfh")
    }
    rows = []
    for name in CLASSES:
        cid = classes.index(name) + 1
        pts = models[cid] - models[cid].mean(axis=0)
        long_axis = np.linalg.eigh(pts.T @ pts)[1][:, -1]
        idx = np.flatnonzero((segs.cls_id == cid) & segs.valid)
        err = np.einsum("nji,njk->nik", segs.R[idx].astype(np.float64), est.R[idx])
        rv = Rotation.from_matrix(err).as_rotvec()
        deg = np.degrees(np.linalg.norm(rv, axis=1))
        cos = np.abs(rv @ long_axis) / np.maximum(np.linalg.norm(rv, axis=1), 1e-12)
        big = deg > BIG_DEG
        about = big & (cos > np.cos(np.radians(AXIS_DEG)))
        row = {
            "class": name,
            "n": len(idx),
            "net: error > 20 deg": int(big.sum()),
            "net: of those about the long axis": int(about.sum()),
            "net: their median angle (deg)": float(np.median(deg[about]))
            if about.any()
            else np.nan,
        }
        for m, table in base.items():
            e = table.loc[table["class"] == name, "net_rot_sym_err_deg"].to_numpy()
            row[f"{m}: < 10 deg"] = int((e < 10).sum())
            row[f"{m}: > 135 deg"] = int((e > 135).sum())
        rows.append(row)
    df = pd.DataFrame(rows)
    print(
        f"# Rotation errors of {run.info.run_name} (run {run.info.run_id}) "
        "against the baselines, test set, without ICP\n"
    )
    print(
        f"_made by `python reports/diagnostics/near_symmetry.py --seed {args.seed}"
        + (f" --run {args.run}" if args.run else "")
        + f"`; data "
        f"{data.data_key[:10]}; error over {BIG_DEG:.0f} deg 'about the long axis' when its axis is "
        f"within {AXIS_DEG:.0f} deg of the model's principal axis; the baselines' columns count "
        "rotation errors modulo symmetry_\n"
    )
    print("| " + " | ".join(df.columns) + " |")
    print("|---|" + "---:|" * (len(df.columns) - 1))
    for row in df.itertuples(index=False):
        print("| " + " | ".join(f"{v:.0f}" if isinstance(v, float) else str(v) for v in row) + " |")


if __name__ == "__main__":
    main()
