"""Synthetic YCB-Video scenes: layout, determinism, resumability, plausibility, noise, generator
versions (version 1 frozen), stacking, missing depth against real frames."""

from __future__ import annotations

import hashlib
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from scipy.spatial import ConvexHull

from cloudpose.config import DataConfig
from cloudpose.conventions import DEPTH_FACTOR_YCB, IMAGE_SHAPE, YCB_INTRINSICS
from cloudpose.data import synth
from cloudpose.data.synth import sensor
from cloudpose.data.ycb import YCBVideo
from cloudpose.report import fidelity

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def gen():
    return synth.frames._generator()


@pytest.fixture(scope="module")
def small_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synth") / "ds"
    s = synth.synthesize(root, 2, 1, seed=3, workers=1, progress=False)
    assert s.frames_written == 3 and s.frames_skipped == 0
    return root


def _files(root: Path, fid: str) -> dict[str, Path]:
    seq, name = fid.split("/")
    return {k: root / "data" / seq / f"{name}-{k}" for k in ("depth.png", "label.png", "meta.mat")}


# --------------------------------------------------------------------------- resting poses


def test_resting_poses_of_a_box_are_its_faces(gen):
    box = gen.models[2]  # 003_cracker_box
    rp = gen.resting[2]
    extent = np.sort(box.max(0) - box.min(0))
    tops = np.sort(rp.heights_up)
    # the three heights a box can stand at, each found among its stable faces
    for e in extent:
        assert np.abs(tops - e).min() < 0.01
    assert np.isclose(rp.probabilities.sum(), 1.0)
    for R in rp.rotations:
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(R), 1.0)


def test_every_model_has_a_stable_pose_with_lowest_point_on_table(gen):
    for c, pts in gen.models.items():
        rp = gen.resting[c]
        assert len(rp.probabilities) >= 1, c
        for R, h in zip(rp.rotations, rp.heights, strict=True):
            z = (pts @ R.T)[:, 2] + h
            assert abs(z.min()) < 1e-9
            # the centre of mass lies above the contact region, not beyond its edge
            com = pts.mean(0) @ R.T
            contact = (pts @ R.T)[z < 0.002]
            assert (contact[:, 0].min() < com[0] < contact[:, 0].max()) and (
                contact[:, 1].min() < com[1] < contact[:, 1].max()
            )


# --------------------------------------------------------------------------- scenes


def test_table_scenes_are_plausible(gen):
    convex = {1, 2, 3, 4, 5, 6, 7, 8, 9, 16, 21}  # cans and boxes: hull test is meaningful
    for i in range(12):
        rng = np.random.default_rng([7, i])
        sc = synth.sample_table_scene(rng, gen.models, gen.resting)
        n = len(sc.cls_ids)
        assert synth.N_OBJECTS[0] <= n <= synth.N_OBJECTS[1]
        assert len(set(sc.cls_ids.tolist())) == n
        world = [
            gen.models[c] @ P[:, :3].T + P[:, 3]
            for c, P in zip(sc.cls_ids, sc.model_to_world, strict=True)
        ]
        for w in world:  # resting on the table: lowest point at z = 0
            assert abs(w[:, 2].min()) < 1e-9
        R, t = sc.world_to_camera[:, :3], sc.world_to_camera[:, 3]
        eye = -R.T @ t
        dist = np.linalg.norm(eye - sc.look_at)
        assert synth.CAMERA_DISTANCE[0] - 1e-9 <= dist <= synth.CAMERA_DISTANCE[1] + 1e-9
        forward = R[2]
        assert np.allclose((sc.look_at - eye) / dist, forward)
        elevation = np.degrees(np.arcsin(-forward[2]))
        assert synth.CAMERA_ELEVATION_DEG[0] - 1e-6 <= elevation <= synth.CAMERA_ELEVATION_DEG[1]
        assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
        # the camera is above the table, every object in front of it
        assert eye[2] > 0.1
        for w in world:
            assert ((w @ R.T + t)[:, 2] > 0.1).all()
        # no interpenetration: footprints on a 5 mm raster are disjoint, and no point of one
        # convex object lies inside another convex object's hull
        cells = [
            {
                tuple(x)
                for x in synth.scenes._footprint_cells((gen.models[c] @ P[:, :3].T)[:, :2])
                + np.floor(P[:2, 3] / synth.scenes._GRID).astype(int)
            }
            for c, P in zip(sc.cls_ids, sc.model_to_world, strict=True)
        ]
        for a in range(n):
            for b in range(a + 1, n):
                assert not cells[a] & cells[b]
                if sc.cls_ids[a] in convex and sc.cls_ids[b] in convex:
                    eq = ConvexHull(world[b]).equations
                    inside = (world[a] @ eq[:, :3].T + eq[:, 3] < 0).all(axis=1)
                    assert inside.mean() < 0.01


def test_floating_scenes_have_uniform_rotations_and_no_overlap(gen):
    for i in range(10):
        sc = synth.sample_floating_scene(np.random.default_rng([8, i]), gen.models)
        P = sc.poses()
        assert np.allclose(P, sc.model_to_world)  # world = camera
        R = P[:, :, :3]
        assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-9)
        assert np.allclose(np.linalg.det(R), 1.0)
        radii = [np.linalg.norm(gen.models[c], axis=1).max() for c in sc.cls_ids]
        for a in range(len(P)):
            assert P[a, 2, 3] > 0.3
            for b in range(a + 1, len(P)):
                assert np.linalg.norm(P[a, :, 3] - P[b, :, 3]) > radii[a] + radii[b]
    # rotations of many objects: the mean of a uniform SO(3) sample is near 0
    for sampler in (synth.scenes.uniform_rotations, synth.scenes._random_rotations):
        Rs = sampler(np.random.default_rng(0), 4000)
        assert np.abs(Rs.mean(0)).max() < 0.05
        assert np.allclose(Rs @ np.swapaxes(Rs, 1, 2), np.eye(3), atol=1e-9)


# --------------------------------------------------------------------------- noise


def test_noise_statistics_on_a_plane_and_an_edge():
    rng = np.random.default_rng(0)
    clean = np.ones((200, 200))
    clean[:, 100:] = 1.5  # a 0.5 m step: a depth edge at columns 99/100
    clean[:10] = 0.0  # no surface
    noisy = synth.add_sensor_noise(clean, rng)
    assert (noisy[:10] == 0).all()  # never a reading where there was none
    flat = (clean == 1.0) & (np.arange(200) < 90)[None]
    ok = flat & (noisy > 0)
    sigma = synth.NoiseModel().sigma0 + synth.NoiseModel().sigma2 * 0.6**2
    err = noisy[ok] - 1.0
    assert abs(err.mean()) < 5e-4
    # Gaussian noise plus disparity quantisation (2.9 mm steps at 1 m -> 0.84 mm std)
    assert sigma < err.std() < np.hypot(sigma, 0.0029 / np.sqrt(12)) * 1.2
    drop_flat = 1 - ok.sum() / flat.sum()
    assert drop_flat < 0.02
    edge = noisy[10:, 99:101]
    assert 0.3 < (edge == 0).mean() < 0.7  # half the edge pixels lose their reading
    mixed = (edge > 1.02) & (edge < 1.48)  # flying pixels between the two surfaces
    assert mixed.mean() > 0.02


def _two_objects_on_a_slope(shape=(90, 120)):
    """Clean depth and labels: a sloped background and two objects, one a tilted slab in
    front of a box, touching it and the image border."""
    H, W = shape
    v, u = np.mgrid[0:H, 0:W].astype(float)
    depth = 1.2 + 0.002 * v  # the table, sloping away
    label = np.zeros(shape, np.uint8)
    box = (v >= 20) & (v < 60) & (u >= 30) & (u < 70)
    slab = (v >= 40) & (v < 90) & (u >= 60) & (u < 110) & ~((v < 45) & (u < 65))
    depth = np.where(box, 0.9 + 0.0005 * u, depth)
    depth = np.where(slab, 0.8 + 0.001 * v - 0.0007 * u, depth)
    label[box], label[slab] = 5, 11
    return depth, label


def test_object_pixel_geometry_is_the_image_functions_at_object_pixels():
    """Jump and incidence cosine of object pixels: kernel and numpy twin agree, equal
    incidence_cosine and the edge jump of the whole-image readings, and need the background
    only on the ring around the objects."""
    from cloudpose.kernels import disabled

    depth, label = _two_objects_on_a_slope()
    K = np.array([[300.0, 0, 60], [0, 300.0, 45], [0, 0, 1]])
    v, u = np.nonzero(label > 0)
    pad, lpad = np.pad(depth, 1), np.pad(label, 1)
    jump, cos = sensor.object_pixel_geometry(pad, lpad, v, u, K)
    with disabled():
        jump2, cos2 = sensor.object_pixel_geometry(pad, lpad, v, u, K)
    assert np.allclose(jump, jump2, atol=1e-12) and np.allclose(cos, cos2, atol=1e-9)
    assert np.allclose(cos, sensor.incidence_cosine(depth, K, label)[v, u], atol=1e-9)
    assert (cos < 1).any() and (cos == 1).any()  # tilted faces, and borders and edges
    nbs = np.stack(
        [pad[v, u + 1], pad[v + 2, u + 1], pad[v + 1, u], pad[v + 1, u + 2]], axis=-1
    )  # up, down, left, right
    diff = np.where(nbs > 0, nbs - depth[v, u][:, None], 0.0)
    expect = diff[np.arange(len(v)), np.abs(diff).argmax(axis=-1)]
    assert np.array_equal(jump, expect) and (np.abs(jump) > 0.02).any()
    ring = sensor.object_ring(label)
    sparse = np.where((label > 0) | ring, depth, 0.0)
    j3, c3 = sensor.object_pixel_geometry(np.pad(sparse, 1), lpad, v, u, K)
    assert np.array_equal(j3, jump) and np.array_equal(c3, cos)


def test_object_pixel_noise_is_the_version_2_law():
    """Readings of object pixels only: on each object pixel the same law as the whole-image
    version-2 sensor (mean, spread, missing share on the inside and at the edges), nothing on
    the background."""
    depth, label = _two_objects_on_a_slope()
    K = np.array([[300.0, 0, 60], [0, 300.0, 45], [0, 0, 1]])
    obj = label > 0
    edge = sensor.edge_distance(label) <= 2
    sparse = np.where(obj | sensor.object_ring(label), depth, 0.0)
    full, part = [], []
    for k in range(60):
        full.append(sensor.add_sensor_noise_v2(depth, label, K, np.random.default_rng([1, k])))
        part.append(
            sensor.add_sensor_noise_v2_objects(sparse, label, K, np.random.default_rng([2, k]))
        )
    full, part = np.stack(full), np.stack(part)
    assert (part[:, ~obj] == 0).all()
    for where in (obj & ~edge, obj & edge):
        a, b = full[:, where], part[:, where]
        assert abs((a == 0).mean() - (b == 0).mean()) < 0.02, ((a == 0).mean(), (b == 0).mean())
        ra = (a - depth[where])[a > 0]
        rb = (b - depth[where])[b > 0]
        # inside: noise about the surface; at edges: flying pixels pull the mean off it
        assert abs(ra.mean() - rb.mean()) < 3e-4 + 0.1 * abs(ra.mean())
        assert abs(ra.std() - rb.std()) < 0.1 * ra.std()


# --------------------------------------------------------------------------- frames on disk


def test_layout_reads_back_and_meta_has_alone_pixels(small_root, gen):
    ds = YCBVideo(small_root)
    assert ds.image_set("train") == ["0000/000001", "0000/000002"]
    assert ds.image_set("test") == ["1000/000001"] == ds.image_set("keyframe")
    assert ds.models_root == small_root / "models"
    assert np.allclose(ds.model_points(5), gen.models[5])
    for fid in ds.image_set("train") + ds.image_set("test"):
        f = ds.frame(fid)
        assert f.depth.shape == IMAGE_SHAPE and np.allclose(f.K, YCB_INTRINSICS)
        assert 3 <= len(f.cls_ids) <= 8
        meta = scipy.io.loadmat(_files(small_root, fid)["meta.mat"])
        assert float(meta["factor_depth"].ravel()[0]) == DEPTH_FACTOR_YCB
        alone = meta["alone_pixels"].ravel()
        visible = np.array([(f.label == c).sum() for c in f.cls_ids])
        assert (visible >= synth.MIN_VISIBLE_PIXELS).all()
        assert (alone >= visible).all()
        # background depth (table, floor) exists where no object is
        assert (f.depth[f.label == 0] > 0).mean() > 0.5


def test_determinism_and_prefix(small_root, tmp_path):
    # a bigger set with the same seed starts with the same frames, byte for byte
    root = tmp_path / "ds"
    synth.synthesize(root, 3, 2, seed=3, workers=1, progress=False)
    for fid in ["0000/000001", "0000/000002", "1000/000001"]:
        a, b = _files(small_root, fid), _files(root, fid)
        for k in ("depth.png", "label.png"):
            assert a[k].read_bytes() == b[k].read_bytes(), (fid, k)
        ma, mb = scipy.io.loadmat(a["meta.mat"]), scipy.io.loadmat(b["meta.mat"])
        for k in ("cls_indexes", "poses", "intrinsic_matrix", "alone_pixels"):
            assert np.array_equal(ma[k], mb[k])
    # another frame index or seed gives another scene
    d1 = _files(root, "0000/000001")["depth.png"].read_bytes()
    assert d1 != _files(root, "0000/000003")["depth.png"].read_bytes()
    other = synth.generate_frame("train", 0, seed=4)
    assert not np.array_equal(other.label, YCBVideo(root).frame("0000/000001").label)


def test_resume_rewrites_only_missing_frames(small_root, tmp_path):
    import shutil

    root = tmp_path / "ds"
    shutil.copytree(small_root, root)
    victim = _files(root, "0000/000002")
    victim["meta.mat"].unlink()
    keep = _files(root, "0000/000001")
    before = {k: p.stat().st_mtime_ns for k, p in keep.items()}
    # leftovers of an interrupted run: a staged frame and a temporary file
    dead = subprocess.Popen(["true"])
    dead.wait()
    stage = root / ".staging" / str(dead.pid) / "data" / "0000"
    stage.mkdir(parents=True)
    (stage / "000001-depth.png").write_bytes(b"partial")
    tmp = root / "data" / "0000" / ".000003-depth.png.999.tmp"
    tmp.write_bytes(b"partial")
    s = synth.synthesize(root, 2, 1, seed=3, workers=1, progress=False)
    assert (s.frames_written, s.frames_skipped) == (1, 2)
    assert {k: p.stat().st_mtime_ns for k, p in keep.items()} == before
    assert victim["meta.mat"].is_file()
    assert (
        victim["depth.png"].read_bytes()
        == _files(small_root, "0000/000002")["depth.png"].read_bytes()
    )
    assert not (root / ".staging").exists()
    ds = YCBVideo(root)
    assert ds.image_set("train") == ["0000/000001", "0000/000002"]
    ds.frame("0000/000002")
    # fewer frames asked: the image sets shrink, the frames stay
    synth.synthesize(root, 1, 1, seed=3, workers=1, progress=False)
    assert YCBVideo(root).image_set("train") == ["0000/000001"]
    assert victim["meta.mat"].is_file()


def test_other_settings_in_same_root_raise(small_root):
    with pytest.raises(ValueError, match=r"synth\.json"):
        synth.synthesize(small_root, 2, 1, seed=3, noise=False, workers=1, progress=False)
    with pytest.raises(ValueError, match="frame counts"):
        synth.synthesize(small_root, -1, 1, seed=3, workers=1, progress=False)


def test_frames_of_another_renderer_raise(small_root, tmp_path, monkeypatch):
    # synth.json records the surface build; a root made with other surfaces is not extended
    import json
    import shutil

    from cloudpose.data.synth import surfaces

    root = tmp_path / "copy"
    shutil.copytree(small_root, root)
    assert json.loads((root / "synth.json").read_text())["surfaces"] == surfaces.surface_settings(2)
    monkeypatch.setattr(surfaces, "SURFACE_VERSION", surfaces.SURFACE_VERSION + 1)
    with pytest.raises(ValueError, match=r"synth\.json.*surfaces"):
        synth.synthesize(root, 2, 1, seed=3, workers=1, progress=False)
    # a synth.json from before the key existed is refused too, and says why
    monkeypatch.undo()
    info = json.loads((root / "synth.json").read_text())
    del info["surfaces"]
    (root / "synth.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match="older cloudpose"):
        synth.synthesize(root, 2, 1, seed=3, workers=1, progress=False)


def test_noise_off_depth_is_the_rendering(tmp_path, gen):
    root = tmp_path / "clean"
    synth.synthesize(root, 1, 0, seed=5, noise=False, workers=1, progress=False)
    f = YCBVideo(root).frame("0000/000001")
    r = gen.renderer.render(f.K, f.depth.shape, f.cls_ids, f.poses)
    assert np.array_equal(r.label, f.label)
    obj = f.label > 0
    assert np.abs(f.depth[obj] - r.depth[obj]).max() <= 0.5 / DEPTH_FACTOR_YCB + 1e-6
    # the rendered frame with noise differs from it on object pixels, labels do not
    g = synth.generate_frame("train", 0, seed=5, noise=True)
    assert np.array_equal(g.label, f.label)
    assert np.abs(g.depth - g.clean_depth)[obj & (g.depth > 0)].mean() > 5e-4
    assert np.array_equal(g.clean_depth[obj], r.depth[obj].astype(np.float64))


def test_uniform_rotation_frames(gen):
    f = synth.generate_frame("test", 0, seed=1, uniform_rotation=True, generator=gen)
    assert np.allclose(f.scene.world_to_camera, np.c_[np.eye(3), np.zeros(3)])
    assert (f.visible_pixels >= synth.MIN_VISIBLE_PIXELS).all()
    assert (f.depth[f.label == 0] > 0).mean() > 0.5  # the wall behind


@pytest.mark.slow
def test_parallel_equals_serial(small_root, tmp_path):
    root = tmp_path / "par"
    s = synth.synthesize(root, 2, 1, seed=3, workers=2, progress=False)
    assert s.frames_written == 3
    for fid in ["0000/000001", "0000/000002", "1000/000001"]:
        for k in ("depth.png", "label.png"):
            assert _files(root, fid)[k].read_bytes() == _files(small_root, fid)[k].read_bytes()
    assert not any(p.name.endswith(".tmp") for p in root.rglob("*"))
    assert sorted(os.listdir(root / "data")) == ["0000", "1000"]


# --------------------------------------------------------------------------- versions

V1_FRAME_DIGESTS = {
    ("train", 0, 0, False): "bad84870dd0c30f0",
    ("test", 1, 0, False): "601e41c14d85bbfa",
    ("train", 2, 3, True): "3032fb307b726c5e",
}
"""Digests (:func:`frame_digest`) of version-1 frames (split, index, seed, uniform_rotation),
recorded from the generator before version 2 existed: the committed cpu results were made from
such frames, and the sweep that continues them needs the same bytes."""


def frame_digest(f) -> str:
    """16 hex digits of what a frame writes: depth as stored (0.1 mm), labels, classes, poses
    (to 1e-9) and alone pixels."""
    h = hashlib.sha256()
    depth = np.round(f.depth * DEPTH_FACTOR_YCB).astype(np.uint16)
    for a in (depth, f.label.astype(np.uint8), f.cls_ids.astype(np.int64)):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(np.ascontiguousarray(np.round(f.poses, 9)).tobytes())
    h.update(np.ascontiguousarray(f.alone_pixels.astype(np.int64)).tobytes())
    return h.hexdigest()[:16]


def test_version1_frames_are_byte_identical():
    from cloudpose.data.synth import surfaces

    gen = synth.frames._generator(1)
    for (split, i, seed, uniform), digest in V1_FRAME_DIGESTS.items():
        f = synth.generate_frame(split, i, seed, uniform_rotation=uniform, generator=gen, version=1)
        assert frame_digest(f) == digest, (split, i, seed, uniform)
    # what synth.json records for version 1 (a root made before versions existed resumes)
    assert surfaces.surface_settings(1) == "(1, (1.0, 2.0, 4.0, 8.0), 8.0, 30.0, 0.001)"


def test_versions_never_share_a_root(small_root, tmp_path):
    from cloudpose.data.dataset import synthetic_root

    with pytest.raises(ValueError, match=r"generator version 2, not 1 \(data\.synth_version\)"):
        synth.synthesize(small_root, 2, 1, seed=3, workers=1, progress=False, version=1)
    root = tmp_path / "v1"
    synth.synthesize(root, 1, 0, seed=3, workers=1, progress=False, version=1)
    with pytest.raises(ValueError, match="generator version 1, not 2"):
        synth.synthesize(root, 1, 0, seed=3, workers=1, progress=False)
    assert synthetic_root(DataConfig(synth_version=1), tmp_path).name == "synth-seed0"
    assert synthetic_root(DataConfig(), tmp_path).name == "synth-seed0-v2"
    with pytest.raises(ValueError, match=r"generator version 3: expected one of \(1, 2\)"):
        DataConfig(synth_version=3)
    with pytest.raises(ValueError, match="generator of version 2 asked for a version-1 frame"):
        synth.generate_frame("train", 0, generator=synth.frames._generator(2), version=1)


def test_presets_of_the_committed_sweep_pin_version1():
    from cloudpose.config import Config
    from cloudpose.registry import resolve

    for preset in ("cpu", "cpu-paper"):
        assert resolve("shared-0", preset).data.synth_version == 1
    assert resolve("shared-0", "smoke").data.synth_version == 2
    # a stored config without the field is version 1, with the fingerprint it had
    cfg = resolve("shared-0", "cpu")
    d = cfg.to_dict()
    del d["data"]["synth_version"]
    assert Config.from_dict(d) == cfg and Config.from_dict(d).fingerprint() == cfg.fingerprint()
    assert (
        resolve("shared-0", "smoke").fingerprint()
        != resolve("shared-0", "smoke", overrides={"data": {"synth_version": 1}}).fingerprint()
    )


# --------------------------------------------------------------------------- stacking


def _inside_depth(points: np.ndarray, hull_points: np.ndarray) -> np.ndarray:
    """(P,) how far each point lies inside the convex hull of ``hull_points`` (metres; <= 0
    outside or on it)."""
    eq = ConvexHull(hull_points).equations
    return -(points @ eq[:, :3].T + eq[:, 3]).max(axis=1)


def test_stacked_scenes_are_physically_plausible(gen):
    """Objects rest on the top of another: touching it, centre of mass over the contact, and no
    point of one inside the other's convex hull by more than 1 mm."""
    convex = {1, 2, 3, 4, 5, 6, 7, 8, 9, 16, 21}
    stacked = 0
    for i in range(10):
        rng = np.random.default_rng([9, i])
        sc = synth.sample_table_scene(rng, gen.models, gen.resting, stack_share=1.0)
        world = [
            gen.models[c] @ P[:, :3].T + P[:, 3]
            for c, P in zip(sc.cls_ids, sc.model_to_world, strict=True)
        ]
        for a, b in enumerate(sc.support):
            if b < 0:
                assert abs(world[a][:, 2].min()) < 1e-9  # on the table
                continue
            stacked += 1
            assert sc.support[b] == -1  # one level: the support stands on the table
            top = world[b][:, 2].max()
            assert abs(world[a][:, 2].min() - top) < 1e-9  # touching
            assert _inside_depth(world[a], world[b]).max() < 1e-3
            assert _inside_depth(world[b], world[a]).max() < 1e-3
            # centre of mass over the top surface of the support and the resting face
            com = world[a].mean(axis=0)[None, :2]
            base_top = world[b][world[b][:, 2] > top - synth.scenes.STACK_CONTACT, :2]
            face = world[a][world[a][:, 2] < top + synth.scenes.STACK_CONTACT, :2]
            for region in (base_top, face):
                eq = ConvexHull(region).equations
                assert (com @ eq[:, :2].T + eq[:, 2]).max() < 0
        for a in range(len(world)):
            for b in range(len(world)):
                if a != b and sc.cls_ids[b] in convex:
                    assert _inside_depth(world[a], world[b]).max() < 1e-3
    assert stacked >= 5


TABLE_SCENES = {
    (0, 0.0): ([9, 8, 6, 4, 5, 2, 1, 20], None, 1224268757, [0.078944, 0.031047, 0.011968]),
    (1, 0.35): ([14, 19, 9, 1, 4], [-1] * 5, 2143709454, [0.009788, -0.076527, 0.042761]),
    (2, 0.35): ([2, 8, 5, 20, 21, 9], [-1] * 6, 1991058916, [0.133147, 0.043928, 0.002972]),
    (3, 1.0): (
        [5, 18, 4, 16, 3, 13, 2],
        [-1, -1, -1, -1, 2, 3, -1],
        2011935010,
        [-0.010938, 0.006136, 0.009861],
    ),
    (4, 1.0): (
        [15, 9, 20, 19, 16, 2, 17],
        [-1, -1, -1, -1, 0, -1, -1],
        1654093881,
        [0.013023, -0.028404, 0.039288],
    ),
}
"""Table scenes (seed, stack_share) -> (class ids, support, the generator's next
``integers(2**31)``, look-at point): the sampler's draws, in order, fix the scenes of stored
datasets of every version."""


@pytest.mark.parametrize("seed_stack", sorted(TABLE_SCENES))
def test_table_scene_draws_are_pinned(gen, seed_stack):
    cls_ids, support, next_draw, look_at = TABLE_SCENES[seed_stack]
    rng = np.random.default_rng(seed_stack[0])
    sc = synth.sample_table_scene(rng, gen.models, gen.resting, stack_share=seed_stack[1])
    assert sc.cls_ids.tolist() == cls_ids
    assert (None if sc.support is None else sc.support.tolist()) == support
    assert int(rng.integers(2**31)) == next_draw
    np.testing.assert_allclose(sc.look_at, look_at, atol=2e-6)


def test_scene_subset_takes_what_rests_on_a_removed_object():
    sc = synth.Scene(
        np.array([1, 2, 3]),
        np.zeros((3, 3, 4)),
        np.zeros((3, 4)),
        np.zeros(3),
        [],
        np.array([-1, 0, -1]),
    )
    assert sc.supported(np.array([False, True, True])).tolist() == [False, False, True]
    sub = sc.subset(np.array([True, True, False]))
    assert sub.cls_ids.tolist() == [1, 2] and sub.support.tolist() == [-1, 0]
    assert sc.subset(np.array([False, True, True])).cls_ids.tolist() == [3]


# --------------------------------------------------------------------------- missing depth


def _missing_stats(frames) -> tuple[float, float]:
    """(share of mask pixels without depth, chance a mask pixel next to a missing one misses)."""
    obj = miss = hits = pairs = 0
    for f in frames:
        o = f.label > 0
        obj, miss = obj + o.sum(), miss + (o & (f.depth == 0)).sum()
        h, p = fidelity._neighbour_missing(f.depth, f.label)
        hits, pairs = hits + h, pairs + p
    return miss / obj, hits / pairs


def test_missing_depth_matches_the_real_frames():
    """Version 2 misses depth inside masks about as often, and in blobs, as the real frames
    (10.7% of the mask pixels of tests/data's two frames; 2-4% for version 1)."""
    real = fidelity.read_real_frames([DATA / "ycb_real", DATA / "demo_no_gt"])
    real_share, real_next = _missing_stats(real)
    assert 0.09 < real_share < 0.12 and real_next > 0.8
    v = {
        ver: _missing_stats(
            [
                synth.generate_frame(
                    "test", i, 0, generator=synth.frames._generator(ver), version=ver
                )
                for i in range(2)
            ]
        )
        for ver in (1, 2)
    }
    assert v[1][0] < 0.05 and v[1][1] < 0.4
    assert 0.5 * real_share < v[2][0] < 2.0 * real_share
    assert v[2][1] > 0.75


def test_dropout_model_terms():
    m = sensor.DropoutModel(
        edge_rate=0.5,
        edge_scale=2.0,
        graze_cos=0.2,
        graze_width=0.05,
        class_rates=((3, 0.1),),
        default_rate=0.02,
    )
    p = m.probability(
        np.array([1.0, 3.0, 100.0, 100.0, 100.0]),
        np.array([1.0, 1.0, 1.0, 0.2, 1.0]),
        np.array([3, 3, 3, 5, 0]),
    )
    np.testing.assert_allclose(p[0], 1 - 0.5 * 0.9, atol=1e-6)  # edge ring, class 3
    np.testing.assert_allclose(p[1], 1 - (1 - 0.5 * np.exp(-1)) * 0.9, atol=1e-6)
    np.testing.assert_allclose(p[2], 0.1, atol=1e-6)  # inside: the class rate
    np.testing.assert_allclose(p[3], 1 - 0.5 * 0.98, atol=1e-6)  # half at graze_cos, default
    assert p[4] < 1e-6  # background: no class term
    label = np.zeros((6, 6), int)
    label[2:, 2:] = 4
    d = sensor.edge_distance(label)
    assert d[2, 2] == 1 and d[1, 2] == 1 and d[5, 5] == 4 and d[0, 5] == 2
    u = sensor.correlated_uniform(np.random.default_rng(0), (480, 640), 4.0)
    assert abs(u.mean() - 0.5) < 0.02 and abs((u < 0.1).mean() - 0.1) < 0.02
    assert np.corrcoef(u[:, 1:].ravel(), u[:, :-1].ravel())[0, 1] > 0.9
