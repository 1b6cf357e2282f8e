"""Training-step throughput against this machine's GEMM rate (``train_fraction_of_peak``).

One run measures, in the same processes:

- this machine's float32 GEMM rate (``benchmarks.common.gemm_peak``: the 128 -> 1024 layer's
  products at B*n = 32768 points, median of repeats, into preallocated outputs) and bf16's;
- training steps (forward, pose loss, backward, Adam) at batch 128, n = 256, float32, of the
  plain network and of the same network with ``cloudpose.models.fused.fuse_model``, repeats
  interleaved so that load from other processes hits both alike; every variant in the full run;
- the same with the allocator the CLI installs (tcmalloc / jemalloc, via
  ``cloudpose.runtime``), with glibc's malloc as is, and with glibc after
  ``cloudpose.runtime.tune_glibc_malloc`` (the CLI's fallback), each in its own child process (an
  allocator is fixed at process start).

FLOPs are counted analytically from the plain network's Linear layers (forward hooks record
each layer's rows per sample): forward 2*rows*c_in*c_out, backward the same twice (grad input,
grad weight), except the first layer of each branch, whose input is data and needs no grad
input. For shared-0 that is 232.0 MFLOP per BaseNet and 464.0 per sample for the pair; the
128 -> 1024 layer is 201.3 of each 232.0. BatchNorm, ReLU, max pool, loss and Adam are not
counted. ``fraction_of_peak = samples/s * FLOP/sample / GEMM rate``; the fused network does
fewer FLOPs than it is credited with (its backward skips two of the three big GEMMs), so its
fraction can exceed 1.

Usage: ``python -m benchmarks.bench_train [--quick] [--compile]`` prints JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch
from torch import nn

from benchmarks.common import describe_machine, gemm_peak, gemm_rate, summarize
from cloudpose.geometry.rotations import rotvec_to_rotmat
from cloudpose.models import build_model
from cloudpose.models.fused import fuse_model
from cloudpose.registry import resolve, variants
from cloudpose.runtime import (
    active_allocator,
    configure_threads,
    cpu_features,
    preferred_allocator,
    tune_glibc_malloc,
)
from cloudpose.train.losses import pose_loss

BATCH = 128
N_POINTS = 256


def train_flops_per_sample(variant: str, n_points: int = N_POINTS) -> float:
    """Analytic FLOPs of one training sample (forward + backward) of the plain network.

    Counts every ``nn.Linear`` call: ``2 * rows * c_in * c_out`` forward, twice that backward,
    minus the grad-input product where the layer's input needs no gradient (raw points).
    """
    cfg = resolve(variant, "paper")
    model = build_model(cfg.model)
    B = 2
    total = 0.0

    def hook(mod: nn.Linear, inputs: tuple[torch.Tensor, ...], _out: torch.Tensor) -> None:
        nonlocal total
        rows = inputs[0].numel() // inputs[0].shape[-1]
        mac = rows * mod.in_features * mod.out_features
        total += 2 * mac * (3 if inputs[0].requires_grad else 2)

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Linear)]
    pts, cls, *_ = make_batch(B, n_points, cfg.model.num_classes, seed=0)
    model(pts, cls)
    for h in handles:
        h.remove()
    return total / B


def make_batch(
    B: int, n: int, num_classes: int, seed: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Synthetic segments: (B, n, 3) points near 0.8 m, class ids, (B, 3, 3) R and (B, 3) t."""
    g = torch.Generator().manual_seed(seed)
    t = torch.randn(B, 3, generator=g) * 0.05 + torch.tensor([0.0, 0.0, 0.8])
    R = rotvec_to_rotmat(torch.randn(B, 3, generator=g))
    pts = (torch.randn(B, n, 3, generator=g) * 0.04) @ R.mT + t[:, None]
    cls = torch.randint(1, num_classes + 1, (B,), generator=g)
    return pts, cls, R, t


def make_step(
    variant: str,
    impl: str,
    B: int,
    n: int,
    compile_mode: str | None = None,
    device: str = "cpu",
):
    """A closure running one training step of ``variant``; it returns the loss, so a step on a
    GPU is timed to its end (``.item()`` waits for the device).

    Args:
        impl: "plain", "fused" (float32) or "fused_bf16" (fused bf16 GEMM + bf16 autocast).
        compile_mode: torch.compile mode for the model, or None.
        device: where the model, the batch and the step live.
    """
    cfg = resolve(variant, "paper")
    torch.manual_seed(0)
    model = build_model(cfg.model)
    if impl != "plain":
        fuse_model(model, bf16=impl == "fused_bf16")
    model.to(device)
    net = torch.compile(model, mode=compile_mode) if compile_mode else model
    opt = torch.optim.Adam(model.parameters(), lr=cfg.train.lr)
    pts, cls, R, t = (x.to(device) for x in make_batch(B, n, cfg.model.num_classes, seed=1))
    bf16 = impl == "fused_bf16"
    autocast_device = torch.device(device).type

    def step() -> float:
        with torch.autocast(autocast_device, dtype=torch.bfloat16, enabled=bf16):
            out = net(pts, cls)
        loss = pose_loss(
            out.R.float(),
            out.t.float(),
            R,
            t,
            rotation=cfg.loss.rotation,
            alpha=cfg.loss.alpha,
            rotvec_pred=out.rot_raw.float(),
        ).total
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return loss.item()

    return step


def bf16_accuracy(
    steps: int = 240, batch: int = 32, n: int = N_POINTS, seeds: tuple[int, int] = (1, 2)
) -> dict[str, Any]:
    """A short training of shared-0 (cpu recipe) at fp32 and at bf16 from the same seed.

    Segments of the 21 objects synthesized on line (:class:`~cloudpose.data.synth.online.
    OnlineSynth`, version 2, n points): ``8 * batch`` training segments cycled for ``steps``
    Adam steps (the same batches in the same order for every run) and ``4 * batch`` held-out
    ones. Runs: fp32 and bf16 (fused bf16 GEMM + bf16 autocast, as ``train.precision =
    "bf16"``) from ``seeds[0]``, and fp32 from ``seeds[1]``: the seed-to-seed difference is
    the yardstick for "equal accuracy". All held-out figures are of the eval-mode network in
    float32 (as evaluation runs it), so only the training differs.

    Returns:
        Per run: the training-loss curve (mean of each eighth of the steps), held-out loss,
        median rotation error (deg, plain geodesic) and median translation error (mm);
        ``equal_accuracy``: bf16's held-out loss within the seed-to-seed difference of fp32's
        (at least 2% of it).
    """
    import numpy as np

    from cloudpose.data.synth.chunks import OnlineSettings
    from cloudpose.data.synth.online import OnlineSynth
    from cloudpose.geometry.rotations import rotmat_geodesic_distance

    cfg = resolve("shared-0", "cpu")
    synth = OnlineSynth(OnlineSettings(2, n_points=n))

    def tensors(step: int, size: int) -> tuple[torch.Tensor, ...]:
        b = synth.batch(0, step, size)
        return tuple(
            torch.from_numpy(np.ascontiguousarray(a)) for a in (b.points, b.cls_id, b.R, b.t)
        )

    train_batches = [tensors(k, batch) for k in range(8)]
    held = tensors(1000, 4 * batch)

    def loss_of(out, R, t, cls) -> torch.Tensor:
        return pose_loss(
            out.R.float(),
            out.t.float(),
            R,
            t,
            rotation=cfg.loss.rotation,
            alpha=cfg.loss.alpha,
            rotvec_pred=out.rot_raw.float(),
            symmetric=cfg.loss.symmetric,
            cls_id=cls,
        ).total

    def one(bf16: bool, seed: int) -> dict[str, Any]:
        torch.manual_seed(seed)
        model = build_model(cfg.model)
        fuse_model(model, bf16=bf16)
        opt = torch.optim.Adam(model.parameters(), lr=cfg.train.lr)
        curve: list[float] = []
        model.train()
        for k in range(steps):
            pts, cls, R, t = train_batches[k % len(train_batches)]
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                out = model(pts, cls)
            loss = loss_of(out, R, t, cls)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            curve.append(float(loss))
        model.eval()
        for m in model.modules():
            if hasattr(m, "bf16"):
                m.bf16 = False  # evaluation runs the network in float32
        pts, cls, R, t = held
        with torch.no_grad():
            out = model(pts, cls)
            rot = torch.rad2deg(rotmat_geodesic_distance(out.R.float(), R))
            trans = (out.t.float() - t).norm(dim=1) * 1e3
            held_loss = float(loss_of(out, R, t, cls))
        eighth = max(1, steps // 8)
        return {
            "train_loss_curve": [
                round(float(np.mean(curve[i : i + eighth])), 4) for i in range(0, steps, eighth)
            ],
            "heldout_loss": held_loss,
            "heldout_rot_err_deg_median": float(rot.median()),
            "heldout_trans_err_mm_median": float(trans.median()),
        }

    runs = {
        f"fp32_seed{seeds[0]}": one(False, seeds[0]),
        f"bf16_seed{seeds[0]}": one(True, seeds[0]),
        f"fp32_seed{seeds[1]}": one(False, seeds[1]),
    }
    f32, b16, f32b = (runs[k]["heldout_loss"] for k in runs)
    yardstick = max(abs(f32b - f32), 0.02 * abs(f32))
    return {
        "runs": runs,
        "steps": steps,
        "batch": batch,
        "n_points": n,
        "bf16_minus_fp32_heldout_loss": b16 - f32,
        "seed_to_seed_heldout_loss": f32b - f32,
        "equal_accuracy": bool(abs(b16 - f32) <= yardstick),
    }


def measure_interleaved(
    cases: dict[str, Any], repeats: int, warmup: int, B: int
) -> dict[str, dict[str, float]]:
    """Time each case's step ``repeats`` times, round-robin, after ``warmup`` rounds."""
    times: dict[str, list[float]] = {name: [] for name in cases}
    first: dict[str, float] = {}
    for name, step in cases.items():
        t0 = time.perf_counter()
        step()
        first[name] = time.perf_counter() - t0  # includes compilation where compiled
        for _ in range(warmup - 1):
            step()
    for _ in range(repeats):
        for name, step in cases.items():
            t0 = time.perf_counter()
            step()
            times[name].append(time.perf_counter() - t0)
    out = {}
    for name, ts in times.items():
        s = summarize(ts)
        out[name] = {
            "samples_per_s": B / s["median_s"],
            "samples_per_s_best": B / s["min_s"],
            "step_ms_median": s["median_s"] * 1e3,
            "step_ms_all": [round(x * 1e3, 1) for x in ts],
            "first_step_s": first[name],
        }
    return out


def child(spec: dict[str, Any]) -> dict[str, Any]:
    """One process's measurements (its allocator was fixed when it started)."""
    configure_threads(spec.get("threads"))
    tuned = tune_glibc_malloc() if spec.get("tune_glibc") else False
    quick = spec["quick"]
    res: dict[str, Any] = {"machine": describe_machine(), "allocator": active_allocator()}
    res["machine"]["glibc_tuned"] = tuned
    if spec.get("gemm"):
        res["gemm_fp32"] = gemm_peak(torch.float32, repeats=5 if quick else 9, quick=quick)
        res["gemm_bf16"] = gemm_rate(2048, 128, 1024, torch.bfloat16, repeats=3)
    B, n = spec["batch"], spec["n_points"]
    runs: dict[str, Any] = {}
    for variant in spec["variants"]:
        cases = {impl: make_step(variant, impl, B, n) for impl in spec["impls"]}
        runs[variant] = measure_interleaved(cases, spec["repeats"], spec["warmup"], B)
    res["train"] = runs
    if spec.get("bf16_accuracy_steps"):
        res["bf16_accuracy"] = bf16_accuracy(steps=spec["bf16_accuracy_steps"])
    if spec.get("compile_modes"):
        comp = {}
        for mode in spec["compile_modes"]:
            cases = {
                f"{impl}+compile:{mode}": make_step("shared-0", impl, B, n, compile_mode=mode)
                for impl in ("plain", "fused")
            }
            comp.update(measure_interleaved(cases, spec["repeats"], spec["warmup"], B))
        res["compile"] = comp
    return res


def _run_child(spec: dict[str, Any], allocator: str) -> dict[str, Any]:
    env = dict(os.environ)
    env["CLOUDPOSE_NO_TCMALLOC"] = "1"  # the parent decides the allocator
    preload = [p for p in env.get("LD_PRELOAD", "").split(":") if p]
    preload = [p for p in preload if "tcmalloc" not in p and "jemalloc" not in p]
    if allocator != "glibc":
        lib = preferred_allocator()
        assert lib is not None
        preload.insert(0, str(lib))
        env.setdefault("TCMALLOC_LARGE_ALLOC_REPORT_THRESHOLD", str(1 << 40))
    env["LD_PRELOAD"] = ":".join(preload)
    root = Path(__file__).resolve().parents[1]
    env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    cmd = [sys.executable, "-m", "benchmarks.bench_train", "--child", json.dumps(spec)]
    proc = subprocess.run(cmd, env=env, cwd=root, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"benchmark child ({allocator}) failed:\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def bf16_figure(
    spec: dict[str, Any],
    allocator: str,
    flop_per_sample: float,
    bf16_rate: float,
    fp32_rate: float,
    quick: bool,
) -> dict[str, Any]:
    """bf16 training against fp32 where this CPU has bf16 hardware (avx512_bf16 or AMX).

    One child process times fused fp32 and fused bf16 steps interleaved (ratios within one
    process: the machine may be shared), one thread and all threads, and trains both briefly
    from the same seed (:func:`bf16_accuracy`). Elsewhere the figure is skipped, with the CPU
    named.
    """
    cpu = cpu_features()
    common = {
        "cpu": cpu["model"],
        "cpu_flags": cpu["flags"],
        "bf16_gemm_gflops": bf16_rate / 1e9,
        "bf16_over_fp32_gemm_rate": bf16_rate / fp32_rate,
    }
    if not cpu["bf16_hardware"]:
        return {
            "value": None,
            **common,
            "skipped": f"not tried: {cpu['model']} has no avx512_bf16 or AMX (flags "
            f"{' '.join(cpu['flags']) or '-'}), so bfloat16 products are emulated "
            f"({bf16_rate / fp32_rate:.2f}x the fp32 GEMM rate here)",
        }
    spec_bf16 = dict(
        spec,
        gemm=False,
        variants=["shared-0"],
        impls=["fused", "fused_bf16"],
        repeats=3 if quick else 9,
        bf16_accuracy_steps=16 if quick else 240,
    )
    res = _run_child(spec_bf16, allocator)
    r = res["train"]["shared-0"]
    one = _run_child(dict(spec_bf16, threads=1, bf16_accuracy_steps=0), allocator)
    r1 = one["train"]["shared-0"]
    speedup = r["fused_bf16"]["samples_per_s"] / r["fused"]["samples_per_s"]
    speedup_1 = r1["fused_bf16"]["samples_per_s"] / r1["fused"]["samples_per_s"]
    acc = res["bf16_accuracy"]
    faster = speedup > 1.05 and speedup_1 > 1.05
    keep = faster and acc["equal_accuracy"]
    return {
        "value": r["fused_bf16"]["samples_per_s"],
        **common,
        "fp32_samples_per_s_same_process": r["fused"]["samples_per_s"],
        "bf16_over_fp32": speedup,
        "bf16_over_fp32_one_thread": speedup_1,
        "fraction_of_bf16_peak": r["fused_bf16"]["samples_per_s"] * flop_per_sample / bf16_rate,
        "accuracy": acc,
        "faster": faster,
        "equal_accuracy": acc["equal_accuracy"],
        "verdict": (
            "bf16 is faster at equal accuracy on this CPU: train.precision = 'bf16' is worth "
            "setting here (no preset sets it)"
            if keep
            else "bf16 is "
            + ("faster" if faster else "not faster (> 5% in both thread counts)")
            + " and "
            + ("of equal accuracy" if acc["equal_accuracy"] else "less accurate")
            + " here: keep fp32"
        ),
        "detail": {"all_threads": r, "one_thread": r1},
    }


def run(quick: bool = False, compile: bool = False) -> dict[str, Any]:
    """All training-throughput figures, as a JSON-able dict.

    Args:
        quick: shared-0 only and fewer repeats (about a minute on 2 cores).
        compile: also time shared-0 with ``torch.compile`` (default mode), plain and fused;
            the first step's time (compilation included) is reported.

    Returns:
        ``{"machine", "gemm_fp32_gflops", "train_fraction_of_peak", "train_bf16_samples_per_s",
        "train_by_allocator", "compile"?}``.
    """
    fast_alloc = "tcmalloc" if preferred_allocator() is not None else "glibc"
    all_variants = ["shared-0"] if quick else list(variants())
    spec = {
        "quick": quick,
        "batch": BATCH,
        "n_points": N_POINTS,
        "repeats": 3 if quick else 7,
        "warmup": 2,
        "gemm": True,
        "variants": all_variants,
        "impls": ["plain", "fused"],
    }
    if compile:
        spec["compile_modes"] = ["default"]
    main = _run_child(spec, fast_alloc)
    flops = {v: train_flops_per_sample(v) for v in all_variants}
    peak = main["gemm_fp32"]["peak_gflops"] * 1e9
    bf16_rate = main["gemm_bf16"]["median_gflops"] * 1e9

    bf16 = bf16_figure(spec, fast_alloc, flops["shared-0"], bf16_rate, peak, quick)

    per_variant = {}
    for v, impls in main["train"].items():
        per_variant[v] = {
            "mflop_per_sample": flops[v] / 1e6,
            **{
                impl: {
                    "samples_per_s": r["samples_per_s"],
                    "fraction_of_peak": r["samples_per_s"] * flops[v] / peak,
                    "step_ms_median": r["step_ms_median"],
                    "step_ms_all": r["step_ms_all"],
                }
                for impl, r in impls.items()
            },
            "speedup": impls["fused"]["samples_per_s"] / impls["plain"]["samples_per_s"],
        }
    s0 = per_variant["shared-0"]

    alloc: dict[str, Any] = {fast_alloc: main["train"]["shared-0"]}
    spec_glibc = dict(spec, gemm=False, variants=["shared-0"])
    if fast_alloc != "glibc":
        alloc["glibc"] = _run_child(spec_glibc, "glibc")["train"]["shared-0"]
    spec_glibc["tune_glibc"] = True
    alloc["glibc_mallopt"] = _run_child(spec_glibc, "glibc")["train"]["shared-0"]

    out: dict[str, Any] = {
        "machine": main["machine"],
        "gemm_fp32_gflops": main["gemm_fp32"],
        "train_fraction_of_peak": {
            "value": s0["fused"]["fraction_of_peak"],
            "what": "shared-0, fused, float32, batch 128, n = 256, allocator "
            f"{fast_alloc}: samples/s * analytic FLOP/sample / fp32 GEMM rate",
            "samples_per_s": s0["fused"]["samples_per_s"],
            "plain_samples_per_s": s0["plain"]["samples_per_s"],
            "plain_fraction_of_peak": s0["plain"]["fraction_of_peak"],
            "mflop_per_sample": s0["mflop_per_sample"],
            "gemm_gflops": peak / 1e9,
            "per_variant": per_variant,
        },
        "train_bf16_samples_per_s": bf16,
        "train_by_allocator": {
            a: {impl: r["samples_per_s"] for impl, r in res.items()} for a, res in alloc.items()
        },
    }
    if compile:
        out["compile"] = main["compile"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="shared-0 only, fewer repeats")
    parser.add_argument("--compile", action="store_true", help="also time torch.compile")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return
    print(json.dumps(run(quick=args.quick, compile=args.compile), indent=2))


if __name__ == "__main__":
    main()
