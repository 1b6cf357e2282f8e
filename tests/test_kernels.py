"""Compiled kernels against brute force: k-d tree, bounded nearest neighbour, ADS, exact FPS."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from cloudpose import kernels as K
from cloudpose.conventions import resource_path
from cloudpose.data.segments import farthest_point_sampling_reference

pytestmark = pytest.mark.skipif(
    not K.enabled(), reason="compiled kernels off (numba missing or CLOUDPOSE_NO_NUMBA)"
)


def clouds(rng):
    """Random, clustered, quantised (many ties), duplicated and tiny point sets."""
    yield rng.normal(size=(500, 3)) * 0.05
    yield np.concatenate([rng.normal(size=(200, 3)) * 1e-4, rng.normal(size=(50, 3)) + 1.0])
    yield np.round(rng.uniform(-0.05, 0.05, size=(400, 3)), 3)  # 1 mm grid: exact ties
    yield np.repeat(rng.normal(size=(30, 3)), 4, axis=0)  # every point 4 times
    yield rng.normal(size=(1, 3))
    yield rng.normal(size=(2, 3))


def test_kdtree_partitions_the_points_into_boxed_leaves():
    rng = np.random.default_rng(0)
    for pts in clouds(rng):
        for leaf in (1, 4, 16):
            t = K.build_kdtree(pts, leaf)
            np.testing.assert_array_equal(t.points, pts[t.index])
            assert sorted(t.index.tolist()) == list(range(len(pts)))
            assert t.start[0] == 0 and t.end[0] == len(pts)
            for node in range(len(t.left)):
                s, e = t.start[node], t.end[node]
                p = t.points[s:e]
                assert (p >= t.box[node, :3]).all() and (p <= t.box[node, 3:]).all()
                a = t.left[node]
                if a >= 0:  # children split the node's range
                    assert t.right[node] == a + 1
                    assert t.start[a] == s and t.end[a] == t.start[a + 1] and t.end[a + 1] == e
                    assert t.end[a] > s and t.end[a] < e
                else:
                    assert e - s <= leaf or np.ptp(p, axis=0).max() == 0


@pytest.mark.parametrize("bound", [np.inf, 0.05, 1e-3])
def test_nearest_bounded_equals_brute_force(bound):
    rng = np.random.default_rng(1)
    for pts in clouds(rng):
        q = np.concatenate([pts[: min(20, len(pts))], rng.normal(size=(100, 3)) * 0.06])
        t = K.build_kdtree(pts, 4)
        d2, idx = K.nearest_bounded(t, q, bound)
        D = cdist(q, pts, "sqeuclidean")
        best = D.min(axis=1)
        found = best < bound**2
        np.testing.assert_array_equal(idx >= 0, found)
        np.testing.assert_allclose(d2[found], best[found], rtol=1e-12, atol=1e-30)
        np.testing.assert_allclose(D[found, idx[found]], best[found], rtol=1e-12, atol=1e-30)


def _brute_adds(model, W):
    out = []
    for w in W:
        q = model @ w[:, :3].T + w[:, 3]
        out.append(np.sqrt(cdist(q, model, "sqeuclidean").min(axis=1)).mean())
    return np.array(out)


@pytest.fixture(params=["delaunay", "lists"])
def graph_kind(request, monkeypatch):
    """Both neighbour structures: the Delaunay graph, and the lists used where there is none."""
    if request.param == "lists":
        monkeypatch.setattr(K.graph, "_delaunay_graph", lambda P: None)
    return request.param


@pytest.mark.parametrize("n_neighbours", [1, 8, 32, 10_000])
def test_adds_mean_equals_brute_force(n_neighbours, graph_kind):
    rng = np.random.default_rng(2)
    model = np.loadtxt(resource_path("models", "025_mug", "points.xyz"))[::4]
    M = 12
    deg = np.array([0, 0.5, 2, 5, 10, 30, 90, 180, 2, 5, 10, 45])
    R = Rotation.from_rotvec(
        rng.normal(size=(M, 3)) / np.sqrt(3) * np.deg2rad(deg)[:, None]
    ).as_matrix()
    b = (
        rng.normal(size=(M, 3))
        * np.array([0, 0, 1e-3, 3e-3, 1e-2, 5e-2, 0.1, 0, 0, 0, 0.2, 0])[:, None]
    )
    W = np.concatenate([R, b[:, :, None]], axis=2)
    index = K.build_nn_index(model, n_neighbours=n_neighbours, leaf_size=8)
    got = K.adds_mean(index, W)
    np.testing.assert_allclose(got, _brute_adds(model, W), rtol=1e-12, atol=1e-16)
    assert got[0] == 0.0


def test_delaunay_graph_is_used_where_it_exists():
    rng = np.random.default_rng(6)
    assert len(K.build_nn_index(rng.normal(size=(50, 3))).adj) > 0
    flat = np.c_[rng.normal(size=(50, 2)), np.zeros(50)]  # no 3-D triangulation: lists
    index = K.build_nn_index(flat)
    assert len(index.adj) == 0 and index.nbr.shape == (50, 32)
    W = np.concatenate([Rotation.random(3, random_state=1).as_matrix(), np.ones((3, 3, 1))], 2)
    np.testing.assert_allclose(K.adds_mean(index, W), _brute_adds(flat, W), rtol=1e-12)


def test_adds_mean_with_duplicates_and_tiny_models(graph_kind):
    rng = np.random.default_rng(3)
    for pts in clouds(rng):
        W = np.concatenate(
            [Rotation.random(5, random_state=4).as_matrix(), rng.normal(size=(5, 3, 1)) * 0.01],
            axis=2,
        )
        for L in (1, 3, 48):
            got = K.adds_mean(K.build_nn_index(pts, L, 2), W)
            np.testing.assert_allclose(got, _brute_adds(pts, W), rtol=1e-12, atol=1e-16)


def test_icp_kernel_degenerate_and_identity(graph_kind):
    model = np.loadtxt(resource_path("models", "025_mug", "points.xyz"))
    index = K.build_nn_index(model)
    T, n, s = K.icp_model_frame(index, model + 1.0, np.array([0.01, 0.009]))  # far away
    assert n == -1 and np.array_equal(T, np.eye(4))
    T, n, s = K.icp_model_frame(index, model[::3], np.array([0.01, 0.009]))  # exact fit
    np.testing.assert_allclose(T, np.eye(4), atol=1e-12)
    assert n == len(model[::3]) and s < 1e-28


def test_fps_order_rejects_bad_k_and_start():
    pts = np.zeros((4, 3), np.float32)
    for k, s in ((0, 0), (5, 0), (2, 4), (2, -1)):
        with pytest.raises(ValueError, match="fps_order"):
            K.fps_order(pts, k, s)


def test_fps_order_equals_the_numpy_loop_with_ties():
    rng = np.random.default_rng(5)
    for pts in clouds(rng):
        pts = pts.astype(np.float32)
        for leaf in (1, 8, 128):
            k = min(len(pts), 64)
            for s in {0, len(pts) - 1, int(rng.integers(len(pts)))}:
                np.testing.assert_array_equal(
                    K.fps_order(pts, k, s, leaf_size=leaf),
                    farthest_point_sampling_reference(pts, k, s),
                )


@pytest.mark.parametrize("P", [3, 6, 40])
def test_icp_on_flat_and_tiny_models_equals_the_pykdtree_loop(P):
    """Models without a 3-D triangulation (flat, few points) use the neighbour lists."""
    from cloudpose.kernels.model_index import ModelIndex
    from cloudpose.refine import icp_refine

    rng = np.random.default_rng(P)
    model = np.c_[rng.uniform(-0.03, 0.03, size=(P, 2)), np.zeros(P)]  # a flat plate
    index = ModelIndex(model)
    assert index.compiled is not None and len(index.compiled.adj) == 0
    plain = ModelIndex(model, compiled=False)
    obs = model[rng.integers(P, size=200)] + rng.normal(0, 0.002, (200, 3))
    R0 = Rotation.from_rotvec([0.02, -0.01, 0.03]).as_matrix()
    t0 = np.array([0.001, 0.002, -0.001])
    a, b = icp_refine(obs, index, R0, t0), icp_refine(obs, plain, R0, t0)
    np.testing.assert_allclose(a.R, b.R, atol=1e-12)
    np.testing.assert_allclose(a.t, b.t, atol=1e-12)
    assert a.fitness == b.fitness and a.inlier_rmse == pytest.approx(b.inlier_rmse, abs=1e-15)
