"""The benchmark suite: every figure in one run -> reports/benchmarks.{md,json}.

Each figure is measured beside its reference in the same run (interleaved repeats, medians),
and reported as value, reference, ratio, target and whether it is met, with the machine
described (``benchmarks.common.describe_machine``: CPU and flags, cores, torch, allocator,
load). Figures (JSON keys):

- ``train_fraction_of_peak``, ``train_bf16_samples_per_s`` (``benchmarks.bench_train``; bf16
  where the CPU has avx512_bf16 or AMX, ``cloudpose.runtime.cpu_features``)
- ``infer_ms_per_object``, ``infer_ms_frame8`` (``benchmarks.bench_infer``)
- ``icp_ms_per_object``, ``ads_ms_per_10k`` (``benchmarks.bench_refine_metrics``)
- ``fps_ms_20k`` (``benchmarks.bench_fps``)
- ``baseline_fpfh_ms_per_object``, ``baseline_ppf_ms_per_object`` (``benchmarks.bench_baselines``)
- ``synth_frames_per_s``, ``prepare_frames_per_s`` (``benchmarks.bench_data``)
- ``online_supply_ratio``: on-line synthesis against training consumption (``benchmarks.bench_online``)
- ``online_v2_supply_ratio``: on-line synthesis version 2 (the compiled path, one process) at
  reuse 1 against training consumption, version 1 beside it (``benchmarks.bench_online``)
- ``online_v3_supply_ratio``: on-line synthesis version 3 (two worker processes) at reuse 1
  against training consumption, version 1 beside it, stage times of versions 1, 2 and 3
  (``benchmarks.bench_online``)
- ``stored_in_process_speedup``: a ``cpu-online-4x`` on-line loop on a full chunk store with
  the chunks read in the training process (every thread trains) against the preset's one
  synthesis worker, alone and two side by side (``benchmarks.bench_stored``)
- ``cpu_variant_wall_s``: wall time of one ``cpu``-preset variant, train + evaluate. Not run by
  default (it takes minutes): read from the MLflow store (start to end of the newest finished
  ``cpu`` run; training and evaluation log into the same run), else null with a note;
  ``--cpu-variant`` runs ``cloudpose run --preset cpu`` for real (into a temporary MLflow
  store) and times it.
- ``ray_executor_wall_s``: a smoke sweep on a loopback Ray cluster against the local executor
  (``benchmarks.bench_cluster``).

``--merge`` puts the figures run now into the report already in ``--out`` and leaves every
other figure as it is; a merged figure carries its own command, commit, time and CPU (JSON
``measured``). The Markdown report is one table in which each row names its machine (each
machine described once) and the date it was measured on.

The process sets itself up as the CLI does (``cloudpose.runtime``: tcmalloc re-exec, threads).

Usage: ``python -m benchmarks.run_all [--quick] [--only NAME[,NAME]] [--cpu-variant]
[--out reports] [--merge] [--render]``; ``make bench``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ROOT = Path(__file__).resolve().parents[1]
CPU_VARIANT_TARGET_S = 600.0

FIGURES = (
    "train_fraction_of_peak",
    "train_bf16_samples_per_s",
    "infer_ms_per_object",
    "infer_ms_frame8",
    "icp_ms_per_object",
    "icp_starts24_ms_per_object",
    "fps_ms_20k",
    "ads_ms_per_10k",
    "baseline_fpfh_ms_per_object",
    "baseline_ppf_ms_per_object",
    "synth_frames_per_s",
    "prepare_frames_per_s",
    "online_supply_ratio",
    "online_v2_supply_ratio",
    "online_v3_supply_ratio",
    "stored_in_process_speedup",
    "cpu_variant_wall_s",
    "ray_executor_wall_s",
)
"""Every figure's JSON key, in report order."""

GROUPS = {
    "train": ("train_fraction_of_peak", "train_bf16_samples_per_s"),
    "infer": ("infer_ms_per_object", "infer_ms_frame8"),
    "refine_metrics": ("icp_ms_per_object", "icp_starts24_ms_per_object", "ads_ms_per_10k"),
    "fps": ("fps_ms_20k",),
    "baselines": ("baseline_fpfh_ms_per_object", "baseline_ppf_ms_per_object"),
    "data": ("synth_frames_per_s", "prepare_frames_per_s"),
    "online": ("online_supply_ratio", "online_v2_supply_ratio", "online_v3_supply_ratio"),
    "stored": ("stored_in_process_speedup",),
    "cpu_variant": ("cpu_variant_wall_s",),
    "cluster": ("ray_executor_wall_s",),
}
"""Which benchmark module measures which figures."""


# ---------------------------------------------------------------------------------------------
# Groups


def _train(quick: bool, _args: argparse.Namespace) -> dict[str, Any]:
    from benchmarks import bench_train

    res = bench_train.run(quick=quick)
    tf = res["train_fraction_of_peak"]
    plain_frac = tf["plain_fraction_of_peak"]
    bf = res["train_bf16_samples_per_s"]
    return {
        "train_fraction_of_peak": {
            "value": tf["value"],
            "unit": "fraction of the fp32 GEMM rate",
            "what": tf["what"],
            "reference": {"name": "plain network (Conv1d-like Linear + BN)", "value": plain_frac},
            "ratio": tf["value"] / plain_frac if plain_frac else None,
            "target": ">= 0.80 (shared-0, fp32)",
            "met": bool(tf["value"] >= 0.80),
            "note": None
            if tf["value"] >= 0.80
            else f"not met on {res['machine'].get('cpu', {}).get('model', 'this CPU')} "
            f"({res['machine'].get('torch_cpu_capability', '?')}): {1 - tf['value']:.0%} of the "
            "step would fit in the time it spends outside the GEMM rate: BatchNorm, ReLU and "
            "their gradients on the 64- and 128-wide per-point layers, and the pooled layer's "
            "argmax and gradient scatter, are memory-bound and do not speed up with the vector "
            "width as the products do",
            "detail": {
                **{k: v for k, v in tf.items() if k not in ("value", "what")},
                "gemm_fp32": res["gemm_fp32_gflops"],
                "train_by_allocator": res["train_by_allocator"],
            },
        },
        "train_bf16_samples_per_s": {
            "value": bf.get("value"),
            "unit": "samples/s",
            "what": "shared-0, fused, bfloat16 GEMM + autocast (train.precision = 'bf16'), "
            "batch 128, n = 256; fp32 timed in the same process, interleaved",
            "reference": {
                "name": "fp32 fused samples/s, same process",
                "value": bf.get("fp32_samples_per_s_same_process"),
            },
            "ratio": bf.get("bf16_over_fp32"),
            "target": "faster than fp32 at equal accuracy, where avx512_bf16 or AMX exist "
            "(then worth setting; no preset depends on it)",
            "met": (bool(bf["faster"] and bf["equal_accuracy"]) if bf.get("value") else None),
            "note": bf.get("skipped") or bf.get("verdict"),
            "detail": bf,
        },
    }


def _infer(quick: bool, _args: argparse.Namespace) -> dict[str, Any]:
    from benchmarks import bench_infer

    return bench_infer.run(quick=quick)


def _refine_metrics(quick: bool, _args: argparse.Namespace) -> dict[str, Any]:
    from benchmarks import bench_refine_metrics

    return bench_refine_metrics.run(quick=quick)


def _fps(quick: bool, _args: argparse.Namespace) -> dict[str, Any]:
    from benchmarks import bench_fps

    return bench_fps.run(quick=quick)


def _baselines(quick: bool, _args: argparse.Namespace) -> dict[str, Any]:
    from benchmarks import bench_baselines

    return bench_baselines.run(quick=quick)


def _data(quick: bool, _args: argparse.Namespace) -> dict[str, Any]:
    from benchmarks import bench_data

    return bench_data.run(quick=quick)


def _online(quick: bool, _args: argparse.Namespace) -> dict[str, Any]:
    from benchmarks import bench_online

    return bench_online.run(quick=quick)


def _stored(quick: bool, _args: argparse.Namespace) -> dict[str, Any]:
    from benchmarks import bench_stored

    return bench_stored.run(quick=quick)


def _cpu_variant(quick: bool, args: argparse.Namespace) -> dict[str, Any]:
    if getattr(args, "cpu_variant", False):
        return {"cpu_variant_wall_s": cpu_variant_run(args.variant, args.seed)}
    return {"cpu_variant_wall_s": cpu_variant_from_store()}


def _cluster(quick: bool, _args: argparse.Namespace) -> dict[str, Any]:
    from benchmarks import bench_cluster

    return bench_cluster.run(quick=quick)


RUNNERS: dict[str, Callable[[bool, argparse.Namespace], dict[str, Any]]] = {
    "train": _train,
    "infer": _infer,
    "refine_metrics": _refine_metrics,
    "fps": _fps,
    "baselines": _baselines,
    "data": _data,
    "online": _online,
    "stored": _stored,
    "cpu_variant": _cpu_variant,
    "cluster": _cluster,
}


def _cpu_figure(value: float | None, what: str, detail: dict, note: str | None = None) -> dict:
    return {
        "value": value,
        "unit": "s",
        "what": what,
        "reference": {
            "name": "the budget of one cpu-preset variant",
            "value": CPU_VARIANT_TARGET_S,
        },
        "ratio": (value / CPU_VARIANT_TARGET_S) if value is not None else None,
        "target": f"<= {CPU_VARIANT_TARGET_S:g} s (train + evaluate)",
        "met": (bool(value <= CPU_VARIANT_TARGET_S) if value is not None else None),
        "note": note,
        "detail": detail,
    }


def cpu_variant_from_store(project_dir: Path | None = None) -> dict[str, Any]:
    """``cpu_variant_wall_s`` from the newest finished ``cpu``-preset run in the MLflow store.

    The wall time is the run's end minus its start: training and the evaluation (with and
    without ICP) log into the same run, which ends when evaluation ends. Data synthesis and
    segment preparation are not in it.
    """
    try:
        from cloudpose.store import tracking

        client = tracking.setup(project_dir)
        runs = tracking.find_runs(client, preset="cpu")
    except Exception as exc:  # an unreadable store must not stop the suite
        return _cpu_figure(
            None, "cpu preset, train + evaluate", {}, f"MLflow store unreadable: {exc}"
        )
    timed = [r for r in runs if r.info.end_time and r.info.start_time]
    if not timed:
        return _cpu_figure(
            None,
            "cpu preset, train + evaluate",
            {"store": tracking.tracking_uri(project_dir)},
            "no finished cpu-preset run in the MLflow store; run `python -m benchmarks.run_all "
            "--only cpu_variant --cpu-variant` (or the ablations) first",
        )
    newest = timed[0]
    walls = [(r.info.end_time - r.info.start_time) / 1000.0 for r in timed]
    walls_sorted = sorted(walls)
    tags = newest.data.tags
    return _cpu_figure(
        walls[0],
        f"newest finished cpu run {tags.get('variant')}/seed{tags.get('seed')}: MLflow start to "
        "end (train + evaluate with and without ICP)",
        {
            "run_id": newest.info.run_id,
            "variant": tags.get("variant"),
            "runs_in_store": len(timed),
            "median_over_runs_s": walls_sorted[len(walls_sorted) // 2],
            "max_over_runs_s": walls_sorted[-1],
            "store": tracking.tracking_uri(project_dir),
        },
        "read from the MLflow store, not measured in this run",
    )


def cpu_variant_run(variant: str = "shared-0", seed: int = 1) -> dict[str, Any]:
    """Run ``cloudpose run --preset cpu`` for real (a temporary MLflow store) and time it.

    Synthesis and preparation are done first (``cloudpose prepare``, skipped when cached) and
    not counted; the timed command trains and evaluates.
    """
    cli = [sys.executable, "-m", "cloudpose.cli"]
    env = dict(os.environ)
    with tempfile.TemporaryDirectory(prefix="cloudpose-bench-mlflow-") as tmp:
        env["MLFLOW_TRACKING_URI"] = f"sqlite:///{Path(tmp) / 'mlflow.db'}"
        # synthesis and segment caching (skipped when cached) are not part of the figure
        subprocess.run(
            [*cli, "prepare", "--preset", "cpu", "--no-progress"], cwd=ROOT, env=env, check=True
        )
        t0 = time.perf_counter()
        proc = subprocess.run(
            [
                *cli,
                "run",
                "--variant",
                variant,
                "--preset",
                "cpu",
                "--seed",
                str(seed),
                "--no-progress",
            ],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            check=False,
        )
        wall = time.perf_counter() - t0
    if proc.returncode != 0:
        return _cpu_figure(
            None,
            f"cloudpose run --variant {variant} --preset cpu",
            {"stderr": proc.stderr[-2000:]},
            f"the run failed (exit {proc.returncode})",
        )
    return _cpu_figure(
        wall,
        f"cloudpose run --variant {variant} --preset cpu --seed {seed} (train + evaluate), "
        "measured in this run",
        {"stdout_tail": proc.stdout[-1500:]},
    )


# ---------------------------------------------------------------------------------------------
# Report


def git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=False,
        ).stdout.strip()
        return out + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        return f"{v:.3g}" if abs(v) < 100 else f"{v:,.0f}"
    return str(v)


DESCRIPTIONS = "## What each figure is"
MACHINES = "## Machines"
NOT_RECORDED = "not recorded (figures merged before the report recorded each one's CPU)"
END = "Details (per size, per variant, every repeat) are in benchmarks.json."
"""The last line of the rendered part of benchmarks.md: what follows it (hand-written sections,
such as the GPU figures) is kept as it is by :func:`merge_report`."""


def _cpu_and_load(machine: dict[str, Any] | str) -> tuple[str, str | None]:
    """(the CPU a figure was measured on, the load average it saw) from a run's machine dict,
    or from the text a merged figure stores (``measured.machine``)."""
    text = machine if isinstance(machine, str) else _machine_line(machine)
    cpu, _, load = text.partition("; load average at start ")
    return cpu, load or None


def _where(report: dict[str, Any], f: dict[str, Any]) -> dict[str, Any]:
    """Where and when ``f`` was measured: its own ``measured`` record if it was merged from
    another run, else the report's run."""
    m = f.get("measured") or {
        k: report.get(k) for k in ("command", "commit", "started", "quick", "machine")
    }
    cpu, load = _cpu_and_load(m["machine"]) if m.get("machine") else (NOT_RECORDED, None)
    return {**m, "cpu": cpu, "load": load, "date": str(m.get("started") or "")[:10]}


def _machine_ids(report: dict[str, Any], keys: list[str]) -> dict[str, str]:
    """CPU description -> a short name (M1, M2, ...), in the order the table meets them."""
    ids: dict[str, str] = {}
    for k in keys:
        cpu = _where(report, report["figures"][k])["cpu"]
        ids.setdefault(cpu, f"M{len(ids) + 1}")
    return ids


def _row(key: str, f: dict[str, Any], machine: str = "-", date: str = "-") -> str:
    """A figure's table row: value, reference and ratio (both measured in the same run on the
    same machine), target, and the machine and date it was measured on."""
    ref = f.get("reference") or {}
    ref_s = f"{_fmt(ref.get('value'))} ({ref.get('name', '')})" if ref else "-"
    return (
        f"| `{key}` | {_fmt(f.get('value'))} | {f.get('unit', '')} | {ref_s} | "
        f"{_fmt(f.get('ratio'))} | {f.get('target') or '-'} | {_fmt(f.get('met'))} | "
        f"{machine} | {date} |"
    )


def _description(key: str, f: dict[str, Any], where: dict[str, Any] | None = None) -> str:
    """A figure's line under "What each figure is": what it measures, its note, and the
    command, commit and load it was measured with."""
    note = f" Note: {f['note'].rstrip('.')}." if f.get("note") else ""
    how = ""
    if where:
        load = f", load average at start {where['load']}" if where.get("load") else ""
        how = f" Measured by `{where.get('command')}`, commit `{where.get('commit')}`{load}."
    return f"- `{key}`: {f.get('what', '')}.{note}{how}"


def _machine_line(machine: dict[str, Any]) -> str:
    """The CPU a run measured on, and the load it saw: where a merged figure came from."""
    from cloudpose.runtime import describe_cpu

    cpu = machine["cpu"]
    text = describe_cpu(cpu) if "vendor" in cpu else f"{cpu['model']} ({' '.join(cpu['flags'])})"
    load = machine.get("load_average_1_5_15min")
    return text + (f"; load average at start {load}" if load else "")


def merge_report(out: Path, report: dict[str, Any]) -> dict[str, Any]:
    """Put ``report``'s figures into the report in ``out`` (its ``benchmarks.json`` and
    ``benchmarks.md``), keeping every other figure as it is.

    Each merged figure gets ``measured`` (``report``'s command, commit, start, quick flag and
    machine: CPU and load). ``benchmarks.md`` is rendered again from the merged JSON; what
    follows its rendered part (:data:`END`) is kept.

    Returns:
        The merged report (as written to ``benchmarks.json``).
    """
    old = json.loads((out / "benchmarks.json").read_text())
    measured = {k: report[k] for k in ("command", "commit", "started", "quick")}
    measured["machine"] = _machine_line(report["machine"])
    new = {k: {**f, "measured": measured} for k, f in report["figures"].items()}
    figures = {**old["figures"], **new}
    old["figures"] = {k: figures[k] for k in FIGURES if k in figures}
    old.setdefault("errors", {}).update(report["errors"])
    (out / "benchmarks.json").write_text(json.dumps(old, indent=2, default=_json_default))
    render_again(out)
    return old


def render_again(out: Path) -> None:
    """Render ``out/benchmarks.md`` from ``out/benchmarks.json`` (no measurement), keeping what
    follows its rendered part."""
    md = out / "benchmarks.md"
    text = md.read_text() if md.exists() else ""
    tail = text.partition(END)[2] if END in text else ""
    report = json.loads((out / "benchmarks.json").read_text())
    md.write_text(render_markdown(report) + tail.removeprefix("\n"))


def render_markdown(report: dict[str, Any]) -> str:
    """The human-readable report: one table where each row names the machine (described once
    under "Machines") and the date it was measured on, then what each figure is."""
    m = report["machine"]
    shown = [k for k in FIGURES if report["figures"].get(k) is not None]
    ids = _machine_ids(report, shown)
    own_cpu = _cpu_and_load(m)[0]
    lines = [
        "# Benchmarks",
        "",
        f"The last full run: `{report['command']}`, commit `{report['commit']}`, "
        f"{report['started']} (took {report.get('seconds', 0):.0f} s) on "
        f"{ids.get(own_cpu, own_cpu)}; torch {m['torch']}, {m['torch_threads']} threads, "
        f"allocator {m['allocator']}, numba {m.get('numba') or 'no'}. A figure measured in "
        "another run (`--merge`) names its own machine and date.",
        "",
        "Ratio = reference / value for times (higher is faster), value / reference for rates "
        "and fractions. A figure and its reference are measured in the same run on the same "
        "machine, interleaved where cheap; figures of different machines are never put in one "
        "ratio.",
        "",
        MACHINES,
        "",
        *[f"- {name}: {cpu}" for cpu, name in ids.items()],
        "",
        "| figure | value | unit | reference | ratio | target | met | machine | measured |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    wheres = {k: _where(report, report["figures"][k]) for k in shown}
    lines += [
        _row(k, report["figures"][k], ids[wheres[k]["cpu"]], wheres[k]["date"]) for k in shown
    ]
    lines += ["", DESCRIPTIONS, ""]
    lines += [_description(k, report["figures"][k], wheres[k]) for k in shown]
    if report.get("errors"):
        lines += ["", "## Errors", ""]
        lines += [f"- `{k}`: {v}" for k, v in report["errors"].items()]
    lines += ["", END, ""]
    return "\n".join(lines)


def run(
    names: list[str] | None = None,
    quick: bool = False,
    out_dir: Path | None = None,
    args: argparse.Namespace | None = None,
    merge: bool = False,
) -> dict[str, Any]:
    """Run the selected benchmark groups and write ``benchmarks.json`` / ``benchmarks.md``.

    Args:
        names: figure keys or group names (``GROUPS``) to run; None = all.
        quick: small sizes and few repeats (the test's smoke run).
        out_dir: where the reports go (default ``reports/`` of the repository).
        args: the parsed command line (``--cpu-variant``, ``--variant``, ``--seed``).
        merge: merge the figures into the report in ``out_dir`` (:func:`merge_report`)
            instead of writing a report of these figures alone.

    Returns:
        The report dict of this run (what is written, unless merged).
    """
    from benchmarks.common import describe_machine

    args = args or argparse.Namespace(cpu_variant=False, variant="shared-0", seed=1)
    groups = select_groups(names)
    t0 = time.perf_counter()
    machine = describe_machine()
    try:
        import numba

        machine["numba"] = numba.__version__
    except ImportError:
        machine["numba"] = None
    report: dict[str, Any] = {
        "command": " ".join([Path(sys.executable).name, "-m", "benchmarks.run_all", *sys.argv[1:]])
        if sys.argv and sys.argv[0].endswith("run_all.py")
        else f"benchmarks.run_all.run(names={names}, quick={quick})",
        "commit": git_commit(),
        "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "quick": quick,
        "machine": machine,
        "figures": {},
        "errors": {},
    }
    for g in groups:
        try:
            res = RUNNERS[g](quick, args)
        except Exception as exc:  # one failing group must not lose the others
            report["errors"][g] = f"{type(exc).__name__}: {exc}"
            for key in GROUPS[g]:
                report["figures"][key] = {"value": None, "note": f"failed: {exc}"}
            continue
        report["figures"].update(res)
    report["seconds"] = time.perf_counter() - t0
    try:
        report["load_average_at_end"] = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        report["load_average_at_end"] = None
    # figures in report order, with null entries for those not run
    report["figures"] = {k: report["figures"][k] for k in FIGURES if k in report["figures"]}
    out = Path(out_dir) if out_dir is not None else ROOT / "reports"
    out.mkdir(parents=True, exist_ok=True)
    if merge and (out / "benchmarks.json").exists():
        merge_report(out, report)
        return report
    (out / "benchmarks.json").write_text(json.dumps(report, indent=2, default=_json_default))
    (out / "benchmarks.md").write_text(render_markdown(report))
    return report


def _json_default(o: Any) -> Any:
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    return str(o)


def select_groups(names: list[str] | None) -> list[str]:
    """Benchmark groups to run for ``--only`` names (figure keys or group names)."""
    if not names:
        return list(GROUPS)
    chosen = []
    for name in names:
        if name in GROUPS:
            g = name
        else:
            g = next((g for g, keys in GROUPS.items() if name in keys), None)
            if g is None:
                valid = sorted({*GROUPS, *FIGURES})
                raise ValueError(f"--only: unknown benchmark {name!r}; valid: {', '.join(valid)}")
        if g not in chosen:
            chosen.append(g)
    return chosen


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes, few repeats (smoke)")
    ap.add_argument(
        "--only", default="", help="NAME[,NAME]: figure keys or groups " + str(list(GROUPS))
    )
    ap.add_argument(
        "--cpu-variant",
        action="store_true",
        help="run one cpu-preset variant (train + evaluate) for real instead of reading MLflow",
    )
    ap.add_argument("--variant", default="shared-0", help="variant for --cpu-variant")
    ap.add_argument("--seed", type=int, default=1, help="seed for --cpu-variant")
    ap.add_argument("--out", type=Path, default=None, help="report folder (default reports/)")
    ap.add_argument(
        "--merge",
        action="store_true",
        help="put these figures into the report in --out, keeping the others as they are",
    )
    ap.add_argument(
        "--render",
        action="store_true",
        help="measure nothing: render benchmarks.md again from benchmarks.json in --out",
    )
    args = ap.parse_args(argv)
    out = args.out or ROOT / "reports"
    if args.render:
        render_again(out)
        print((out / "benchmarks.md").read_text())
        return
    names = [n.strip() for n in args.only.split(",") if n.strip()] or None
    try:
        select_groups(names)
    except ValueError as exc:
        ap.error(str(exc))
    report = run(names, quick=args.quick, out_dir=args.out, args=args, merge=args.merge)
    print((out / "benchmarks.md").read_text())
    if report["errors"]:
        sys.exit(1)


if __name__ == "__main__":
    from cloudpose.runtime import configure_threads, reexec_with_allocator

    reexec_with_allocator()
    configure_threads()
    main()
