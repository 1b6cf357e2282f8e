"""Rotation conversions and the geodesic distance against scipy, twins, edge cases, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats
from scipy.spatial.transform import Rotation

from cloudpose.geometry import (
    normalize_quat,
    random_rotmat,
    rot6d_to_rotmat,
    rotmat_geodesic_distance,
    rotmat_to_rot6d,
    rotmat_to_rotvec,
    rotmat_to_unitquat,
    rotvec_to_rotmat,
    safe_norm,
    skew,
    unitquat_to_rotmat,
    vee,
)
from cloudpose.geometry.rotations import _series_threshold

DTYPES = [torch.float32, torch.float64]
EDGE_ANGLES = [0.0, 1e-7, 1e-3, 1.0, math.pi - 1e-6, math.pi]
AXIS = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
# Value tolerance per dtype: a float32 rotation matrix only holds angles to ~1e-7 rad.
TOL = {torch.float32: 2e-6, torch.float64: 1e-12}


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def _random_rotvecs(n: int, seed: int = 0, max_angle: float = math.pi) -> np.ndarray:
    """(n, 3) rotation vectors with uniform axes and angles in [0, max_angle)."""
    rng = _rng(seed)
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return axes * rng.uniform(0, max_angle, size=(n, 1))


def _edge_rotvecs() -> np.ndarray:
    """(6, 3) rotation vectors at the edge angles, about one fixed axis."""
    return AXIS[None] * np.array(EDGE_ANGLES)[:, None]


def _t(x: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
    return torch.as_tensor(x, dtype=dtype)


# ---------------------------------------------------------------- exponential map


@pytest.mark.parametrize("dtype", DTYPES)
def test_rotvec_to_rotmat_matches_scipy(dtype):
    r = np.concatenate([_random_rotvecs(200, max_angle=3 * math.pi), _edge_rotvecs()])
    R = rotvec_to_rotmat(_t(r, dtype))
    assert R.dtype == dtype and R.shape == (len(r), 3, 3)
    expected = Rotation.from_rotvec(r).as_matrix()
    np.testing.assert_allclose(R.double().numpy(), expected, atol=10 * TOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_rotvec_to_rotmat_agrees_with_matrix_exponential_twin(dtype):
    """Slow twin: R = expm([r]_x), value and gradient, across the series/closed-form switch."""
    th = _series_threshold(dtype)
    angles = [*EDGE_ANGLES, 1e-5, 0.999 * th, 1.001 * th, 2.5, 7.0]
    r64 = torch.tensor(AXIS)[None] * torch.tensor(angles)[:, None]
    w = torch.randn(
        len(angles), 3, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64
    )

    r = r64.to(dtype).requires_grad_()
    (g,) = torch.autograd.grad((rotvec_to_rotmat(r) * w.to(dtype)).sum(), r)
    r_ref = r64.clone().requires_grad_()
    R_ref = torch.linalg.matrix_exp(skew(r_ref))
    (g_ref,) = torch.autograd.grad((R_ref * w).sum(), r_ref)

    tol = 1e-6 if dtype == torch.float32 else 1e-13
    torch.testing.assert_close(
        rotvec_to_rotmat(r64.to(dtype)).double(), R_ref.detach(), atol=tol, rtol=0
    )
    torch.testing.assert_close(g.double(), g_ref, atol=10 * tol, rtol=0)


def test_rotvec_to_rotmat_gradcheck_small_and_large():
    r = torch.tensor(
        [[0.0, 0.0, 0.0], [1e-7, -2e-7, 3e-8], [1e-3, 2e-3, -1e-3], [0.4, 2.0, -1.0]],
        dtype=torch.float64,
        requires_grad=True,
    )
    assert torch.autograd.gradcheck(rotvec_to_rotmat, (r,), eps=1e-9, atol=1e-7)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", EDGE_ANGLES)
def test_rotvec_to_rotmat_gradient_finite_at_edges(dtype, angle):
    r = _t(AXIS * angle, dtype).requires_grad_()
    R = rotvec_to_rotmat(r)
    assert torch.isfinite(R).all()
    (g,) = torch.autograd.grad(R.sum() + (R * R).sum(), r)
    assert torch.isfinite(g).all()


def test_rotvec_to_rotmat_batch_shapes_and_orthonormality():
    r = _t(_random_rotvecs(24, seed=1), torch.float64).reshape(2, 3, 4, 3)
    R = rotvec_to_rotmat(r)
    assert R.shape == (2, 3, 4, 3, 3)
    torch.testing.assert_close(
        R @ R.mT, torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-12, rtol=0
    )
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(2, 3, 4, dtype=torch.float64))
    # Identity at zero, exactly.
    assert torch.equal(rotvec_to_rotmat(torch.zeros(3)), torch.eye(3))


# ---------------------------------------------------------------- logarithm map


@pytest.mark.parametrize("dtype", DTYPES)
def test_rotmat_to_rotvec_matches_scipy_below_pi(dtype):
    r = np.concatenate([_random_rotvecs(200, seed=2), _edge_rotvecs()[:-1]])  # all angles < pi
    R = Rotation.from_rotvec(r).as_matrix()
    out = rotmat_to_rotvec(_t(R, dtype))
    assert out.dtype == dtype and out.shape == (len(r), 3)
    atol = 1e-5 if dtype == torch.float32 else 1e-9  # float32 near pi: axis from tiny off-diagonals
    np.testing.assert_allclose(out.double().numpy(), r, atol=atol, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_rotmat_to_rotvec_at_pi_is_either_sign(dtype):
    for axis in [AXIS, np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, -1.0])]:
        R = Rotation.from_rotvec(axis * math.pi).as_matrix()
        r = rotmat_to_rotvec(_t(R, dtype)).double().numpy()
        assert abs(np.linalg.norm(r) - math.pi) < 1e-5
        err = min(np.abs(r - axis * math.pi).max(), np.abs(r + axis * math.pi).max())
        assert err < 1e-5


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", EDGE_ANGLES)
def test_rotvec_round_trip_at_edges(dtype, angle):
    r = _t(AXIS * angle, dtype)
    back = rotmat_to_rotvec(rotvec_to_rotmat(r))
    assert torch.isfinite(back).all()
    # Modulo the double cover at pi: compare the rotations, and the angle itself.
    assert abs(back.double().norm().item() - angle) < 10 * TOL[dtype]
    torch.testing.assert_close(
        rotvec_to_rotmat(back), rotvec_to_rotmat(r), atol=10 * TOL[dtype], rtol=0
    )


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", [0.0, 1e-7, 1.0, math.pi - 1e-6])
def test_rotmat_to_rotvec_gradient_finite(dtype, angle):
    R = _t(Rotation.from_rotvec(AXIS * angle).as_matrix(), dtype).requires_grad_()
    (g,) = torch.autograd.grad(rotmat_to_rotvec(R).sum(), R)
    assert torch.isfinite(g).all()


# ---------------------------------------------------------------- quaternions (XYZW)


@pytest.mark.parametrize("dtype", DTYPES)
def test_unitquat_to_rotmat_matches_scipy_xyzw(dtype):
    q = Rotation.random(100, random_state=3).as_quat()  # scipy: XYZW
    R = unitquat_to_rotmat(_t(q, dtype))
    np.testing.assert_allclose(
        R.double().numpy(), Rotation.from_quat(q).as_matrix(), atol=10 * TOL[dtype]
    )
    # A quarter turn about z, written out: XYZW = (0, 0, sin(pi/4), cos(pi/4)).
    s = math.sqrt(0.5)
    Rz = unitquat_to_rotmat(torch.tensor([0.0, 0.0, s, s], dtype=dtype))
    torch.testing.assert_close(Rz, torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_rotmat_to_unitquat_matches_scipy_with_positive_w(dtype):
    r = np.concatenate([_random_rotvecs(100, seed=4), _edge_rotvecs()])
    R = Rotation.from_rotvec(r)
    q = rotmat_to_unitquat(_t(R.as_matrix(), dtype))
    assert (q[:, 3] >= 0).all()
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(len(r), dtype=dtype))
    expected = R.as_quat()
    expected *= np.where(expected[:, 3:] < 0, -1.0, 1.0)
    # At exactly pi (w = 0) the sign is arbitrary: compare up to sign there.
    qn = q.double().numpy()
    err = np.minimum(np.abs(qn - expected).max(1), np.abs(qn + expected).max(1))
    assert err.max() < 10 * TOL[dtype]
    np.testing.assert_allclose(qn[:-1], expected[:-1], atol=10 * TOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
def test_quat_round_trip(dtype):
    R = random_rotmat(50, generator=torch.Generator().manual_seed(5), dtype=dtype)
    torch.testing.assert_close(
        unitquat_to_rotmat(rotmat_to_unitquat(R)), R, atol=10 * TOL[dtype], rtol=0
    )


def test_normalize_quat():
    q = torch.tensor(
        [[0.0, 0.0, 3.0, 4.0], [0.0, 0.0, 0.0, 0.0], [1e-20, 0.0, 0.0, 0.0]], requires_grad=True
    )
    n = normalize_quat(q)
    torch.testing.assert_close(n[0], torch.tensor([0.0, 0.0, 0.6, 0.8]))
    assert torch.equal(n[1], torch.zeros(4))  # zero stays zero, no NaN
    (g,) = torch.autograd.grad(n.sum(), q)
    assert torch.isfinite(g).all()
    # Normalised network output + quaternion -> rotation gives an orthonormal matrix.
    raw = torch.randn(10, 4, generator=torch.Generator().manual_seed(6), dtype=torch.float64) * 5
    R = unitquat_to_rotmat(normalize_quat(raw))
    torch.testing.assert_close(R @ R.mT, torch.eye(3, dtype=torch.float64).expand(10, 3, 3))


# ---------------------------------------------------------------- 6D (Zhou et al.), columns


def _gram_schmidt_twin(a1: np.ndarray, a2: np.ndarray) -> np.ndarray:
    """Zhou et al. eq. (16), one sample at a time: columns b1, b2, b3."""
    b1 = a1 / np.linalg.norm(a1)
    u2 = a2 - (b1 @ a2) * b1
    b2 = u2 / np.linalg.norm(u2)
    return np.stack([b1, b2, np.cross(b1, b2)], axis=1)


@pytest.mark.parametrize("dtype", DTYPES)
def test_rot6d_to_rotmat_agrees_with_gram_schmidt_twin(dtype):
    x = _rng(7).normal(size=(50, 6))
    R = rot6d_to_rotmat(_t(x, dtype)).double().numpy()
    expected = np.stack([_gram_schmidt_twin(v[:3], v[3:]) for v in x])
    np.testing.assert_allclose(R, expected, atol=10 * TOL[dtype])
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=10 * TOL[dtype])
    # a1 = first column (direction), a2 lies in the span of the first two columns.
    np.testing.assert_allclose(
        R[:, :, 0], x[:, :3] / np.linalg.norm(x[:, :3], axis=1, keepdims=True), atol=1e-6
    )
    np.testing.assert_allclose(np.einsum("bij,bi->bj", R, x[:, 3:])[:, 2], 0.0, atol=1e-5)


@pytest.mark.parametrize("dtype", DTYPES)
def test_rot6d_round_trip_and_column_convention(dtype):
    R = random_rotmat((4, 5), generator=torch.Generator().manual_seed(8), dtype=dtype)
    x = rotmat_to_rot6d(R)
    assert x.shape == (4, 5, 6)
    torch.testing.assert_close(x[..., :3], R[..., :, 0])
    torch.testing.assert_close(x[..., 3:], R[..., :, 1])
    torch.testing.assert_close(rot6d_to_rotmat(x), R, atol=10 * TOL[dtype], rtol=0)


def test_rot6d_degenerate_input_is_finite():
    x = torch.tensor([[0.0] * 6, [1.0, 0, 0, 2.0, 0, 0]], requires_grad=True)
    R = rot6d_to_rotmat(x)
    assert torch.isfinite(R).all()
    (g,) = torch.autograd.grad(R.sum(), x)
    assert torch.isfinite(g).all()


# ---------------------------------------------------------------- geodesic distance


@pytest.mark.parametrize("dtype", DTYPES)
def test_geodesic_matches_scipy(dtype):
    R1 = Rotation.random(200, random_state=9)
    R2 = Rotation.random(200, random_state=10)
    d = rotmat_geodesic_distance(_t(R1.as_matrix(), dtype), _t(R2.as_matrix(), dtype))
    assert d.shape == (200,) and d.dtype == dtype
    np.testing.assert_allclose(
        d.double().numpy(), (R1 * R2.inv()).magnitude(), atol=10 * TOL[dtype]
    )


@pytest.mark.parametrize("dtype", DTYPES)
def test_geodesic_agrees_with_arccos_twin(dtype):
    """Slow twin: docs/design.md's arccos((trace(R1 R2^T) - 1) / 2), fine away from 0 and pi."""
    R1 = random_rotmat(100, generator=torch.Generator().manual_seed(11), dtype=torch.float64)
    R2 = random_rotmat(100, generator=torch.Generator().manual_seed(12), dtype=torch.float64)
    cos = ((R1 @ R2.mT).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    keep = cos.abs() < 0.99
    twin = torch.arccos(cos[keep])
    d = rotmat_geodesic_distance(R1.to(dtype), R2.to(dtype))[keep]
    torch.testing.assert_close(
        d.double(), twin, atol=1e-5 if dtype == torch.float32 else 1e-12, rtol=0
    )


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", EDGE_ANGLES)
def test_geodesic_value_and_gradient_at_edges(dtype, angle):
    R0 = random_rotmat(1, generator=torch.Generator().manual_seed(13), dtype=torch.float64)[0]
    delta = Rotation.from_rotvec(AXIS * angle).as_matrix()
    R1 = _t(delta @ R0.numpy(), dtype).requires_grad_()
    R2 = R0.to(dtype).requires_grad_()
    d = rotmat_geodesic_distance(R1, R2)
    assert abs(d.item() - angle) < 10 * TOL[dtype]
    g1, g2 = torch.autograd.grad(d, (R1, R2))
    assert torch.isfinite(g1).all() and torch.isfinite(g2).all()


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", EDGE_ANGLES)
def test_geodesic_through_exp_map_gradient(dtype, angle):
    """The training path: d(geodesic(exp(r) R0, R0))/dr is finite, and equals r/|r| inside (0, pi)."""
    R0 = random_rotmat(1, generator=torch.Generator().manual_seed(14), dtype=dtype)[0]
    r = _t(AXIS * angle, dtype).requires_grad_()
    d = rotmat_geodesic_distance(rotvec_to_rotmat(r) @ R0, R0)
    (g,) = torch.autograd.grad(d, r)
    assert torch.isfinite(g).all()
    if 1e-3 <= angle <= 1.0:
        torch.testing.assert_close(
            g, _t(AXIS, dtype), atol=1e-4 if dtype == torch.float32 else 1e-10, rtol=0
        )


def test_geodesic_gradcheck_interior():
    R1 = random_rotmat(3, generator=torch.Generator().manual_seed(15), dtype=torch.float64)
    R2 = random_rotmat(3, generator=torch.Generator().manual_seed(16), dtype=torch.float64)
    assert torch.autograd.gradcheck(
        rotmat_geodesic_distance, (R1.requires_grad_(), R2.requires_grad_())
    )


@pytest.mark.parametrize("dtype", DTYPES)
def test_geodesic_symmetry_and_invariance(dtype):
    gen = torch.Generator().manual_seed(17)
    R1, R2, A = (random_rotmat(64, generator=gen, dtype=dtype) for _ in range(3))
    d = rotmat_geodesic_distance(R1, R2)
    atol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(rotmat_geodesic_distance(R2, R1), d, atol=atol, rtol=0)
    torch.testing.assert_close(rotmat_geodesic_distance(A @ R1, A @ R2), d, atol=atol, rtol=0)
    torch.testing.assert_close(rotmat_geodesic_distance(R1 @ A, R2 @ A), d, atol=atol, rtol=0)
    assert (d >= 0).all() and (d <= math.pi).all()
    # Broadcasting against a single rotation.
    torch.testing.assert_close(
        rotmat_geodesic_distance(R1, torch.eye(3, dtype=dtype)),
        rotmat_geodesic_distance(R1, torch.eye(3, dtype=dtype).expand_as(R1)),
    )


# ---------------------------------------------------------------- sampling and helpers


def test_random_rotmat_is_uniform_and_reproducible():
    R = random_rotmat(4000, generator=torch.Generator().manual_seed(18), dtype=torch.float64)
    assert R.shape == (4000, 3, 3) and R.dtype == torch.float64
    torch.testing.assert_close(R @ R.mT, torch.eye(3, dtype=torch.float64).expand_as(R))
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(4000, dtype=torch.float64))
    # Haar measure: angle CDF is (t - sin t) / pi, and E[R] = 0.
    angle = rotmat_geodesic_distance(R, torch.eye(3, dtype=torch.float64)).numpy()
    assert stats.kstest(angle, lambda t: (t - np.sin(t)) / np.pi).pvalue > 1e-3
    assert R.mean(0).abs().max() < 0.05
    again = random_rotmat(4000, generator=torch.Generator().manual_seed(18), dtype=torch.float64)
    assert torch.equal(R, again)
    assert random_rotmat(2).dtype == torch.float32


def test_skew_vee_safe_norm():
    r = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    v = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    torch.testing.assert_close(skew(r) @ v, torch.linalg.cross(r, v))
    torch.testing.assert_close(vee(skew(r)), r)
    x = torch.tensor([[3.0, 4.0], [0.0, 0.0]], requires_grad=True)
    n = safe_norm(x)
    torch.testing.assert_close(n, torch.tensor([5.0, 0.0]))
    (g,) = torch.autograd.grad(n.sum(), x)
    torch.testing.assert_close(g, torch.tensor([[0.6, 0.8], [0.0, 0.0]]))


def test_bad_shapes_raise_value_error():
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        rotvec_to_rotmat(torch.zeros(4, 4))
    with pytest.raises(ValueError, match=r"\(\.\.\., 4\)"):
        unitquat_to_rotmat(torch.zeros(3))
    with pytest.raises(ValueError, match=r"\(\.\.\., 6\)"):
        rot6d_to_rotmat(torch.zeros(2, 9))
    with pytest.raises(ValueError, match=r"3, 3"):
        rotmat_geodesic_distance(torch.zeros(4, 3), torch.eye(3))
    with pytest.raises(ValueError, match=r"3, 3"):
        rotmat_to_rotvec(torch.zeros(2, 2))


# ---------------------------------------------------------------- properties (hypothesis)

_coord = st.floats(-1.0, 1.0, allow_nan=False)
_axis = st.tuples(_coord, _coord, _coord).filter(lambda v: np.linalg.norm(v) > 1e-3)


@settings(max_examples=50, deadline=None)
@given(axis=_axis, angle=st.floats(0.0, math.pi - 1e-4))
def test_property_exp_log_round_trip(axis, angle):
    r = torch.tensor(axis, dtype=torch.float64)
    r = r / r.norm() * angle
    R = rotvec_to_rotmat(r)
    torch.testing.assert_close(rotmat_to_rotvec(R), r, atol=1e-9, rtol=0)
    torch.testing.assert_close(
        rotmat_geodesic_distance(R, torch.eye(3, dtype=torch.float64)),
        torch.tensor(angle, dtype=torch.float64),
        atol=1e-12,
        rtol=0,
    )


@settings(max_examples=50, deadline=None)
@given(a=_axis, b=_axis, c=_axis, ta=st.floats(0, 10), tb=st.floats(0, 10), tc=st.floats(0, 10))
def test_property_geodesic_triangle_and_invariance(a, b, c, ta, tb, tc):
    def rot(v, t):
        v = torch.tensor(v, dtype=torch.float64)
        return rotvec_to_rotmat(v / v.norm() * t)

    A, B, C = rot(a, ta), rot(b, tb), rot(c, tc)
    dab = rotmat_geodesic_distance(A, B)
    assert 0.0 <= dab.item() <= math.pi
    assert dab <= rotmat_geodesic_distance(A, C) + rotmat_geodesic_distance(C, B) + 1e-12
    torch.testing.assert_close(rotmat_geodesic_distance(C @ A, C @ B), dab, atol=1e-12, rtol=0)
    torch.testing.assert_close(rotmat_geodesic_distance(A @ C, B @ C), dab, atol=1e-12, rtol=0)


@settings(max_examples=50, deadline=None)
@given(
    x=st.lists(st.floats(-10, 10, allow_nan=False), min_size=6, max_size=6).filter(
        lambda v: (
            np.linalg.norm(np.cross(v[:3], v[3:]))
            > 1e-2 * (1 + np.linalg.norm(v[:3]) * np.linalg.norm(v[3:]))
        )
    )
)
def test_property_rot6d_gives_rotation_with_a1_first_column(x):
    xt = torch.tensor(x, dtype=torch.float64)
    R = rot6d_to_rotmat(xt)
    torch.testing.assert_close(R @ R.mT, torch.eye(3, dtype=torch.float64), atol=1e-10, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.tensor(1.0, dtype=torch.float64))
    torch.testing.assert_close(R[:, 0], xt[:3] / xt[:3].norm())
    torch.testing.assert_close(rot6d_to_rotmat(rotmat_to_rot6d(R)), R, atol=1e-12, rtol=0)
