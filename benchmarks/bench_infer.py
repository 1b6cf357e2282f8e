"""Inference latency of the pose networks (``infer_ms_per_object``, ``infer_ms_frame8``).

Both networks of ``shared-0`` (paper widths, n = 256 points, float32, eval mode) on 1 object and
on a frame of 8 objects, in the same process and interleaved:

- ``folded``: ``cloudpose.models.inference.fold_for_inference`` (every BatchNorm folded into its
  Linear, one-hot as a class bias, max before bias/ReLU, both branches batched), the path
  ``evaluate`` and ``predict`` use;
- ``plain``: the PoseNet as built (eval mode, ``torch.inference_mode``), the reference;
- ``fused``: PoseNet with ``cloudpose.models.fused.fuse_model`` (what ``load_checkpoint`` gave
  before folding).

The lower bound is the forward FLOPs (counted from the Linear layers) at this machine's
float32 GEMM rate for the 128 -> 1024 layer's shape, measured in the same run. Threads: all
usable cores (``cloudpose.runtime.configure_threads``).

Usage: ``python -m benchmarks.bench_infer [--quick]``
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch
from torch import nn

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import gemm_rate, quick_main
from cloudpose.config import resolve
from cloudpose.models import build_model
from cloudpose.models.fused import fuse_model
from cloudpose.models.inference import fold_for_inference

N_POINTS = 256
TARGET_MS_1 = 1.0
TARGET_MS_8 = 4.0


def forward_flops(model: nn.Module, B: int, n: int = N_POINTS) -> float:
    """FLOPs (2 per multiply-add) of the Linear layers in one forward of B objects."""
    total = 0.0

    def hook(mod: nn.Linear, inputs: tuple[torch.Tensor, ...], _out: torch.Tensor) -> None:
        nonlocal total
        rows = inputs[0].numel() // inputs[0].shape[-1]
        total += 2.0 * rows * mod.in_features * mod.out_features

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Linear)]
    pts, cls = _batch(B, n)
    with torch.inference_mode():
        model(pts, cls)
    for h in handles:
        h.remove()
    return total


def _batch(B: int, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(B, n, 3, generator=g) * 0.04 + torch.tensor([0.0, 0.0, 0.8])
    return pts, torch.randint(1, 22, (B,), generator=g)


def _trained_like(variant: str) -> nn.Module:
    """A network with non-trivial BatchNorm statistics (as after training), eval mode."""
    torch.manual_seed(0)
    model = build_model(resolve(variant, "paper").model)
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, nn.BatchNorm1d):
                m.running_mean.normal_(0.0, 0.1)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.normal_(1.0, 0.2)
    return model.eval()


def _one_thread_ms(
    impls: dict[str, nn.Module], batches: dict[int, tuple], repeats: int
) -> dict[str, dict[str, float]]:
    """The same timings with one intra-op thread: stable when another process holds a core
    (with two threads a forward then waits for scheduler time slices, 5-30x slower)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        times: dict[str, dict[int, list[float]]] = {k: {B: [] for B in batches} for k in impls}
        with torch.inference_mode():
            for _ in range(repeats + 1):
                for name, m in impls.items():
                    for B, b in batches.items():
                        t0 = time.perf_counter()
                        m(*b)
                        times[name][B].append((time.perf_counter() - t0) * 1e3)
        return {
            k: {str(B): statistics.median(v[1:]) for B, v in d.items()} for k, d in times.items()
        }
    finally:
        torch.set_num_threads(threads)


def run(quick: bool = False, repeats: int | None = None, variant: str = "shared-0") -> dict:
    """Inference figures (ms, median of interleaved repeats).

    Args:
        quick: few repeats (a smoke run for tests).
        repeats: timed rounds (default 30; quick 3).
        variant: the network.

    Returns:
        ``{"infer_ms_per_object": figure, "infer_ms_frame8": figure}``.
    """
    repeats = repeats or (2 if quick else 30)
    plain = _trained_like(variant)
    fused = fuse_model(_trained_like(variant)).eval()
    folded = fold_for_inference(plain)
    impls = {"folded": folded, "plain": plain, "fused": fused}
    batches = {1: _batch(1, N_POINTS), 8: _batch(8, N_POINTS)}
    with torch.inference_mode():
        ref = plain(*batches[8])
        out = folded(*batches[8])
    max_diff = max(float((a - b).abs().max()) for a, b in zip(out, ref, strict=True))
    times: dict[str, dict[int, list[float]]] = {k: {1: [], 8: []} for k in impls}
    with torch.inference_mode():
        for _ in range(2):
            for m in impls.values():
                for b in batches.values():
                    m(*b)
        for _ in range(repeats):
            for name, m in impls.items():
                for B, b in batches.items():
                    t0 = time.perf_counter()
                    m(*b)
                    times[name][B].append((time.perf_counter() - t0) * 1e3)
    med = {k: {B: statistics.median(v) for B, v in d.items()} for k, d in times.items()}
    one_thread = _one_thread_ms({"folded": folded, "plain": plain}, batches, max(2, repeats // 3))
    gemm = {
        "rows_256": gemm_rate(256, 128, 1024, repeats=3 if quick else 21)["median_gflops"],
        "rows_2048": gemm_rate(2048, 128, 1024, repeats=3 if quick else 21)["median_gflops"],
    }
    flops = {B: forward_flops(plain, B) for B in batches}
    bound = {1: flops[1] / gemm["rows_256"] / 1e6, 8: flops[8] / gemm["rows_2048"] / 1e6}
    detail = {
        "ms": {k: {str(B): v for B, v in d.items()} for k, d in med.items()},
        "forward_mflop": {str(B): f / 1e6 for B, f in flops.items()},
        "gemm_gflops": gemm,
        "lower_bound_ms_at_gemm_rate": {str(B): v for B, v in bound.items()},
        "folded_vs_plain_max_abs_diff": max_diff,
        "threads": torch.get_num_threads(),
        "one_thread_ms": one_thread,
        "repeats": repeats,
        "variant": variant,
        "bf16": "not tried: this CPU has no bf16 GEMM hardware (bench_train: bf16 GEMM "
        "slower than fp32)",
    }

    def figure(B: int, target: float, what: str) -> dict[str, Any]:
        v = med["folded"][B]
        return {
            "value": v,
            "unit": "ms",
            "what": what,
            "reference": {"name": "plain PoseNet, eval mode", "value": med["plain"][B]},
            "ratio": med["plain"][B] / v,
            "target": f"<= {target:g} ms (fp32 lower bound here {bound[B]:.2f} ms)",
            "met": bool(v <= target),
            "fraction_of_gemm_bound": bound[B] / v,
            "detail": detail,
        }

    return {
        "infer_ms_per_object": figure(
            1, TARGET_MS_1, f"{variant} rotation + translation nets, 1 object, n = 256, fp32"
        ),
        "infer_ms_frame8": figure(
            8, TARGET_MS_8, f"{variant} rotation + translation nets, 8 objects, n = 256, fp32"
        ),
    }


def main() -> None:
    from cloudpose.runtime import configure_threads

    quick_main(run, __doc__, setup=configure_threads)


if __name__ == "__main__":
    main()
