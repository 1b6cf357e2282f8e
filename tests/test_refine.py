"""ICP refinement: the fast model-frame path against ten Open3D calls, and Open3D's semantics."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from cloudpose.conventions import resource_path
from cloudpose.geometry.rigid import correspondence_moments, umeyama_from_moments, umeyama_rigid
from cloudpose.kernels.model_index import ModelIndex
from cloudpose.metrics import rotation_error_deg
from cloudpose.refine import (
    ICPSettings,
    ICPSolution,
    icp_refine,
    icp_refine_batch,
    icp_refine_open3d,
    schedule_for,
    start_rotations,
)

MODELS = ("025_mug", "003_cracker_box", "024_bowl", "002_master_chef_can", "037_scissors")


def load_model(name: str) -> np.ndarray:
    return np.loadtxt(resource_path("models", name, "points.xyz"))


def visible_case(rng, model, n=1024, deg=3.0, mm=3.0, noise=0.001):
    """Observed = camera-facing part of the model at a random GT pose + noise; init = GT
    perturbed by ``deg`` degrees and ``mm`` millimetres (random directions)."""
    R = Rotation.random(random_state=rng).as_matrix()
    t = np.array([0.05, -0.03, 0.8]) + rng.normal(0, 0.05, 3)
    cam = model @ R.T + t
    c = cam.mean(axis=0)
    visible = (cam - c) @ (-c / np.linalg.norm(c)) > -0.005  # the half facing the camera
    pts = cam[visible]
    pts = pts[rng.choice(len(pts), n)] + rng.normal(0, noise, (n, 3))
    axis = rng.normal(size=3)
    dR = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.deg2rad(deg)).as_matrix()
    dt = rng.normal(size=3)
    return pts, dR @ R, t + dt / np.linalg.norm(dt) * mm / 1000, R, t


def assert_same(a: ICPSolution, b: ICPSolution, tol=1e-9):
    np.testing.assert_allclose(a.R, b.R, atol=tol)
    np.testing.assert_allclose(a.t, b.t, atol=tol)
    assert a.fitness == pytest.approx(b.fitness, abs=1e-12)
    assert a.inlier_rmse == pytest.approx(b.inlier_rmse, abs=1e-12)


@pytest.mark.parametrize("name", MODELS)
@pytest.mark.parametrize(("deg", "mm"), [(3.0, 3.0), (10.0, 8.0)])
def test_fast_matches_ten_open3d_calls(name, deg, mm):
    model = load_model(name)
    rng = np.random.default_rng([MODELS.index(name), int(deg)])
    for _ in range(4):
        obs, R0, t0, _, _ = visible_case(rng, model, deg=deg, mm=mm)
        fast = icp_refine(obs, model, R0, t0)
        ref = icp_refine_open3d(obs, model, R0, t0)
        assert_same(fast, ref)
        assert 0 < fast.fitness <= 1
        np.testing.assert_allclose(fast.R.T @ fast.R, np.eye(3), atol=1e-12)
        assert np.linalg.det(fast.R) == pytest.approx(1.0)


@pytest.mark.parametrize(
    "settings",
    [ICPSettings(iterations=3), ICPSettings(max_distance=0.02, shrink=1.0), ICPSettings(1, 0.005)],
)
def test_other_schedules_match_open3d(settings):
    model = load_model("006_mustard_bottle")
    rng = np.random.default_rng(3)
    for _ in range(3):
        obs, R0, t0, _, _ = visible_case(rng, model, n=500, deg=5, mm=5)
        assert_same(
            icp_refine(obs, model, R0, t0, settings),
            icp_refine_open3d(obs, model, R0, t0, settings),
        )


def test_refinement_moves_towards_ground_truth():
    model = load_model("003_cracker_box")
    rng = np.random.default_rng(0)
    before, after = [], []
    for _ in range(5):
        obs, R0, t0, R, t = visible_case(rng, model, deg=3, mm=4, noise=0.0005)
        sol = icp_refine(obs, model, R0, t0)
        # AD-style error over the model points, metres
        before.append(np.linalg.norm(model @ (R0 - R).T + (t0 - t), axis=1).mean())
        after.append(np.linalg.norm(model @ (sol.R - R).T + (sol.t - t), axis=1).mean())
    assert np.mean(after) < 0.5 * np.mean(before)


def test_exact_pose_is_a_fixed_point():
    model = load_model("025_mug")
    rng = np.random.default_rng(1)
    R = Rotation.random(random_state=rng).as_matrix()
    t = np.array([0.0, 0.1, 0.7])
    obs = model[rng.choice(len(model), 600, replace=False)] @ R.T + t
    sol = icp_refine(obs, model, R, t)
    np.testing.assert_allclose(sol.R, R, atol=1e-12)
    np.testing.assert_allclose(sol.t, t, atol=1e-12)
    assert sol.fitness == 1.0
    assert sol.inlier_rmse < 1e-12


def test_fitness_and_rmse_follow_open3d_definitions():
    """Fitness = share of observed points with a model point within the last radius at the
    refined pose; inlier RMSE = RMS of those nearest distances (brute force here)."""
    model = load_model("021_bleach_cleanser")
    rng = np.random.default_rng(5)
    obs, R0, t0, _, _ = visible_case(rng, model, n=800, deg=8, mm=8, noise=0.003)
    settings = ICPSettings()
    sol = icp_refine(obs, model, R0, t0, settings)
    d = cdist(obs, model @ sol.R.T + sol.t).min(axis=1)
    r = settings.radii()[-1]
    inl = d < r
    assert 0 < inl.mean() < 1  # a case that exercises the radius
    assert sol.fitness == pytest.approx(inl.mean(), abs=1e-12)
    assert sol.inlier_rmse == pytest.approx(np.sqrt(np.mean(d[inl] ** 2)), rel=1e-9)


def test_batch_equals_single_calls():
    models = {n: load_model(n) for n in ("025_mug", "024_bowl")}
    rng = np.random.default_rng(7)
    obs, mps, Rs, ts = [], [], [], []
    for k in range(6):
        name = ("025_mug", "024_bowl")[k % 2]
        o, R0, t0, _, _ = visible_case(rng, models[name], n=300 + 50 * k, deg=5, mm=5)
        obs.append(o)
        mps.append(models[name] if k < 4 else ModelIndex(models[name]))
        Rs.append(R0)
        ts.append(t0)
    obs.append(np.zeros((2, 3)))  # degenerate: returned as is
    mps.append(models["025_mug"])
    Rs.append(np.eye(3))
    ts.append(np.zeros(3))
    with pytest.warns(UserWarning, match="2 observed points"):
        batch = icp_refine_batch(obs, mps, np.stack(Rs), np.stack(ts))
    assert len(batch) == len(obs)
    for o, m, R0, t0, b in zip(obs[:-1], mps, Rs, ts, batch, strict=False):
        assert_same(b, icp_refine(o, m, R0, t0), tol=0)
    assert batch[-1].fitness == 0.0


@pytest.mark.parametrize("impl", [icp_refine, icp_refine_open3d])
def test_too_few_points_returns_init_with_warning(impl):
    model = load_model("025_mug")
    R0, t0 = Rotation.from_euler("z", 30, degrees=True).as_matrix(), np.array([0, 0, 1.0])
    with pytest.warns(UserWarning, match="observed points"):
        sol = impl(model[:2] @ R0.T + t0, model, R0, t0)
    np.testing.assert_array_equal(sol.R, R0)
    np.testing.assert_array_equal(sol.t, t0)
    assert (sol.fitness, sol.inlier_rmse) == (0.0, 0.0)


@pytest.mark.parametrize("impl", [icp_refine, icp_refine_open3d])
def test_no_correspondence_returns_init_with_warning(impl):
    model = load_model("025_mug")
    R0, t0 = np.eye(3), np.array([0, 0, 1.0])
    far = model @ R0.T + t0 + np.array([0.5, 0, 0])  # half a metre from the posed model
    with pytest.warns(UserWarning, match="no model point within"):
        sol = impl(far, model, R0, t0)
    np.testing.assert_array_equal(sol.R, R0)
    np.testing.assert_array_equal(sol.t, t0)
    assert sol.fitness == 0.0


def test_no_warning_in_the_normal_case():
    model = load_model("025_mug")
    obs, R0, t0, R, t = visible_case(np.random.default_rng(2), model)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sol = icp_refine(obs, model, R0, t0)
    # and the refinement did its job: 3 deg / 3 mm off brought to within 1 deg / 1 mm
    assert rotation_error_deg(R, sol.R) < 1.0 and np.linalg.norm(sol.t - t) < 1e-3
    assert sol.fitness > 0.9


def test_settings_schedule_and_validation():
    radii = ICPSettings().radii()
    assert len(radii) == 10
    np.testing.assert_allclose(radii, 0.01 * 0.9 ** np.arange(10), rtol=1e-14)
    bad_settings = (
        dict(iterations=0),
        dict(max_distance=0.0),
        dict(shrink=0.0),
        dict(shrink=1.5),
        dict(starts=25),
        dict(start_margin=-0.1),
    )
    for bad in bad_settings:
        with pytest.raises(ValueError, match="ICPSettings"):
            ICPSettings(**bad)


def test_bad_shapes_raise():
    model = load_model("025_mug")
    with pytest.raises(ValueError, match="observed"):
        icp_refine(np.zeros((10, 2)), model, np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="R_init"):
        icp_refine(model, model, np.eye(4), np.zeros(3))
    with pytest.raises(ValueError, match="model_points"):
        icp_refine(model, model[:, :2], np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="R_init"):
        icp_refine_batch([model], [model], np.eye(3), np.zeros((1, 3)))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_umeyama_recovers_a_rigid_motion(dtype):
    rng = np.random.default_rng(4)
    src = rng.normal(size=(50, 3)).astype(dtype)
    R = Rotation.random(random_state=rng).as_matrix()
    t = rng.normal(size=3)
    dst = src @ R.T + t
    R_hat, t_hat = umeyama_rigid(src.astype(float), dst)
    tol = 1e-5 if dtype == np.float32 else 1e-12
    np.testing.assert_allclose(R_hat, R, atol=tol)
    np.testing.assert_allclose(t_hat, t, atol=tol)


def test_umeyama_gives_a_rotation_for_a_reflected_target():
    rng = np.random.default_rng(6)
    src = rng.normal(size=(40, 3))
    dst = src * np.array([1, 1, -1])  # a mirror image: no rotation fits exactly
    R, _ = umeyama_rigid(src, dst)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_umeyama_matches_scipy_align_vectors():
    """The moment-form Umeyama (numpy and compiled) against scipy's Kabsch on centred points."""
    from cloudpose.kernels.icp import _umeyama_moments

    rng = np.random.default_rng(8)
    for n in (3, 10, 500):
        src = rng.normal(scale=0.05, size=(n, 3))
        dst = src @ Rotation.random(random_state=rng).as_matrix().T + rng.normal(0, 0.01, (n, 3))
        c_s, c_d = src.mean(axis=0), dst.mean(axis=0)
        R_ref = Rotation.align_vectors(dst - c_d, src - c_s)[0].as_matrix()
        S = correspondence_moments(src, dst)
        T = umeyama_from_moments(S)
        np.testing.assert_allclose(T[:3, :3], R_ref, atol=1e-10)
        np.testing.assert_allclose(T[:3, 3], c_d - R_ref @ c_s, atol=1e-10)
        np.testing.assert_allclose(_umeyama_moments(S), T, atol=1e-12)
        R, t = umeyama_rigid(src, dst)
        np.testing.assert_allclose(R, R_ref, atol=1e-10)
        np.testing.assert_allclose(t, c_d - R_ref @ c_s, atol=1e-10)
    np.testing.assert_array_equal(umeyama_from_moments(np.zeros((4, 4))), np.eye(4))


def test_the_compiled_umeyama_is_the_numpy_one_on_every_branch():
    """kernels/icp.py's ``_umeyama_moments`` is geometry/rigid.py's ``umeyama_from_moments``
    compiled (issue 63: one Umeyama or a tested twin): the same transform on each branch, no
    pairs, one or two pairs (a translation), a rotation and a mirror image (the weakest
    direction flipped)."""
    from cloudpose.kernels.icp import _umeyama_moments

    rng = np.random.default_rng(9)
    src = rng.normal(scale=0.05, size=(40, 3))
    turned = src @ Rotation.random(random_state=rng).as_matrix().T + 0.01
    mirrored = src * np.array([1, 1, -1]) + 0.02
    cases = {"none": (src[:0], src[:0]), "one": (src[:1], turned[:1])}
    cases |= {"two": (src[:2], turned[:2]), "rotation": (src, turned)}
    cases |= {"mirror": (src, mirrored)}
    for name, (a, b) in cases.items():
        S = correspondence_moments(a, b)
        T = umeyama_from_moments(S)
        np.testing.assert_allclose(_umeyama_moments(S), T, rtol=0, atol=1e-12, err_msg=name)
    S = correspondence_moments(src, mirrored)
    assert np.linalg.det(umeyama_from_moments(S)[:3, :3]) == pytest.approx(1.0)
    assert np.linalg.det(_umeyama_moments(S)[:3, :3]) == pytest.approx(1.0)


@pytest.mark.parametrize("graph", ["delaunay", "lists"])
@pytest.mark.parametrize("name", MODELS)
def test_compiled_loop_equals_the_pykdtree_loop(name, graph, monkeypatch):
    """The numba ICP loop (correspondences from each point's previous match) and the pykdtree
    loop give the same poses, fitness and RMSE, including cases with outliers."""
    from cloudpose import kernels

    if not kernels.enabled():
        pytest.skip("compiled kernels off (numba not installed or CLOUDPOSE_NO_NUMBA)")
    if graph == "lists":  # the structure used where a model has no 3-D triangulation
        monkeypatch.setattr(kernels.graph, "_delaunay_graph", lambda P: None)
    model = load_model(name)
    rng = np.random.default_rng(MODELS.index(name) + 11)
    index = ModelIndex(model)
    plain = ModelIndex(model, compiled=False)
    for deg, mm in ((1.0, 1.0), (5.0, 6.0), (12.0, 9.0)):
        obs, R0, t0, _, _ = visible_case(rng, model, n=700, deg=deg, mm=mm)
        obs[:40] += rng.normal(0, 0.03, (40, 3))  # outliers beyond every radius
        assert_same(icp_refine(obs, index, R0, t0), icp_refine(obs, plain, R0, t0), tol=1e-12)


def diverging_case():
    """A banana seen from the front, the start 3 cm to its side: ICP slides further off (3.0 ->
    3.4 cm) with 27% of the observed points within the last radius."""
    model = load_model("011_banana")
    rng = np.random.default_rng(0)
    R, t = np.eye(3), np.array([0.0, 0.0, 0.8])
    cam = model @ R.T + t
    c = cam.mean(axis=0)
    visible = (cam - c) @ (-c / np.linalg.norm(c)) > -0.005
    obs = cam[visible][rng.choice(int(visible.sum()), 500)] + rng.normal(0, 0.001, (500, 3))
    return obs, model, R, t + np.array([0.03, 0.0, 0.0]), t


@pytest.mark.parametrize("impl", [icp_refine, icp_refine_open3d])
def test_fallback_keeps_the_start_when_icp_diverges(impl):
    obs, model, R0, t0, t = diverging_case()
    plain = impl(obs, model, R0, t0)
    assert np.linalg.norm(plain.t - t) > np.linalg.norm(t0 - t) + 0.003  # ICP made it worse
    assert plain.fitness < 0.3 and not plain.fallback
    guarded = impl(obs, model, R0, t0, ICPSettings(fallback=True, min_fitness=0.3))
    np.testing.assert_array_equal(guarded.R, R0)
    np.testing.assert_array_equal(guarded.t, t0)
    assert guarded.fallback
    # the figures of the rejected refinement stay, for the per-object log (Open3D's threaded
    # sums may differ in the last bit between two calls)
    assert guarded.fitness == plain.fitness
    assert guarded.inlier_rmse == pytest.approx(plain.inlier_rmse, rel=1e-12)
    batch = icp_refine_batch(
        [obs], [model], R0[None], t0[None], ICPSettings(fallback=True, min_fitness=0.3)
    )
    assert batch[0].fallback
    np.testing.assert_array_equal(batch[0].t, t0)


def test_fallback_leaves_a_converged_refinement_alone():
    model = load_model("025_mug")
    obs, R0, t0, _, _ = visible_case(np.random.default_rng(2), model)
    on = ICPSettings(fallback=True, min_fitness=0.5)
    assert_same(icp_refine(obs, model, R0, t0, on), icp_refine(obs, model, R0, t0), tol=0)
    assert not icp_refine(obs, model, R0, t0, on).fallback


def test_guard_threshold_is_checked():
    with pytest.raises(ValueError, match="min_fitness"):
        ICPSettings(min_fitness=1.5)
    from cloudpose.config import ICPConfig

    with pytest.raises(ValueError, match=r"icp\.fallback_min_fitness"):
        ICPConfig(fallback_min_fitness=-0.1)


def test_icp_config_section_keeps_stored_runs_identity():
    """A config stored before the ``icp`` section existed reads back with the guard off and
    the same fingerprint; turning the guard on is another config; the paper presets keep it
    off."""
    from cloudpose.config import Config
    from cloudpose.registry import resolve

    cfg = resolve("shared-0", "cpu", 1)
    stored = cfg.to_dict()
    del stored["icp"]
    back = Config.from_dict(stored)
    assert back == cfg and back.fingerprint() == cfg.fingerprint()
    assert cfg.fingerprint() == "ef338e3a7c1144f5"  # the committed cpu sweep's shared-0 seed 1
    on = resolve("shared-0", "cpu", 1, {"icp": {"fallback": True}})
    assert on.fingerprint() != cfg.fingerprint()
    assert ICPSettings.from_config(on.icp) == ICPSettings(fallback=True, min_fitness=0.1)
    for preset in ("paper", "cpu-paper"):
        assert not resolve("shared-0", preset, 1).icp.fallback


@pytest.mark.parametrize("n", [1, 12, 24, 60])
def test_start_rotations_are_a_rotation_group_with_the_identity_first(n):
    D = start_rotations(n)
    assert D.shape == (n, 3, 3)
    np.testing.assert_array_equal(D[0], np.eye(3))
    np.testing.assert_allclose(
        np.einsum("nij,nkj->nik", D, D), np.broadcast_to(np.eye(3), D.shape), atol=1e-12
    )
    # closed under composition, every element distinct: the group itself
    prod = np.einsum("aij,bjk->abik", D, D).reshape(-1, 1, 9)
    assert (np.abs(prod - D.reshape(1, n, 9)).max(axis=2) < 1e-9).any(axis=1).all()
    assert len(np.unique(np.round(D.reshape(n, 9), 6), axis=0)) == n


def test_several_starts_recover_an_estimate_turned_beyond_icps_reach():
    """An estimate a quarter turn off an asymmetric object: ICP from it alone stays in the
    wrong basin; from the octahedral group's 24 starts the best fit is the true pose."""
    model = load_model("035_power_drill")
    rng = np.random.default_rng(5)
    obs, _, _, R, t = visible_case(rng, model)
    turn = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    R0, t0 = R @ turn, t + np.array([0.002, -0.001, 0.002])
    one = icp_refine(obs, model, R0, t0)
    assert rotation_error_deg(one.R[None], R[None])[0] > 45
    many = icp_refine(obs, model, R0, t0, ICPSettings(starts=24))
    assert rotation_error_deg(many.R[None], R[None])[0] < 2
    assert many.fitness > one.fitness + 0.02
    batch = icp_refine_batch([obs], [model], R0[None], t0[None], ICPSettings(starts=24))
    assert_same(batch[0], many, tol=0)
    with pytest.raises(ValueError, match="starts=1"):
        icp_refine_open3d(obs, model, R0, t0, ICPSettings(starts=24))


def test_several_starts_keep_the_estimate_where_fits_tie():
    """On a can, turns about its axis fit equally well: the estimate's own refinement stays
    (the margin), so a symmetric object's pose is the network's, not the first tied start's."""
    model = load_model("002_master_chef_can")
    rng = np.random.default_rng(6)
    obs, R0, t0, _, _ = visible_case(rng, model, deg=2.0, mm=2.0)
    one = icp_refine(obs, model, R0, t0)
    assert_same(icp_refine(obs, model, R0, t0, ICPSettings(starts=24)), one, tol=0)
    # the estimate itself at one start equals the paper's schedule exactly
    assert_same(icp_refine(obs, model, R0, t0, ICPSettings(starts=1)), one, tol=0)


def test_a_start_without_correspondences_is_passed_over_quietly():
    """Starts that leave every observed point outside the first radius are not candidates and
    warn nothing; the estimate's own refinement, which has correspondences, is kept."""
    model = load_model("003_cracker_box")
    obs, R0, t0, _, _ = visible_case(np.random.default_rng(7), model)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sol = icp_refine(obs, model, R0, t0, ICPSettings(starts=60, max_distance=0.002))
    assert sol.fitness > 0


def test_icp_starts_keep_stored_runs_identity():
    from cloudpose.config import Config, ICPConfig
    from cloudpose.registry import resolve

    cfg = resolve("shared-0", "cpu-online", 1)
    stored = cfg.to_dict()
    del stored["icp"]["starts"], stored["icp"]["start_margin"]
    assert Config.from_dict(stored).fingerprint() == cfg.fingerprint()
    many = resolve("shared-0", "cpu-online", 1, {"icp": {"starts": 24}})
    assert many.fingerprint() != cfg.fingerprint()
    assert ICPSettings.from_config(many.icp).starts == 24
    with pytest.raises(ValueError, match=r"icp\.starts must be one of \[1, 12, 24, 60\]"):
        ICPConfig(starts=6)


def test_a_wider_first_radius_ends_at_the_papers_last_radius():
    paper = ICPSettings()
    assert ICPSettings(**schedule_for(0.01)) == paper
    for radius in (0.02, 0.03, 0.05, 0.08, 0.12, 0.5):
        radii = ICPSettings(**schedule_for(radius)).radii()
        assert radii[0] == radius
        assert radii[-1] == pytest.approx(paper.radii()[-1], rel=0.05)
    for radius in (0.005, 0.6, float("nan")):
        with pytest.raises(ValueError, match=r"expected from the paper's 0\.01 to 0\.5 m"):
            schedule_for(radius)


@pytest.mark.parametrize("name", ["003_cracker_box", "006_mustard_bottle", "025_mug"])
def test_a_wider_first_radius_brings_home_an_estimate_25_mm_off(name):
    """25 mm and 10 degrees off: from the paper's 1 cm radius ICP stays more than 1 cm away;
    from 5 cm (schedule_for) it ends on the true pose."""
    model = load_model(name)
    obs, R0, t0, R, t = visible_case(np.random.default_rng(1), model, deg=10.0, mm=25.0)
    paper = icp_refine(obs, model, R0, t0)
    assert np.linalg.norm(paper.t - t) > 0.01
    wide = icp_refine(obs, model, R0, t0, ICPSettings(**schedule_for(0.05)))
    assert np.linalg.norm(wide.t - t) < 0.002
    assert rotation_error_deg(wide.R[None], R[None])[0] < 1.0
    batch = icp_refine_batch([obs], [model], R0[None], t0[None], ICPSettings(**schedule_for(0.05)))
    assert_same(batch[0], wide, tol=0)


def test_icp_radius_keeps_stored_runs_identity():
    from cloudpose.config import Config, ICPConfig
    from cloudpose.registry import resolve

    cfg = resolve("shared-0", "cpu-online", 1)
    stored = cfg.to_dict()
    del stored["icp"]["radius"]
    assert Config.from_dict(stored).fingerprint() == cfg.fingerprint()
    assert ICPSettings.from_config(cfg.icp) == ICPSettings()
    wide = resolve("shared-0", "cpu-online", 1, {"icp": {"radius": 0.05}})
    assert wide.fingerprint() != cfg.fingerprint()
    assert ICPSettings.from_config(wide.icp) == ICPSettings(max_distance=0.05, iterations=25)
    with pytest.raises(ValueError, match=r"icp\.radius must be in \[0.01, 0.5\] metres"):
        ICPConfig(radius=0.002)


def test_refine_poses_applies_the_guard_and_reports_each_object():
    """The per-object figures that evaluate logs (fitness, inlier RMSE, fallback) and the pose
    kept where the guard trips."""
    from cloudpose.data.cache import SegmentSet
    from cloudpose.refine import Estimates, refine_poses

    obs, model, R0, t0, _ = diverging_case()
    segs = SegmentSet.__new__(SegmentSet)
    segs.points = np.stack([obs, obs]).astype(np.float32)
    segs.count = np.array([500, 500])
    segs.cls_id = np.array([11, 11])
    segs.valid = np.array([True, False])
    est = Estimates(np.stack([R0, R0]), np.stack([t0, t0]))
    out, stats = refine_poses(segs, est, {11: model}, ICPSettings(fallback=True, min_fitness=0.3))
    assert stats.fallback.tolist() == [True, False]
    assert 0 < stats.fitness[0] < 0.3 and 0 < stats.inlier_rmse[0] < 0.004
    assert np.isnan(stats.fitness[1]) and np.isnan(stats.inlier_rmse[1])
    np.testing.assert_allclose(out.t[0], t0, atol=1e-6)


def zbuffer_view(model, R, t, f=300.0, size=120):
    """A depth image of the posed model alone (nearest point per pixel, 0 elsewhere) and its
    intrinsics: the observed depth of a scene that holds the object only."""
    from cloudpose.refine import DepthView

    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    X = model @ R.T + t
    uv = np.floor(X @ K.T / X[:, 2:3] + 0.5)[:, :2].astype(int)
    depth = np.full((size, size), np.inf)
    ok = (uv >= 0).all(axis=1) & (uv < size).all(axis=1)
    np.minimum.at(depth, (uv[ok, 1], uv[ok, 0]), X[ok, 2])
    depth[np.isinf(depth)] = 0.0
    return DepthView(depth, K)


def test_depth_agreement_sees_a_model_in_front_of_the_observed_surface():
    """At the true pose no model point lies in front of the observed depth and the segment is
    covered; moved 3 cm towards the camera, much of the model lies in seen-through space."""
    from cloudpose.refine import depth_agreement, depth_score

    model = load_model("003_cracker_box")
    obs, _, _, R, t = visible_case(np.random.default_rng(8), model, noise=0.0)
    view = zbuffer_view(model, R, t)
    true = depth_agreement(obs, model, R, t, view)
    assert true.violation == 0.0 and true.coverage > 0.99
    near = depth_agreement(obs, model, R, t - 0.03 * t / np.linalg.norm(t), view)
    assert near.violation > 0.2 and near.coverage < true.coverage
    assert depth_score(1.0, true) > depth_score(1.0, near)


def test_depth_selection_recovers_the_turned_estimate_and_needs_the_depth():
    """Scored by the depth, the 24 starts find the true pose of the quarter-turned drill as the
    fitness does; without a view the setting is refused, and it is checked by name."""
    from cloudpose.config import Config, ICPConfig
    from cloudpose.registry import resolve

    model = load_model("035_power_drill")
    obs, _, _, R, t = visible_case(np.random.default_rng(5), model)
    turn = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    R0, t0 = R @ turn, t + np.array([0.002, -0.001, 0.002])
    view = zbuffer_view(model, R, t)
    depth = icp_refine(obs, model, R0, t0, ICPSettings(starts=24, select="depth"), view=view)
    assert rotation_error_deg(depth.R[None], R[None])[0] < 2
    batch = icp_refine_batch(
        [obs], [model], R0[None], t0[None], ICPSettings(starts=24, select="depth"), views=[view]
    )
    assert_same(batch[0], depth, tol=0)
    # one start: nothing to select, the paper's refinement whatever the score
    one = icp_refine(obs, model, R0, t0)
    assert_same(icp_refine(obs, model, R0, t0, ICPSettings(select="depth"), view=view), one, 0)
    with pytest.raises(ValueError, match="need the frame's depth"):
        icp_refine(obs, model, R0, t0, ICPSettings(starts=24, select="depth"))
    with pytest.raises(ValueError, match=r"ICPSettings\.select"):
        ICPSettings(select="votes")
    with pytest.raises(ValueError, match=r"icp\.select"):
        ICPConfig(select="votes")
    cfg = resolve("shared-0", "cpu-online", 1, {"icp": {"starts": 24, "select": "depth"}})
    assert ICPSettings.from_config(cfg.icp).select == "depth"
    # a stored run without the field keeps its identity (select is implied "fitness")
    own = resolve("shared-0", "cpu-online", 1)
    stored = own.to_dict()
    del stored["icp"]["select"]
    assert Config.from_dict(stored).fingerprint() == own.fingerprint()


def _rows(points, valid):
    """A segment set of the given points (all observed), class 1, without ground truth."""
    from cloudpose.data.segment_set import SegmentSet

    m = len(points)
    return SegmentSet(
        points=points.astype(np.float32),
        count=np.full(m, points.shape[1], dtype=np.int32),
        cls_id=np.ones(m, dtype=np.int16),
        R=np.full((m, 3, 3), np.nan, np.float32),
        t=np.full((m, 3), np.nan, np.float32),
        occlusion=np.full(m, np.nan, np.float32),
        frame_id=np.array([f"0000/{i:06d}" for i in range(m)]),
        instance=np.zeros(m, dtype=np.int16),
        valid=np.asarray(valid, dtype=bool),
    )


def _box_scene():
    """A 10 cm box (model frame), its front face seen at 0.95 m on a depth image that reads
    0.95 m everywhere, and two poses that both explain the face: the box behind it (right) and
    the box 10 cm nearer, its back face on the observed one and its body in the free space the
    sensor saw through."""
    from cloudpose.refine import DepthView

    g = np.linspace(-0.05, 0.05, 11)
    model = np.array(
        [(x, y, z) for x in g for y in g for z in g if max(abs(x), abs(y), abs(z)) == 0.05]
    )
    face = np.array([(x, y, 0.95) for x in g for y in g])
    K = np.array([[500.0, 0, 64], [0, 500.0, 64], [0, 0, 1]])
    view = DepthView(np.full((128, 128), 0.95), K)
    right, nearer = np.array([0, 0, 1.0]), np.array([0, 0, 0.9])
    return model, face, view, right, nearer


def test_select_refinements_keeps_the_best_score_per_row():
    """Fitness: the higher per row, the first on a tie, 0 for a miss; depth: of two poses that
    explain the segment alike, the one whose model does not stick out into seen free space."""
    from cloudpose.refine import Estimates, ICPStats, select_refinements

    model, face, view, right, nearer = _box_scene()
    rows = _rows(np.stack([face, face, face]), [True, True, False])
    eye = np.tile(np.eye(3), (3, 1, 1))
    a = Estimates(eye, np.stack([nearer, right, right]))
    b = Estimates(eye, np.stack([right, nearer, right]))

    def stats(fit):
        f = np.asarray(fit, dtype=float)
        return ICPStats(f, np.zeros(3), np.zeros(3, dtype=bool))

    models = {1: model}
    pick = select_refinements(
        rows, [a, b], [stats([0.5, 0.9, 1]), stats([0.8, 0.9, 1])], models, "fitness"
    )
    assert pick.tolist() == [1, 0, 0]  # higher fitness; a tie keeps the first; a miss: 0
    same = [stats([1.0, 1.0, np.nan])] * 2
    pick = select_refinements(rows, [a, b], same, models, "depth", [view] * 3)
    assert pick.tolist() == [1, 0, 0]  # the pose behind the observed face, in either slot
    with pytest.raises(ValueError, match="depth views"):
        select_refinements(rows, [a, b], same, models, "depth")
    with pytest.raises(ValueError, match="expected one of"):
        select_refinements(rows, [a, b], same, models, "closest")
    with pytest.raises(ValueError, match="one of each per network"):
        select_refinements(rows, [a, b], same[:1], models, "fitness")
