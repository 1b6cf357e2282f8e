"""YCB-Video reader/writer: the real annotated frame, round trips, and every bad-input case."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from PIL import Image

from cloudpose.conventions import YCB_INTRINSICS, resource_path
from cloudpose.data import ycb
from cloudpose.data.ycb import (
    DegenerateDataWarning,
    YCBVideo,
    load_classes,
    load_model_points,
    read_frame,
    write_frame,
)

REAL = Path(__file__).parent / "data" / "ycb_real"
DEMO = Path(__file__).parent / "data" / "demo_no_gt"
FID = "0000/000001"


@pytest.fixture(scope="module")
def real():
    return YCBVideo(REAL).frame(FID, with_color=True)


@pytest.fixture
def copy_root(tmp_path) -> Path:
    """A writable copy of the real dataset root, to corrupt."""
    root = tmp_path / "ycb"
    shutil.copytree(REAL, root)
    return root


def frame_file(root: Path, kind: str) -> Path:
    return root / "data" / "0000" / f"000001-{kind}.{'mat' if kind == 'meta' else 'png'}"


def edit_meta(root: Path, **changes) -> None:
    path = frame_file(root, "meta")
    meta = {k: v for k, v in scipy.io.loadmat(path).items() if not k.startswith("__")}
    for k, v in changes.items():
        if v is None:
            meta.pop(k)
        else:
            meta[k] = v
    scipy.io.savemat(path, meta)


# --------------------------------------------------------------------------- the real frame


def test_real_frame_fields(real):
    ds = YCBVideo(REAL)
    assert [ds.classes[c - 1] for c in real.cls_ids] == [
        "009_gelatin_box",
        "025_mug",
        "061_foam_brick",
    ]
    assert real.frame_id == FID
    assert real.cls_ids.dtype == np.int64
    assert real.depth.shape == real.label.shape == (480, 640)
    assert real.depth.dtype == np.float32 and real.label.dtype == np.uint8
    assert real.color.shape == (480, 640, 3) and real.color.dtype == np.uint8
    assert real.poses.shape == (3, 3, 4) and real.poses.dtype == np.float64
    np.testing.assert_allclose(real.K, YCB_INTRINSICS)
    assert set(np.unique(real.label)) == {0, 8, 14, 21}
    # raw PNG value / 10000 = metres: a table-top scene 0.5 .. 2 m away
    raw = np.asarray(Image.open(frame_file(REAL, "depth")))
    np.testing.assert_array_equal(real.depth, (raw / 10000.0).astype(np.float32))
    assert 0.4 < np.median(real.depth[real.label > 0]) < 1.0
    for R in real.poses[:, :, :3]:
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)
        assert np.linalg.det(R) > 0


def test_real_frame_geometry_is_consistent(real):
    """Back-projected object pixels lie on the posed model points (checks K, depth units, the
    pose direction model->camera)."""
    from pykdtree.kdtree import KDTree

    ds = YCBVideo(REAL)
    K = real.K
    for c, P in zip(real.cls_ids, real.poses, strict=True):
        v, u = np.nonzero((real.label == c) & (real.depth > 0))
        z = real.depth[v, u].astype(np.float64)
        X = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
        model_cam = ds.model_points(c) @ P[:, :3].T + P[:, 3]
        d, _ = KDTree(model_cam).query(X)
        assert np.median(d) < 0.005, (c, np.median(d))


def test_dataset_lists_and_models():
    ds = YCBVideo(REAL)
    assert ds.classes == load_classes(resource_path("classes.txt"))
    assert len(ds.classes) == 21
    keys = ds.image_set("keyframe")
    assert keys[0] == "0048/000001" and all(len(k.split("/")) == 2 for k in keys)
    models = ds.models()
    assert sorted(models) == list(range(1, 22))
    for pts in models.values():
        assert pts.ndim == 2 and pts.shape[1] == 3 and pts.shape[0] > 2000
        assert 0.01 < np.ptp(pts, axis=0).max() < 0.5  # metres
    assert ds.model_points(14) is ds.model_points(14)  # cached


def test_models_root_precedence(tmp_path):
    root = tmp_path / "r"
    (root / "data").mkdir(parents=True)
    mroot = tmp_path / "m" / "025_mug"
    mroot.mkdir(parents=True)
    (mroot / "points.xyz").write_text("0 0 0\n0.1 0 0\n0 0.1 0\n")
    ds = YCBVideo(root, models_root=tmp_path / "m")
    assert ds.model_points(14).shape == (3, 3)
    (root / "models" / "025_mug").mkdir(parents=True)
    (root / "models" / "025_mug" / "points.xyz").write_text("0 0 0\n")
    assert YCBVideo(root, models_root=tmp_path / "m").model_points(14).shape == (1, 3)
    assert YCBVideo(root).models_root == root / "models"


def test_image_set(tmp_path):
    (tmp_path / "image_sets").mkdir()
    (tmp_path / "image_sets" / "train.txt").write_text("0000/000001\n\n0001/000010\n")
    ds = YCBVideo(tmp_path)
    assert ds.image_set("train") == ["0000/000001", "0001/000010"]
    with pytest.raises(FileNotFoundError, match=r"val"):
        ds.image_set("val")
    (tmp_path / "image_sets" / "bad.txt").write_text("0000/000001\n000002\n")
    with pytest.raises(ValueError, match=r"bad\.txt, line 2"):
        ds.image_set("bad")


# --------------------------------------------------------------------------- round trips


def test_write_frame_reads_back_identically(real, tmp_path):
    write_frame(
        tmp_path,
        "0003/000042",
        real.depth,
        real.label,
        real.K,
        real.cls_ids,
        real.poses,
        color=real.color,
    )
    back = YCBVideo(tmp_path).frame("0003/000042", with_color=True)
    np.testing.assert_array_equal(back.depth, real.depth)  # sensor depth is already 0.1 mm
    np.testing.assert_array_equal(back.label, real.label)
    np.testing.assert_array_equal(back.cls_ids, real.cls_ids)
    np.testing.assert_array_equal(back.poses, real.poses)
    np.testing.assert_array_equal(back.K, real.K)
    np.testing.assert_array_equal(back.color, real.color)
    meta = scipy.io.loadmat(frame_file(tmp_path, "meta").parent.parent / "0003" / "000042-meta.mat")
    assert meta["cls_indexes"].shape == (3, 1) and meta["poses"].shape == (3, 4, 3)
    assert not list(tmp_path.rglob("*.tmp"))


def test_depth_png_is_16_bit_exact(tmp_path):
    rng = np.random.default_rng(0)
    raw = rng.integers(0, 65536, size=(7, 9)).astype(np.uint16)
    raw[0, :3] = [0, 1, 65535]
    depth = raw / 10000.0
    label = np.zeros((7, 9), np.uint8)
    write_frame(tmp_path, "a/b", depth, label, YCB_INTRINSICS, [], np.zeros((0, 3, 4)))
    png = tmp_path / "data" / "a" / "b-depth.png"
    assert Image.open(png).mode == "I;16"
    np.testing.assert_array_equal(np.asarray(Image.open(png)), raw)
    back = YCBVideo(tmp_path).frame("a/b")
    np.testing.assert_array_equal(back.depth, (raw / 10000.0).astype(np.float32))
    assert back.cls_ids.shape == (0,) and back.poses.shape == (0, 3, 4)


def test_write_frame_quantises_depth_to_a_tenth_millimetre(tmp_path):
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.3, 2.0, size=(6, 5))
    write_frame(tmp_path, "s/f", depth, np.zeros((6, 5)), YCB_INTRINSICS, [], np.zeros((0, 3, 4)))
    back = YCBVideo(tmp_path).frame("s/f")
    assert np.abs(back.depth - depth).max() <= 0.5e-4 + 1e-6


def test_write_frame_extra_meta_fields(tmp_path):
    empty = (np.zeros((6, 5)), np.zeros((6, 5)), YCB_INTRINSICS, [], np.zeros((0, 3, 4)))
    write_frame(tmp_path, "s/f", *empty, extra_meta={"alone_pixels": np.zeros((0, 1))})
    meta = scipy.io.loadmat(tmp_path / "data" / "s" / "f-meta.mat")
    assert "alone_pixels" in meta and meta["alone_pixels"].size == 0
    assert float(meta["factor_depth"][0, 0]) == 10000.0
    with pytest.raises(ValueError, match=r"extra_meta may not replace the fields \['poses'\]"):
        write_frame(tmp_path, "s/g", *empty, extra_meta={"poses": np.zeros((3, 4, 0))})
    assert not (tmp_path / "data" / "s" / "g-depth.png").exists()  # refused before writing


def test_single_object_meta_with_matlab_2d_poses(tmp_path, real):
    """MATLAB stores a 3x4x1 array as 3x4: one-object frames must still read."""
    write_frame(
        tmp_path,
        "0000/000001",
        real.depth,
        np.where(real.label == 14, 14, 0),
        real.K,
        [14],
        real.poses[1:2],
    )
    edit_meta(tmp_path, poses=real.poses[1])
    f = YCBVideo(tmp_path).frame("0000/000001")
    assert f.poses.shape == (1, 3, 4)
    np.testing.assert_array_equal(f.poses[0], real.poses[1])


def test_read_frame_loose_files_without_meta():
    f = read_frame(
        DEMO / "depth.png", DEMO / "label.png", color_png=DEMO / "color.png", K=YCB_INTRINSICS
    )
    assert f.poses is None
    np.testing.assert_array_equal(f.cls_ids, [2, 4, 5, 10, 15])
    assert f.color.shape == (480, 640, 3)
    with pytest.raises(ValueError, match=r"depth\.png.*K"):
        read_frame(DEMO / "depth.png", DEMO / "label.png")


def test_read_frame_with_meta_matches_dataset(real):
    d = REAL / "data" / "0000"
    f = read_frame(
        d / "000001-depth.png", d / "000001-label.png", d / "000001-meta.mat", K=YCB_INTRINSICS
    )
    np.testing.assert_array_equal(f.depth, real.depth)
    np.testing.assert_array_equal(f.poses, real.poses)
    with pytest.raises(ValueError, match=r"disagrees"):
        read_frame(
            d / "000001-depth.png",
            d / "000001-label.png",
            d / "000001-meta.mat",
            K=YCB_INTRINSICS * 1.1 + np.diag([0, 0, -0.1]),
        )


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("kind", ["depth", "label", "meta"])
def test_missing_file(copy_root, kind):
    frame_file(copy_root, kind).unlink()
    with pytest.raises(FileNotFoundError, match=rf"000001-{kind}"):
        YCBVideo(copy_root).frame(FID)


def test_missing_color_only_when_asked(copy_root):
    frame_file(copy_root, "color").unlink()
    YCBVideo(copy_root).frame(FID)
    with pytest.raises(FileNotFoundError, match=r"color"):
        YCBVideo(copy_root).frame(FID, with_color=True)


@pytest.mark.parametrize("kind", ["depth", "label"])
def test_corrupt_png(copy_root, kind):
    path = frame_file(copy_root, kind)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # truncated
    with pytest.raises(ValueError, match=rf"000001-{kind}.png.*not a readable PNG"):
        YCBVideo(copy_root).frame(FID)
    path.write_bytes(b"not a png at all")
    with pytest.raises(ValueError, match=rf"000001-{kind}.png"):
        YCBVideo(copy_root).frame(FID)


def test_corrupt_meta(copy_root):
    frame_file(copy_root, "meta").write_bytes(b"garbage" * 10)
    with pytest.raises(ValueError, match=r"000001-meta.mat.*not a readable"):
        YCBVideo(copy_root).frame(FID)


def test_depth_png_of_wrong_bit_depth(copy_root):
    Image.fromarray(np.zeros((480, 640), np.uint8)).save(frame_file(copy_root, "depth"))
    with pytest.raises(ValueError, match=r"depth.*mode 'L'.*16-bit"):
        YCBVideo(copy_root).frame(FID)


def test_label_png_of_wrong_mode(copy_root):
    Image.fromarray(np.zeros((480, 640, 3), np.uint8)).save(frame_file(copy_root, "label"))
    with pytest.raises(ValueError, match=r"label.*mode 'RGB'"):
        YCBVideo(copy_root).frame(FID)


def test_mismatched_image_shapes(copy_root):
    lab = np.asarray(Image.open(frame_file(copy_root, "label")))
    Image.fromarray(lab[:-1]).save(frame_file(copy_root, "label"))
    with pytest.raises(ValueError, match=r"label.*\(479, 640\).*\(480, 640\)"):
        YCBVideo(copy_root).frame(FID)
    frame_file(copy_root, "label").unlink()
    shutil.copy(frame_file(REAL, "label"), frame_file(copy_root, "label"))
    col = np.asarray(Image.open(frame_file(copy_root, "color")))
    Image.fromarray(col[:, :-2]).save(frame_file(copy_root, "color"))
    with pytest.raises(ValueError, match=r"color"):
        YCBVideo(copy_root).frame(FID, with_color=True)


def test_label_class_not_in_meta(copy_root):
    edit_meta(
        copy_root,
        cls_indexes=np.array([[8], [14]]),
        poses=scipy.io.loadmat(frame_file(REAL, "meta"))["poses"][:, :, :2],
    )
    with pytest.raises(ValueError, match=r"label.*\[21\].*cls_indexes"):
        YCBVideo(copy_root).frame(FID)


def test_class_id_out_of_range(copy_root):
    edit_meta(copy_root, cls_indexes=np.array([[8], [14], [22]]))
    with pytest.raises(ValueError, match=r"cls_indexes.*\[22\].*1\.\.21"):
        YCBVideo(copy_root).frame(FID)
    edit_meta(copy_root, cls_indexes=np.array([[8], [14], [0]]))
    with pytest.raises(ValueError, match=r"cls_indexes.*\[0\]"):
        YCBVideo(copy_root).frame(FID)


def test_label_id_out_of_range(copy_root):
    lab = np.asarray(Image.open(frame_file(copy_root, "label"))).copy()
    lab[0, 0] = 40
    Image.fromarray(lab).save(frame_file(copy_root, "label"))
    with pytest.raises(ValueError, match=r"label ids \[40\] out of range"):
        YCBVideo(copy_root).frame(FID)


def test_pose_count_mismatch(copy_root):
    poses = scipy.io.loadmat(frame_file(REAL, "meta"))["poses"]
    edit_meta(copy_root, poses=poses[:, :, :2])
    with pytest.raises(ValueError, match=r"poses has 2 poses but cls_indexes lists 3"):
        YCBVideo(copy_root).frame(FID)


@pytest.mark.parametrize("bad", ["scaled", "reflection", "nan"])
def test_pose_not_a_rotation(copy_root, bad):
    poses = scipy.io.loadmat(frame_file(REAL, "meta"))["poses"].copy()
    if bad == "scaled":
        poses[:, :3, 1] *= 1.01
    elif bad == "reflection":
        poses[:, :3, 1] = -poses[:, :3, 1]
    else:
        poses[0, 3, 1] = np.nan
    edit_meta(copy_root, poses=poses)
    msg = "NaN" if bad == "nan" else "pose 1 is not a rotation"
    with pytest.raises(ValueError, match=rf"meta.mat: poses.*{msg}"):
        YCBVideo(copy_root).frame(FID)


def test_small_rotation_noise_is_accepted(copy_root):
    poses = scipy.io.loadmat(frame_file(REAL, "meta"))["poses"].copy()
    poses[:, :3, 0] *= 1 + 2e-4
    edit_meta(copy_root, poses=poses)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        frame = YCBVideo(copy_root).frame(FID)
    # accepted as given: the rotations are read, not silently re-orthonormalised
    np.testing.assert_allclose(frame.poses[0, :, :3], poses[:, :3, 0])


@pytest.mark.parametrize("field", ["cls_indexes", "poses", "intrinsic_matrix", "factor_depth"])
def test_missing_meta_field(copy_root, field):
    edit_meta(copy_root, **{field: None})
    with pytest.raises(ValueError, match=rf"meta.mat: meta has no field '{field}'"):
        YCBVideo(copy_root).frame(FID)


def test_bad_intrinsics_and_factor(copy_root):
    edit_meta(copy_root, intrinsic_matrix=np.eye(3)[:2])
    with pytest.raises(ValueError, match=r"intrinsic_matrix.*\(2, 3\)"):
        YCBVideo(copy_root).frame(FID)
    edit_meta(copy_root, intrinsic_matrix=YCB_INTRINSICS, factor_depth=np.array([[0.0]]))
    with pytest.raises(ValueError, match=r"factor_depth"):
        YCBVideo(copy_root).frame(FID)


def test_bad_frame_ids_and_roots(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"dataset root"):
        YCBVideo(tmp_path / "nope")
    ds = YCBVideo(REAL)
    with pytest.raises(ValueError, match=r"SEQ/FRAME"):
        ds.frame("000001")
    with pytest.raises(ValueError, match=r"1\.\.21"):
        ds.model_points(22)


def test_bad_class_and_point_files(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"classes.txt"):
        load_classes(tmp_path / "classes.txt")
    (tmp_path / "classes.txt").write_text("\n\n")
    with pytest.raises(ValueError, match=r"empty"):
        load_classes(tmp_path / "classes.txt")
    (tmp_path / "classes.txt").write_text("a\nb\na\n")
    with pytest.raises(ValueError, match=r"twice"):
        load_classes(tmp_path / "classes.txt")
    pts = tmp_path / "points.xyz"
    with pytest.raises(FileNotFoundError, match=r"points.xyz"):
        load_model_points(pts)
    pts.write_text("0 0\n1 1\n")
    with pytest.raises(ValueError, match=r"points.xyz.*2 columns, expected 3"):
        load_model_points(pts)
    pts.write_text("0 0 x\n")
    with pytest.raises(ValueError, match=r"points.xyz.*cannot parse"):
        load_model_points(pts)
    pts.write_text("")
    with pytest.raises(ValueError, match=r"points.xyz.*no model points"):
        load_model_points(pts)
    pts.write_text("0 0 0\n100 0 0\n")  # millimetres, not metres
    with pytest.raises(ValueError, match=r"points.xyz.*metres"):
        load_model_points(pts)


def test_write_frame_rejects_bad_input(tmp_path, real):
    args = (real.depth, real.label, real.K, real.cls_ids, real.poses)
    with pytest.raises(ValueError, match=r"frame_id"):
        write_frame(tmp_path, "bad", *args)
    with pytest.raises(ValueError, match=r"uint16"):
        write_frame(tmp_path, "a/b", real.depth * 10, *args[1:])
    with pytest.raises(ValueError, match=r"label has shape"):
        write_frame(tmp_path, "a/b", real.depth, real.label[1:], *args[2:])
    with pytest.raises(ValueError, match=r"not a rotation"):
        write_frame(tmp_path, "a/b", *args[:4], real.poses * 2)
    with pytest.raises(ValueError, match=r"does not list"):
        write_frame(tmp_path, "a/b", *args[:3], real.cls_ids[:2], real.poses[:2])
    assert not (tmp_path / "data" / "a").exists() or not list((tmp_path / "data" / "a").iterdir())


# --------------------------------------------------------------------------- degenerate


def test_object_without_depth_warns_and_counts(copy_root):
    raw = np.asarray(Image.open(frame_file(copy_root, "depth"))).copy()
    lab = np.asarray(Image.open(frame_file(copy_root, "label")))
    raw[lab == 14] = 0  # the mug has no depth reading at all
    Image.fromarray(raw).save(frame_file(copy_root, "depth"))
    ds = YCBVideo(copy_root)
    before = ycb.degenerate_counts["no_depth"]
    with pytest.warns(DegenerateDataWarning, match=r"class 14 has no pixel"):
        f = ds.frame(FID)
    assert ds.degenerate_counts["no_depth"] == 1
    assert ycb.degenerate_counts["no_depth"] == before + 1
    np.testing.assert_array_equal(f.cls_ids, [8, 14, 21])  # nothing is dropped


def test_annotated_class_without_pixels_is_legal(copy_root):
    lab = np.asarray(Image.open(frame_file(copy_root, "label"))).copy()
    lab[lab == 21] = 0  # fully occluded brick: annotated, no pixel
    Image.fromarray(lab).save(frame_file(copy_root, "label"))
    with pytest.warns(DegenerateDataWarning, match=r"class 21"):
        f = YCBVideo(copy_root).frame(FID)
    assert 21 in f.cls_ids


def test_real_frame_reads_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        frame = YCBVideo(REAL).frame(FID)
    assert frame.depth.shape == frame.label.shape == (480, 640)
    assert len(frame.cls_ids) > 0 and frame.poses.shape == (len(frame.cls_ids), 3, 4)
    assert set(frame.cls_ids.tolist()) <= set(np.unique(frame.label).tolist())
