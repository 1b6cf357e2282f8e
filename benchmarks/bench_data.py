"""Data pipeline throughput (``synth_frames_per_s``, ``prepare_frames_per_s``).

- ``synth_frames_per_s``: ``cloudpose.data.synth.synthesize`` of N training frames into a
  temporary root with all cores (the CLI's default), beside the same with one process
  (``workers=1``) on other frames; the ratio is the parallel speed-up.
- ``prepare_frames_per_s``: ``cloudpose.data.cache.prepare`` of those frames (segments: mask,
  back-projection, outlier filter, FPS of 1024) with all cores, beside the same with the
  previous FPS (fpsample's exact loop; ``CLOUDPOSE_NO_NUMBA=1`` in the workers); the ratio is
  what the compiled FPS buys end to end. The two caches are compared array by array: the FPS
  orders must be identical.

Usage: ``python -m benchmarks.bench_data [--quick]``
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import quick_main
from cloudpose import kernels
from cloudpose.config import DataConfig
from cloudpose.data.cache import SegmentSet, prepare
from cloudpose.data.synth import synthesize


@contextlib.contextmanager
def _without_numba():
    """The previous FPS path, in this process and in spawned workers."""
    old_env = os.environ.get("CLOUDPOSE_NO_NUMBA")
    os.environ["CLOUDPOSE_NO_NUMBA"] = "1"
    try:
        with kernels.disabled():
            yield
    finally:
        if old_env is None:
            os.environ.pop("CLOUDPOSE_NO_NUMBA", None)
        else:
            os.environ["CLOUDPOSE_NO_NUMBA"] = old_env


def run(quick: bool = False, frames: int | None = None, workdir: str | None = None) -> dict:
    """Synthesis and segment-preparation rates, frames per second.

    Args:
        quick: 2 frames (a smoke run for tests).
        frames: frames per measurement (default 16; quick 2).
        workdir: where the temporary datasets go (default: the system's temp folder).

    Returns:
        ``{"synth_frames_per_s": figure, "prepare_frames_per_s": figure}``.
    """
    n = frames or (2 if quick else 16)
    cores = os.cpu_count() or 1
    with tempfile.TemporaryDirectory(prefix="cloudpose-bench-", dir=workdir) as tmp:
        par_root, one_root = Path(tmp) / "par", Path(tmp) / "one"
        # One process first (it also warms the model files' page cache for the parallel run).
        one = synthesize(one_root, n, 0, seed=1, workers=1, progress=False)
        par = synthesize(par_root, n, 0, seed=0, workers=None, progress=False)
        synth_rate = {"all_cores": n / par.seconds, "one_process": n / one.seconds}

        cfg = DataConfig(n_fps=1024)
        t0 = time.perf_counter()
        fast_path = prepare(par_root, "train", cfg, cache_dir=Path(tmp) / "c1", progress=False)
        t_fast = time.perf_counter() - t0
        with _without_numba():
            t0 = time.perf_counter()
            ref_path = prepare(par_root, "train", cfg, cache_dir=Path(tmp) / "c2", progress=False)
            t_ref = time.perf_counter() - t0
        a, b = SegmentSet.load(fast_path), SegmentSet.load(ref_path)
        identical = all(
            np.array_equal(getattr(a, k), getattr(b, k), equal_nan=k in ("R", "t", "occlusion"))
            for k in ("points", "count", "cls_id", "R", "t", "occlusion", "instance", "valid")
        )
        segments = len(a)
    prep = {"compiled_fps": n / t_fast, "fpsample_fps": n / t_ref}
    common: dict[str, Any] = {"frames": n, "cores": cores}
    return {
        "synth_frames_per_s": {
            "value": synth_rate["all_cores"],
            "unit": "frames/s",
            "what": f"synthesize {n} training frames (render, noise, write), all cores",
            "reference": {"name": "the same, one process", "value": synth_rate["one_process"]},
            "ratio": synth_rate["all_cores"] / synth_rate["one_process"],
            "target": None,
            "met": None,
            "detail": {**common, "seconds": {"all_cores": par.seconds, "one": one.seconds}},
        },
        "prepare_frames_per_s": {
            "value": prep["compiled_fps"],
            "unit": "frames/s",
            "what": f"prepare the segments of {n} frames (FPS of 1024 per object), all cores",
            "reference": {
                "name": "the same with fpsample's exact FPS (previous path)",
                "value": prep["fpsample_fps"],
            },
            "ratio": prep["compiled_fps"] / prep["fpsample_fps"],
            "target": "identical caches",
            "met": bool(identical),
            "detail": {**common, "segments": segments, "caches_identical": identical},
        },
    }


def main() -> None:
    quick_main(run, __doc__)


if __name__ == "__main__":
    main()
