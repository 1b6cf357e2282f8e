"""Pose metrics: AD/ADS fast vs reference twins, rotation/translation errors, the toolbox's VOCap
AUC on hand-computed cases, summaries and occlusion bins."""

from __future__ import annotations

import math
import re

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from cloudpose.conventions import resource_path
from cloudpose.kernels.model_index import ModelIndex
from cloudpose.metrics import (
    SUMMARY_KEYS,
    accuracy_curve,
    add_distance,
    add_distance_reference,
    adds_distance,
    adds_distance_reference,
    flatten_summary,
    fraction_below,
    occlusion_bins,
    per_class_table,
    pose_errors,
    rotation_error_deg,
    summarize,
    translation_error,
    voc_ap_auc,
)


def load_model(name: str) -> np.ndarray:
    return np.loadtxt(resource_path("models", name, "points.xyz"))


def random_poses(rng, M, deg, mm):
    """M ground-truth poses and estimates off by about ``deg`` and ``mm``, as the metrics'
    keyword arguments."""
    R_gt = Rotation.random(M, random_state=rng).as_matrix()
    t_gt = rng.normal(0, 0.1, (M, 3)) + np.array([0, 0, 0.9])
    dR = Rotation.from_rotvec(rng.normal(size=(M, 3)) * np.deg2rad(deg)).as_matrix()
    R_est, t_est = dR @ R_gt, t_gt + rng.normal(0, mm / 1000, (M, 3))
    return {"R_est": R_est, "t_est": t_est, "R_gt": R_gt, "t_gt": t_gt}


def poses_of(R_est, t_est, R_gt, t_gt):
    return {"R_est": R_est, "t_est": t_est, "R_gt": R_gt, "t_gt": t_gt}


def symmetric_ring(n_fold=12, rings=5):
    """Points with exact n-fold symmetry about z (angles k * 360/n)."""
    ang = 2 * np.pi * np.arange(n_fold) / n_fold
    pts = [
        np.c_[r * np.cos(ang + 0.1 * k), r * np.sin(ang + 0.1 * k), np.full(n_fold, z)]
        for k, (r, z) in enumerate(
            zip(np.linspace(0.02, 0.05, rings), np.linspace(-0.03, 0.04, rings), strict=True)
        )
    ]
    return np.concatenate(pts)


# --- AD / ADS --------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["025_mug", "024_bowl", "002_master_chef_can", "036_wood_block"])
@pytest.mark.parametrize(("deg", "mm"), [(0.5, 0.5), (5, 10), (40, 50)])
def test_fast_matches_reference(name, deg, mm):
    model = load_model(name)
    rng = np.random.default_rng([len(name), int(deg)])
    poses = random_poses(rng, 12, deg, mm)
    np.testing.assert_allclose(
        add_distance(model, **poses), add_distance_reference(model, **poses), rtol=1e-12, atol=1e-15
    )
    np.testing.assert_allclose(
        adds_distance(model, **poses),
        adds_distance_reference(model, **poses),
        rtol=1e-12,
        atol=1e-15,
    )


def test_chunks_and_prebuilt_tree_give_the_same_values(monkeypatch):
    import cloudpose.metrics.errors as metrics

    model = load_model("011_banana")
    poses = random_poses(np.random.default_rng(0), 30, 10, 10)
    ad, ads = add_distance(model, **poses), adds_distance(model, **poses)
    monkeypatch.setattr(metrics, "_AD_CHUNK_POINTS", 3 * len(model))
    monkeypatch.setattr(metrics, "_ADS_CHUNK_POINTS", 7 * len(model))
    np.testing.assert_allclose(add_distance(model, **poses), ad, rtol=1e-13)
    np.testing.assert_allclose(
        adds_distance(model, **poses, index=ModelIndex(model)), ads, rtol=1e-13
    )


def test_single_pose_and_float32():
    model = load_model("025_mug")
    poses = random_poses(np.random.default_rng(1), 1, 5, 5)
    one = adds_distance(model, **{k: a[0] for k, a in poses.items()})
    assert one.shape == ()
    assert float(one) == pytest.approx(adds_distance_reference(model, **poses)[0], rel=1e-12)
    # float32 inputs are computed in float64: the same values as the float64 copies
    m32 = model.astype(np.float32)
    f32 = {k: a.astype(np.float32) for k, a in poses.items()}
    f64 = {k: a.astype(np.float64) for k, a in f32.items()}
    np.testing.assert_allclose(
        add_distance(m32, **f32), add_distance_reference(m32.astype(float), **f64), rtol=1e-12
    )
    # ADS maps into the estimate's frame with R^T, exact only for an orthonormal R: float32
    # rounding of a rotation (~1e-7) moves it by about that much, relatively
    np.testing.assert_allclose(
        adds_distance(m32, **f32), adds_distance_reference(m32.astype(float), **f64), rtol=1e-6
    )


def test_identity_and_pure_translation():
    model = load_model("006_mustard_bottle")
    R = Rotation.random(3, random_state=2).as_matrix()
    t = np.array([[0, 0, 1.0], [0.1, 0, 0.8], [0, -0.1, 1.2]])
    same = poses_of(R, t, R, t)
    np.testing.assert_allclose(add_distance(model, **same), 0, atol=1e-15)
    np.testing.assert_allclose(adds_distance(model, **same), 0, atol=1e-15)
    shift = np.array([0.003, -0.004, 0.0])  # 5 mm
    moved = poses_of(R, t + shift, R, t)
    np.testing.assert_allclose(add_distance(model, **moved), 0.005, rtol=1e-12)


def test_symmetric_object_ads_is_zero_for_a_symmetry_and_below_ad():
    ring = symmetric_ring(12)
    R_gt = np.eye(3)[None]
    t_gt = np.array([[0, 0, 1.0]])
    R_sym = Rotation.from_euler("z", 360 / 12 * 5, degrees=True).as_matrix()[None]
    turned = poses_of(R_sym, t_gt, R_gt, t_gt)
    assert add_distance(ring, **turned)[0] > 0.02
    assert adds_distance(ring, **turned)[0] == pytest.approx(0, abs=1e-12)
    assert adds_distance_reference(ring, **turned)[0] == pytest.approx(0, abs=1e-12)
    # ADS <= AD on any pose (the corresponding point is one of the candidates)
    for name in ("024_bowl", "002_master_chef_can", "035_power_drill"):
        model = load_model(name)
        poses = random_poses(np.random.default_rng(3), 20, 30, 20)
        assert (adds_distance(model, **poses) <= add_distance(model, **poses) + 1e-15).all()


def test_bad_shapes_raise():
    model = load_model("025_mug")
    R, t = np.eye(3)[None], np.zeros((1, 3))
    with pytest.raises(ValueError, match="model_points"):
        add_distance(model[:, :2], **poses_of(R, t, R, t))
    with pytest.raises(ValueError, match="t_est"):
        adds_distance(model, **poses_of(R, np.zeros((2, 3)), R, t))
    with pytest.raises(ValueError, match="index: built on"):
        adds_distance(model, **poses_of(R, t, R, t), index=ModelIndex(model[:100]))


# --- rotation / translation errors ----------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_rotation_error_known_angles(dtype):
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    R0 = Rotation.random(random_state=4).as_matrix()
    for deg in (0.0, 1e-5, 1.0, 10.0, 90.0, 179.999, 180.0):
        R1 = R0 @ Rotation.from_rotvec(axis * np.deg2rad(deg)).as_matrix()
        got = rotation_error_deg(R0.astype(dtype), R1.astype(dtype))
        tol = 1e-3 if dtype == np.float32 else 1e-9
        assert got == pytest.approx(deg, abs=tol)
        assert rotation_error_deg(R1, R0) == pytest.approx(rotation_error_deg(R0, R1), abs=1e-9)


def test_rotation_error_matches_scipy_batched():
    A = Rotation.random(50, random_state=5)
    B = Rotation.random(50, random_state=6)
    expect = np.degrees((A.inv() * B).magnitude())
    np.testing.assert_allclose(rotation_error_deg(A.as_matrix(), B.as_matrix()), expect, atol=1e-9)


def test_translation_error():
    assert translation_error([0.003, 0.004, 1], [0, 0, 1]) == pytest.approx(0.005)
    np.testing.assert_allclose(translation_error(np.eye(3)[:2], np.zeros((2, 3))), [1, 1])


def _bop_adi(R_est, t_est, R_gt, t_gt, pts):
    """bop_toolkit_lib/pose_error.py ``adi``, transliterated."""
    from scipy.spatial import cKDTree

    pts_est = (R_est.dot(pts.T) + t_est.reshape((3, 1))).T
    pts_gt = (R_gt.dot(pts.T) + t_gt.reshape((3, 1))).T
    nn_dists, _ = cKDTree(pts_est).query(pts_gt, k=1)
    return nn_dists.mean()


def _bop_add(R_est, t_est, R_gt, t_gt, pts):
    """bop_toolkit_lib/pose_error.py ``add``, transliterated."""
    pts_est = (R_est.dot(pts.T) + t_est.reshape((3, 1))).T
    pts_gt = (R_gt.dot(pts.T) + t_gt.reshape((3, 1))).T
    return np.linalg.norm(pts_est - pts_gt, axis=1).mean()


def test_argument_order_is_bop_toolkits():
    """ADS of a pose pair where swapping estimate and ground truth gives another number: the
    keyword arguments mean what bop_toolkit's positions mean, estimate first; positional poses
    are refused."""
    rng = np.random.default_rng(11)
    # a rod whose points thin out along x, the estimate 1 cm along it: the mean distance from
    # the ground-truth copy to the estimate's is not the mean distance back
    x = 0.1 * rng.random(600) ** 3
    model = np.c_[x, rng.normal(0, 0.003, (600, 2))]
    R_est = Rotation.from_rotvec([0.3, 0.1, 0.0]).as_matrix()
    t_est, R_gt, t_gt = np.array([0.01, 0.0, 0.9]), np.eye(3), np.array([0.0, 0.0, 0.9])
    bop = _bop_adi(R_est, t_est, R_gt, t_gt, model)
    swapped = _bop_adi(R_gt, t_gt, R_est, t_est, model)
    assert abs(bop - swapped) > 0.5 * swapped  # the case tells the orders apart (4.9, 2.4 mm)
    poses = poses_of(R_est, t_est, R_gt, t_gt)
    assert float(adds_distance(model, **poses)) == pytest.approx(bop, rel=1e-12)
    assert float(adds_distance_reference(model, **poses)) == pytest.approx(bop, rel=1e-12)
    assert float(add_distance(model, **poses)) == pytest.approx(
        _bop_add(R_est, t_est, R_gt, t_gt, model), rel=1e-12
    )
    M = {1: model}
    out = pose_errors(M, [1], **{k: a[None] for k, a in poses.items()})
    assert out["ads"][0] == pytest.approx(bop, rel=1e-12)
    for f in (add_distance, adds_distance, add_distance_reference, adds_distance_reference):
        with pytest.raises(TypeError):
            f(model, R_est, t_est, R_gt, t_gt)
    with pytest.raises(TypeError):
        pose_errors(M, [1], R_est[None], t_est[None], R_gt[None], t_gt[None])
    # the symmetric errors take bop's order positionally; a swap gives the same number
    assert translation_error(t_est, t_gt) == translation_error(t_gt, t_est)
    assert rotation_error_deg(R_est, R_gt) == rotation_error_deg(R_gt, R_est)


# --- pose_errors over mixed classes ---------------------------------------------------------


def test_pose_errors_mixed_classes_with_misses():
    models = {5: load_model("006_mustard_bottle"), 13: load_model("024_bowl")}
    rng = np.random.default_rng(7)
    cls = np.array([5, 13, 5, 13, 13, 5])
    poses = random_poses(rng, 6, 10, 10)
    miss = np.array([False, False, True, False, True, False])
    poses["R_est"][miss] = np.nan  # estimates of misses are ignored
    out = pose_errors(models, cls, **poses, miss=miss)
    assert set(out) == {"cls_id", "miss", "ad", "ads", "rot_err_deg", "trans_err"}
    for key in ("ad", "ads", "rot_err_deg", "trans_err"):
        assert np.isinf(out[key][miss]).all()
        assert np.isfinite(out[key][~miss]).all()
    for i in np.flatnonzero(~miss):
        one = {k: a[i : i + 1] for k, a in poses.items()}
        assert out["ad"][i] == pytest.approx(
            add_distance_reference(models[cls[i]], **one)[0], rel=1e-12
        )
        assert out["ads"][i] == pytest.approx(
            adds_distance_reference(models[cls[i]], **one)[0], rel=1e-12
        )
    dt = np.linalg.norm(poses["t_gt"] - poses["t_est"], axis=1)
    np.testing.assert_allclose(out["trans_err"][~miss], dt[~miss])
    assert len(pd.DataFrame(out)) == 6


def test_pose_errors_rejects_bad_input():
    models = {1: load_model("002_master_chef_can")}
    poses = random_poses(np.random.default_rng(8), 2, 5, 5)
    with pytest.raises(ValueError, match=r"classes \[7\]"):
        pose_errors(models, [1, 7], **poses)
    poses["R_est"][1] = np.nan
    with pytest.raises(ValueError, match="not marked as misses"):
        pose_errors(models, [1, 1], **poses)


# --- VOCap AUC -------------------------------------------------------------------------------


def voc_ap_matlab(distances, max_threshold=0.1):
    """Line-by-line transliteration of the YCB-Video toolbox (MATLAB) VOCap, with its loop."""
    d = np.array(distances, dtype=float)
    d[d > max_threshold] = np.inf
    d = np.sort(d)
    n = len(d)
    acc = np.cumsum(np.ones(n)) / n
    rec, prec = d[np.isfinite(d)], acc[np.isfinite(d)]
    if len(rec) == 0:
        return 0.0
    mrec = [0.0, *rec, max_threshold]
    mpre = [0.0, *prec, prec[-1]]
    for i in range(1, len(mpre)):
        mpre[i] = max(mpre[i], mpre[i - 1])
    ap = 0.0
    for i in range(1, len(mrec)):
        if mrec[i] != mrec[i - 1]:
            ap += (mrec[i] - mrec[i - 1]) * mpre[i]
    return ap / max_threshold


@pytest.mark.parametrize(
    ("distances", "expected"),
    [
        ([0.0, 0.0, 0.0], 1.0),  # all perfect
        ([0.0, np.inf], 0.5),  # one miss among two: x=[0,0,.1], y=[0,.5,.5]
        ([0.05], 1.0),  # VOCap takes the right end of each step
        ([0.02, 0.04, np.inf, 0.2], 0.45),  # 10*(.02*.25 + .02*.5 + .06*.5); 0.2 m -> inf
        ([0.03, 0.03], 0.85),  # a tie: 10*(.03*.5 + .07*1); the repeated x is skipped
        ([0.1], 1.0),  # exactly 0.1 m stays in range
        ([0.1000001], 0.0),  # just above: infinite
        ([np.inf, np.inf], 0.0),  # all misses
        (
            [0.01, 0.02, 0.03, 0.04],
            10 * (0.01 * 0.25 + 0.01 * 0.5 + 0.01 * 0.75 + 0.01 * 1 + 0.06 * 1),
        ),
    ],
)
def test_voc_ap_hand_computed(distances, expected):
    assert voc_ap_auc(np.array(distances)) == pytest.approx(expected, abs=1e-12)
    assert voc_ap_matlab(distances) == pytest.approx(expected, abs=1e-12)


def test_voc_ap_order_free_and_empty():
    d = np.array([0.07, np.inf, 0.001, 0.03, 0.5, 0.03])
    assert voc_ap_auc(d) == pytest.approx(voc_ap_auc(d[::-1]), abs=1e-15)
    assert math.isnan(voc_ap_auc(np.array([])))
    with pytest.raises(ValueError, match="distances"):
        voc_ap_auc(np.array([0.01, np.nan]))


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.one_of(st.floats(0, 0.15, allow_nan=False), st.just(math.inf)), min_size=1, max_size=30
    ),
    st.integers(0, 29),
    st.floats(0, 1),
)
def test_voc_ap_matches_transliteration_and_is_monotone(distances, i, shrink):
    d = np.array(distances)
    auc = voc_ap_auc(d)
    assert auc == pytest.approx(voc_ap_matlab(d), abs=1e-12)
    assert 0.0 <= auc <= 1.0 + 1e-12
    # improving one instance never lowers the AUC
    better = d.copy()
    j = i % len(d)
    better[j] = shrink * d[j] if np.isfinite(d[j]) else 0.05 * shrink
    assert voc_ap_auc(better) >= auc - 1e-12


def test_accuracy_curve_and_fraction_below():
    d = np.array([0.005, 0.01, 0.02, np.inf])
    np.testing.assert_allclose(
        accuracy_curve(d, [0.0, 0.005, 0.01, 0.05, 1.0]), [0, 0.25, 0.5, 0.75, 0.75]
    )
    assert fraction_below(d, 0.01) == 0.25  # strictly below
    assert fraction_below(d, 0.0101) == 0.5
    assert math.isnan(fraction_below(np.array([]), 0.01))


# --- summaries ------------------------------------------------------------------------------


def results_frame():
    return pd.DataFrame(
        {
            "cls_id": [1, 1, 1, 2],
            "class": ["can", "can", "can", "box"],
            "ad": [0.005, 0.02, np.inf, 0.0],
            "ads": [0.005, 0.012, np.inf, 0.0],
            "rot_err_deg": [5.0, 12.0, np.inf, 25.0],
            "trans_err": [0.002, 0.03, np.inf, 0.0],
        }
    )


def test_summarize_pooled_class_mean_and_per_class():
    df = results_frame()
    s = summarize(df)
    pooled = s["pooled"]
    assert pooled["count"] == 4
    assert pooled["ads_lt_1cm"] == pytest.approx(2 / 4)
    assert pooled["rot_lt_10deg"] == pytest.approx(1 / 4)
    assert pooled["rot_lt_15deg"] == pytest.approx(2 / 4)
    assert pooled["rot_lt_20deg"] == pytest.approx(2 / 4)
    assert pooled["trans_lt_1cm"] == pytest.approx(2 / 4)
    assert pooled["ads_auc"] == pytest.approx(voc_ap_matlab(df["ads"]))
    assert pooled["ad_auc"] == pytest.approx(voc_ap_matlab(df["ad"]))
    table = s["per_class"]
    assert list(table.index) == ["can", "box"]
    assert table.loc["can", "ads_lt_1cm"] == pytest.approx(1 / 3)
    assert table.loc["box", "ads_auc"] == pytest.approx(1.0)
    assert table.loc["can", "count"] == 3
    for key in SUMMARY_KEYS:
        assert s["class_mean"][key] == pytest.approx(table[key].mean())
    assert s["class_mean"]["ads_lt_1cm"] == pytest.approx((1 / 3 + 1) / 2)
    assert all(table.dtypes.map(pd.api.types.is_numeric_dtype))


def test_flat_keys_are_valid_mlflow_keys():
    flat = flatten_summary(summarize(results_frame()))
    assert flat["ads_lt_1cm"] == pytest.approx(0.5)
    assert "class_mean/ads_auc" in flat and "class/can/ads_auc" in flat
    assert all(re.fullmatch(r"[A-Za-z0-9_\-. /]+", k) for k in flat)


def test_per_class_by_id_without_names_and_missing_columns():
    df = results_frame().drop(columns="class")
    assert list(per_class_table(df).index) == [1, 2]
    with pytest.raises(ValueError, match="missing columns"):
        summarize(df.drop(columns="ads"))


def test_occlusion_bins():
    occ = np.array([0.0, 0.05, 0.1, 0.3, 0.3, 0.95, 1.0, -0.02, np.nan])
    ads = np.array([0.001, 0.02, 0.005, 0.009, np.inf, 0.0, 0.5, 0.001, 0.0])
    bins = occlusion_bins(occ, ads)
    assert list(bins.columns) == ["bin_lo", "bin_hi", "count", "ads_lt_1cm"]
    assert len(bins) == 10
    np.testing.assert_allclose(bins["bin_lo"], np.arange(10) / 10)
    # bin 0: 0.0, 0.05, -0.02 (clipped) -> 2 of 3 hits; 0.1 -> bin 1; both 0.3 -> bin 3; 0.95
    # and 1.0 -> bin 9; NaN left out
    np.testing.assert_array_equal(bins["count"], [3, 1, 0, 2, 0, 0, 0, 0, 0, 2])
    np.testing.assert_allclose(bins["ads_lt_1cm"].iloc[[0, 1, 3, 9]], [2 / 3, 1, 0.5, 0.5])
    assert np.isnan(bins["ads_lt_1cm"].iloc[2])
    with pytest.raises(ValueError, match="width"):
        occlusion_bins(occ, ads, width=0.3)


# --- compiled ADS against the pykdtree path ---------------------------------------------------


@pytest.mark.parametrize(("deg", "mm"), [(0.0, 0.0), (2, 3), (5, 10), (30, 50), (180, 200)])
def test_compiled_ads_equals_the_pykdtree_path(deg, mm, monkeypatch):
    """The numba kernel (neighbour walk + certificate) and the vectorised pykdtree path agree
    to rounding over the whole error range, and both with the per-instance reference."""
    from cloudpose import kernels

    if not kernels.enabled():
        pytest.skip("compiled kernels off (numba not installed or CLOUDPOSE_NO_NUMBA)")
    model = load_model("035_power_drill")
    poses = random_poses(np.random.default_rng(int(deg) + 1), 40, deg, mm)
    index = ModelIndex(model)
    assert index.compiled is not None
    fast = adds_distance(model, **poses, index=index)
    slow = adds_distance(model, **poses, index=ModelIndex(model, compiled=False))  # pykdtree
    np.testing.assert_allclose(fast, slow, rtol=1e-13, atol=1e-17)
    ref = adds_distance_reference(model, **{k: a[:8] for k, a in poses.items()})
    np.testing.assert_allclose(fast[:8], ref, rtol=1e-12, atol=1e-15)


def test_one_occlusion_binning_for_the_plot_and_the_histogram():
    from types import SimpleNamespace

    from cloudpose.metrics import occlusion_bin_index, occlusion_bins
    from cloudpose.report.plots import occlusion_histogram

    occ = np.array([-0.05, 0.0, 0.1, 0.95, 1.0, np.nan])
    index, n_bins = occlusion_bin_index(occ)
    assert n_bins == 10 and index.tolist() == [0, 0, 1, 9, 9, -1]
    plot = occlusion_bins(occ, np.zeros(6))["count"].to_numpy()
    hist = occlusion_histogram(SimpleNamespace(occlusion=occ))
    assert plot.tolist() == hist.tolist() == [2, 1, 0, 0, 0, 0, 0, 0, 0, 2]
