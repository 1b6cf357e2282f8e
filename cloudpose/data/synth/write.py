"""Writing synthetic frames into a YCB-Video-layout root: atomic, resumable, multi-process."""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import shutil
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
from tqdm import tqdm

from cloudpose.config import GENERATOR_VERSION, check_synth_version
from cloudpose.conventions import YCB_INTRINSICS, packaged_classes, resource_path
from cloudpose.data.synth.frames import (
    SynthFrame,
    _Generator,
    _generator,
    frame_id,
    generate_frame,
)
from cloudpose.data.synth.surfaces import surface_settings
from cloudpose.data.ycb import write_frame
from cloudpose.files import CorruptFileError, atomic_text, atomic_write, read_json

# --------------------------------------------------------------------------- writing


_worker_gen: _Generator | None = None


def _frame_done(root: Path, fid: str) -> bool:
    """Whether the frame's depth, label and meta files are there and not empty (a zero-byte
    file, which no write of this module leaves, is rendered again; a truncated one is named by
    the first reader)."""
    seq, name = fid.split("/")
    d = root / "data" / seq
    for k in ("depth.png", "label.png", "meta.mat"):
        try:
            if (d / f"{name}-{k}").stat().st_size == 0:
                return False
        except FileNotFoundError:
            return False
    return True


def _write(root: Path, f: SynthFrame) -> None:
    """Write a frame atomically: stage it whole, then rename depth, label and meta (last)."""

    stage = root / ".staging" / f"{os.getpid()}"
    alone = {"alone_pixels": f.alone_pixels.astype(np.float64).reshape(-1, 1)}
    write_frame(
        stage, f.frame_id, f.depth, f.label, YCB_INTRINSICS, f.cls_ids, f.poses, extra_meta=alone
    )
    seq, name = f.frame_id.split("/")
    src, dst = stage / "data" / seq, root / "data" / seq
    dst.mkdir(parents=True, exist_ok=True)
    for suffix in ("depth.png", "label.png", "meta.mat"):
        os.replace(src / f"{name}-{suffix}", dst / f"{name}-{suffix}")


def _init_worker(version: int) -> None:
    global _worker_gen
    _worker_gen = _generator(version)


def _work(args: tuple[str, str, int, int, bool, bool, int]) -> str:
    root, split, index, seed, noise, uniform, version = args
    assert _worker_gen is not None
    f = generate_frame(split, index, seed, noise, uniform, _worker_gen, version)
    _write(Path(root), f)
    return f.frame_id


class SynthSummary(NamedTuple):
    """What :func:`synthesize` did."""

    frames_written: int
    frames_skipped: int
    seconds: float


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _clean_staging(root: Path) -> None:
    """Remove staged frames of processes that are gone (an interrupted run's leftovers); a
    concurrent run's own staging folder is left alone."""
    stage = root / ".staging"
    if not stage.is_dir():
        return
    for d in stage.iterdir():
        pid = int(d.name) if d.name.isdigit() else 0
        if pid <= 0 or pid == os.getpid() or not _pid_alive(pid):
            shutil.rmtree(d, ignore_errors=True)
    try:
        stage.rmdir()
    except OSError:
        pass  # another run is staging


_LOST = (
    "which generator made the frames here is unknown: restore the file, or delete the folder and "
    "run the command again to render it anew"
)


def _prepare_root(root: Path, seed: int, noise: bool, uniform_rotation: bool, version: int) -> None:
    # Frames depend on the generator and on the rendered surfaces: both versions are recorded,
    # so frames made by another generator or renderer are never mixed on resume.
    settings = {
        "generator": "cloudpose.data.synth",
        "version": version,
        "surfaces": surface_settings(version),
        "seed": seed,
        "noise": noise,
        "uniform_rotation": uniform_rotation,
    }
    info = root / "synth.json"
    if info.is_file():
        old = read_json(
            info, "the record of the settings this folder's frames were made with", _LOST
        )
        if not isinstance(old, dict):
            raise CorruptFileError(info, f"holds {type(old).__name__}, not the settings; {_LOST}")
        old = {k: old.get(k) for k in settings}
        if old["version"] != version:
            raise ValueError(
                f"{info}: this folder holds frames of synthetic generator version "
                f"{old['version']}, not {version} (data.synth_version); frames of two versions "
                f"never share a folder: render into another root, or ask for version "
                f"{old['version']} (data.synth_version = {old['version']})"
            )
        if old != settings:
            raise ValueError(
                f"{info}: this folder holds synthetic frames made with {old}, not {settings} "
                "(a missing key: made by an older cloudpose); choose another root (or delete "
                "the folder)"
            )
    root.mkdir(parents=True, exist_ok=True)
    _clean_staging(root)
    atomic_text(info, json.dumps(settings, indent=2) + "\n")
    _copy_packaged(resource_path("classes.txt"), root / "classes.txt")
    for name in packaged_classes():
        _copy_packaged(
            resource_path("models", name, "points.xyz"), root / "models" / name / "points.xyz"
        )


def _copy_packaged(src: Path, dst: Path) -> None:
    """Copy a packaged file into the root atomically, again when the copy there is not the
    same size (cut short or emptied since)."""
    if dst.is_file() and dst.stat().st_size == src.stat().st_size:
        return
    atomic_write(dst, lambda tmp: shutil.copyfile(src, tmp))


def synthesize(
    root: str | Path,
    train_frames: int,
    test_frames: int,
    seed: int = 0,
    noise: bool = True,
    uniform_rotation: bool = False,
    workers: int | None = None,
    progress: bool = True,
    version: int = GENERATOR_VERSION,
) -> SynthSummary:
    """Write (or complete) a synthetic dataset in the YCB-Video layout under ``root``.

    Resumable: frames whose depth, label and meta files exist are kept (a frame's meta is
    renamed into place last, so an interrupted frame has none and is made again). The image
    sets list exactly the requested counts.

    Args:
        root: dataset root (created if missing).
        train_frames: frames listed in image_sets/train.txt.
        test_frames: frames listed in image_sets/test.txt and keyframe.txt.
        seed: scene seed; frame i depends on (seed, split, i) only.
        noise: apply :func:`add_sensor_noise`.
        uniform_rotation: floating objects in uniform SO(3) rotations instead of table scenes.
        workers: processes (default: all cores); 1 renders in this process.
        progress: show a tqdm progress bar.
        version: generator version (:data:`~cloudpose.config.GENERATOR_VERSIONS`).

    Returns:
        :class:`SynthSummary`.

    Raises:
        ValueError: negative counts, an unknown version, or ``root`` holds frames made with
            another version or other settings.
    """
    if train_frames < 0 or test_frames < 0:
        raise ValueError(f"frame counts must be >= 0, got {train_frames=}, {test_frames=}")
    check_synth_version(version)
    t0 = time.perf_counter()
    root = Path(root)
    _prepare_root(root, seed, noise, uniform_rotation, version)
    wanted = [("train", i) for i in range(train_frames)] + [("test", i) for i in range(test_frames)]
    todo = [(s, i) for s, i in wanted if not _frame_done(root, frame_id(s, i))]
    jobs = [(str(root), s, i, seed, noise, uniform_rotation, version) for s, i in todo]
    workers = min(workers or os.cpu_count() or 1, max(len(jobs), 1))

    bar = tqdm(total=len(jobs), desc="synth", unit="frame", disable=not progress or not jobs)
    if workers <= 1:
        gen = _generator(version) if jobs else None
        for root_s, s, i, *_ in jobs:
            _write(Path(root_s), generate_frame(s, i, seed, noise, uniform_rotation, gen, version))
            bar.update()
    else:
        ctx = mp.get_context("spawn")
        with ctx.Pool(workers, initializer=_init_worker, initargs=(version,)) as pool:
            for _ in pool.imap_unordered(_work, jobs):
                bar.update()
    bar.close()
    _clean_staging(root)
    train_ids = [frame_id("train", i) for i in range(train_frames)]
    test_ids = [frame_id("test", i) for i in range(test_frames)]
    atomic_text(root / "image_sets" / "train.txt", "".join(f + "\n" for f in train_ids))
    atomic_text(root / "image_sets" / "test.txt", "".join(f + "\n" for f in test_ids))
    atomic_text(root / "keyframe.txt", "".join(f + "\n" for f in test_ids))
    return SynthSummary(len(jobs), len(wanted) - len(jobs), time.perf_counter() - t0)
