"""A run whose chunk store is full, on both cores (``stored_in_process_speedup``).

An on-line run trains on ``train.threads - data.online_workers`` threads while its synthesis
workers run (:class:`cloudpose.data.synth.online.OnlineStream`): the presets' one worker keeps a
core for synthesis, and training has one thread on a 2-core machine. Once the seed's chunk store
is full the worker only reads files, so its core idles. ``data.online_workers = 0`` reads the
chunks in the training process, which then trains on every thread (the ``cpu-online-4x-2t``
preset). The thread count is part of a run's numbers, so such a run is another run, with seeds
of its own.

Measured in one run, on a chunk store filled first (not timed), at the ``cpu-online-4x``
preset's settings (batch, n, reuse and synthesis version read from it): steps/s of the on-line
loop (``OnlineStream.next``, then a shared-0 fused training step on the step's own tensors: the
same work as on the streamed ones)

- one loop alone, one synthesis worker (the preset) and none (chunks read in process),
  alternately, each the median of repeats;
- two loops side by side (two processes started together, as a sweep runs two runs), one
  worker each and none each: steps/s of the two together.

The figure is the in-process loop's steps/s alone over the one-worker loop's: what a single run
saves. The pairs say what a sweep of several runs should do: two one-worker runs side by side
against two in-process runs side by side (each then two threads on a shared core's share).

Usage: ``python -m benchmarks.bench_stored [--quick]``
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import quick_main

PRESET = "cpu-online-4x"
ROOT = Path(__file__).resolve().parents[1]


def _setup() -> tuple:
    """``(settings, batch, reuse, train threads)`` of shared-0 at :data:`PRESET`."""
    from cloudpose.conventions import packaged_classes
    from cloudpose.data.synth.chunks import OnlineSettings
    from cloudpose.registry import resolve

    cfg = resolve("shared-0", PRESET)
    settings = OnlineSettings.from_config(cfg, packaged_classes())
    return settings, cfg.train.batch_size, cfg.data.online_reuse, cfg.train.threads


def _chunks(steps: int, reuse: int) -> int:
    from cloudpose.data.synth.online import REUSE_SPACING

    return steps + (reuse - 1) * REUSE_SPACING


def loop_rate(store: str, steps: int, workers: int, warm: int = 4) -> float:
    """Steps/s of ``steps`` on-line steps read from the full store ``store`` (seed 0), each
    followed by a training step of shared-0 (on its own tensors), with ``workers``
    synthesis processes; training gets the threads the stream leaves it."""
    import torch

    from benchmarks.bench_train import make_step
    from cloudpose.data.synth.online import OnlineStream

    settings, batch, reuse, threads = _setup()
    torch.set_num_threads(threads)
    step = make_step("shared-0", "fused", batch, settings.n_points)
    stream = OnlineStream(settings, 0, batch, reuse, warm + steps, workers=workers, store=store)
    try:
        for _ in range(warm):
            stream.next()
            step()
        t0 = time.perf_counter()
        for _ in range(steps):
            stream.next()
            step()
        return steps / (time.perf_counter() - t0)
    finally:
        stream.close()


def _child(store: str, steps: int, workers: int) -> subprocess.Popen:
    code = (
        "import sys, json; sys.path.insert(0, sys.argv[1]); "
        "from benchmarks.bench_stored import loop_rate; "
        "print(json.dumps(loop_rate(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]))))"
    )
    return subprocess.Popen(
        [sys.executable, "-c", code, str(ROOT), store, str(steps), str(workers)],
        stdout=subprocess.PIPE,
        text=True,
    )


def pair_rate(store: str, steps: int, workers: int) -> list[float]:
    """Steps/s of each of two loops started together (:func:`loop_rate` in two processes)."""
    procs = [_child(store, steps, workers) for _ in range(2)]
    out = []
    for p in procs:
        text, _ = p.communicate()
        if p.returncode:
            raise RuntimeError(f"a side-by-side loop failed (exit {p.returncode})")
        out.append(float(json.loads(text.strip().splitlines()[-1])))
    return out


def run(quick: bool = False) -> dict:
    """The figure ``stored_in_process_speedup`` and its parts (see the module doc)."""
    from cloudpose.data.synth.online import store_chunks

    settings, batch, reuse, threads = _setup()
    steps = 6 if quick else 80
    repeats = 1 if quick else 3
    load_start = os.getloadavg()
    alone: dict[int, list[float]] = {1: [], 0: []}
    with tempfile.TemporaryDirectory() as store:
        t0 = time.perf_counter()
        store_chunks(settings, 0, batch // reuse, _chunks(4 + steps, reuse), store, progress=False)
        fill_s = time.perf_counter() - t0
        for _ in range(repeats):
            for workers in alone:
                alone[workers].append(loop_rate(store, steps, workers))
        pairs = {w: pair_rate(store, steps, w) for w in (1, 0)}
    load_end = os.getloadavg()
    one, none = statistics.median(alone[1]), statistics.median(alone[0])
    pair_one, pair_none = sum(pairs[1]), sum(pairs[0])
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    load = (
        f"load average {', '.join(f'{x:.2f}' for x in load_start)} at the start and "
        f"{', '.join(f'{x:.2f}' for x in load_end)} at the end on {cores} cores"
    )
    note = (
        f"one run alone: {none:.2f} steps/s reading the store in process ({threads} training "
        f"threads) against {one:.2f} with one synthesis worker ({max(1, threads - 1)} training "
        f"thread): {none / one:.2f}x; two runs side by side: {pair_one:.2f} steps/s together "
        f"with one worker each, {pair_none:.2f} reading in process, i.e. {pair_one / one:.2f}x "
        f"and {pair_none / none:.2f}x one such run alone. A sweep keeps two one-worker runs side "
        f"by side where {pair_one:.2f} > {none:.2f}; {load}"
    )
    return {
        "stored_in_process_speedup": {
            "value": none / one,
            "unit": "x",
            "what": f"steps/s of one {PRESET} on-line loop (shared-0, batch {batch}, reuse "
            f"{reuse}, chunks read from a full store) with data.online_workers = 0 over the "
            "same loop with the preset's one synthesis worker, alone on the machine",
            "reference": {"name": "the preset's loop (one worker), steps/s", "value": one},
            "ratio": none / one,
            "target": "> 1: a run alone on a full store trains faster reading it in process",
            "met": bool(none > one),
            "note": note,
            "detail": {
                "steps": steps,
                "alone_steps_per_s": {"workers_1": alone[1], "workers_0": alone[0]},
                "pair_steps_per_s": {"workers_1": pairs[1], "workers_0": pairs[0]},
                "pair_total_steps_per_s": {"workers_1": pair_one, "workers_0": pair_none},
                "train_threads": threads,
                "store_fill_s": fill_s,
            },
        }
    }


if __name__ == "__main__":
    quick_main(run, __doc__)
