"""Compiled kernels against brute force or their numpy twins: k-d tree, bounded nearest
neighbour, ADS, exact FPS, the table-scene sampler's loops, version 3's edge distance."""

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


# --------------------------------------------------------------------------- scene sampler


def test_slide_steps_is_the_numpy_loop():
    """The slide's step (footprint box tests first, then its cells) is the numpy loop's, on
    and off the grid, with and without occupied cells, for footprints of every size."""
    from cloudpose.data.synth.scenes import _GRID, _GRID_HALF, _START, _slide_numpy
    from cloudpose.kernels.placement import slide_steps

    rng = np.random.default_rng(3)
    n = 2 * _GRID_HALF
    for t in range(200):
        occupied = np.zeros((n, n), dtype=bool)
        for _ in range(int(rng.integers(0, 4))):  # a few blobs near the centre
            i, j = rng.integers(n // 2 - 40, n // 2 + 40, 2)
            occupied[i : i + int(rng.integers(1, 30)), j : j + int(rng.integers(1, 30))] = True
        cells = rng.integers(-int(rng.integers(1, 25)), int(rng.integers(1, 25)), (40, 2))
        cells = np.unique(cells[: int(rng.integers(1, 41))], axis=0)
        anchor = rng.normal(0.0, 0.1 if t % 4 else 0.7, 2)  # sometimes near the grid's edge
        a = rng.uniform(0.0, 2.0 * np.pi)
        step = np.array([np.cos(a), np.sin(a)])
        want = _slide_numpy(cells, occupied, anchor, step)
        k = slide_steps(cells, occupied, anchor, step, int(_START / _GRID), _GRID, _GRID_HALF)
        got = None if k < 0 else anchor + step * (k * _GRID)
        assert (got is None) == (want is None)
        if got is not None:
            np.testing.assert_array_equal(got, want)


def test_hull_margin_is_qhulls():
    """The support margin from the integer hull is qhull's facet margin to rounding (inside,
    outside, on an edge), and collinear or repeated cells are the cells qhull rejects."""
    from scipy.spatial import ConvexHull, QhullError

    from cloudpose.data.synth.scenes import _GRID, _supports, _supports_numpy
    from cloudpose.kernels.placement import hull_margin

    rng = np.random.default_rng(8)
    for t in range(500):
        k = int(rng.integers(1, 40))
        if t % 8 == 0:  # on one line
            cells = rng.integers(-50, 50, 2) + np.outer(
                rng.integers(0, 9, k), rng.integers(-2, 3, 2)
            )
        else:
            cells = rng.integers(-60, 60, 2) + rng.integers(-9, 10, (k, 2))
        cells = cells.astype(np.int64)
        p = (cells.mean(axis=0) + 0.5 + rng.normal(0.0, 2.0, 2)) * _GRID
        status, margin = hull_margin(cells, _GRID, p[0], p[1])
        try:
            eq = ConvexHull((cells + 0.5) * _GRID).equations
        except QhullError:
            assert status == 1
        else:
            assert status == 0
            assert margin == pytest.approx(-(eq[:, :2] @ p + eq[:, 2]).max(), abs=1e-15)
        assert _supports(cells, p) == _supports_numpy(cells, p)
    square = np.array([[0, 0], [0, 4], [4, 0], [4, 4], [2, 2]], np.int64)
    assert hull_margin(square, 1.0, 2.5, 2.5) == (0, 2.0)
    assert hull_margin(square, 1.0, 0.5, 2.5)[1] == 0.0  # on an edge
    assert hull_margin(square, 1.0, -0.5, 2.5)[1] == -1.0  # outside
    assert hull_margin(np.zeros((4, 2), np.int64), 1.0, 0.5, 0.5)[0] == 1  # one cell 4 times


def test_column_means_and_in_image_counts_are_numpys():
    """The mean of an object's points is ``np.mean(axis=0)``'s to the bit (the same sums
    in the same order), and the in-image share is the numpy test's, points behind the camera,
    on the image's edges and outside it included."""
    from cloudpose.conventions import IMAGE_SHAPE, YCB_INTRINSICS
    from cloudpose.data.synth.scenes import _in_image_fraction, _in_image_fraction_numpy
    from cloudpose.kernels.placement import column_means

    rng = np.random.default_rng(2)
    for n in (1, 2, 7, 8, 9, 1000, 2621):
        pts = rng.normal(0.0, 0.05, (n, 3)) @ Rotation.random(random_state=n).as_matrix().T
        np.testing.assert_array_equal(column_means(pts), np.mean(pts, axis=0))
        np.testing.assert_array_equal(column_means(pts[:, :2].copy()), np.mean(pts[:, :2], 0))
    H, W = IMAGE_SHAPE
    for _ in range(50):
        cam = rng.normal(0.0, 0.3, (500, 3)) + np.array([0.0, 0.0, rng.uniform(-0.2, 1.0)])
        uv = rng.integers(-1, [W + 1, H + 1], (100, 2)).astype(np.float64)  # on the edges
        cam[:100] = np.c_[
            (uv - YCB_INTRINSICS[:2, 2]) / YCB_INTRINSICS[[0, 1], [0, 1]], np.ones(100)
        ]
        assert _in_image_fraction(cam, YCB_INTRINSICS, IMAGE_SHAPE) == _in_image_fraction_numpy(
            cam, YCB_INTRINSICS, IMAGE_SHAPE
        )


def test_contact_membership_is_isin():
    from cloudpose.data.synth.scenes import _member, _member_numpy

    rng = np.random.default_rng(1)
    for n, m in ((0, 5), (5, 0), (30, 1), (200, 600)):
        keys, of = rng.integers(0, 3 * max(n, m, 1), n), rng.integers(0, 3 * max(n, m, 1), m)
        np.testing.assert_array_equal(_member(keys, of), _member_numpy(keys, of))


def test_top_contact_and_placed_cells_are_the_numpy_steps():
    """The top surface, the contact with it and the final place of an object, compiled: the
    numpy steps' cells, in their order, and the same answer on and off the grid."""
    from cloudpose.data.synth import scenes as S
    from cloudpose.kernels.backend import disabled

    rng = np.random.default_rng(9)
    n = 2 * S._GRID_HALF
    for t in range(60):
        pts = rng.normal(0.0, rng.uniform(0.005, 0.05), (int(rng.integers(1, 800)), 3))
        pts = pts @ Rotation.random(random_state=t).as_matrix().T + [*rng.uniform(-0.3, 0.3, 2), 0]
        top, z = S._top_cells(pts)
        bottom = pts[pts[:, 2] <= pts[:, 2].min() + S.STACK_CONTACT, :2]
        origin = rng.normal(0.0, 0.01, 2)
        keys = np.sort(S._cell_keys(top))
        contact = S._contact_cells(bottom, origin, keys)
        occupied = rng.random((n, n)) < 0.001 * (t % 3)
        cells = S._footprint_cells(pts[:, :2] - pts[:, :2].mean(axis=0))
        xy = rng.normal(0.0, 0.2 if t % 5 else 0.9, 2)
        ij, free = S._placed_cells(cells, occupied, xy)
        with disabled():
            top_n, z_n = S._top_cells(pts)
            np.testing.assert_array_equal(top, top_n)
            assert z == z_n
            np.testing.assert_array_equal(contact, S._contact_cells(bottom, origin, keys))
            ij_n, free_n = S._placed_cells(cells, occupied, xy)
        np.testing.assert_array_equal(ij, ij_n)
        assert free == free_n
    empty = S._contact_cells(bottom, origin, np.zeros(0, np.int64))
    assert empty.shape == (0, 2)


# --------------------------------------------------------------------------- scene pass


def test_edge_squared_distance_is_brute_force():
    """Version 3's edge distance is the squared distance to the nearest boundary pixel by
    brute force, on label images of every shape (one row, one column, one label, many)."""
    from cloudpose.kernels.scene_pass import edge_squared_distance

    rng = np.random.default_rng(6)
    for shape in ((1, 1), (1, 7), (7, 1), (2, 2), (9, 13), (31, 24)):
        for blocks in (1, 2, 4):
            lab = rng.integers(-1, 3, (shape[0] // blocks + 1, shape[1] // blocks + 1))
            lab = np.kron(lab, np.ones((blocks, blocks), np.int64))[: shape[0], : shape[1]]
            lab = np.ascontiguousarray(lab)
            H, W = lab.shape
            bnd = np.zeros_like(lab, dtype=bool)
            bnd[1:] |= lab[1:] != lab[:-1]
            bnd[:-1] |= lab[:-1] != lab[1:]
            bnd[:, 1:] |= lab[:, 1:] != lab[:, :-1]
            bnd[:, :-1] |= lab[:, :-1] != lab[:, 1:]
            want = np.full((H, W), np.inf)
            if bnd.any():
                yx = np.argwhere(bnd)
                grid = np.stack(np.meshgrid(np.arange(H), np.arange(W), indexing="ij"), -1)
                want = ((grid[:, :, None, :] - yx[None, None]) ** 2).sum(-1).min(-1).astype(float)
            np.testing.assert_array_equal(edge_squared_distance(lab), want)


def test_edge_squared_distance_over_each_rows_objects_is_exact_there():
    """Version 3 runs the row envelopes over the columns of each row's object pixels only:
    at every object pixel, the full transform's value (images whose objects touch the edge
    included)."""
    from cloudpose.kernels.scene_pass import _edge_squared_distance, edge_squared_distance

    rng = np.random.default_rng(11)
    for t in range(40):
        H, W = rng.integers(1, 40, 2)
        lab = rng.integers(-3, 3, (H // 3 + 1, W // 3 + 1))
        lab = np.kron(lab, np.ones((3, 3), np.int64))[:H, :W]
        lab = np.ascontiguousarray(np.where(rng.random((H, W)) < 0.05, -1, lab) if t % 2 else lab)
        obj = lab >= 0
        lo = np.where(obj.any(1), obj.argmax(1), W)
        hi = np.where(obj.any(1), W - obj[:, ::-1].argmax(1), 0)
        got = _edge_squared_distance(lab, lo, hi)
        want = edge_squared_distance(lab)
        np.testing.assert_array_equal(np.where(got[obj] < 0, np.inf, got[obj]), want[obj])
