"""PoseCNN's released segmentation as a mask source (cloudpose.data.posecnn), on a tiny results
folder written here for the real frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io

from cloudpose.data.mask_sources import get_mask_source, mask_source_label
from cloudpose.data.posecnn import PoseCNNMasks
from cloudpose.data.segments import extract_segments
from cloudpose.data.ycb import YCBVideo

REAL = Path(__file__).parent / "data" / "ycb_real"
FID = "0000/000001"


@pytest.fixture(scope="module")
def frame():
    return YCBVideo(REAL).frame(FID)


def write_results(folder: Path, frame, detected: list[int], line: int = 1) -> Path:
    """A results folder whose keyframe list has the real frame on ``line`` (0-based): PoseCNN's
    labels are the ground truth's, its rois list ``detected`` (class id in column 2), and
    every other line's file is absent."""
    folder.mkdir(parents=True, exist_ok=True)
    others = [f"0099/{i:06d}" for i in range(line)]
    (folder / "keyframe.txt").write_text("\n".join([*others, FID]) + "\n")
    rois = np.zeros((len(detected), 6))
    rois[:, 1] = detected  # MATLAB column 2
    rois[:, 2:] = [10, 20, 100, 200]
    scipy.io.savemat(
        folder / f"{line:06d}.mat", {"labels": frame.label.astype(np.int32), "rois": rois}
    )
    return folder


def test_file_of_a_frame_is_its_keyframe_line(tmp_path, frame):
    src = PoseCNNMasks(write_results(tmp_path / "r", frame, [8, 14, 21], line=2))
    assert src.path(FID) == tmp_path / "r" / "000002.mat"
    with pytest.raises(FileNotFoundError, match=r"000000\.mat"):
        src.content_files("0099/000000")
    with pytest.raises(ValueError, match="not in"):
        src.path("0048/000001")
    # without a list of its own, the toolbox's keyframes that ship in the package
    bare = tmp_path / "bare"
    bare.mkdir()
    assert PoseCNNMasks(bare).path("0048/000036") == bare / "000001.mat"
    assert PoseCNNMasks(bare).path("0059/001857") == bare / "002948.mat"


def test_masks_are_posecnn_labels_of_detected_classes(tmp_path, frame):
    folder = write_results(tmp_path / "results_PoseCNN_RSS2018", frame, [8, 21])
    name = f"posecnn:{folder}"
    src = get_mask_source(name)
    assert mask_source_label(name) == "posecnn-results_PoseCNN_RSS2018"
    assert np.array_equal(src(frame, 8), frame.label == 8)
    assert np.array_equal(src(frame, 21), frame.label == 21)
    assert not src(frame, 14).any()  # labelled but not among the rois: no mask
    segs = extract_segments(frame, segmentation=name, rng=np.random.default_rng(0))
    valid = {s.cls_id: s.valid for s in segs}
    assert valid == {8: True, 14: False, 21: True}  # the undetected mug is a miss
    gt = extract_segments(frame, rng=np.random.default_rng(0))
    assert np.array_equal(segs[0].points, gt[0].points)


def test_bad_results_are_named(tmp_path, frame):
    with pytest.raises(FileNotFoundError, match="PoseCNN results folder"):
        get_mask_source(f"posecnn:{tmp_path / 'nope'}")
    folder = write_results(tmp_path / "r", frame, [8], line=0)
    scipy.io.savemat(folder / "000000.mat", {"labels": np.zeros((4, 4)), "rois": np.zeros((0, 6))})
    with pytest.raises(ValueError, match="labels have shape"):
        PoseCNNMasks(folder)(frame, 8)
    scipy.io.savemat(folder / "000000.mat", {"labels": frame.label})
    with pytest.raises(ValueError, match="no field 'rois'"):
        PoseCNNMasks(folder)(frame, 8)
    with pytest.raises(ValueError, match="posecnn:DIR"):
        get_mask_source("posecnn-typo")


def test_posecnn_results_are_part_of_the_cache_key(tmp_path, frame):
    from cloudpose.config import DataConfig
    from cloudpose.data.cache import cache_key

    folder = write_results(tmp_path / "r", frame, [8, 21], line=0)
    cfg = DataConfig(segmentation=f"posecnn:{folder}")
    key = cache_key(REAL, "all", cfg)
    assert key != cache_key(REAL, "all", DataConfig())
    write_results(folder, frame, [8, 14, 21], line=0)
    assert cache_key(REAL, "all", cfg) != key


@pytest.mark.slow
def test_evaluate_with_posecnn_masks_counts_undetected_objects_as_misses(
    smoke_project, tmp_path, frame
):
    """cloudpose evaluate --masks posecnn:DIR: the instance PoseCNN did not detect is a miss in
    every error and AUC; the others are scored as with ground-truth masks."""
    from typer.testing import CliRunner

    from cloudpose.cli import app
    from cloudpose.evaluate import evaluate
    from cloudpose.store import tracking

    proj, out = smoke_project
    folder = write_results(tmp_path / "results_PoseCNN_RSS2018", frame, [8, 21], line=0)
    gt = evaluate(str(out.run_dir), data=str(REAL), frames="all", progress=False)
    res = CliRunner().invoke(
        app,
        [
            "evaluate",
            "--run",
            str(out.run_dir),
            "--data",
            str(REAL),
            "--frames",
            "all",
            "--masks",
            f"posecnn:{folder}",
            "--no-progress",
        ],
    )
    assert res.exit_code == 0, res.output
    ev = evaluate(
        str(out.run_dir),
        data=str(REAL),
        frames="all",
        segmentation=f"posecnn:{folder}",
        progress=False,
    )
    assert ev.name.endswith("-posecnn-results_PoseCNN_RSS2018") and ev.name in res.output
    t = ev.table.set_index("class")
    assert bool(t.loc["025_mug", "miss"]) and not t.drop("025_mug")["miss"].any()
    for col in ("net_ad", "net_ads", "icp_ad", "icp_ads", "icp_rot_err_deg", "icp_trans_err"):
        assert np.isinf(t.loc["025_mug", col])
    # the first instance's segment is the ground truth's (later ones draw other FPS starts:
    # the miss draws none)
    g = gt.table.set_index("class")
    assert t.loc["009_gelatin_box", "icp_ads"] == pytest.approx(g.loc["009_gelatin_box", "icp_ads"])
    assert not g["miss"].any()
    assert ev.metrics[f"{ev.name}_icp/ads_auc"] <= gt.metrics[f"{gt.name}_icp/ads_auc"]
    tags = tracking.setup(proj).get_run(out.run_id).data.tags
    assert tags[f"eval/{ev.name}/segmentation"] == f"posecnn:{folder}"
