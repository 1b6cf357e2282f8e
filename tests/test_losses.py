"""Losses on hand-computed cases, the alpha weighting, the l2 branch, errors, and gradients."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from cloudpose.config import LossConfig
from cloudpose.geometry import random_rotmat, rotmat_to_rotvec, rotvec_to_rotmat
from cloudpose.train.losses import (
    LossTerms,
    geodesic_loss,
    pose_loss,
    rotvec_l2_loss,
    translation_loss,
)


def rot_z(theta: float, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """(3, 3) rotation about z by theta radians, written out."""
    c, s = math.cos(theta), math.sin(theta)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)


def _pose_pair():
    """Prediction off by 0.3 rad about z and by (0.03, 0.04, 0) m: l_r = 0.3, l_t = 0.05."""
    R_gt = torch.eye(3, dtype=torch.float64)[None]
    R_pred = rot_z(0.3)[None]
    t_gt = torch.zeros(1, 3, dtype=torch.float64)
    t_pred = torch.tensor([[0.03, 0.04, 0.0]], dtype=torch.float64)
    return R_pred, t_pred, R_gt, t_gt


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_geodesic_loss_hand_computed(dtype):
    R_pred = torch.stack(
        [rot_z(0.3, dtype), rot_z(-2.0, dtype), rot_z(math.pi, dtype), torch.eye(3, dtype=dtype)]
    )
    R_gt = torch.eye(3, dtype=dtype).expand(4, 3, 3)
    loss = geodesic_loss(R_pred, R_gt)
    assert loss.shape == (4,)
    torch.testing.assert_close(
        loss, torch.tensor([0.3, 2.0, math.pi, 0.0], dtype=dtype), atol=1e-6, rtol=0
    )


def test_translation_loss_is_euclidean_not_squared():
    t_pred = torch.tensor([[0.03, 0.04, 0.0], [0.0, 0.0, 0.0], [1.0, 2.0, 2.0]])
    t_gt = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    torch.testing.assert_close(translation_loss(t_pred, t_gt), torch.tensor([0.05, 0.0, 3.0]))


def test_rotvec_l2_loss_hand_computed_and_double_cover():
    r_pred = torch.tensor([[0.0, 0.0, 0.5], [0.1, 0.2, 0.3]], dtype=torch.float64)
    r_gt = torch.tensor([[0.0, 0.0, 0.3], [0.1, 0.2, 0.3]], dtype=torch.float64)
    torch.testing.assert_close(
        rotvec_l2_loss(r_pred, r_gt), torch.tensor([0.2, 0.0], dtype=torch.float64)
    )
    # Near pi: two rotations 0.02 rad apart, but their vectors are 2 pi - 0.02 apart.
    a = math.pi - 0.01
    r1, r2 = (
        torch.tensor([[0.0, 0.0, a]], dtype=torch.float64),
        torch.tensor([[0.0, 0.0, -a]], dtype=torch.float64),
    )
    torch.testing.assert_close(rotvec_l2_loss(r1, r2), torch.tensor([2 * a], dtype=torch.float64))
    torch.testing.assert_close(
        geodesic_loss(rotvec_to_rotmat(r1), rotvec_to_rotmat(r2)),
        torch.tensor([0.02], dtype=torch.float64),
    )


def test_pose_loss_hand_computed_default_alpha():
    terms = pose_loss(*_pose_pair())
    assert isinstance(terms, LossTerms)
    torch.testing.assert_close(terms.rotation, torch.tensor(0.3, dtype=torch.float64))
    torch.testing.assert_close(terms.translation, torch.tensor(0.05, dtype=torch.float64))
    torch.testing.assert_close(terms.total, torch.tensor(10 * 0.05 + 0.3, dtype=torch.float64))
    assert terms.total.dim() == 0


@pytest.mark.parametrize(("alpha", "total"), [(0.0, 0.3), (1.0, 0.35), (2.0, 0.4), (100.0, 5.3)])
def test_pose_loss_alpha_weighting(alpha, total):
    terms = pose_loss(*_pose_pair(), alpha=alpha)
    torch.testing.assert_close(terms.total, torch.tensor(total, dtype=torch.float64))
    torch.testing.assert_close(terms.rotation, torch.tensor(0.3, dtype=torch.float64))


def test_pose_loss_is_batch_mean():
    R_pred = torch.stack([rot_z(0.3), rot_z(0.1)])
    R_gt = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    t_pred = torch.tensor([[0.03, 0.04, 0.0], [0.0, 0.0, 0.01]], dtype=torch.float64)
    t_gt = torch.zeros(2, 3, dtype=torch.float64)
    terms = pose_loss(R_pred, t_pred, R_gt, t_gt, alpha=10.0)
    torch.testing.assert_close(
        terms.rotation, torch.tensor(0.2, dtype=torch.float64)
    )  # (0.3 + 0.1) / 2
    torch.testing.assert_close(
        terms.translation, torch.tensor(0.03, dtype=torch.float64)
    )  # (0.05 + 0.01) / 2
    torch.testing.assert_close(terms.total, torch.tensor(0.5, dtype=torch.float64))


def test_pose_loss_l2_branch_compares_to_log_of_gt():
    R_pred, t_pred, _, t_gt = _pose_pair()
    R_gt = rot_z(0.3)[None]  # log map: (0, 0, 0.3)
    rotvec_pred = torch.tensor([[0.0, 0.0, 0.5]], dtype=torch.float64)
    terms = pose_loss(
        R_pred, t_pred, R_gt, t_gt, rotation="l2", alpha=10.0, rotvec_pred=rotvec_pred
    )
    # l2 uses rotvec_pred, not R_pred (which equals R_gt here, geodesic 0).
    torch.testing.assert_close(terms.rotation, torch.tensor(0.2, dtype=torch.float64))
    torch.testing.assert_close(terms.total, torch.tensor(0.7, dtype=torch.float64))
    assert pose_loss(R_pred, t_pred, R_gt, t_gt).rotation.item() == pytest.approx(0.0, abs=1e-12)


def test_pose_loss_accepts_loss_config_fields():
    cfg = LossConfig(rotation="geodesic", alpha=2.0)
    terms = pose_loss(*_pose_pair(), **dataclasses.asdict(cfg))
    torch.testing.assert_close(terms.total, torch.tensor(0.4, dtype=torch.float64))


def test_the_loss_modulo_symmetry_follows_the_configured_table():
    """A pudding box turned by a half turn about one of its in-plane axes: a real symmetry
    that table 1 misses (nearly pi of loss) and table 2 finds (zero loss)."""
    from cloudpose.conventions import resource_path
    from cloudpose.data.ycb import load_classes
    from cloudpose.geometry.symmetry import load_symmetries

    cls = load_classes(resource_path("classes.txt")).index("008_pudding_box") + 1
    group = load_symmetries(2)["008_pudding_box"].discrete
    S = next(G for G in group if G[2, 2] < -0.9)  # a half turn that reverses the model z
    R_gt = torch.eye(3, dtype=torch.float64)[None]
    R_pred = torch.from_numpy(S)[None]
    t = torch.zeros(1, 3, dtype=torch.float64)
    cls_id = torch.tensor([cls])
    losses = {
        table: float(
            pose_loss(
                R_pred, t, R_gt, t, symmetric=True, symmetry_table=table, cls_id=cls_id
            ).rotation
        )
        for table in (1, 2)
    }
    assert losses[1] > 2.5 and losses[2] < 1e-6, losses


def test_pose_loss_errors():
    args = _pose_pair()
    with pytest.raises(ValueError, match=r"one of \('geodesic', 'l2'\).*'cosine'"):
        pose_loss(*args, rotation="cosine")
    with pytest.raises(ValueError, match="rotvec_pred"):
        pose_loss(*args, rotation="l2")
    R_pred, t_pred, R_gt, t_gt = args
    with pytest.raises(ValueError, match=r"t_pred must have shape \(B, 3\), got \(1, 4\)"):
        pose_loss(R_pred, torch.zeros(1, 4), R_gt, t_gt)
    with pytest.raises(ValueError, match=r"R_pred must have shape \(B, 3, 3\), got \(3, 3\)"):
        pose_loss(R_pred[0], t_pred, R_gt, t_gt)
    with pytest.raises(ValueError, match=r"t_gt has batch shape \(2,\), expected \(1,\)"):
        pose_loss(R_pred, t_pred, R_gt, torch.zeros(2, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"rotvec_pred has batch shape"):
        pose_loss(*args, rotation="l2", rotvec_pred=torch.zeros(3, 3))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("rotation", ["geodesic", "l2"])
def test_pose_loss_gradients_finite_at_perfect_and_pi(dtype, rotation):
    """Training path r -> R -> loss: finite gradients at a perfect prediction and at pi."""
    gen = torch.Generator().manual_seed(0)
    R_gt = random_rotmat(3, generator=gen, dtype=dtype)
    r_gt = rotmat_to_rotvec(R_gt)
    r_pi = torch.tensor([[0.0, 0.0, math.pi]], dtype=dtype)
    r = torch.cat([r_gt[:2], r_pi]).requires_grad_()
    R_gt = torch.cat([R_gt[:2], torch.eye(3, dtype=dtype)[None]])  # last: pi away from gt
    t_gt = torch.rand(3, 3, generator=gen, dtype=dtype)
    t = t_gt.clone().requires_grad_()
    terms = pose_loss(rotvec_to_rotmat(r), t, R_gt, t_gt, rotation=rotation, rotvec_pred=r)
    gr, gt = torch.autograd.grad(terms.total, (r, t))
    assert torch.isfinite(gr).all() and torch.isfinite(gt).all()
    assert terms.translation.item() == 0.0
    expected_rot = math.pi / 3  # (0 + 0 + pi) / 3, both for geodesic and for |r - 0|
    assert terms.rotation.item() == pytest.approx(expected_rot, abs=1e-5)


def test_pose_loss_decreases_under_gradient_descent():
    """A few steps of SGD on r and t from a bad start reduce the loss (gradients point the right way)."""
    gen = torch.Generator().manual_seed(1)
    R_gt = random_rotmat(8, generator=gen, dtype=torch.float64)
    t_gt = torch.rand(8, 3, generator=gen, dtype=torch.float64)
    r = torch.zeros(8, 3, dtype=torch.float64, requires_grad=True)
    t = torch.zeros(8, 3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.SGD([r, t], lr=0.1)
    first = None
    for _ in range(50):
        opt.zero_grad()
        loss = pose_loss(rotvec_to_rotmat(r), t, R_gt, t_gt).total
        first = loss.item() if first is None else first
        loss.backward()
        opt.step()
    assert loss.item() < 0.5 * first
