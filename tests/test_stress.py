"""Stress curves (cloudpose.studies.stress): each perturbation does what it says, level 0 is the identity,
and the command runs end to end on a tiny subset."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd
import pytest

from cloudpose.studies import perturbations as pt
from cloudpose.studies import stress as st
from tests.conftest import DATA, cli


def _cloud(n=500, seed=0) -> np.ndarray:
    """(n, 3) points of a 10 cm patch 0.8 m in front of the camera."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.05, 0.05, size=(n, 2))
    z = 0.8 + 0.02 * np.sin(20 * xy[:, 0])
    return np.column_stack([xy, z])


def test_erosion_removes_the_boundary_band_and_dilation_adds_one():
    mask = np.zeros((40, 40), dtype=bool)
    mask[10:30, 10:30] = True
    for k in (1, 2, 4):
        eroded = pt.erode_mask(mask, k)
        assert eroded.sum() == (20 - 2 * k) ** 2  # a square loses k pixels on every side
        assert not (eroded & ~mask).any()
        dilated = pt.dilate_mask(mask, k)
        assert (dilated & mask).sum() == mask.sum()
        assert dilated[10 - k, 20] and not dilated[10 - k - 1, 20]  # k pixels out, no more
    point = np.zeros((11, 11), dtype=bool)
    point[5, 5] = True
    assert pt.dilate_mask(point, 2).sum() == 13  # the disk of radius 2
    assert np.array_equal(pt.erode_mask(mask, 0), mask)
    assert np.array_equal(pt.dilate_mask(mask, 0), mask)


def test_shift_moves_the_mask_k_pixels_the_same_way_at_every_level():
    mask = np.zeros((40, 40), dtype=bool)
    mask[10:30, 12:26] = True
    centre = np.argwhere(mask).mean(axis=0)
    moves = {}
    for k in (0, 1, 2, 4, 6):
        shifted = pt.shift_mask(mask, k, np.random.default_rng(3))  # one instance's stream
        assert shifted.sum() == mask.sum()  # moved whole, nothing cut at the image border
        moves[k] = np.argwhere(shifted).mean(axis=0) - centre
        assert np.linalg.norm(moves[k]) == pytest.approx(k, abs=0.75)  # whole pixels
    assert np.array_equal(pt.shift_mask(mask, 0, np.random.default_rng(3)), mask)
    direction = moves[6] / 6
    for k in (2, 4):
        assert np.linalg.norm(moves[k] / k - direction) < 0.3
    edge = np.zeros((10, 10), dtype=bool)
    edge[:, :2] = True  # pushed out of the image on one side it loses pixels, never wraps
    for seed in range(8):
        out = pt.shift_mask(edge, 3, np.random.default_rng(seed))
        assert out.sum() <= edge.sum() and not out[:, 6:].any()


def test_holes_drop_about_the_share_inside_the_mask_only():
    depth = np.full((60, 60), 0.8)
    mask = np.zeros((60, 60), dtype=bool)
    mask[10:50, 10:50] = True
    same = pt.drop_depth_blobs(depth, mask, 0.0, np.random.default_rng(0))
    assert np.array_equal(same, depth)
    for share in (0.1, 0.35, 0.7):
        out = pt.drop_depth_blobs(depth, mask, share, np.random.default_rng(0))
        gone = (out == 0) & mask
        assert np.array_equal(out[~mask], depth[~mask])  # nothing outside the mask
        assert share <= gone.sum() / mask.sum() <= share + 0.15  # up to one last blob more


def test_depth_noise_and_bias_move_points_along_their_rays():
    p = _cloud()
    rng = np.random.default_rng(1)
    for q in (pt.depth_noise(p, 4.0, rng), pt.depth_bias(p, 20.0)):
        cross = np.linalg.norm(np.cross(p / np.linalg.norm(p, axis=1, keepdims=True), q), axis=1)
        assert cross.max() < 1e-12  # same ray
    dz = pt.depth_noise(p, 4.0, np.random.default_rng(2))[:, 2] - p[:, 2]
    assert 3.5e-3 < dz.std() < 4.5e-3
    np.testing.assert_allclose(pt.depth_bias(p, 20.0)[:, 2], p[:, 2] * 1.02)
    np.testing.assert_array_equal(pt.depth_noise(p, 0.0, rng), p)
    np.testing.assert_array_equal(pt.depth_bias(p, 0.0), p)


@pytest.mark.parametrize("share", [0.1, 0.35, 0.7])
def test_cut_plane_removes_the_share_on_one_side(share):
    p = _cloud()
    kept = pt.cut_plane(p, share, np.random.default_rng(3))
    n = np.random.default_rng(3).standard_normal(3)  # the plane's normal: the stream's first draw
    n /= np.linalg.norm(n)
    assert len(kept) == int(np.ceil(len(p) * (1 - share)))
    gone = np.array([not (row == kept).all(axis=1).any() for row in p])
    assert (kept @ n).max() <= (p[gone] @ n).min()  # all removed points beyond the plane
    np.testing.assert_array_equal(pt.cut_plane(p, 0.0, np.random.default_rng(3)), p)


@pytest.mark.parametrize("shift_mm", [2.0, 8.0])
def test_lateral_shift_moves_the_centroid_across_the_ray(shift_mm):
    p = _cloud(2000)
    kept = pt.lateral_shift(p, shift_mm, np.random.default_rng(4))
    move = kept.mean(axis=0) - p.mean(axis=0)
    ray = p.mean(axis=0) / np.linalg.norm(p.mean(axis=0))
    across = np.linalg.norm(move - (move @ ray) * ray)
    assert shift_mm / 1000 <= across < shift_mm / 1000 + 1e-3
    assert len(kept) < len(p)
    np.testing.assert_array_equal(pt.lateral_shift(p, 0.0, np.random.default_rng(4)), p)


def test_lateral_shift_beyond_reach_keeps_the_least_share_without_a_warning():
    """A shift no removal reaches stops at MIN_KEEP of the points, and no step divides by the
    empty rest (numpy warned "invalid value encountered in matmul" there)."""
    import warnings

    p = _cloud(500)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        kept = pt.lateral_shift(p, 1e6, np.random.default_rng(4))
    assert len(kept) == int(np.ceil(pt.MIN_KEEP * len(p)))


def test_resampling_scales_the_count_on_the_same_surface():
    p = _cloud(400)
    rng = np.random.default_rng(5)
    assert len(pt.resample_points(p, 0.25, rng)) == 100
    more = pt.resample_points(p, 2.0, rng)
    assert len(more) == 800
    np.testing.assert_array_equal(more[:400], p)
    # the added points are midpoints of neighbours: within the patch, near its surface
    assert np.abs(more[400:, :2]).max() <= 0.05
    np.testing.assert_array_equal(pt.resample_points(p, 1.0, rng), p)


def _real_fixture():
    from cloudpose.data.layout import open_dataset

    ds = open_dataset(DATA / "ycb_real")
    fid = "0000/000001"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ds, pt.FrameData(ds.frame(fid), 0, None)


def test_identity_level_is_the_project_segment():
    """Level 0 of every perturbation gives the segment the project makes (same mask, filter,
    count); a perturbed level changes it; the same call twice gives the same points."""
    from cloudpose.data.segments import backproject, extract_segments

    _, fd = _real_fixture()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = extract_segments(fd.frame, rng=np.random.default_rng(0))
    f = fd.frame
    full = backproject(f.depth, f.label == f.cls_ids[0], f.K).astype(np.float32)
    full_set = {tuple(r) for r in full}
    for name, p in pt.PERTURBATIONS.items():
        seg, _ = pt.perturbed_segment(
            fd, 0, p, pt.identity_level(p), seed=1, source="real", n_fps=256
        )
        assert seg.count == ref[0].count, name
        k = min(seg.count, 256)
        assert {tuple(r) for r in seg.points[:k]} <= full_set, name
    twice = [
        pt.perturbed_segment(fd, 0, pt.PERTURBATIONS["cut"], 0.35, seed=1, source="real")[0]
        for _ in range(2)
    ]
    np.testing.assert_array_equal(twice[0].points, twice[1].points)
    assert twice[0].count < ref[0].count


def test_pixel_statistics_follow_the_pixels():
    _, fd = _real_fixture()
    p = pt.PERTURBATIONS
    _, px0 = pt.perturbed_segment(fd, 0, p["holes"], 0.0, seed=1, source="real")
    _, px1 = pt.perturbed_segment(fd, 0, p["holes"], 0.35, seed=1, source="real")
    assert px1["no_depth"] >= px0["no_depth"] + 0.3
    _, pd_ = pt.perturbed_segment(fd, 0, p["dilate"], 4, seed=1, source="real")
    _, pe = pt.perturbed_segment(fd, 0, p["erode"], 4, seed=1, source="real")
    assert pe["mask_px"] < px0["mask_px"] < pd_["mask_px"]
    # a shifted mask keeps its size (less what leaves the image) and moves the segment
    seg_s, ps = pt.perturbed_segment(fd, 0, p["shift"], 4, seed=1, source="real")
    seg_0, p_0 = pt.perturbed_segment(fd, 0, p["shift"], 0, seed=1, source="real")
    assert ps["mask_px"] <= p_0["mask_px"] == px0["mask_px"]
    # smoothing keeps the mask and raises the depth error's correlation
    _, p_smooth = pt.perturbed_segment(fd, 0, p["smooth"], 2, seed=1, source="real")
    assert p_smooth["mask_px"] == px0["mask_px"]
    assert p_smooth["depth_corr"] > px0["depth_corr"]
    moved = seg_s.points[: seg_s.count].mean(axis=0) - seg_0.points[: seg_0.count].mean(axis=0)
    assert np.linalg.norm(moved) > 1e-3  # metres


def test_smoothing_stays_on_the_mask_and_makes_the_noise_correlated():
    rng = np.random.default_rng(0)
    depth = np.full((80, 80), 1.5)  # the background
    mask = np.zeros((80, 80), dtype=bool)
    mask[10:70, 10:70] = True
    # a plane tilted 1 mm a pixel, with 2 mm of independent noise per pixel
    plane = 0.9 + 0.001 * np.broadcast_to(np.arange(80), (80, 80))
    depth[mask] = (plane + 0.002 * rng.standard_normal((80, 80)))[mask]
    depth[40, 40] = 0.0  # a missing reading stays missing
    out = pt.smooth_depth(depth, mask, 1.5)
    assert np.array_equal(out[~mask], depth[~mask]) and out[40, 40] == 0.0
    inner = np.zeros_like(mask)
    inner[20:60, 20:60] = True
    inner[40, 40] = False
    noise = lambda d: np.std((d - plane)[inner])  # noqa: E731
    # a Gaussian of sigma s averages ~4 pi s^2 pixels of independent noise
    assert noise(out) == pytest.approx(noise(depth) / np.sqrt(4 * np.pi * 1.5**2), rel=0.25)
    # the tilt is kept away from the edge: the average of a plane is the plane
    assert np.abs((out - plane)[inner]).mean() < 0.4 * np.abs((depth - plane)[inner]).mean()
    assert np.array_equal(pt.smooth_depth(depth, mask, 0), depth)
    before, after = pt.depth_correlation(depth, mask), pt.depth_correlation(out, mask)
    assert abs(before) < 0.1 < 0.3 < after
    assert np.isnan(pt.depth_correlation(depth, np.zeros_like(mask)))


def test_real_level_interpolates_the_synthetic_curve():
    p = pt.PERTURBATIONS["noise"]
    stats = pd.DataFrame(
        [{"source": "real", "perturbation": "noise", "level": 0.0, "noise": 3.0}]
        + [
            {"source": "synth", "perturbation": "noise", "level": lv, "noise": 1.0 + lv}
            for lv in p.levels
        ]
    )
    level, _ = st.real_level(p, stats)
    assert level == pytest.approx(2.0)
    stats.loc[0, "noise"] = 0.5  # cleaner than synthetic: the identity
    assert st.real_level(p, stats)[0] == 0.0


def test_conditions_hold_the_identity_once():
    conds = st.conditions(list(pt.PERTURBATIONS.values()))
    identities = [c for c in conds if c[1] == pt.identity_level(c[0])]
    assert len(identities) == 1
    n_levels = sum(len(p.levels) for p in pt.PERTURBATIONS.values())
    assert len(conds) == n_levels - len(pt.PERTURBATIONS) + 1


def test_a_network_named_by_its_run_is_the_same_method_wherever_it_was_downloaded():
    """A sweep resumed (or a second source swept) with a run's checkpoint downloaded to another
    temporary folder adds to the same results; another run, or another checkpoint file of a
    network not named by a run, is another method."""
    a = {"checkpoint": "/tmp/cloudpose-checkpoint-1/model.pt", "limit": None, "run_id": "ab12"}
    b = {**a, "checkpoint": "/tmp/cloudpose-checkpoint-2/model.pt", "ends_only": True}
    assert st._same(a) == st._same(b)
    assert st._same(a) != st._same({**a, "run_id": "cd34"})
    plain = {"checkpoint": "runs/x/model.pt", "limit": None}
    assert st._same(plain) != st._same({**plain, "checkpoint": "runs/y/model.pt"})


def _sweep_results(root):
    """A sweep's result files for one real object pose whose segments hold far more points off
    the model than the synthetic ones, and the synthetic frames' cache beside them."""
    meta = {"preset": "smoke", "seed": 1, "sources": {"real": "", "synth": ""}, "methods": {}}
    (root / "sweep.json").parent.mkdir(parents=True)
    (root / "sweep.json").write_text(__import__("json").dumps(meta))
    stats = {k: [0.0, 0.0] for k in pt.STATISTICS}
    ident = {"frame_id": ["0000/000001", "0000/000002"], "instance": [0, 0]}
    synth = pd.DataFrame({**ident, **stats, "off_model": [0.01, 0.02]})
    real = pd.DataFrame({**ident, **stats, "off_model": [0.30, 0.40]})
    errors = pd.DataFrame(
        {
            **ident,
            "cls_id": [8, 8],
            "icp_rot_sym_err_deg": [40.0, 50.0],
            "icp_trans_err": [0.02] * 2,
        }
    )
    for source, table in (("real", real), ("synth", synth)):
        path = st.result_path(root, source, "dilate", 0.0, "stats")
        path.parent.mkdir(parents=True, exist_ok=True)
        table.to_csv(path, index=False)
    errors.to_csv(st.result_path(root, "real", "dilate", 0.0, "net-seed1"), index=False)
    errors.to_csv(st.result_path(root, "real", "dilate", 0.0, "fpfh"), index=False)
    (root / "icp_select" / "real" / "starts1").mkdir(parents=True)
    errors.to_csv(root / "icp_select" / "real" / "starts1" / "net-seed1.csv", index=False)
    (root / "synth" / "data").mkdir(parents=True)
    (root / "synth" / "data" / "frame.npz").write_bytes(b"cache")


def test_a_pose_names_every_perturbation_its_statistic_places(tmp_path):
    """off_model places both mask dilation and a shifted mask: the miss names both."""
    from cloudpose.report.stress import per_pose_markdown

    _sweep_results(tmp_path / "run")
    row = [r for r in per_pose_markdown(tmp_path / "run").splitlines() if r.startswith("| 0000/8")]
    assert len(row) == 1 and "| miss | off_model (100) | dilate or shift |" in row[0], row


def _method_table(ads: list[float]) -> pd.DataFrame:
    """A method's result table on instances 0..n-1 of one frame: ADS (m) before and after ICP
    as given, every other error the same."""
    n = len(ads)
    cols = {"frame_id": ["0000/000001"] * n, "instance": list(range(n)), "cls_id": [8] * n}
    for stage in ("net", "icp"):
        cols |= {
            f"{stage}_ad": ads,
            f"{stage}_ads": ads,
            f"{stage}_rot_err_deg": [5.0] * n,
            f"{stage}_rot_sym_err_deg": [5.0] * n,
            f"{stage}_trans_err": [0.005] * n,
        }
    return pd.DataFrame({**cols, "seconds": [1.0] * n})  # fmt: skip


def test_the_ensemble_is_paired_with_fpfh_at_the_real_level(tmp_path):
    """An ensemble is a learned method: it is measured on FPFH's instances as each network is,
    and the fragility section sets it against FPFH at the real frames' level and counts the
    pairs at or above it."""
    import json

    from cloudpose.report.stress import _fragility_section, fragility, with_network_mean

    methods = {"net-seed1": {"checkpoint": "a.pt", "limit": None},
               "fpfh": {"checkpoint": "", "limit": 2},
               "ensemble": {"checkpoint": "", "limit": None, "members": ["a.pt", "b.pt"]}}  # fmt: skip
    meta = {"preset": "smoke", "seed": 1, "sources": {"real": ""}, "methods": methods,
            "perturbations": {"dilate": [0.0, 1.0]}}  # fmt: skip
    tmp_path.joinpath("sweep.json").write_text(json.dumps(meta))
    # on FPFH's instances 0 and 1, ADS AUC: network 80, FPFH 90, ensemble 95
    ads = {"net-seed1": [0.04, 0.06, 0.001], "fpfh": [0.02, 0.05], "ensemble": [0.01, 0.03, 0.001]}
    for level in (0.0, 1.0):
        for m, a in ads.items():
            path = st.result_path(tmp_path, "real", "dilate", level, m)
            path.parent.mkdir(parents=True, exist_ok=True)
            _method_table(a).to_csv(path, index=False)
    collected = st.collect(tmp_path)
    # rows in the sweep's order of methods, whatever the process's string hashing
    assert list(collected.method.unique()) == [
        "net-seed1", "fpfh", "ensemble", "net-seed1@fpfh", "ensemble@fpfh"
    ]  # fmt: skip
    summary = with_network_mean(collected)
    assert {"ensemble@fpfh", "net-seed1@fpfh", "network@fpfh"} <= set(summary.method)
    assert "fpfh@ensemble" not in set(summary.method)
    frag = fragility(summary, {"dilate": 0.5})
    row = frag.iloc[0]
    assert row["ensemble@fpfh_at_real"] > row["fpfh_at_real"] > row["network@fpfh_at_real"]
    lines, _ = _fragility_section(frag)
    text = "\n".join(lines)
    assert "| ensemble - FPFH at real |" in text
    assert "network + ICP on 0; the ensemble + ICP on 1." in text
    gap = row["ensemble@fpfh_at_real"] - row["fpfh_at_real"]
    assert f"| {gap:+.1f} |" in next(r for r in lines if r.startswith("| real | dilate"))


def test_packed_results_read_back_as_the_folder(tmp_path):
    """The archive holds the result files and not the frames' cache, packs byte-identically
    twice, and unpacks to the same files."""
    run = tmp_path / "run"
    _sweep_results(run)
    a, b = tmp_path / "a.tar.xz", tmp_path / "b.tar.xz"
    assert st.pack_results(run, a) == 6  # sweep.json, 4 results, 1 icp_select
    st.pack_results(run, b)
    assert a.read_bytes() == b.read_bytes()
    with st.results_folder(a) as folder:
        got = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
        assert not any(g.startswith("synth/") for g in got) and len(got) == 6
        for g in got:
            assert (folder / g).read_bytes() == (run / g).read_bytes()
    assert not folder.exists()  # the temporary folder goes
    with st.results_folder(run) as same:
        assert same == run


def test_an_archive_that_is_not_stress_results_is_refused(tmp_path):
    import tarfile

    other = tmp_path / "other.tar.xz"
    (tmp_path / "notes.txt").write_text("x")
    with tarfile.open(other, "w:xz") as tar:
        tar.add(tmp_path / "notes.txt", arcname="notes.txt")
    with pytest.raises(ValueError, match=r"'notes\.txt' is not a stress result"):
        with st.results_folder(other):
            pass
    outside = tmp_path / "outside.tar.xz"
    with tarfile.open(outside, "w:xz") as tar:
        tar.add(tmp_path / "notes.txt", arcname="results/../../evil.txt")
    with pytest.raises(ValueError, match=r"'results/\.\./\.\./evil\.txt' refused"):
        with st.results_folder(outside):
            pass
    assert not (tmp_path.parent / "evil.txt").exists()
    broken = tmp_path / "broken.tar.xz"
    broken.write_bytes(b"\xfd7zXZ\x00 truncated")
    with pytest.raises(ValueError, match=r"broken\.tar\.xz: not a readable archive"):
        with st.results_folder(broken):
            pass
    with pytest.raises(FileNotFoundError, match=r"no sweep\.json"):
        st.pack_results(tmp_path, tmp_path / "x.tar.xz")


@pytest.mark.slow
def test_stress_command_end_to_end(smoke_project, tmp_path):
    """The command on two real instances and two synthetic ones, one perturbation: every
    result file, a resumed call that computes nothing, the report and its figures."""
    results = tmp_path / "res"
    args = [
        "stress", "--preset", "smoke", "--run", "shared-0/smoke/seed1",
        "--sample", "instances=2,fpfh-instances=1,ppf-instances=0,synth-frames=1",
        "--only", "cut", "--results", str(results), "--out", str(tmp_path / "rep"),
        "--no-progress",
    ]  # fmt: skip
    res = cli(*args, "--dry-run")
    assert res.exit_code == 0 and "stress plan" in res.output, res.output
    assert not (results / "sweep.json").exists()  # a plan commits the folder to nothing
    res = cli(*args)
    assert res.exit_code == 0, res.output
    assert "stress plan" in res.output
    files = sorted(results.glob("results/*/*/*/*.csv"))
    # (identity + 5 cut levels) x 2 sources x (stats, network, fpfh)
    assert len(files) == 6 * 2 * 3
    table = pd.read_csv(results / "results" / "real" / "cut" / "0.7" / "net-seed1.csv")
    assert len(table) == 2 and {"net_ads", "icp_ads", "icp_rot_sym_err_deg"} <= set(table)
    again = cli(*args)
    assert again.exit_code == 0, again.output
    assert "conditions left" not in again.output  # nothing left to compute
    md = (tmp_path / "rep" / "stress.md").read_text()
    assert "Where the real frames sit" in md and "### cut" in md
    assert (tmp_path / "rep" / "stress.png").stat().st_size > 0
    summary = pd.read_csv(tmp_path / "rep" / "stress.csv")
    assert set(summary.method) >= {"net-seed1", "fpfh", "network"}
    packed = tmp_path / "stress-results.tar.xz"
    rendered = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "rep").iterdir()}
    res = cli(*args, "--steps", "none", "--pack", str(packed))
    assert res.exit_code == 0 and "packed" in res.output, res.output
    # --steps none: the archive only, the report left as it was
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "rep").iterdir()} == rendered
    res = cli("stress", "--preset", "smoke", "--steps", "report", "--results", str(packed),
              "--out", str(tmp_path / "again"))  # fmt: skip
    assert res.exit_code == 0, res.output
    again = (tmp_path / "again" / "stress.csv").read_text()
    assert again == (tmp_path / "rep" / "stress.csv").read_text()
    res = cli("stress", "--preset", "smoke", "--run", "x", "--results", str(packed))
    assert res.exit_code != 0 and "--steps report" in res.output
    assert "the paper's schedule from a 1 cm radius" in md
    res = cli(*args, "--refine", "radius=0.05")  # these results are the paper's schedule's
    words = " ".join(res.output.split())
    assert res.exit_code != 0 and "from a first radius of 0.01 m, not 0.05" in words, words


@pytest.mark.slow
def test_a_sweep_from_a_wider_icp_radius_refines_every_method_from_it(smoke_project, tmp_path):
    """``--refine radius=R``: sweep.json keeps it, each method's ICP starts there (a refinement
    differs from the paper's schedule's on the same estimates), and the report says so."""
    args = [
        "stress", "--preset", "smoke", "--run", "shared-0/smoke/seed1",
        "--sample", "instances=3,fpfh-instances=3,ppf-instances=0,synth-frames=1",
        "--only", "cut", "--only", "real", "--no-progress",
    ]  # fmt: skip
    tables = {}
    for radius in ("0.01", "0.08"):
        res = cli(*args, "--refine", f"radius={radius}", "--results", str(tmp_path / radius),
                  "--out", str(tmp_path / f"rep{radius}"))  # fmt: skip
        assert res.exit_code == 0, res.output
        assert json.loads((tmp_path / radius / "sweep.json").read_text())["icp_radius"] == float(
            radius
        )
        tables[radius] = pd.read_csv(tmp_path / radius / "results/real/cut/0.1/fpfh.csv")
    # FPFH's estimates (the smoke network's are too far off for any radius) are the same;
    # their refinements are not
    paper, wide = tables["0.01"], tables["0.08"]
    np.testing.assert_array_equal(paper["net_ads"], wide["net_ads"])
    assert not np.array_equal(paper["icp_ads"], wide["icp_ads"])
    md = (tmp_path / "rep0.08" / "stress.md").read_text()
    assert "from a first radius of 8 cm (30 iterations" in md


@pytest.mark.slow
def test_an_ensemble_of_one_network_twice_is_that_network(smoke_project, tmp_path):
    """Two members that agree everywhere tie everywhere: the ensemble keeps the first, so its
    results are the network's own; an ensemble of one network is refused."""
    _, out = smoke_project
    ckpt = str(out.run_dir / "model.pt")
    results = tmp_path / "res"
    args = [
        "stress", "--preset", "smoke", "--run", ckpt,
        "--sample", "instances=3,fpfh-instances=0,ppf-instances=0,synth-frames=1",
        "--only", "cut", "--only", "real", "--results", str(results), "--steps", "sweep",
        "--no-progress",
    ]  # fmt: skip
    res = cli(*args, "--run", ckpt, "--ensemble")
    assert res.exit_code == 0, res.output
    for level in ("0.1", "0.7"):
        folder = results / "results" / "real" / "cut" / level
        ens, net = pd.read_csv(folder / "ensemble.csv"), pd.read_csv(folder / "net-seed1.csv")
        for col in ("net_ads", "icp_ads", "icp_rot_sym_err_deg"):
            np.testing.assert_array_equal(ens[col], net[col])
    res = cli(*args, "--ensemble")
    words = " ".join(res.output.replace("│", " ").split())  # the usage box wraps to the terminal
    assert res.exit_code == 2 and "1 given, at least 2 needed" in words, res.output


def test_a_sweeps_start_selection_results_are_still_reported(tmp_path):
    """The retired start-selection study's tables, where a sweep folder holds them (the
    committed cpu-online sweep does), are one section of the report: a row per source and
    network, a cell per setting."""
    from cloudpose.report.stress import ICP_SELECTIONS, icp_selection_markdown

    assert icp_selection_markdown(tmp_path) == ""
    table = pd.DataFrame({
        "frame_id": ["0000/000001"] * 2, "instance": [1, 2], "cls_id": [1, 2], "icp_ad": [0.001, 0.002],
        "icp_ads": [0.001, 0.002], "icp_rot_err_deg": [2.0, 20.0],
        "icp_rot_sym_err_deg": [2.0, 20.0], "icp_trans_err": [0.004, 0.02], "seconds": [0.5, 0.5],
    })  # fmt: skip
    for setting in ICP_SELECTIONS[:2]:
        path = tmp_path / "icp_select" / "real" / setting / "net-seed1.csv"
        path.parent.mkdir(parents=True)
        table.to_csv(path, index=False)
    md = icp_selection_markdown(tmp_path)
    row = next(line for line in md.splitlines() if line.startswith("| real | net-seed1 |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2] == "2"
    assert "/ 50% / 50% / 12.0 (250 ms)" in cells[3] and cells[4] == cells[3]
    assert cells[5:] == ["", "", ""]  # the settings without a table
