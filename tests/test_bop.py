"""The BOP ycbv layout (cloudpose.data.bop): export, reading back, layout detection, the model
frame, the symmetry cross-check and the results CSV."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image
from typer.testing import CliRunner

from cloudpose.cli import app
from cloudpose.data.bop import (
    CSV_HEADER,
    BOPYcbv,
    bop_ids,
    check_results_csv,
    model_origin,
    read_ply_vertices,
    write_results_csv,
)
from cloudpose.data.cache import segments_for
from cloudpose.data.layout import describe_split, detect_layout, open_dataset
from cloudpose.data.synth.surfaces import load_packaged_models
from cloudpose.data.ycb import YCBVideo

REAL = Path(__file__).parent / "data" / "ycb_real"
FID = "0000/000001"


@pytest.fixture(scope="module")
def bop_real(tmp_path_factory) -> Path:
    """The real frame exported by the command line."""
    out = tmp_path_factory.mktemp("bop") / "ycbv"
    res = CliRunner().invoke(
        app,
        ["export", "--format", "bop", "--data", str(REAL), "--out", str(out), "--frames", "all"],
    )
    assert res.exit_code == 0, res.output
    assert "1 frames, 3 instances, 3 BOP19 targets" in res.output
    return out


def test_bop_reader_gives_the_ycb_frame_back(bop_real):
    a = YCBVideo(REAL).frame(FID, with_color=True)
    b = BOPYcbv(bop_real).frame(FID, with_color=True)
    for field in ("depth", "label", "K", "cls_ids", "color"):
        assert np.array_equal(getattr(a, field), getattr(b, field)), field
    np.testing.assert_allclose(b.poses, a.poses, atol=1e-12)
    assert b.frame_id == FID
    assert BOPYcbv(bop_real).image_set("keyframe") == [FID] == BOPYcbv(bop_real).image_set("all")


def test_bop_round_trip_gives_the_same_segments(bop_real, tmp_path):
    a = segments_for(REAL, "all", cache_dir=tmp_path / "a", workers=1, progress=False)
    b = segments_for(bop_real, "keyframe", cache_dir=tmp_path / "b", workers=1, progress=False)
    assert len(a) == len(b) == 3
    for name in a._ARRAYS:
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.data_key != b.data_key  # other files, other content key


def test_bop_files_follow_the_format(bop_real):
    scene = bop_real / "test" / "000000"
    gt = json.loads((scene / "scene_gt.json").read_text())["1"]
    cam = json.loads((scene / "scene_camera.json").read_text())["1"]
    info = json.loads((scene / "scene_gt_info.json").read_text())["1"]
    assert [g["obj_id"] for g in gt] == [8, 14, 21]
    assert cam["depth_scale"] == 0.1 and len(cam["cam_K"]) == 9
    label = YCBVideo(REAL).frame(FID).label
    for g, (e, i) in enumerate(zip(gt, info, strict=True)):
        assert len(e["cam_R_m2c"]) == 9 and 300 < e["cam_t_m2c"][2] < 2000  # millimetres
        visib = np.asarray(Image.open(scene / "mask_visib" / f"000001_{g:06d}.png")) > 0
        full = np.asarray(Image.open(scene / "mask" / f"000001_{g:06d}.png")) > 0
        assert i["px_count_visib"] == visib.sum() == (label == e["obj_id"]).sum()
        assert abs(int(full.sum()) - i["px_count_all"]) <= 0.01 * i["px_count_all"]
        assert 0 < i["visib_fract"] <= 1
    depth = np.asarray(Image.open(scene / "depth" / "000001.png"))
    raw = np.asarray(Image.open(REAL / "data" / "0000" / "000001-depth.png"))
    assert np.array_equal(depth, raw)  # depth_scale 0.1 mm keeps YCB-Video's numbers
    assert detect_layout(bop_real) == "bop" and detect_layout(REAL) == "ycb"
    assert describe_split(bop_real, "keyframe") == "BOP19 ycbv test targets (1 images)"
    assert describe_split(REAL, "keyframe") == "YCB-Video keyframe (2949 frames)"
    assert isinstance(open_dataset(bop_real), BOPYcbv)


def test_bop_models_are_the_toolbox_points_in_the_bop_frame(bop_real):
    ds = BOPYcbv(bop_real)
    assert ds.check_models() == []
    pts = ds.model_points(14)
    V = read_ply_vertices(bop_real / "models" / "obj_000014.ply")
    np.testing.assert_allclose(V, (pts - model_origin(pts)) * 1000, atol=1e-5)
    info = json.loads((bop_real / "models" / "models_info.json").read_text())
    assert abs(info["14"]["min_x"] + info["14"]["size_x"] / 2) < 1e-9  # origin = bbox centre
    # a model in another frame is reported
    shifted = bop_real.parent / "shifted"
    shutil.copytree(bop_real, shifted)
    text = (shifted / "models" / "obj_000014.ply").read_text().splitlines()
    head = text.index("end_header") + 1
    for k in range(head, head + len(V)):
        x, y, z = (float(v) for v in text[k].split())
        text[k] = f"{x + 10} {y} {z}"  # 10 mm off
    (shifted / "models" / "obj_000014.ply").write_text("\n".join(text) + "\n")
    (bad,) = BOPYcbv(shifted).check_models()
    assert "obj_000014.ply" in bad and "025_mug" in bad


def test_published_bop_offsets_are_the_point_sets_bounding_box_centres():
    """BOP's ycbv model origin: the bounding-box centre of the toolbox's points.xyz. Offsets
    (mm) as published in dornik/sporeagent dataset/ycbv_offsets.json (BOP pose -> toolbox)."""
    published = {
        1: [-1.3360000000000127, 0.5, -3.510499999999979],
        11: [-5.337000000000103, -5.885499999999979, -25.611499999999978],
        17: [-7.053500000000099, 28.131999999999977, -0.04200000000003001],
        21: [0.0805000000000291, -0.08049999999997226, 8.24350000000004],
    }
    models = load_packaged_models()
    for c, offset in published.items():
        np.testing.assert_allclose(model_origin(models[c]) * 1000, offset, atol=1e-9)


def test_bop_pose_is_read_in_the_toolbox_frame(bop_real, tmp_path):
    """A BOP pose written with the converters' formula (pose_toolbox = pose_bop @ [I | -c],
    4x4 matrices in mm) reads back as the toolbox pose."""
    root = tmp_path / "b"
    shutil.copytree(bop_real, root)
    truth = YCBVideo(REAL).frame(FID)
    models = load_packaged_models()
    gt_path = root / "test" / "000000" / "scene_gt.json"
    gt = json.loads(gt_path.read_text())
    for e, P in zip(gt["1"], truth.poses, strict=True):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = P[:, :3], 1000 * P[:, 3]
        undo = np.eye(4)
        undo[:3, 3] = -1000 * model_origin(models[e["obj_id"]])
        T_bop = T @ np.linalg.inv(undo)
        e["cam_R_m2c"], e["cam_t_m2c"] = T_bop[:3, :3].ravel().tolist(), T_bop[:3, 3].tolist()
    gt_path.write_text(json.dumps(gt))
    np.testing.assert_allclose(BOPYcbv(root).frame(FID).poses, truth.poses, atol=1e-12)


def test_bop_reader_refuses_bad_input(bop_real, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match=r"neither a YCB-Video layout.*nor a BOP"):
        open_dataset(empty)
    with pytest.raises(FileNotFoundError, match="nope"):
        detect_layout(tmp_path / "nope")
    with pytest.raises(ValueError, match="digits"):
        bop_ids("seq/frame")
    root = tmp_path / "b"
    shutil.copytree(bop_real, root)
    gt_path = root / "test" / "000000" / "scene_gt.json"
    gt = json.loads(gt_path.read_text())
    gt["1"][1]["obj_id"] = 8  # the same class twice
    gt_path.write_text(json.dumps(gt))
    with pytest.raises(ValueError, match=r"scene_gt\.json.*repeat"):
        BOPYcbv(root).frame(FID)
    del gt["1"][1]["cam_t_m2c"]
    gt["1"][1]["obj_id"] = 14
    gt_path.write_text(json.dumps(gt))
    with pytest.raises(ValueError, match="annotation 1: no field 'cam_t_m2c'"):
        BOPYcbv(root).frame(FID)
    with pytest.raises(ValueError, match="expected keyframe"):
        BOPYcbv(root).image_set("val")
    res = CliRunner().invoke(
        app, ["export", "--data", str(REAL), "--out", str(root), "--frames", "all"]
    )
    assert res.exit_code == 2 and "not empty" in res.output


def test_read_ply_vertices_binary(tmp_path):
    V = np.array([[1.0, 2.0, 3.0], [-4.5, 5.25, 6.0]])
    rec = np.zeros(
        2, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("red", "u1")]
    )
    rec["x"], rec["y"], rec["z"] = V.T
    head = (
        "ply\nformat binary_little_endian 1.0\ncomment t\nelement vertex 2\n"
        "property float x\nproperty float y\nproperty float z\nproperty float nx\n"
        "property uchar red\nelement face 0\nproperty list uchar int vertex_indices\n"
        "end_header\n"
    )
    path = tmp_path / "m.ply"
    path.write_bytes(head.encode() + rec.tobytes())
    np.testing.assert_array_equal(read_ply_vertices(path), V)
    path.write_text("ply\nformat ascii 1.0\nelement face 1\nend_header\n")
    with pytest.raises(ValueError, match="vertex element first"):
        read_ply_vertices(path)


# --------------------------------------------------------------------------- symmetries


def _flip_x() -> list[float]:
    return [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]


def _turn_z(deg: float) -> list[float]:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return [c, -s, 0, 0, s, c, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]


def test_symmetry_cross_check_reports_disagreements():
    """A models_info.json written here in BOP's structure (4x4 row-major discrete rotations,
    translations in mm; continuous {axis, offset}); the published ycbv file is not stored in
    the repository, so the entries follow the format, not BOP's values."""
    from cloudpose.conventions import resource_path
    from cloudpose.data.ycb import load_classes
    from cloudpose.geometry.symmetry import bop_symmetry_disagreements

    names = load_classes(resource_path("classes.txt"))
    info = {
        "1": {
            "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
            "symmetries_discrete": [_flip_x()],
        },  # a can with flip: agrees
        "13": {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]},  # bowl
        "8": {"symmetries_discrete": [_turn_z(180)]},  # gelatin box: table 2 has 3 half-turns
        "14": {"symmetries_discrete": [_turn_z(180)]},  # mug: none in the table
        "5": {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]},  # can, no flip
        "2": {"symmetries_discrete": [_flip_x()]},  # box: the table has 3 half-turns
    }
    diffs = bop_symmetry_disagreements(info, names)
    assert len(diffs) == 4, diffs
    assert any(d.startswith("009_gelatin_box (obj 8): different rotations") for d in diffs)
    # table 1 turned the gelatin box about z only, as this file does
    assert len(bop_symmetry_disagreements(info, names, table=1)) == 3
    assert any(d.startswith("025_mug (obj 14): different kind") for d in diffs)
    assert any(d.startswith("006_mustard_bottle (obj 5): different kind") for d in diffs)
    assert any(d.startswith("003_cracker_box (obj 2): different rotations") for d in diffs)


def test_exported_models_info_agrees_with_the_table(bop_real):
    from cloudpose.conventions import resource_path
    from cloudpose.data.ycb import load_classes
    from cloudpose.geometry.symmetry import bop_symmetry_disagreements

    info = json.loads((bop_real / "models" / "models_info.json").read_text())
    assert bop_symmetry_disagreements(info, load_classes(resource_path("classes.txt"))) == []
    res = CliRunner().invoke(app, ["symmetries", "--bop", str(bop_real)])
    assert res.exit_code == 0, res.output
    assert "0 classes differ" in res.output


# --------------------------------------------------------------------------- results CSV


def _table() -> pd.DataFrame:
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([[0.1, 0.2, 0.3], [0.0, 0.0, 0.0], [1.0, 0, 0]]).as_matrix()
    t = np.array([[0.1, 0.0, 0.8], [0.0, 0.1, 0.9], [0, 0, 1.0]])
    return pd.DataFrame(
        {
            "frame_id": ["0048/000001", "0048/000001", "0049/000010"],
            "cls_id": [1, 14, 21],
            "miss": [False, False, True],
            "icp_R": [" ".join(f"{v:.17g}" for v in r.ravel()) for r in R[:2]] + [""],
            "icp_t": [" ".join(f"{v:.17g}" for v in x) for x in t[:2]] + [""],
        }
    )


def test_results_csv_is_bop_and_in_the_bop_frame(tmp_path):
    path = tmp_path / "r.csv"
    assert write_results_csv(_table(), path, "icp", seconds_per_object=0.002) == 2
    assert check_results_csv(path) == []
    lines = path.read_text().splitlines()
    assert lines[0] == CSV_HEADER
    f = lines[1].split(",")
    assert f[:4] == ["48", "1", "1", "1"] and f[6] == lines[2].split(",")[6] == "0.004"
    R = np.array(f[4].split(), float).reshape(3, 3)
    c = model_origin(load_packaged_models()[1])
    np.testing.assert_allclose(
        np.array(f[5].split(), float), 1000 * (np.array([0.1, 0, 0.8]) + R @ c), atol=1e-5
    )
    with pytest.raises(ValueError, match="net_R"):
        write_results_csv(_table(), path, "net")


@pytest.mark.parametrize(
    "line, problem",
    [
        ("48,2,1,1,1 0 0 0 1 0 0 0 1,0 0 800", "7"),
        ("48,2,1,1,1 0 0 0 1 0 0 0,0 0 800,-1", "R has 8"),
        ("48,2,1,1,2 0 0 0 1 0 0 0 1,0 0 800,-1", "not a rotation"),
        ("48,2,1,1,1 0 0 0 1 0 0 0 -1,0 0 800,-1", "not a rotation"),
        ("48,2,1,1,1 0 0 0 1 0 0 0 1,0 0 0.8,-1", "millimetres"),
        ("48,2,1,1,1 0 0 0 1 0 0 0 1,0 0 800,-2", "time -2"),
        ("48,2,0,1,1 0 0 0 1 0 0 0 1,0 0 800,-1", "obj_id >= 1"),
        ("48,1,2,1,1 0 0 0 1 0 0 0 1,0 0 800,0.5", "one time per image"),
    ],
)
def test_results_csv_check_finds_each_rule(tmp_path, line, problem):
    path = tmp_path / "r.csv"
    path.write_text(f"{CSV_HEADER}\n48,1,1,1,1 0 0 0 1 0 0 0 1,0 0 800,0.1\n{line}\n")
    problems = check_results_csv(path)
    assert len(problems) == 1 and problem in problems[0] and "line 3" in problems[0]
    path.write_text("scene_id,im_id,obj_id,R,t\n")
    assert "header" in check_results_csv(path)[0]


@pytest.mark.slow
def test_smoke_run_bop_csv_and_both_layouts_agree(smoke_project, bop_real, tmp_path):
    """The BOP results CSV of a smoke run passes the format check; the real frame evaluated
    from the BOP export gives the YCB-Video layout's errors, and each names its split."""
    from cloudpose.store import tracking

    proj, out = smoke_project
    csv = tmp_path / "smoke_ycbv-test.csv"
    res = CliRunner().invoke(
        app,
        [
            "evaluate",
            "--run",
            str(out.run_dir),
            "--data",
            str(bop_real),
            "--bop-csv",
            str(csv),
            "--no-progress",
        ],
    )
    assert res.exit_code == 0, res.output
    assert "BOP19 ycbv test targets (1 images)" in res.output
    assert check_results_csv(csv) == [] and len(csv.read_text().splitlines()) == 4
    from cloudpose.evaluate import evaluate

    ycb = evaluate(str(out.run_dir), data=str(REAL), frames="all", progress=False)
    bop = evaluate(str(out.run_dir), data=str(bop_real), frames="keyframe", progress=False)
    assert ycb.split == "YCB-Video all (1 frames)"
    cols = ["net_ad", "net_ads", "icp_ad", "icp_ads", "occlusion", "points"]
    np.testing.assert_allclose(bop.table[cols].to_numpy(), ycb.table[cols].to_numpy(), atol=1e-9)
    tags = tracking.setup(proj).get_run(out.run_id).data.tags
    assert tags[f"eval/{bop.name}/split"] == "BOP19 ycbv test targets (1 images)"


def test_a_scene_without_ground_truth_is_named_not_left_out(bop_real, tmp_path):
    """`--frames all` (and train_real/) refuses a scene folder without scene_gt.json, naming
    it and the count, instead of evaluating the other scenes' instances without a word."""
    root = tmp_path / "b"
    shutil.copytree(bop_real, root)
    bare = root / "test" / "000001"
    shutil.copytree(root / "test" / "000000", bare)
    (bare / "scene_gt.json").unlink()
    with pytest.raises(FileNotFoundError) as info:
        BOPYcbv(root).image_set("all")
    message = str(info.value)
    assert str(bare / "scene_gt.json") in message and "1 of 2 scenes" in message
    res = CliRunner().invoke(
        app,
        [
            "baseline",
            "--method",
            "fpfh",
            "--preset",
            "smoke",
            "--data",
            str(root),
            "--frames",
            "all",
            "--no-progress",
        ],
    )
    assert res.exit_code == 2 and "000001/scene_gt.json: ground truth not found" in res.output
    assert BOPYcbv(root).image_set("keyframe") == [FID]  # the targets name scene 0 only
    shutil.rmtree(bare)
    assert BOPYcbv(root).image_set("all") == [FID]


def test_exported_symmetries_map_each_model_onto_itself_in_the_bop_frame():
    """A symmetry about a centre off the bounding-box centre (the clamp's turn about its
    centroid) is exported with its translation: the 4x4 maps the BOP-frame model points onto
    themselves, as BOP's own symmetries do."""
    from scipy.spatial import cKDTree

    from cloudpose.conventions import resource_path
    from cloudpose.data.bop import model_origin, models_info
    from cloudpose.data.ycb import load_classes

    names = load_classes(resource_path("classes.txt"))
    pick = [names.index(n) + 1 for n in ("051_large_clamp", "008_pudding_box", "011_banana")]
    models = {c: np.loadtxt(resource_path("models", names[c - 1], "points.xyz")) for c in pick}
    info = models_info(models, names)
    for c in pick:
        V = (models[c] - model_origin(models[c])) * 1000.0  # mm, BOP frame
        diameter = info[str(c)]["diameter"]
        assert info[str(c)].get("symmetries_discrete"), names[c - 1]
        for m in info[str(c)]["symmetries_discrete"]:
            T = np.asarray(m).reshape(4, 4)
            d, _ = cKDTree(V).query(V @ T[:3, :3].T + T[:3, 3])
            assert np.percentile(d, 95) < 0.06 * diameter, names[c - 1]
            # without the translation the clamp's turn would not map it onto itself
            if names[c - 1] == "051_large_clamp":
                d0, _ = cKDTree(V).query(V @ T[:3, :3].T)
                assert np.percentile(d0, 95) > 2 * np.percentile(d, 95)
