"""The network on a CUDA device beside the same machine's CPU (run where torch sees a GPU).

Both parts are measured in one process on one machine, so their ratios hold whatever the card:

- training steps (forward, pose loss, backward, Adam: :func:`benchmarks.bench_train.make_step`)
  of shared-0 at batch 32 (the default preset's) and 128, n = 256, plain and fused; on the GPU
  in float32 with full-precision products (torch's default, which training keeps) and with
  TF32 products (``torch.set_float32_matmul_precision("high")``); on the CPU at the training
  default of 2 threads (``train.threads``) and at every core;
- evaluation of a trained checkpoint on a prepared test set: the network's poses computed on
  the GPU and on the CPU (2 threads), ms per object (one batched pass over every valid
  segment), the largest difference between the two devices' poses, and the share of rotations
  within 10 degrees modulo symmetry from each (misses count as failures; the run's own
  ``loss.symmetry_table``). ICP and the ADS metrics run on the CPU whatever the device, so they
  are not here.

The evaluation reads a segments file that ``--export`` writes from a project's test-set cache
(``data/<dataset>/cache/<dataset>-test-*.npz``): the first 256 FPS points of every segment (what
the network sees), class ids, ground-truth rotations, validity and the class names, about a
quarter of the cache, so it travels to a GPU machine with the checkpoint.

Usage::

    python -m benchmarks.bench_cuda --export CACHE.npz --out segments.npz     # here
    python -m benchmarks.bench_cuda --checkpoint model.pt --segments segments.npz [--quick]

prints JSON (``--json FILE`` also writes it); ``--render FILE`` prints a saved one as the
markdown section of ``reports/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

from benchmarks.bench_train import N_POINTS, make_step, measure_interleaved
from benchmarks.common import describe_machine, summarize, time_calls
from cloudpose.runtime import tune_glibc_malloc

CPU_THREADS = 2
"""The CPU baseline's threads: ``train.threads``' default."""


def export_segments(cache: Path, out: Path, classes: list[str], n: int = N_POINTS) -> int:
    """Write the evaluation's segments file from a test-set cache; returns its segment count."""
    d = np.load(cache)
    np.savez_compressed(
        out,
        points=np.ascontiguousarray(d["points"][:, :n], np.float32),
        cls_id=d["cls_id"],
        R=d["R"],
        valid=d["valid"],
        classes=np.asarray(classes),
        source=np.asarray(str(cache.name)),
    )
    return len(d["cls_id"])


class _Segments(SimpleNamespace):
    """What :func:`cloudpose.infer.estimate_poses` reads of a test set."""

    def __len__(self) -> int:
        return len(self.cls_id)


def training_steps(quick: bool) -> dict[str, Any]:
    """ms per step and segments per second of shared-0's training step, GPU beside CPU."""
    repeats, warmup = (10, 3) if quick else (40, 10)
    out: dict[str, Any] = {}
    for B in (32, 128):
        cases = {}
        for impl in ("plain", "fused"):
            cases[f"cuda_{impl}"] = make_step("shared-0", impl, B, N_POINTS, device="cuda")
        gpu = {}
        for precision in ("highest", "high"):
            torch.set_float32_matmul_precision(precision)
            for name, r in measure_interleaved(cases, repeats, warmup, B).items():
                gpu[f"{name}_{'fp32' if precision == 'highest' else 'tf32'}"] = r
        torch.set_float32_matmul_precision("highest")
        cpu = {}
        for threads in (CPU_THREADS, torch.get_num_threads()):
            before = torch.get_num_threads()
            torch.set_num_threads(threads)
            step = make_step("shared-0", "plain", B, N_POINTS)
            cpu[f"cpu_plain_{threads}threads"] = measure_interleaved(
                {"cpu": step}, max(3, repeats // 4), 2, B
            )["cpu"]
            torch.set_num_threads(before)
        figures = gpu | cpu
        for r in figures.values():
            r.pop("step_ms_all", None)
        base = figures[f"cpu_plain_{CPU_THREADS}threads"]["samples_per_s"]
        out[f"batch{B}"] = {
            name: r | {"x_cpu_2threads": round(r["samples_per_s"] / base, 1)}
            for name, r in figures.items()
        }
    return out


def evaluation(
    checkpoint: Path, segments: Path, quick: bool, device: str = "cuda"
) -> dict[str, Any]:
    """The checkpoint's poses on ``device`` and on the CPU over the segments file's test set."""
    from cloudpose.geometry.rigid import rotation_error_deg
    from cloudpose.geometry.symmetry import rotation_errors_modulo_symmetry
    from cloudpose.infer import estimate_poses, load_checkpoint

    d = np.load(segments)
    segs = _Segments(points=d["points"], cls_id=d["cls_id"], valid=d["valid"])
    n_valid = int(segs.valid.sum())
    repeats = 3 if quick else 5
    out: dict[str, Any] = {
        "segments": len(segs.cls_id),
        "valid": n_valid,
        "source": str(d["source"]),
    }
    poses = {}
    before = torch.get_num_threads()
    torch.set_num_threads(CPU_THREADS)
    try:
        for name, where in (("device", device), ("cpu", "cpu")):
            model, cfg = load_checkpoint(checkpoint, device=where)
            n = cfg.train.n_points

            def run(model=model, n=n, where=where):
                return estimate_poses(model, segs, n, device=where)

            times = time_calls(run, repeats, warmup=1)
            est = run()
            poses[name] = est
            miss = ~np.isfinite(est.t).all(axis=1)
            err = rotation_errors_modulo_symmetry(
                segs.cls_id, d["R"], est.R, list(d["classes"]), miss, cfg.loss.symmetry_table
            )
            out[name] = {
                "ms_per_object": 1e3 * summarize(times)["median_s"] / n_valid,
                "pass_s": summarize(times),
                "rot_sym_lt_10deg_pct": 100.0 * float(np.mean(err < 10.0)),
            }
    finally:
        torch.set_num_threads(before)
    ok = np.isfinite(poses["cpu"].t).all(axis=1)
    out["max_rotation_difference_deg"] = float(
        rotation_error_deg(poses["cpu"].R[ok], poses["device"].R[ok]).max()
    )
    out["max_translation_difference_mm"] = float(
        1e3 * np.abs(poses["cpu"].t[ok] - poses["device"].t[ok]).max()
    )
    out["device_x_cpu"] = round(out["cpu"]["ms_per_object"] / out["device"]["ms_per_object"], 1)
    return out


def markdown(figures: dict[str, Any], command: str) -> str:
    """The figures as the section of ``reports/benchmarks.md`` that holds them."""
    m = figures["machine"]
    cpu = m["cpu"]
    lines = [
        f"- command: `{command}`; machine: {m['cuda']}, {cpu['model']} with {cpu['cores']} cores"
        f" ({m['platform']}); torch {m['torch']}, allocator {m['allocator']}",
        "",
        "| training step, shared-0, n = 256 | batch | ms / step | segments / s | x CPU, 2 threads |",
        "|---|---:|---:|---:|---:|",
    ]
    names = {
        "cuda_plain_fp32": "GPU, float32 products (what training uses)",
        "cuda_plain_tf32": "GPU, TF32 products",
        "cuda_fused_fp32": "GPU, fused network (the CPU kernel), float32",
        "cuda_fused_tf32": "GPU, fused network, TF32",
    }
    for batch, cases in figures["training"].items():
        for name, r in cases.items():
            label = names.get(
                name, name.replace("cpu_plain_", "CPU, ").replace("threads", " threads")
            )
            lines.append(
                f"| {label} | {batch.removeprefix('batch')} | {r['step_ms_median']:.1f} |"
                f" {r['samples_per_s']:,.0f} | {r['x_cpu_2threads']} |"
            )
    e = figures.get("evaluation")
    if e is not None:
        lines += [
            "",
            f"Evaluation of a trained checkpoint on {e['valid']:,} test segments"
            f" (`{e['source']}`), one batched pass of the network:",
            "",
            "| device | ms / object | rot. < 10 deg mod sym |",
            "|---|---:|---:|",
            f"| GPU | {e['device']['ms_per_object']:.3f} | {e['device']['rot_sym_lt_10deg_pct']:.2f}% |",
            f"| CPU, {CPU_THREADS} threads | {e['cpu']['ms_per_object']:.3f} |"
            f" {e['cpu']['rot_sym_lt_10deg_pct']:.2f}% |",
            "",
            f"Largest difference between the two devices' poses: {e['max_rotation_difference_deg']:.4f}"
            f" deg, {e['max_translation_difference_mm']:.4f} mm.",
        ]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--export", type=Path, help="a test-set cache to write a segments file from")
    ap.add_argument("--out", type=Path, help="the segments file --export writes")
    ap.add_argument("--checkpoint", type=Path, help="a run's model.pt")
    ap.add_argument("--segments", type=Path, help="a segments file (--export)")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--render", type=Path, help="print a saved --json file as markdown")
    args = ap.parse_args()
    if args.render is not None:
        figures = json.loads(args.render.read_text())
        print(markdown(figures, figures.get("command", "python -m benchmarks.bench_cuda")), end="")
        return
    if args.export is not None:
        if args.out is None:
            ap.error("--export needs --out")
        from cloudpose.conventions import packaged_classes

        count = export_segments(args.export, args.out, list(packaged_classes()))
        print(f"{args.out}: {count} segments")
        return
    if not torch.cuda.is_available():
        ap.error("no CUDA device: this benchmark compares a GPU with the CPU")
    tune_glibc_malloc()  # as the command line does where no tcmalloc / jemalloc is installed
    figures: dict[str, Any] = {
        "command": "python -m benchmarks.bench_cuda " + " ".join(sys.argv[1:]),
        "machine": describe_machine(),
        "training": training_steps(args.quick),
    }
    if args.checkpoint is not None and args.segments is not None:
        figures["evaluation"] = evaluation(args.checkpoint, args.segments, args.quick)
    text = json.dumps(figures, indent=2)
    print(text)
    if args.json is not None:
        args.json.write_text(text + "\n")


if __name__ == "__main__":
    main()
