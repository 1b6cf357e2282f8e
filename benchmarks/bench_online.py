"""On-line synthesis against the rate training consumes segments (``online_supply_ratio``).

Measured in one run, on the same cores, at the default preset's settings
(:data:`cloudpose.config.DEFAULT_PRESET`; generator version, batch size, n and
``online_reuse`` read from the preset):

- training: segments/s of shared-0 fused training steps at batch 32 on ready tensors
  (all threads);
- on-line synthesis, one process: segments/s of ``OnlineSynth.batch`` (scene, window ray cast,
  the version's sensor, segment path);
- the frame path it replaces: segments/s of ``generate_frame`` + ``extract_segments`` (the
  rendered-frame route to the same segments, one process);
- the on-line training loop end to end: steps/s of ``OnlineStream`` with one synthesis worker
  feeding the same training step, i.e. what a run of the preset gets here, and the same loop
  reading every chunk from the chunk store (:mod:`cloudpose.data.synth.store`), i.e. what every
  later run of the seed gets;
- where a scene's time goes: milliseconds per stage of ``OnlineSynth`` (scene sampling, the
  objects' windows, the ray cast, the background ring, the sensor, the segment path), one
  thread.

The figure is the supply ratio ``synthesis x reuse / consumption``: >= 2 means synthesis never
stalls training. ``reuse`` = 1 is reported beside it (every segment used once).

Usage: ``python -m benchmarks.bench_online [--quick]``
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_train import make_step
from benchmarks.common import quick_main
from cloudpose.config import DEFAULT_PRESET, resolve

_ONLINE = resolve("shared-0", DEFAULT_PRESET)
BATCH, N_POINTS = _ONLINE.train.batch_size, _ONLINE.train.n_points
REUSE, VERSION = _ONLINE.data.online_reuse, _ONLINE.data.synth_version


def _synthesis_rate(batches: int) -> dict:
    from cloudpose.data.synth.online import OnlineSynth

    synth = OnlineSynth(VERSION, n_points=N_POINTS)
    synth.batch(0, 10_000, BATCH)  # warm-up: surfaces, kernels
    t0, scenes = time.perf_counter(), 0
    for step in range(batches):
        scenes += synth.batch(0, step, BATCH).scenes
    dt = time.perf_counter() - t0
    return {"segments_per_s": batches * BATCH / dt, "ms_per_scene": 1000 * dt / scenes}


def _scene_parts(scenes: int) -> dict:
    """Milliseconds a scene spends in each stage of ``OnlineSynth`` (one process, warm)."""
    import warnings

    from cloudpose.data.segments import SegmentWarning, extract_segments
    from cloudpose.data.synth.online import OnlineSynth
    from cloudpose.data.synth.sensor import (
        add_sensor_noise_v2_objects,
        background_depth_at,
        object_ring,
    )
    from cloudpose.data.ycb import Frame

    synth = OnlineSynth(VERSION, n_points=N_POINTS, nthreads=1)
    synth.batch(0, 10_001, BATCH)  # warm-up: surfaces, kernels, the classes' BVHs
    parts = dict.fromkeys(("scene", "windows", "ray_cast", "background", "sensor", "segments"), 0.0)
    for k in range(scenes):
        rng = np.random.default_rng([0, 99, k])
        t = time.perf_counter()
        scene = synth.sample_scene(rng)
        parts["scene"] += time.perf_counter() - t
        t = time.perf_counter()
        found = synth.windows(scene)
        parts["windows"] += time.perf_counter() - t
        if found is None:
            continue
        wins, (v0, v1, u0, u1) = found
        t = time.perf_counter()
        r = synth._gen.renderer.render_instanced(
            synth.K, synth.shape, scene.cls_ids, scene.poses(), wins, (v0, v1, u0, u1), 1
        )
        parts["ray_cast"] += time.perf_counter() - t
        Kw = synth.K.copy()
        Kw[0, 2] -= u0
        Kw[1, 2] -= v0
        t = time.perf_counter()
        clean = np.where(r.label > 0, r.depth.astype(np.float64), 0.0)
        rv, ru = np.nonzero(object_ring(r.label))
        clean[rv, ru] = background_depth_at(Kw, rv, ru, scene.world_to_camera, scene.background)
        parts["background"] += time.perf_counter() - t
        t = time.perf_counter()
        depth = add_sensor_noise_v2_objects(clean, r.label, Kw, rng)
        parts["sensor"] += time.perf_counter() - t
        t = time.perf_counter()
        frame = Frame("x", depth.astype(np.float32), r.label, Kw, scene.cls_ids, None, None)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SegmentWarning)
            extract_segments(frame, n_fps=N_POINTS, rng=rng, with_gt=False)
        parts["segments"] += time.perf_counter() - t
    return {f"{k}_ms": 1000 * v / scenes for k, v in parts.items()}


def _frame_rate(frames: int) -> dict:
    from cloudpose.conventions import YCB_INTRINSICS
    from cloudpose.data.segments import extract_segments
    from cloudpose.data.synth.frames import generate_frame
    from cloudpose.data.ycb import Frame

    generate_frame("train", 10_000, version=VERSION)  # warm-up
    t0, n = time.perf_counter(), 0
    for i in range(frames):
        f = generate_frame("train", i, version=VERSION)
        fr = Frame(
            "x", f.depth.astype(np.float32), f.label, YCB_INTRINSICS, f.cls_ids, f.poses, None
        )
        n += len(extract_segments(fr, alone_pixels=f.alone_pixels, n_fps=N_POINTS))
    return {"segments_per_s": n / (time.perf_counter() - t0)}


def _train_rate(steps: int) -> dict:
    step = make_step("shared-0", "fused", BATCH, N_POINTS)
    for _ in range(3):
        step()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return {"segments_per_s": steps * BATCH / (time.perf_counter() - t0)}


def _stream_rate(steps: int) -> dict:
    """Steps/s of the on-line loop: one worker synthesizes, this process trains; then the
    same steps again with every chunk read from a chunk store the first pass filled (what
    the runs of a seed after its first get)."""
    import tempfile

    from cloudpose.data.synth.online import OnlineStream

    step = make_step("shared-0", "fused", BATCH, N_POINTS)
    synth_kwargs = {"version": VERSION, "n_points": N_POINTS}
    rates = []
    with tempfile.TemporaryDirectory() as store:
        for _ in range(2):
            stream = OnlineStream(synth_kwargs, 0, BATCH, REUSE, steps + 8, store=store)
            for _ in range(4):
                stream.next()
            t0 = time.perf_counter()
            for _ in range(steps):
                stream.next()
                step()  # the step's own tensors: the same work as on the streamed ones
            rates.append(steps / (time.perf_counter() - t0))
            stream.close()
    return {
        "steps_per_s": rates[0],
        "segments_per_s": rates[0] * BATCH,
        "stored_steps_per_s": rates[1],
    }


def run(quick: bool = False) -> dict:
    """The figure ``online_supply_ratio`` and its parts (see the module doc)."""
    n = 2 if quick else 12
    train = _train_rate(5 if quick else 60)
    synth = _synthesis_rate(n)
    frames = _frame_rate(2 if quick else 8)
    stream = _stream_rate(4 if quick else 60)
    parts = _scene_parts(3 if quick else 40)
    threads = torch.get_num_threads()
    ratio = synth["segments_per_s"] * REUSE / train["segments_per_s"]
    return {
        "online_supply_ratio": {
            "value": ratio,
            "unit": "x the training consumption",
            "what": f"on-line synthesis (1 process) x reuse {REUSE} / shared-0 training "
            f"segments/s (batch {BATCH}, n = {N_POINTS}, {threads} threads)",
            "reference": {
                "name": "reuse 1 (every segment once)",
                "value": synth["segments_per_s"] / train["segments_per_s"],
            },
            "ratio": float(REUSE),
            "target": ">= 2 (synthesis never stalls training)",
            "met": bool(ratio >= 2.0),
            "detail": {
                "train_segments_per_s": train["segments_per_s"],
                "online_segments_per_s": synth["segments_per_s"],
                "online_ms_per_scene": synth["ms_per_scene"],
                "frame_path_segments_per_s": frames["segments_per_s"],
                "online_vs_frame_path": synth["segments_per_s"] / frames["segments_per_s"],
                "stream_steps_per_s": stream["steps_per_s"],
                "stream_vs_training_alone": stream["segments_per_s"] / train["segments_per_s"],
                "stream_from_store_steps_per_s": stream["stored_steps_per_s"],
                "stream_from_store_vs_synthesizing": stream["stored_steps_per_s"]
                / stream["steps_per_s"],
                "scene_parts_ms": parts,
            },
        }
    }


if __name__ == "__main__":
    quick_main(run, __doc__)
