"""Shared benchmark helpers: machine description, timing, this machine's GEMM rate.

Every benchmark reports its figures beside a reference measured in the same run, with the
machine described, so ratios stay comparable across machines and load.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from typing import Any

import torch

from cloudpose.runtime import active_allocator, cpu_features


def cpu_info() -> dict[str, Any]:
    """CPU model, vendor, the GEMM-relevant flags it has, cores (all and usable by this process),
    torch's dispatch capability and whether bf16 products have hardware
    (``cloudpose.runtime.cpu_features``)."""
    return cpu_features()


def describe_machine() -> dict[str, Any]:
    """What a benchmark figure depends on: CPU, torch build and threads, allocator, load."""
    try:
        load = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        load = None
    return {
        "cpu": cpu_info(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "allocator": active_allocator(),
        "ld_preload": os.environ.get("LD_PRELOAD", ""),
        "load_average_1_5_15min": load,
    }


def time_calls(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> list[float]:
    """Wall-clock seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def summarize(times: list[float]) -> dict[str, float]:
    """Median, min and max of repeated timings, in seconds, and how many."""
    return {
        "median_s": statistics.median(times),
        "min_s": min(times),
        "max_s": max(times),
        "repeats": len(times),
    }


GEMM_SHAPES = {
    # (rows, inner, cols) of the 128 -> 1024 layer at B*n = 32768 points (batch 128, n = 256)
    "forward_32768x128x1024": (32768, 128, 1024),
    "grad_input_32768x1024x128": (32768, 1024, 128),
    "grad_weight_1024x32768x128": (1024, 32768, 128),
    "forward_chunk_2048x128x1024": (2048, 128, 1024),
}
"""Matrix products timed for the GEMM rate: the shapes the training step multiplies."""


def gemm_rate(
    m: int, k: int, n: int, dtype: torch.dtype = torch.float32, repeats: int = 9
) -> dict[str, float]:
    """GFLOP/s of ``(m, k) @ (k, n)`` into a preallocated output (no allocator in the way).

    Returns:
        ``median_gflops`` (from the median time), ``best_gflops`` and ``repeats``.
    """
    g = torch.Generator().manual_seed(0)
    a = torch.randn(m, k, generator=g).to(dtype)
    b = torch.randn(k, n, generator=g).to(dtype)
    out = torch.empty(m, n, dtype=dtype)
    flops = 2.0 * m * k * n
    times = time_calls(lambda: torch.mm(a, b, out=out), repeats, warmup=2)
    return {
        "median_gflops": flops / statistics.median(times) / 1e9,
        "best_gflops": flops / min(times) / 1e9,
        "repeats": repeats,
    }


def gemm_peak(dtype: torch.dtype = torch.float32, repeats: int = 9, quick: bool = False) -> dict:
    """This machine's GEMM rate: each training-step shape, and the best median among them.

    The reference for "fraction of peak" is ``peak_gflops``, the highest median over the
    shapes the network actually multiplies (a conservative peak: fractions are not flattered
    by a shape the network never runs).
    """
    shapes = dict(GEMM_SHAPES)
    if quick:
        shapes = {k: v for k, v in shapes.items() if "chunk" in k or k.startswith("forward")}
    per_shape = {
        name: gemm_rate(*shape, dtype=dtype, repeats=repeats) for name, shape in shapes.items()
    }
    best = max(per_shape, key=lambda s: per_shape[s]["median_gflops"])
    return {
        "dtype": str(dtype).removeprefix("torch."),
        "peak_gflops": per_shape[best]["median_gflops"],
        "peak_shape": best,
        "per_shape": per_shape,
    }


def quick_main(run: Callable[..., dict], doc: str | None, setup: Callable[[], None] | None = None):
    """The command line of a benchmark module: ``--quick``, then ``run(quick=...)`` as JSON."""
    import argparse
    import json

    ap = argparse.ArgumentParser(description=(doc or "").splitlines()[0] if doc else None)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    if setup is not None:
        setup()
    print(json.dumps(run(quick=args.quick), indent=2))
