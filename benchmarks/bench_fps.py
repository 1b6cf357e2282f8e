"""Farthest point sampling speed (``fps_ms_20k``), printed as JSON.

1024 samples with a random start from real depth segments: the three annotated objects of the
real YCB-Video frame in ``tests/data/ycb_real`` (17-21k points each, back-projected as the
pipeline does), subsampled to 5,000 and 20,000 points of one segment and 50,000 of the three
together. Beside ``cloudpose.data.segments.farthest_point_sampling`` (the compiled bucket FPS
where numba is installed), in the same run and interleaved: Open3D's
``farthest_point_down_sample`` (exact, float64), fpsample's exact ``fps_sampling`` (the
previous implementation) and a numpy loop like the original code's (``..._reference``, run
fewer times: it takes ~0.5 s). Also checks that the fast order equals fpsample's and the numpy
loop's index for index (ties included).

Usage: ``python -m benchmarks.bench_fps [--quick]``
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import quick_main
from cloudpose.data import segments as sg
from cloudpose.data.ycb import read_frame

REAL_FRAME = Path(__file__).resolve().parents[1] / "tests" / "data" / "ycb_real" / "data" / "0000"
K_SAMPLES = 1024
TARGET_MS = 6.0


def real_segments() -> list[np.ndarray]:
    """The back-projected depth segments (N_i, 3) float32, metres, of the real test frame."""
    f = read_frame(
        REAL_FRAME / "000001-depth.png",
        REAL_FRAME / "000001-label.png",
        REAL_FRAME / "000001-meta.mat",
    )
    return [
        sg.backproject(f.depth, f.label == c, f.K).astype(np.float32) for c in f.cls_ids.tolist()
    ]


def clouds(sizes: list[int], seed: int = 0) -> dict[int, np.ndarray]:
    """Point clouds of the requested sizes cut from the real segments (order kept)."""
    segs = real_segments()
    biggest = max(segs, key=len)
    together = np.concatenate(segs)
    rng = np.random.default_rng(seed)
    out = {}
    for n in sizes:
        src = biggest if n <= len(biggest) else together
        if n > len(src):
            raise ValueError(f"bench_fps: no real cloud has {n} points (largest {len(src)})")
        out[n] = src[np.sort(rng.choice(len(src), n, replace=False))]
    return out


def _open3d_fps(pts: np.ndarray, k: int, start: int) -> None:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    pcd.farthest_point_down_sample(k, start)


def _fpsample_fps(pts: np.ndarray, k: int, start: int) -> np.ndarray:
    import fpsample

    return np.asarray(fpsample.fps_sampling(pts, k, start_idx=start), dtype=np.int64)


def run(quick: bool = False, repeats: int | None = None) -> dict[str, Any]:
    """FPS timings in ms per call (median over repeats) for each size, and the checks.

    Args:
        quick: small sizes and few repeats (a smoke run for tests).
        repeats: interleaved rounds (default 7; quick 2).

    Returns:
        ``{"fps_ms_20k": figure}`` with the 5k and 50k results in ``detail``.
    """
    sizes = [2000, 5000] if quick else [5000, 20000, 50000]
    repeats = repeats or (2 if quick else 7)
    ref_every = 1 if quick else 3  # the numpy loop runs in every third round only
    data = clouds(sizes)
    rng = np.random.default_rng(1)
    impls = {
        "cloudpose": lambda p, s: sg.farthest_point_sampling(p, K_SAMPLES, s),
        "open3d": lambda p, s: _open3d_fps(p, K_SAMPLES, s),
        "fpsample_exact": lambda p, s: _fpsample_fps(p, K_SAMPLES, s),
        "numpy_loop": lambda p, s: sg.farthest_point_sampling_reference(p, K_SAMPLES, s),
    }
    per_size: dict[str, Any] = {}
    for n, pts in data.items():
        starts = rng.integers(n, size=repeats + 1)
        fast = sg.farthest_point_sampling(pts, K_SAMPLES, int(starts[0]))  # warm-up/compile
        same_fpsample = bool(np.array_equal(fast, _fpsample_fps(pts, K_SAMPLES, int(starts[0]))))
        same_loop = bool(
            np.array_equal(
                fast, sg.farthest_point_sampling_reference(pts, K_SAMPLES, int(starts[0]))
            )
        )
        times: dict[str, list[float]] = {k: [] for k in impls}
        for r in range(repeats):
            s = int(starts[r + 1])
            for name, fn in impls.items():
                if name == "numpy_loop" and r % ref_every:
                    continue
                t0 = time.perf_counter()
                fn(pts, s)
                times[name].append((time.perf_counter() - t0) * 1e3)
        med = {k: statistics.median(v) for k, v in times.items()}
        per_size[str(n)] = {
            "ms": med,
            "speedup_vs": {k: med[k] / med["cloudpose"] for k in impls if k != "cloudpose"},
            "same_indices_as_fpsample": same_fpsample,
            "same_indices_as_numpy_loop": same_loop,
            "repeats": {k: len(v) for k, v in times.items()},
        }
    key = "20000" if "20000" in per_size else str(max(sizes))
    main = per_size[key]
    return {
        "fps_ms_20k": {
            "value": main["ms"]["cloudpose"],
            "unit": "ms",
            "what": f"FPS, {K_SAMPLES} of {key} real depth points, random start "
            "(cloudpose.data.segments.farthest_point_sampling)",
            "reference": {
                "name": "open3d farthest_point_down_sample",
                "value": main["ms"]["open3d"],
            },
            "ratio": main["speedup_vs"]["open3d"],
            "target": f"<= {TARGET_MS} ms, exact",
            "met": bool(
                main["ms"]["cloudpose"] <= TARGET_MS
                and main["same_indices_as_fpsample"]
                and main["same_indices_as_numpy_loop"]
            ),
            "detail": per_size,
        }
    }


def main() -> None:
    quick_main(run, __doc__)


if __name__ == "__main__":
    main()
