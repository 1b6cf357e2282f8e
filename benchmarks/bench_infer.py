"""Inference latency of the pose networks (``infer_ms_per_object``, ``infer_ms_frame8``).

Both networks of ``shared-0`` (paper widths, n = 256 points, float32, eval mode) on 1 object and
on a frame of 8 objects, in the same process and interleaved:

- ``folded``: ``cloudpose.models.folded.fold_for_inference`` (every BatchNorm folded into its
  Linear, one-hot as a class bias, max before bias/ReLU, both branches batched), the path
  ``evaluate`` and ``predict`` use;
- ``plain``: the PoseNet as built (eval mode, ``torch.inference_mode``), the reference;
- ``fused``: PoseNet with ``cloudpose.models.fused.fuse_model`` (what ``load_checkpoint`` gave
  before folding).

The floor is the forward FLOPs (counted from the Linear layers) at this machine's float32 GEMM
rate for the 128 -> 1024 layer's shape at the same rows (256 per object), that product timed in
the same loop as the networks, interleaved, so load from other processes hits both alike. The
target is the folded network within 1.25x of the floor, for 1 and for 8 objects. Threads: all
usable cores (``cloudpose.runtime.configure_threads``), and the same figures with one thread
(stable when other processes hold the cores: with two threads a forward then waits for
scheduler time slices). Where the CPU has bf16 hardware (``cloudpose.runtime.cpu_features``)
the folded network under bf16 autocast is timed too, with its deviation (information: the
figures are fp32).

Usage: ``python -m benchmarks.bench_infer [--quick]``
"""

from __future__ import annotations

import statistics
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any

import torch
from torch import nn

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import quick_main
from cloudpose.models import build_model
from cloudpose.models.folded import fold_for_inference
from cloudpose.models.fused import fuse_model
from cloudpose.registry import resolve
from cloudpose.runtime import cpu_features, describe_cpu

N_POINTS = 256
TARGET_OVER_FLOOR = 1.25
D_POOL, C_POOL = 1024, 128  # the pooled layer's product: the floor's GEMM shape


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


def _interleaved_ms(
    cases: dict[str, Any], repeats: int, threads: int | None = None
) -> dict[str, float]:
    """Median ms of each case, round-robin over ``repeats`` rounds after two untimed ones."""
    before = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        times: dict[str, list[float]] = {k: [] for k in cases}
        with torch.inference_mode():
            for _ in range(2):
                for f in cases.values():
                    f()
            for _ in range(repeats):
                for name, f in cases.items():
                    t0 = time.perf_counter()
                    f()
                    times[name].append((time.perf_counter() - t0) * 1e3)
        return {k: statistics.median(v) for k, v in times.items()}
    finally:
        torch.set_num_threads(before)


def _gemm_case(rows: int) -> tuple[Any, float]:
    """The floor's product, (rows, 128) @ (128, 1024) into a preallocated output, and its FLOPs."""
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(rows, C_POOL, generator=g), torch.randn(C_POOL, D_POOL, generator=g)
    out = torch.empty(rows, D_POOL)
    return (lambda: torch.mm(a, b, out=out)), 2.0 * rows * C_POOL * D_POOL


def run(quick: bool = False, repeats: int | None = None, variant: str = "shared-0") -> dict:
    """Inference figures (ms, median of interleaved repeats) against their GEMM floor.

    Args:
        quick: few repeats (a smoke run for tests).
        repeats: timed rounds (default 30; quick 2).
        variant: the network.

    Returns:
        ``{"infer_ms_per_object": figure, "infer_ms_frame8": figure}``.
    """
    repeats = repeats or (2 if quick else 30)
    cpu = cpu_features()
    plain = _trained_like(variant)
    fused = fuse_model(_trained_like(variant)).eval()
    folded = fold_for_inference(plain)
    impls = {"folded": folded, "plain": plain, "fused": fused}
    batches = {1: _batch(1, N_POINTS), 8: _batch(8, N_POINTS)}
    with torch.inference_mode():
        ref = plain(*batches[8])
        out = folded(*batches[8])
    max_diff = max(float((a - b).abs().max()) for a, b in zip(out, ref, strict=True))
    flops = {B: forward_flops(plain, B) for B in batches}
    gemms = {B: _gemm_case(B * N_POINTS) for B in batches}

    def cases(names: tuple[str, ...]) -> dict[str, Any]:
        c: dict[str, Any] = {}
        for B, b in batches.items():
            for name in names:
                c[f"{name}/{B}"] = partial(impls[name], *b)
            c[f"gemm/{B}"] = gemms[B][0]
        return c

    def summary(ms: dict[str, float]) -> dict[str, Any]:
        gflops = {B: gemms[B][1] / ms[f"gemm/{B}"] / 1e6 for B in batches}
        floor = {B: flops[B] / gflops[B] / 1e6 for B in batches}
        return {
            "ms": ms,
            "gemm_gflops": {str(B): v for B, v in gflops.items()},
            "floor_ms": {str(B): v for B, v in floor.items()},
            "folded_over_floor": {str(B): ms[f"folded/{B}"] / floor[B] for B in batches},
        }

    threads = torch.get_num_threads()
    all_t = summary(_interleaved_ms(cases(("folded", "plain", "fused")), repeats))
    one_t = summary(_interleaved_ms(cases(("folded", "plain")), max(2, repeats), threads=1))
    bf16: dict[str, Any] | str
    if cpu["bf16_hardware"]:
        with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
            out16 = folded(*batches[8])
        auto = {f"folded_bf16/{B}": partial(_autocast_call, folded, b) for B, b in batches.items()}
        ms16 = _interleaved_ms({**auto, **cases(("folded",))}, max(2, repeats // 2), threads=1)
        bf16 = {
            "one_thread_ms": ms16,
            "bf16_over_fp32_speed": {
                str(B): ms16[f"folded/{B}"] / ms16[f"folded_bf16/{B}"] for B in batches
            },
            "max_abs_diff_t_m": float((out16.t.float() - out.t).abs().max()),
            "max_abs_diff_R": float((out16.R.float() - out.R).abs().max()),
            "note": "bf16 autocast of the folded network: measured only; evaluation runs fp32",
        }
    else:
        bf16 = f"not tried: {cpu['model']} has no avx512_bf16 or AMX"
    detail = {
        "cpu": describe_cpu(cpu),
        "threads": threads,
        "all_threads": all_t,
        "one_thread": one_t,
        "forward_mflop": {str(B): f / 1e6 for B, f in flops.items()},
        "floor": "forward FLOPs at the fp32 rate of (B*256, 128) @ (128, 1024), timed "
        "interleaved with the networks",
        "folded_vs_plain_max_abs_diff": max_diff,
        "repeats": repeats,
        "variant": variant,
        "bf16": bf16,
    }

    def figure(B: int, what: str) -> dict[str, Any]:
        ms = all_t["ms"]
        v, floor = ms[f"folded/{B}"], all_t["floor_ms"][str(B)]
        over, over_1 = v / floor, one_t["folded_over_floor"][str(B)]
        met = bool(over <= TARGET_OVER_FLOOR)
        if met:
            why = None
        elif over_1 <= TARGET_OVER_FLOOR:
            why = (
                f"not met with {threads} threads ({over:.2f}x the floor) but met with one "
                f"({over_1:.2f}x): the threads wait on each other under load"
            )
        else:
            why = (
                f"{over:.2f}x the floor with {threads} threads, {over_1:.2f}x with one: besides "
                "the pooled product (the floor), the forward streams the head's 1024 -> 512 "
                "weights (4 MiB, memory-bound at one object), reduces the (n, 1024) product "
                "and runs the 64-wide layers, which no GEMM rate covers"
            )
        return {
            "value": v,
            "unit": "ms",
            "what": what,
            "reference": {"name": "fp32 GEMM floor, same run, interleaved", "value": floor},
            "ratio": floor / v,
            "target": f"<= {TARGET_OVER_FLOOR:g}x the floor (fp32, same threads)",
            "met": met,
            "note": why,
            "plain_ms": ms[f"plain/{B}"],
            "folded_over_floor_one_thread": over_1,
            "detail": detail,
        }

    return {
        "infer_ms_per_object": figure(
            1, f"{variant} rotation + translation nets, 1 object, n = 256, fp32, folded"
        ),
        "infer_ms_frame8": figure(
            8, f"{variant} rotation + translation nets, 8 objects, n = 256, fp32, folded"
        ),
    }


def _autocast_call(model: nn.Module, batch: tuple) -> Any:
    with torch.autocast("cpu", dtype=torch.bfloat16):
        return model(*batch)


def main() -> None:
    from cloudpose.runtime import configure_threads

    quick_main(run, __doc__, setup=configure_threads)


if __name__ == "__main__":
    main()
