"""Segment cache: round trip, keys that change with data and settings, the dataset entry point."""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cloudpose.config import DataConfig
from cloudpose.data import cache, dataset
from cloudpose.data.segments import Segment
from cloudpose.data.synth import synthesize
from cloudpose.report.plots import occlusion_histogram

REAL = Path(__file__).parent / "data" / "ycb_real"
CFG = DataConfig(train_frames=2, test_frames=1, n_fps=64)


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> Path:
    """A project folder whose synthetic default data (2 train, 1 test frames) exists."""
    d = tmp_path_factory.mktemp("project")
    synthesize(dataset.synthetic_root(CFG, d), 2, 1, workers=1, progress=False)
    return d


def _segment(i: int, gt: bool = True) -> Segment:
    rng = np.random.default_rng(i)
    return Segment(
        rng.normal(size=(8, 3)).astype(np.float32),
        5 + i,
        1 + i,
        np.eye(3, dtype=np.float32) if gt else None,
        np.array([0, 0, 1 + i], np.float32) if gt else None,
        0.1 * i if gt else float("nan"),
        f"00{i:02d}/000001",
        i,
        i != 1,
    )


def test_segment_set_round_trip_and_subset(tmp_path):
    s = cache.SegmentSet.from_segments([_segment(0), _segment(1), _segment(2, gt=False)], 8)
    s.data_key = "abc"
    assert len(s) == 3
    assert s.points.shape == (3, 8, 3) and s.points.dtype == np.float32
    assert np.isnan(s.R[2]).all() and np.isnan(s.t[2]).all() and np.isnan(s.occlusion[2])
    path = tmp_path / "x.npz"
    s.save(path)
    back = cache.SegmentSet.load(path)
    assert back.data_key == "abc"
    for name in cache.SegmentSet._ARRAYS:
        a, b = getattr(s, name), getattr(back, name)
        assert a.dtype == b.dtype, name
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), name
    sub = back.subset(back.valid)
    assert len(sub) == 2 and sub.frame_id.tolist() == ["0000/000001", "0002/000001"]
    assert len(back.subset(np.array([2]))) == 1 and len(back.subset(slice(0, 2))) == 2
    both = cache.SegmentSet.concatenate([back, sub])
    assert len(both) == 5
    empty = cache.SegmentSet.from_segments([], 8)
    assert empty.points.shape == (0, 8, 3)


def test_load_rejects_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="segment cache"):
        cache.SegmentSet.load(tmp_path / "none.npz")
    np.savez(tmp_path / "bad.npz", points=np.zeros((1, 4, 3)))
    with pytest.raises(ValueError, match="lacks fields"):
        cache.SegmentSet.load(tmp_path / "bad.npz")


def test_prepare_and_keys(project, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(dataset.synthetic_root(CFG, project), root)
    cdir = tmp_path / "cache"
    p = cache.prepare(root, "train", CFG, cdir, workers=1, progress=False)
    s = cache.SegmentSet.load(p)
    assert p.name.startswith("ds-train-") and s.data_key in p.name
    assert len(s) >= 6 and s.valid.all()
    assert s.points.shape[1:] == (64, 3)
    assert set(s.frame_id.tolist()) == {"0000/000001", "0000/000002"}
    assert np.isfinite(s.occlusion).all() and ((s.occlusion >= 0) & (s.occlusion <= 1)).all()
    # t of the GT pose lies near the segment (object centres are within 0.2 m of their points)
    assert (np.linalg.norm(s.points.mean(1) - s.t, axis=1) < 0.2).all()
    # cached: same path, file not rewritten
    mtime = p.stat().st_mtime_ns
    assert cache.prepare(root, "train", CFG, cdir, workers=1, progress=False) == p
    assert p.stat().st_mtime_ns == mtime
    # the key follows settings ...
    key = cache.cache_key(root, "train", CFG)
    for change in ({"n_fps": 32}, {"outlier_radius": 0.1}):
        assert cache.cache_key(root, "train", dataclasses.replace(CFG, **change)) != key
    assert cache.cache_key(root, "train", dataclasses.replace(CFG, train_frames=99)) == key
    with pytest.raises(ValueError, match="valid segmentations"):
        cache.cache_key(root, "train", dataclasses.replace(CFG, segmentation="nope"))
    # ... the split and the frame files
    assert cache.cache_key(root, "test", CFG) != key
    depth = root / "data" / "0000" / "000002-depth.png"
    st = depth.stat()
    os.utime(depth, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    assert cache.cache_key(root, "train", CFG, memo_dir=cdir) == key  # same bytes, same key
    copy = tmp_path / "copy" / root.name
    shutil.copytree(root, copy)  # a copy (new mtimes) is the same data
    assert cache.cache_key(copy, "train", CFG) == key
    meta = copy / "data" / "0000" / "000001-meta.mat"  # rewritten later: a new "Created on"
    raw = meta.read_bytes()
    assert raw.startswith(b"MATLAB 5.0 MAT-file") and b"Created on" in raw[: cache.MAT_TEXT_HEADER]
    meta.write_bytes(b"MATLAB 5.0 MAT-file, written another day".ljust(116, b" ") + raw[116:])
    assert cache.cache_key(copy, "train", CFG) == key  # a re-render is the same data
    meta.write_bytes(raw[:-1] + bytes([raw[-1] ^ 1]))  # any other byte still counts
    assert cache.cache_key(copy, "train", CFG) != key
    # a PNG is its pixels: the same image compressed to other bytes (another encoder, another
    # CPU) is the same data, one pixel changed is not
    label = root / "data" / "0000" / "000002-label.png"
    raw = label.read_bytes()
    with Image.open(label) as im:
        pixels = np.array(im)
    Image.fromarray(pixels).save(label, format="PNG", compress_level=1)
    assert label.read_bytes() != raw
    assert cache.cache_key(root, "train", CFG, memo_dir=cdir) == key
    pixels[tuple(np.argwhere(pixels > 0)[0])] = 0  # one object pixel to background
    Image.fromarray(pixels).save(label, format="PNG")
    key2 = cache.cache_key(root, "train", CFG, memo_dir=cdir)
    assert key2 != key
    p2 = cache.prepare(root, "train", CFG, cdir, workers=1, progress=False)
    assert p2 != p and key2 in p2.name
    (root / "image_sets" / "train.txt").write_text("0000/000001\n")
    assert cache.cache_key(root, "train", CFG) not in (key, key2)
    # the FPS start is seeded: the same data gives the same segments
    p3 = cache.prepare(root, "train", CFG, tmp_path / "cache3", workers=1, progress=False)
    s3 = cache.SegmentSet.load(p3)
    first = s.frame_id == "0000/000001"
    assert np.array_equal(s3.points, s.points[first])


def test_prepare_data_synthetic(project):
    prep = dataset.prepare_data(CFG, project, workers=1, progress=False)
    train, test = prep.train, prep.test
    assert set(train.frame_id.tolist()) == {"0000/000001", "0000/000002"}
    assert set(test.frame_id.tolist()) == {"1000/000001"}
    assert train.points.shape[1] == 64
    fp = dataset.data_fingerprint(CFG, project)
    assert fp == prep.data_key and len(fp) == 16
    assert dataset.data_fingerprint(dataclasses.replace(CFG, n_fps=32), project) != fp
    assert dataset.synthetic_root(CFG, project).name == "synth-seed0-v2"
    assert dataset.dataset_root(CFG, project) == dataset.synthetic_root(CFG, project)
    cfg2 = dataclasses.replace(CFG, noise=False, uniform_rotation=True, synth_seed=2)
    assert dataset.synthetic_root(cfg2, project).name == "synth-seed2-uniform-nonoise-v2"


def test_prepare_data_real_root(tmp_path):
    """A real root is read, never written: alone pixels are rendered, caches go elsewhere."""
    root = tmp_path / "ycb"
    shutil.copytree(REAL / "data", root / "data")
    shutil.copy(REAL / "classes.txt", root / "classes.txt")
    (root / "image_sets").mkdir()
    (root / "image_sets" / "train.txt").write_text("0000/000001\n")
    (root / "keyframe.txt").write_text("0000/000001\n")
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    cfg = DataConfig(root=str(root), n_fps=128)
    prep = dataset.prepare_data(cfg, tmp_path / "proj", workers=1, progress=False)
    train, test = prep.train, prep.test
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before
    assert len(train) == 3 and train.cls_id.tolist() == [8, 14, 21]
    assert np.array_equal(train.points, test.points)
    assert np.isfinite(train.occlusion).all()
    assert list((tmp_path / "proj" / "data" / "cache").glob("ycb-*.npz"))
    assert dataset.dataset_root(cfg, tmp_path / "proj") == root
    from cloudpose.data.ycb import YCBVideo

    every = cache.segments_for(YCBVideo(root), "all", cfg, tmp_path / "c2", progress=False)
    assert every.frame_id.tolist() == ["0000/000001"] * 3
    assert np.array_equal(every.points, train.points)
    assert not (root / "cache").exists()
    with pytest.raises(FileNotFoundError, match=r"data\.root"):
        dataset.prepare_data(DataConfig(root=str(tmp_path / "nope")), tmp_path, progress=False)


def test_occlusion_histogram(tmp_path):
    s = cache.SegmentSet.from_segments([_segment(i) for i in range(3)], 8)
    s.occlusion = np.array([0.0, 0.15, 1.0], np.float32)
    png = tmp_path / "h.png"
    counts = occlusion_histogram(s, png, "test")
    assert counts.tolist() == [1, 1, 0, 0, 0, 0, 0, 0, 0, 1]
    assert png.stat().st_size > 1000


def test_real_frames_are_keyed_by_the_surfaces_that_render_their_occlusion(monkeypatch):
    """A real frame's alone-pixel counts are rendered (synthetic and BOP frames carry theirs),
    so the surface version that renders them is part of its key."""
    key = cache.cache_key(REAL, "all", CFG)
    monkeypatch.setattr(cache, "ALONE_SURFACE_VERSION", 1)
    assert cache.cache_key(REAL, "all", CFG) != key
