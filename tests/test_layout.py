"""Which layout a dataset folder has (cloudpose.data.layout): YCB-Video or BOP ycbv."""

from __future__ import annotations

from pathlib import Path

import pytest

from cloudpose.data.bop import BOPYcbv, export_bop
from cloudpose.data.layout import describe_split, detect_layout, open_dataset
from cloudpose.data.ycb import YCBVideo

REAL = Path(__file__).parent / "data" / "ycb_real"


def _ycb(root: Path, frames: list[str], synthetic: bool = False) -> Path:
    root.mkdir()
    (root / "keyframe.txt").write_text("".join(f"{f}\n" for f in frames))
    if synthetic:
        (root / "synth.json").write_text("{}")
    return root


def test_ycb_layout_is_told_by_its_files(tmp_path):
    assert detect_layout(REAL) == "ycb"
    assert isinstance(open_dataset(REAL), YCBVideo)
    for marker in ("data", "image_sets"):
        (tmp_path / marker).mkdir()
        assert detect_layout(tmp_path) == "ycb"
        (tmp_path / marker).rmdir()
    (tmp_path / "classes.txt").write_text("")
    assert detect_layout(tmp_path) == "ycb"


@pytest.mark.parametrize("split_dir", ["test", "train_real"])
def test_bop_layout_is_told_by_a_scene_or_the_targets(tmp_path, split_dir):
    scene = tmp_path / split_dir / "000048"
    scene.mkdir(parents=True)
    with pytest.raises(ValueError, match="neither"):  # a scene folder without its scene_gt.json
        detect_layout(tmp_path)
    (scene / "scene_gt.json").write_text("{}")
    assert detect_layout(tmp_path) == "bop"
    other = tmp_path.parent / f"targets-{split_dir}"
    other.mkdir()
    (other / "test_targets_bop19.json").write_text("[]")
    assert detect_layout(other) == "bop"


@pytest.mark.slow
def test_bop_folders_open_as_bop(tmp_path):
    bop = tmp_path / "ycbv"
    export_bop(REAL, bop, frames="all", progress=False)
    assert detect_layout(bop) == "bop"
    assert isinstance(open_dataset(bop), BOPYcbv)
    assert describe_split(bop, "keyframe") == "BOP19 ycbv test targets (1 images)"
    assert describe_split(bop, "all") == "BOP ycbv test (1 images)"


def test_neither_layout_names_the_folder(tmp_path):
    with pytest.raises(ValueError, match=f"{tmp_path}: neither a YCB-Video layout"):
        detect_layout(tmp_path)
    with pytest.raises(FileNotFoundError, match="dataset root not found"):
        detect_layout(tmp_path / "missing")


def test_describe_split_names_the_frame_list_and_its_size(tmp_path):
    real = _ycb(tmp_path / "real", ["0001/000001", "0001/000002"])
    assert describe_split(real, "keyframe") == "YCB-Video keyframe (2 frames)"
    assert describe_split(real, "test") == "YCB-Video keyframe (2 frames)"  # test = keyframe
    synth = _ycb(tmp_path / "synth", ["1000/000001"], synthetic=True)
    assert describe_split(synth, "test") == "synthetic YCB-Video-layout keyframe (1 frames)"
    assert describe_split(REAL, "all") == "YCB-Video all (1 frames)"
