"""The Ray executor's overhead against the local executor on the same smoke sweep
(``ray_executor_wall_s``).

The smoke preset's rotation group (3 variants x 1 seed; ``--quick``: 1 variant) is swept twice
in one run, into two fresh project folders holding the same prepared data (made first, not
timed), each with its own SQLite MLflow store: by the local executor (this process, one run
after another), then by the Ray executor on a cluster on loopback (``benchmarks.loopback``: a
head node and one node with this process's cores). Each Ray task asks for all of them, so the
tasks run one at a time with the thread count of the local runs: the difference is the
executor's overhead (connecting, a worker process that imports torch and MLflow, each task
reading the data from the shared folder and opening its own MLflow client), not a speed-up.
Starting the cluster is not timed (it exists before a sweep). Both sweeps must end with the
same test metrics.

Usage: ``python -m benchmarks.bench_cluster [--quick]``
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import quick_main

GROUP = "rotation"
TARGET_RATIO = 0.75
"""The local wall time over the Ray wall time should stay above this (Ray adds <= 1/3)."""


def _sweep(project: Path, variants: list[str], executor: str, ray=None) -> float:
    """Wall seconds of ``ensure_runs`` over ``variants`` (smoke, seed 1) in ``project``."""
    from cloudpose.suite.ablate import ensure_runs

    t0 = time.perf_counter()
    statuses = ensure_runs(
        variants,
        "smoke",
        1,
        group=GROUP,
        project_dir=project,
        progress=False,
        echo=lambda _: None,
        executor=executor,
        ray=ray,
    )
    wall = time.perf_counter() - t0
    assert all(s.status == "trained" for s in statuses), statuses
    return wall


def _test_metrics(project: Path) -> dict[str, dict[str, float]]:
    from cloudpose.store import tracking

    runs = tracking.find_runs(tracking.setup(project), preset="smoke")
    return {
        r.data.tags["variant"]: {
            k: v for k, v in r.data.metrics.items() if k.startswith("test") and "_ms_" not in k
        }
        for r in runs
    }


def run(quick: bool = False) -> dict[str, Any]:
    """Sweep with both executors; the figure ``ray_executor_wall_s``."""
    from benchmarks.loopback import Loopback
    from cloudpose.data.dataset import prepare_data
    from cloudpose.registry import get_group, resolve
    from cloudpose.suite.cluster import RayOptions

    variants = list(get_group(GROUP).members)[: 1 if quick else None]
    cores = len(os.sched_getaffinity(0))
    saved_uri = os.environ.pop("MLFLOW_TRACKING_URI", None)  # each sweep its own store
    try:
        with tempfile.TemporaryDirectory(prefix="cloudpose-bench-cluster-") as tmp:
            base = Path(tmp) / "data-src"
            prepare_data(resolve(variants[0], "smoke").data, base, progress=False)
            projects = {}
            for name in ("local", "ray"):
                projects[name] = Path(tmp) / name
                shutil.copytree(base / "data", projects[name] / "data", symlinks=True)
            local_s = _sweep(projects["local"], variants, "local")
            with Loopback() as lb:
                _, gcs = lb.ray_node()
                lb.ray_node(head=gcs, cpus=cores)
                options = RayOptions(address=f"127.0.0.1:{gcs}", cpus_per_run=cores)
                ray_s = _sweep(projects["ray"], variants, "ray", options)
            same = _test_metrics(projects["local"]) == _test_metrics(projects["ray"])
    finally:
        if saved_uri is not None:
            os.environ["MLFLOW_TRACKING_URI"] = saved_uri
    runs = len(variants)
    return {
        "ray_executor_wall_s": {
            "value": ray_s,
            "unit": "s",
            "what": f"cloudpose ablate --executor ray, smoke {GROUP} group ({runs} runs, seed 1): "
            f"train + evaluate, one {cores}-CPU task at a time on a loopback Ray cluster",
            "reference": {"name": "--executor local, the same sweep", "value": local_s},
            "ratio": local_s / ray_s,
            "target": f">= {TARGET_RATIO} (Ray's overhead <= 1/3 of the sweep)",
            "met": bool(local_s / ray_s >= TARGET_RATIO and same),
            "detail": {
                "runs": runs,
                "overhead_s_per_run": (ray_s - local_s) / runs,
                "same_test_metrics": same,
                "threads_per_run": cores,
            },
        }
    }


def main() -> None:
    quick_main(run, __doc__)


if __name__ == "__main__":
    main()
