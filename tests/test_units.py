"""The depth unit check on every path that reads a dataset's depth (cloudpose.data.cache,
cloudpose.data.bop): depth 10x off in either layout stops prepare, evaluate, baseline and
export with one line naming the scene and the setting; CLOUDPOSE_NO_UNIT_CHECK=1 goes on."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cloudpose.data.bop import export_bop
from cloudpose.data.cache import SegmentSet, prepare, segments_for
from cloudpose.data.segments import UNIT_CHECK_OFF, UnitWarning
from cloudpose.registry import resolve
from tests.conftest import cli, one_line_error

REAL = Path(__file__).parent / "data" / "ycb_real"
FID = "0000/000001"


def _ycb_copy(dest: Path, depth_divisor: int = 1) -> Path:
    """The real test frame as a YCB-Video root with keyframe and train lists (depth PNG
    divided by ``depth_divisor``: 10 writes millimetres under factor_depth 10000)."""
    shutil.copytree(REAL, dest)
    (dest / "keyframe.txt").write_text(FID + "\n")
    (dest / "image_sets").mkdir()
    (dest / "image_sets" / "train.txt").write_text(FID + "\n")
    png = dest / "data" / "0000" / "000001-depth.png"
    depth = np.asarray(Image.open(png)).astype(np.uint32)
    Image.fromarray((depth // depth_divisor).astype(np.uint16)).save(png)
    return dest


@pytest.fixture(scope="module")
def ycb_mm(tmp_path_factory) -> Path:
    return _ycb_copy(tmp_path_factory.mktemp("units") / "ycb_mm", depth_divisor=10)


@pytest.fixture(scope="module")
def bop_ok(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("units") / "bop"
    export_bop(REAL, out, frames="all", progress=False)
    return out


def _bop_with_scale(bop_ok: Path, dest: Path, scale: float) -> Path:
    shutil.copytree(bop_ok, dest)
    path = dest / "test" / "000000" / "scene_camera.json"
    cam = json.loads(path.read_text())
    for entry in cam.values():
        entry["depth_scale"] = scale
    path.write_text(json.dumps(cam))
    return dest


def test_ycb_depth_in_millimetres_stops_prepare_until_overridden(ycb_mm, monkeypatch):
    monkeypatch.delenv(UNIT_CHECK_OFF, raising=False)
    args = ["prepare", "--preset", "smoke", "--data", str(ycb_mm), "--no-progress"]
    line = one_line_error(
        cli(*args),
        str(ycb_mm / "data" / "0000"),
        "10 times too small",
        "factor_depth",
        f"{UNIT_CHECK_OFF}=1 goes on anyway",
    )
    assert "median segment extent 0.08" in line
    monkeypatch.setenv(UNIT_CHECK_OFF, "1")
    res = cli(*args)
    assert res.exit_code == 0, res.output
    assert "train: 3 segments, test: 3 segments" in res.output
    # the cache is there now; every later use checks it again
    monkeypatch.delenv(UNIT_CHECK_OFF)
    one_line_error(cli(*args), "10 times too small")


def test_a_cache_written_before_the_check_is_checked_from_its_segments(ycb_mm, tmp_path):
    cfg = resolve("shared-0", "smoke").data
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(UNIT_CHECK_OFF, "1")
        with pytest.warns(UnitWarning, match="10 times too small"):
            path = prepare(ycb_mm, "all", cfg, tmp_path, workers=1, progress=False)
    SegmentSet.load(path).save(path)  # the segments alone, as older versions wrote them
    with np.load(path) as z:
        assert "unit_stats" not in z.files
    with pytest.raises(ValueError, match="10 times too small"):
        prepare(ycb_mm, "all", cfg, tmp_path, workers=1, progress=False)


def test_data_in_the_right_unit_passes(bop_ok, tmp_path):
    assert len(segments_for(REAL, "all", cache_dir=tmp_path, workers=1, progress=False)) == 3
    assert len(segments_for(bop_ok, "all", cache_dir=tmp_path, workers=1, progress=False)) == 3


@pytest.mark.parametrize(
    ("scale", "looks"), [(1.0, "10 times too large"), (0.01, "10 times too small")]
)
def test_bop_depth_scale_off_by_ten_stops_until_overridden(
    bop_ok, tmp_path, monkeypatch, scale, looks
):
    root = _bop_with_scale(bop_ok, tmp_path / "bop", scale)
    monkeypatch.delenv(UNIT_CHECK_OFF, raising=False)
    cache = tmp_path / "cache"
    with pytest.raises(ValueError, match=looks) as info:
        segments_for(root, "keyframe", cache_dir=cache, workers=1, progress=False)
    message = str(info.value)
    assert str(root / "test" / "000000") in message and "depth_scale" in message
    assert "BOP ycbv 0.1" in message and "\n" not in message
    monkeypatch.setenv(UNIT_CHECK_OFF, "1")
    with pytest.warns(UnitWarning, match=looks):
        segs = segments_for(root, "keyframe", cache_dir=cache, workers=1, progress=False)
    assert len(segs) == 3


def test_baseline_on_data_10x_off_stops_in_one_line(bop_ok, tmp_path, monkeypatch):
    monkeypatch.delenv(UNIT_CHECK_OFF, raising=False)
    root = _bop_with_scale(bop_ok, tmp_path / "bop", 1.0)
    args = ["baseline", "--method", "fpfh", "--preset", "smoke", "--data", str(root)]
    res = cli(*args, "--frames", "all", "--refine", "none", "--no-progress")
    one_line_error(res, "10 times too large", "depth_scale")


def test_export_of_depth_10x_off_stops_before_writing(ycb_mm, tmp_path, monkeypatch):
    monkeypatch.delenv(UNIT_CHECK_OFF, raising=False)
    out = tmp_path / "bop"
    args = ["export", "--data", str(ycb_mm), "--out", str(out), "--frames", "all", "--no-progress"]
    one_line_error(cli(*args), "10 times too small", "factor_depth")
    assert not out.exists()
    monkeypatch.setenv(UNIT_CHECK_OFF, "1")
    res = cli(*args)
    assert res.exit_code == 0, res.output
    assert "1 frames, 3 instances" in res.output


@pytest.mark.slow
def test_evaluate_on_data_10x_off_stops_in_one_line(smoke_project, ycb_mm, monkeypatch):
    _, out = smoke_project
    monkeypatch.delenv(UNIT_CHECK_OFF, raising=False)
    args = ["evaluate", "--run", out.run_id, "--data", str(ycb_mm), "--frames", "all"]
    one_line_error(cli(*args, "--no-progress"), "10 times too small", "factor_depth")
    monkeypatch.setenv(UNIT_CHECK_OFF, "1")
    res = cli(*args, "--no-progress", "--refine", "none")
    assert res.exit_code == 0, res.output
