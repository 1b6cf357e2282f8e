"""A preset's run trained on a machine without MLflow or Open3D (a lent GPU), finished here.

``cloudpose run`` needs MLflow (the run's record) and the preset's rendered frames (Open3D), and a
GPU machine may have neither. On-line training needs neither: its segments are synthesized by
compiled kernels, and only validation reads rendered frames. So the run is split at its last
checkpoint, where a run resumes anyway (:mod:`cloudpose.train.loop`):

1. ``export`` (here): the preset's validation segments and model points in one file (~2 MB).
2. ``train`` (there): the run's own :class:`~cloudpose.train.loop.Trainer` from step 0 to the
   end (the same steps, schedule, augmentation, validation and checkpoints as ``cloudpose run``),
   with the MLflow record replaced by a JSON-lines file of each epoch's metrics. It writes
   ``last.pt`` (split into parts small enough to travel), ``epochs.jsonl`` and ``train.json``
   (device, seconds, steps). Rerun on the same folder, it resumes.
3. ``adopt`` (here): creates the run's MLflow record with the training device's params, logs
   the epochs' metrics, puts ``last.pt`` into the run folder, then runs the pipeline
   (:func:`cloudpose.suite.pipeline.train_and_evaluate`): training resumes where it stopped
   (a run cut short there trains its remaining steps here, on the same stream of segments),
   saves ``model.pt`` and the run is evaluated on the synthetic test set and the real development
   frames, with and without ICP, as every run is.

Usage::

    python -m benchmarks.gpu_run export --preset gpu --out .gpu/val.npz
    python -m benchmarks.gpu_run train --preset gpu --seed 1 --val .gpu/val.npz --out DIR
    python -m benchmarks.gpu_run adopt --preset gpu --seed 1 --from DIR
    python -m benchmarks.gpu_run profile --preset gpu --val .gpu/val.npz   # what bounds it there

``--set KEY=VALUE`` (train and adopt alike) overrides the preset as ``cloudpose run --set`` does.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import sys
import time
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # run as a script: make `cloudpose` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

PART_BYTES = 15 * 2**20
"""``last.pt`` travels in parts of at most this many bytes (a lent machine returns files of
at most 16 MiB)."""


def export(
    preset: str, out: Path, overrides: list[str] | None = None, variant: str = "shared-0"
) -> None:
    """Write ``preset``'s validation segments (every rendered training frame's, as an on-line
    run validates on), its class names and model points to ``out``."""
    from cloudpose.data.batches import Batchable
    from cloudpose.data.dataset import prepare_data
    from cloudpose.registry import parse_overrides, resolve

    cfg = resolve(variant, preset, 1, parse_overrides(overrides))
    if cfg.data.train_source != "online":
        raise SystemExit(
            f"preset {preset}: data.train_source must be 'online' (training on "
            "frames needs them all on the training machine)"
        )
    data = prepare_data(cfg.data, Path.cwd())
    val = Batchable.from_segments(data.train, cfg.train.n_points)
    models = data.dataset.models()
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        out,
        points=val.points.numpy(),
        cls_id=val.cls_id.numpy(),
        R=val.R.numpy(),
        t=val.t.numpy(),
        classes=np.asarray(list(data.dataset.classes)),
        model_ids=np.asarray(sorted(models)),
        **{f"model_{c}": models[c].astype(np.float32) for c in models},
        data_key=np.asarray(str(data.data_key)),
    )
    print(f"{out}: {len(val)} validation segments of data {data.data_key}, {len(models)} models")


def _setup(cfg, val_file: Path):
    """``(device, TrainingSets, the val file)`` of an on-line run from the exported file
    (:func:`cloudpose.train.loop.online_training_sets`, no chunk store)."""
    from cloudpose.data.batches import Batchable
    from cloudpose.train import loop
    from cloudpose.train.distributed import SINGLE

    v = np.load(val_file)
    class_names = [str(c) for c in v["classes"]]
    models = {int(c): v[f"model_{int(c)}"].astype(np.float64) for c in v["model_ids"]}
    val = Batchable(*(torch.from_numpy(v[k]) for k in ("points", "cls_id", "R", "t")))
    device = loop._training_device(cfg, SINGLE)
    return device, loop.online_training_sets(cfg, class_names, val, models, None, device), v


def profile(preset: str, val_file: Path, seconds: float, variant: str = "shared-0") -> dict:
    """What bounds an on-line run here: the run's training step alone (one batch, on the
    device, synchronised), the synthesis of ``data.online_workers`` processes alone, and the
    two together as training sees them (the on-line stream's batches), each for ``seconds``."""
    from cloudpose.data.batches import join_forms
    from cloudpose.registry import resolve
    from cloudpose.train import loop
    from cloudpose.train.distributed import SINGLE
    from cloudpose.train.step import Batch

    cfg = resolve(variant, preset, 1)
    device, sets, _ = _setup(cfg, val_file)
    model, opt = loop._network(cfg, device)
    trainer = loop.Trainer(cfg, model, opt, device, SINGLE, sets, loop.TrainingRun(Path("."), {}))
    bs = cfg.train.batch_size
    fit = sets.fit
    points = fit.points  # a step's batch holds a segment's forms side by side, as the stream's
    if fit.trans_points is not None:
        points = join_forms(fit.points, fit.trans_points)
    batch = Batch(*(x[:bs].to(device) for x in (points, fit.cls_id, fit.R, fit.t)))

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize()

    def rate(fn, warm: int = 20) -> float:
        for _ in range(warm):
            fn()
        sync()
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            fn()
            n += 1
        sync()
        return n / (time.perf_counter() - t0)

    out: dict[str, Any] = {"device": str(device), "threads": torch.get_num_threads()}
    out["train_steps_per_s"] = rate(lambda: trainer._step(batch, loop.Position()))
    stream = loop.OnlineStream(
        sets.online,
        1,
        bs,
        cfg.data.online_reuse,
        10**6,
        start=10**5,
        workers=cfg.data.online_workers,
    )
    out["stream_threads"] = torch.get_num_threads()
    out["supply_steps_per_s"] = rate(lambda: stream.next(), warm=200)
    out["both_steps_per_s"] = rate(
        lambda: trainer._step(Batch(*(x.to(device) for x in stream.next())), loop.Position()),
        warm=50,
    )
    stream.close()
    out |= {
        "batch_size": bs,
        "workers": cfg.data.online_workers,
        "seconds": seconds,
        "cpu_cores": len(os.sched_getaffinity(0)),
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }
    print(json.dumps(out), flush=True)
    return out


def train(
    preset: str,
    seed: int,
    val_file: Path,
    out: Path,
    deadline_s: float,
    overrides: list[str] | None = None,
    max_steps: int | None = None,
    variant: str = "shared-0",
) -> int:
    """Train ``variant`` x ``preset`` x ``seed`` into ``out`` (resuming from its ``last.pt``);
    stop at ``deadline_s`` seconds (the last checkpoint kept) or after ``max_steps`` steps
    (checkpointed there). Returns 0 when the run reached its last step, else 3."""
    from cloudpose.registry import parse_overrides, resolve
    from cloudpose.train import loop
    from cloudpose.train.distributed import SINGLE

    t0 = time.monotonic()
    cfg = resolve(variant, preset, seed, parse_overrides(overrides))
    device, sets, v = _setup(cfg, val_file)
    model, opt = loop._network(cfg, device)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "epochs.jsonl"

    class Record(loop.TrainingRun):
        def log_epoch(self, epoch: int, metrics: dict[str, float]) -> None:
            row = {"epoch": epoch, "elapsed_s": round(time.monotonic() - t0, 1), **metrics}
            with log.open("a") as f:
                f.write(json.dumps(row) + "\n")
            print(json.dumps({k: row[k] for k in row if not k.startswith("fit/")}), flush=True)

    run = Record(out, {}, run_id="local")  # no MLflow client: log_epoch writes the file
    position = loop._resume(run, model, opt, cfg, SINGLE, device)
    trainer = loop.Trainer(cfg, model, opt, device, SINGLE, sets, run)
    print(
        f"{cfg.variant} {cfg.preset} seed {seed} on {device}: from epoch {position.epoch + 1}, "
        f"step {position.batch}; {trainer.total_steps} steps, setup {time.monotonic() - t0:.0f} s",
        flush=True,
    )

    def stop(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGALRM, stop)
    signal.alarm(max(1, int(deadline_s - (time.monotonic() - t0))))
    t_train, finished = time.monotonic(), False
    try:
        trainer.run(position, progress=False, checkpoint_every_s=60.0, max_steps=max_steps)
        finished = True
    except loop.TrainingInterrupted:
        print(f"stopped after {max_steps} steps; last.pt holds them", flush=True)
    except KeyboardInterrupt:
        print("deadline: stopped; last.pt holds the last checkpoint", flush=True)
    finally:
        signal.alarm(0)
    seconds = time.monotonic() - t_train
    state = torch.load(run.last, map_location="cpu", weights_only=False)
    steps_done = state["epoch"] * trainer.n_batches + state["batch"]
    info: dict[str, Any] = {
        "variant": variant,
        "preset": preset,
        "seed": seed,
        "config": cfg.fingerprint(),
        "device": str(device),
        "finished": finished,
        "steps": steps_done,
        "total_steps": trainer.total_steps,
        "train_s": round(seconds, 1),
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "cpu_cores": len(os.sched_getaffinity(0)),
        "torch": torch.__version__,
        "platform": platform.platform(),
        "data_key": str(v["data_key"]),
    }
    (out / "train.json").write_text(json.dumps(info, indent=1) + "\n")
    split(run.last)
    print(json.dumps(info), flush=True)
    return 0 if finished else 3


def split(path: Path) -> list[Path]:
    """``path`` as ``path.part0``, ``path.part1``, ... of at most :data:`PART_BYTES` each."""
    data = path.read_bytes()
    parts = []
    for i in range(0, len(data), PART_BYTES):
        part = path.with_name(f"{path.name}.part{i // PART_BYTES}")
        part.write_bytes(data[i : i + PART_BYTES])
        parts.append(part)
    return parts


def join(folder: Path, name: str = "last.pt") -> bytes:
    """The bytes of ``name`` from its parts in ``folder``."""
    parts = sorted(folder.glob(f"{name}.part*"), key=lambda p: int(p.suffix[5:]))
    if not parts:
        raise SystemExit(f"{folder}: no {name}.part* files")
    return b"".join(p.read_bytes() for p in parts)


def adopt(
    preset: str, seed: int, src: Path, overrides: list[str] | None = None, variant: str = "shared-0"
) -> None:
    """Make the run trained elsewhere (``src``: what ``train`` wrote) a run of this project:
    its MLflow record, its epochs' metrics, its checkpoint; then finish and evaluate it."""
    from cloudpose.data.dataset import prepare_data
    from cloudpose.files import atomic_write
    from cloudpose.registry import groups_of, parse_overrides, resolve
    from cloudpose.store import runs, tracking
    from cloudpose.suite.pipeline import train_and_evaluate
    from cloudpose.train import loop

    info = json.loads((src / "train.json").read_text())
    cfg = resolve(variant, preset, seed, parse_overrides(overrides))
    if info["config"] != cfg.fingerprint():
        raise SystemExit(
            f"{src}: trained config {info['config']}; this preset resolves to {cfg.fingerprint()}"
        )
    project = Path.cwd()
    data = prepare_data(cfg.data, project)
    if str(data.data_key) != info["data_key"]:
        raise SystemExit(f"{src}: validated on data {info['data_key']}, here {data.data_key}")
    folder = runs.run_dir(cfg, data.data_key, project)
    if runs.read_info(folder).get("run_id") is None:
        sets = loop._training_sets(cfg, data, project, torch.device("cpu"))
        model, _ = loop._network(cfg, torch.device("cpu"))
        here = "" if info["finished"] else ", then cpu"
        params = loop._run_params(cfg, data.data_key, model, sets, info["device"] + here)
        params["train.machine"] = f"{info['gpu'] or info['device']}, {info['cpu_cores']} cores"
        params["train.machine_steps"] = info["steps"]
        client = tracking.setup(project)
        group = (groups_of(cfg.variant) or ["misc"])[0]
        rec = runs.open_training_run(
            client, cfg, data.data_key, folder, group=group, params=params, project_dir=project
        )
        epochs = src / "epochs.jsonl"  # none when no epoch ended there
        for line in epochs.read_text().splitlines() if epochs.exists() else []:
            row = json.loads(line)
            metrics = {k: float(x) for k, x in row.items() if k not in ("epoch", "elapsed_s")}
            client.log_batch(rec["run_id"], metrics=tracking.metric_batch(metrics, row["epoch"]))
        client.log_metric(rec["run_id"], "time/train_machine_s", info["train_s"])
        blob = join(src)
        atomic_write(folder / "last.pt", lambda tmp: tmp.write_bytes(blob))
        print(
            f"{folder}: MLflow run {rec['run_id']}, steps 1-{info['steps']} of "
            f"{info['total_steps']} on {info['gpu'] or info['device']}"
            + ("" if info["finished"] else "; the rest train here")
        )
    out = train_and_evaluate(cfg, project_dir=project, data=data)
    print(f"evaluated: {out.train.run_id}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export")
    e.add_argument("--preset", default="gpu")
    e.add_argument("--out", type=Path, required=True)
    e.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    t = sub.add_parser("train")
    t.add_argument("--preset", default="gpu")
    t.add_argument("--seed", type=int, default=1)
    t.add_argument("--val", type=Path, required=True)
    t.add_argument("--out", type=Path, required=True)
    t.add_argument("--deadline-s", type=float, default=1e9)
    t.add_argument("--max-steps", type=int, default=None)
    t.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p = sub.add_parser("profile")
    p.add_argument("--preset", default="gpu")
    p.add_argument("--val", type=Path, required=True)
    p.add_argument("--seconds", type=float, default=15.0)
    a = sub.add_parser("adopt")
    a.add_argument("--preset", default="gpu")
    a.add_argument("--seed", type=int, default=1)
    a.add_argument("--from", dest="src", type=Path, required=True)
    a.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    if args.cmd == "export":
        export(args.preset, args.out, args.set)
        return 0
    if args.cmd == "train":
        return train(
            args.preset, args.seed, args.val, args.out, args.deadline_s, args.set, args.max_steps
        )
    if args.cmd == "profile":
        profile(args.preset, args.val, args.seconds)
        return 0
    adopt(args.preset, args.seed, args.src, args.set)
    return 0


if __name__ == "__main__":
    sys.exit(main())
