"""The segment cache: segments of a dataset split, extracted once and kept as one file.

:func:`prepare` runs :func:`cloudpose.data.segments.extract_segments` over a split's frames (all
cores) and writes one uncompressed ``.npz`` of columnar arrays (:class:`SegmentSet`) that loads
into memory in seconds. The file name holds a key that hashes everything the segments depend on:
the frame list, the content of each frame file (a PNG's decoded image, not its bytes) and model file (and of the files of a predicted
segmentation), and the segment settings (n_fps, outlier_radius, segmentation, FPS seed,
pipeline version). A changed frame or setting gives a new key, so a stale cache is never read.

Every use of a cache runs the depth unit check per scene (:func:`check_units`; the statistics
it needs are stored in the file): a scene whose segments are a tenth or ten times their
model's size stops the command that reads it (prepare, train, evaluate, baseline) with one
line, unless ``CLOUDPOSE_NO_UNIT_CHECK=1``.

A cache file is checked on every use (:meth:`SegmentSet.check`: every field there, with the
shapes the others imply and the bytes its header declares; :meth:`SegmentSet.load`: every
array's CRC): one that is empty, truncated, garbled or of the wrong shape is made again, with
a one-line warning naming it. So is a damaged digest memo. A frame image that cannot be read is
one line naming it (``error: PATH: image is not a readable PNG ...``).

Which dataset a config means, and its preparation for training, are in
:mod:`cloudpose.data.dataset`.

Points are stored as float32 (12 KiB per segment of 1024 points; float16 would round
camera-frame coordinates near 1 m to 0.5-1 mm, too coarse beside the 1 cm accuracy thresholds).
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import os
import warnings
import zlib
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image
from tqdm import tqdm

from cloudpose.config import DataConfig
from cloudpose.data.keys import DataKey
from cloudpose.data.layout import Dataset, as_dataset, open_dataset
from cloudpose.data.mask_sources import get_mask_source
from cloudpose.data.segment_set import SegmentSet, check_units, unit_stats
from cloudpose.data.segments import ALONE_SURFACE_VERSION, Segment, SegmentWarning, extract_segments
from cloudpose.data.synth.render import Renderer
from cloudpose.data.ycb import YCBVideo
from cloudpose.files import CorruptFileError, atomic_text, read_json, read_npz, why

if TYPE_CHECKING:
    from cloudpose.config import DataConfig

PIPELINE_VERSION = 2
"""Bumped whenever a code change alters the segments; part of the cache key. Version 2: each
instance draws its FPS start from its own stream (version 1: one stream per frame, which
``data.segment_streams = "frame"`` still makes, under version 1's key)."""

_STREAMS_VERSION = {"instance": PIPELINE_VERSION, "frame": 1}
"""The pipeline version (and so the key) of segments made with each ``data.segment_streams``."""

FPS_SEED = 0
"""Seed of the FPS start points: frame f's generator is (FPS_SEED, crc32(f)), and each of its
instances draws from its own stream of it (:func:`~cloudpose.data.segments.instance_streams`)."""

# --------------------------------------------------------------------------- keys


def _split_frames(ds: Dataset, split: str) -> list[str]:
    """Frame ids of a split of either layout (:mod:`cloudpose.data.layout`): "train" ->
    image_sets/train.txt (BOP: train_real/); "test" or "keyframe" -> keyframe.txt (BOP: the
    BOP19 test targets); "all" -> every frame; else image_sets/SPLIT.txt."""
    name = "keyframe" if split in ("test", "keyframe") else split
    frames = ds.image_set(name)
    if not frames:
        raise ValueError(f"{ds.root}: the frame list {name!r} (split {split!r}) is empty")
    return frames


def _settings(cfg: DataConfig) -> dict:
    get_mask_source(cfg.segmentation)  # unknown names raise here, before any work
    return {
        "n_fps": int(cfg.n_fps),
        "outlier_radius": float(cfg.outlier_radius),
        "segmentation": cfg.segmentation,
        "fps_seed": FPS_SEED,
        "pipeline_version": _STREAMS_VERSION[cfg.segment_streams],
    }


def cache_key(
    dataset: str | Path | Dataset, split: str, cfg: DataConfig, memo_dir: str | Path | None = None
) -> DataKey:
    """The data key of a split's segments (:data:`~cloudpose.data.keys.DataKey`): hash of frame ids, the *content* of each frame's files and of
    the model files, and the segment settings (20 hex digits).

    The same data gives the same key wherever it lies, whenever and on whichever machine it was
    written (a ``cp -r`` copy, a re-render in another clone or on another CPU, whose PNG
    encoder may compress the same pixels to other bytes). Content digests are remembered by path,
    size and modification time in the memo :data:`DIGEST_MEMO` in ``memo_dir`` (when given),
    so a large dataset is read once, not on every command.
    """
    ds = as_dataset(dataset)
    root = ds.root
    frames = _split_frames(ds, split)
    mask_files = getattr(get_mask_source(cfg.segmentation), "content_files", None)
    files: list[Path] = []
    for fid in frames:
        try:
            files += ds.content_files(fid)
        except FileNotFoundError as e:
            raise FileNotFoundError(f"{e} (split {split!r})") from e
        if mask_files is not None:  # a predicted segmentation's files are data too
            files += mask_files(fid)
    models = ds.model_files()
    digests = content_digests(files + [p for p in models if p.is_file()], memo_dir)
    h = hashlib.sha256()
    h.update(json.dumps(_settings(cfg), sort_keys=True).encode())
    h.update(json.dumps(frames).encode())
    h.update("".join(digests[: len(files)]).encode())
    if isinstance(ds, YCBVideo) and not (root / "synth.json").is_file():
        # real YCB-Video frames carry no alone-pixel counts: they are rendered, by these surfaces
        h.update(f"alone-surfaces:{ALONE_SURFACE_VERSION};".encode())
    # the models feed the rendered alone-pixel counts
    model_digest = iter(digests[len(files) :])
    for name, p in zip(ds.classes, models, strict=True):
        h.update(f"{name}:{next(model_digest) if p.is_file() else '-'};".encode())
    return DataKey(h.hexdigest()[:20])


MAT_TEXT_HEADER = 116
"""Bytes of a MAT-file's descriptive text header: ``MATLAB 5.0 MAT-file ... Created on: <time>``.
``scipy.io.savemat`` writes the time of writing there, so two renders of the same frame differ
in it alone; the digest of a ``.mat`` file leaves it out."""


DIGEST_MEMO = "digests-v3.json"
"""The memo of file digests; its name changes with the digest's definition (v2: a ``.mat``
file's text header left out; v3: a PNG's decoded image, not its bytes), so no digest of an
older definition is reused."""


def _png_digest(path: Path) -> str:
    """BLAKE2b of a PNG's decoded image: mode, size, palette and pixels.

    A PNG's bytes are not its content: the same pixels compress to other bytes under another
    deflate implementation, and Pillow's (zlib-ng) picks its matches by the CPU's instruction
    set, so one frame rendered on two machines gives two files that decode alike.

    Raises:
        CorruptFileError: the file is empty, truncated or not a PNG (named, with what to do).
    """
    try:
        im = Image.open(path)
        im.load()
    except (OSError, SyntaxError, ValueError, EOFError, zlib.error) as e:
        raise CorruptFileError(
            path,
            f"image is not a readable PNG ({why(e)}); replace it (in a synthetic set: delete it "
            "and run the command again, which renders its frame anew)",
        ) from e
    with im:
        h = hashlib.blake2b()
        h.update(f"png:{im.mode};{im.size[0]}x{im.size[1]};".encode())
        palette = im.getpalette()
        if palette is not None:
            h.update(bytes(palette))
        h.update(im.tobytes())
    return h.hexdigest()[:32]


def _file_digest(path: Path) -> str:
    if path.suffix.lower() == ".png":
        return _png_digest(path)
    with open(path, "rb") as f:
        if path.suffix == ".mat":
            f.seek(MAT_TEXT_HEADER)
        return hashlib.file_digest(f, "blake2b").hexdigest()[:32]


def _read_memo(path: Path) -> dict[str, list]:
    """The digest memo in ``path``; {} (after a one-line warning naming it) when it is not one:
    it is only a memo, so it is made again."""
    try:
        memo = read_json(path, "digest memo", "making it again")
        ok = isinstance(memo, dict) and all(
            isinstance(v, list)
            and len(v) == 3
            and all(isinstance(x, int) for x in v[:2])
            and isinstance(v[2], str)
            for v in memo.values()
        )
        if not ok:
            raise CorruptFileError(
                path, "digest memo is not {path: [size, mtime_ns, digest]}; making it again"
            )
    except CorruptFileError as e:
        warnings.warn(str(e), stacklevel=3)
        return {}
    return memo


def content_digests(paths: list[Path], memo_dir: str | Path | None = None) -> list[str]:
    """BLAKE2b digests (32 hex digits) of the files' content, in order: a file's bytes, a
    ``.mat`` file's bytes after its descriptive text header (which holds the time it was
    written), a PNG's decoded image (:func:`_png_digest`).

    Args:
        paths: files to hash.
        memo_dir: folder of the memo :data:`DIGEST_MEMO` (absolute path -> size, mtime_ns,
            digest); a file whose size and mtime match its entry is not read again. None =
            no memo.
    """
    memo_path = Path(memo_dir) / DIGEST_MEMO if memo_dir else None
    memo = _read_memo(memo_path) if memo_path is not None and memo_path.is_file() else {}
    out, changed = [], False
    for p in paths:
        st = os.stat(p)
        key, stamp = str(Path(p).resolve()), [st.st_size, st.st_mtime_ns]
        entry = memo.get(key)
        if entry is None or entry[:2] != stamp:
            entry = memo[key] = [*stamp, _file_digest(Path(p))]
            changed = True
        out.append(entry[2])
    if changed and memo_path is not None:
        atomic_text(memo_path, json.dumps(memo))
    return out


# --------------------------------------------------------------------------- prepare

_worker: dict = {}


def _init_worker(root: str) -> None:
    _worker.clear()
    _worker["ds"] = open_dataset(root)


def _extract(args: tuple[str, dict]) -> tuple[list[Segment], int]:
    fid, settings = args
    ds = _worker["ds"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        frame = ds.frame(fid)
        alone = None
        renderer = None
        if frame.poses is not None:
            alone = ds.alone_pixels(fid)
            if alone is None:
                if "renderer" not in _worker:
                    # copies: the reader's arrays are read-only, Open3D wants writeable ones
                    _worker["renderer"] = Renderer(
                        {c: p.copy() for c, p in ds.models().items()},
                        surface_version=ALONE_SURFACE_VERSION,
                    )
                renderer = _worker["renderer"]
        rng = np.random.default_rng([settings["fps_seed"], zlib.crc32(fid.encode())])
        segs = extract_segments(
            frame,
            alone_pixels=alone,
            renderer=renderer,
            n_fps=settings["n_fps"],
            outlier_radius=settings["outlier_radius"],
            segmentation=settings["segmentation"],
            rng=rng,
            streams="frame" if settings["pipeline_version"] == 1 else "instance",
        )
    return segs, sum(issubclass(w.category, SegmentWarning) for w in caught)


def _run(jobs: list, ds: Dataset, workers: int):
    """Results of :func:`_extract` over ``jobs`` in order, in this process (reading ``ds``) or
    a spawn pool (each process opens the folder again: a dataset is not sent between them)."""
    if workers <= 1:
        _worker.clear()
        _worker["ds"] = ds
        yield from map(_extract, jobs)
        return

    with mp.get_context("spawn").Pool(workers, _init_worker, (str(ds.root),)) as pool:
        yield from pool.imap(_extract, jobs, chunksize=4)


# --------------------------------------------------------------------------- units


def _stored_unit_stats(path: Path, models_by_class: dict[int, np.ndarray]) -> dict:
    """The unit statistics a cache file stores; measured from its segments for a file written
    before they were stored.

    Raises:
        CorruptFileError: the file fails :meth:`SegmentSet.check` or its statistics are
            unreadable.
    """
    SegmentSet.check(path)
    with np.load(path, allow_pickle=False) as z:
        stored = "unit_scene" in z.files and "unit_stats" in z.files
    if stored:
        return read_npz(path, ("unit_scene", "unit_stats"), "segment cache")
    return unit_stats(SegmentSet.load(path), models_by_class)


def _discard(e: CorruptFileError) -> None:
    """A damaged cache file: warn in one line naming it, and remove it (it is made again)."""
    warnings.warn(f"{e}; making it again", stacklevel=3)
    e.path.unlink(missing_ok=True)


def cache_path(
    dataset: str | Path | Dataset, split: str, cfg: DataConfig, cache_dir: str | Path
) -> Path:
    """Where the segments of ``split`` live: ``cache_dir/ROOTNAME-SPLIT-KEY.npz``."""
    ds = as_dataset(dataset)
    data_key = cache_key(ds, split, cfg, memo_dir=cache_dir)
    return Path(cache_dir) / f"{ds.root.resolve().name}-{split}-{data_key}.npz"


def prepare(
    dataset: str | Path | Dataset,
    split: str,
    cfg: DataConfig,
    cache_dir: str | Path | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> Path:
    """Extract and cache the segments of a split (skipped when its keyed cache exists).

    Args:
        dataset: an opened dataset or its root, in either layout (:mod:`cloudpose.data.layout`).
        split: "train" (image_sets/train.txt), "test" or "keyframe" (keyframe.txt; BOP: the
            BOP19 test targets), "all" (every frame) or another image set name.
        cfg: segment settings (n_fps, outlier_radius, segmentation).
        cache_dir: folder of cache files (default ``root/cache``).
        workers: processes (default all cores); 1 extracts in this process.
        progress: tqdm progress bar.

    Returns:
        Path of the cache file.

    A cache file that fails :meth:`SegmentSet.check` (zero bytes, truncated, a field of the
    wrong shape) is made again, with a one-line warning naming it.

    Raises:
        ValueError: a scene's segments look like depth in another unit (:func:`check_units`;
            the cache is written all the same, and checked again on every use).
    """
    ds = as_dataset(dataset)
    root = ds.root
    settings = _settings(cfg)
    path = cache_path(ds, split, cfg, cache_dir or root / "cache")
    if path.is_file():
        try:
            unit = _stored_unit_stats(path, ds.models())
        except CorruptFileError as e:
            _discard(e)
        else:
            check_units(ds, unit)
            return path
    frames = _split_frames(ds, split)
    jobs = [(fid, settings) for fid in frames]
    workers = min(workers or os.cpu_count() or 1, max(len(jobs), 1))

    segments: list[Segment] = []
    n_bad = 0
    with tqdm(total=len(jobs), desc=f"prepare {split}", unit="frame", disable=not progress) as bar:
        for segs, bad in _run(jobs, ds, workers):
            segments.extend(segs)
            n_bad += bad
            bar.update()
    if n_bad:
        warnings.warn(
            f"{root} split {split!r}: {n_bad} warnings about segments (instances without a "
            "usable point are kept as misses; see SegmentWarning)",
            SegmentWarning,
            stacklevel=2,
        )
    out = SegmentSet.from_segments(segments, settings["n_fps"])
    out.data_key = DataKey(path.stem.rsplit("-", 1)[-1])
    unit = unit_stats(out, ds.models())
    out.save(path, extra=unit)
    check_units(ds, unit)
    return path


# --------------------------------------------------------------------------- other folders


def segments_for(
    dataset: str | Path | Dataset,
    frames: str = "keyframe",
    cfg: DataConfig | None = None,
    cache_dir: str | Path | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> SegmentSet:
    """Segments of any dataset folder of either layout (e.g. a real dataset to evaluate on),
    cached.

    Args:
        dataset: a :class:`~cloudpose.data.ycb.YCBVideo`, a :class:`~cloudpose.data.bop.BOPYcbv`
            or its root folder.
        frames: "keyframe", "all", "train" or an image_sets name (see :func:`prepare`).
        cfg: segment settings (default :class:`~cloudpose.config.DataConfig`).
        cache_dir: cache folder (default ``./data/cache``, so a dataset folder is only read).
        workers: processes (default all cores).
        progress: progress bar.
    """

    cfg = cfg or DataConfig()
    cache_dir = Path(cache_dir) if cache_dir else Path.cwd() / "data" / "cache"
    return load_segments(dataset, frames, cfg, cache_dir, workers=workers, progress=progress)


def load_segments(
    dataset: str | Path | Dataset,
    split: str,
    cfg: DataConfig,
    cache_dir: str | Path | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> SegmentSet:
    """The segments of a split: :func:`prepare` (arguments as there), then the cache read
    whole; a file whose bytes turn out damaged on that read (a CRC that fails) is made again,
    with a one-line warning naming it."""
    path = prepare(dataset, split, cfg, cache_dir, workers=workers, progress=progress)
    try:
        return SegmentSet.load(path)
    except CorruptFileError as e:
        _discard(e)
    return SegmentSet.load(prepare(dataset, split, cfg, cache_dir, workers, progress))
