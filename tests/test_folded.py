"""Folded inference networks equal the eval-mode PoseNet they come from, for every variant."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from cloudpose.models import build_model
from cloudpose.models.folded import FoldedPoseNet, fold_bn, fold_for_inference
from cloudpose.models.fused import fuse_model
from cloudpose.registry import resolve, variants


def trained_like(variant: str, dtype: torch.dtype = torch.float32, overrides=None) -> nn.Module:
    """A small network whose BatchNorm layers have non-trivial statistics and affine terms."""
    cfg = resolve(variant, "smoke", overrides=overrides)
    torch.manual_seed(0)
    model = build_model(cfg.model).to(dtype).train()
    g = torch.Generator().manual_seed(1)
    for _ in range(3):  # real running statistics
        pts = torch.randn(6, 32, 3, generator=g, dtype=dtype) * 0.05 + 0.8
        model(pts, torch.randint(1, cfg.model.num_classes + 1, (6,), generator=g))
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, nn.BatchNorm1d):
                m.weight.normal_(1.0, 0.5, generator=g)  # some negative scales too
                m.bias.normal_(0.0, 0.2, generator=g)
    return model.eval()


def batch(dtype: torch.dtype, B: int = 5, n: int = 40):
    g = torch.Generator().manual_seed(2)
    pts = (torch.randn(B, n, 3, generator=g) * 0.05 + torch.tensor([0.1, -0.1, 0.8])).to(dtype)
    return pts, torch.tensor([1, 21, 5, 5, 12][:B])


@pytest.mark.parametrize("variant", list(variants()))
@pytest.mark.parametrize(("dtype", "tol"), [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_folded_equals_eval_mode(variant, dtype, tol):
    model = trained_like(variant, dtype)
    folded = fold_for_inference(model)
    pts, cls = batch(dtype)
    with torch.no_grad():
        ref = model(pts, cls)
    out = folded(pts, cls)
    assert out.R.dtype == dtype and out.R.shape == ref.R.shape
    for name, a, b in zip(ref._fields, out, ref, strict=True):
        torch.testing.assert_close(a, b, rtol=tol, atol=tol, msg=name)


@pytest.mark.parametrize("variant", ["shared-0", "shared-2", "shared-all"])
@pytest.mark.parametrize("rotation_input", ["raw", "centred"])
def test_folded_equals_eval_mode_with_input_settings(variant, rotation_input):
    model = trained_like(
        variant, torch.float64, {"model": {"xyz_scale": 0.03, "rotation_input": rotation_input}}
    )
    pts, cls = batch(torch.float64)
    with torch.no_grad():
        ref = model(pts, cls)
    out = fold_for_inference(model)(pts, cls)
    for name, a, b in zip(ref._fields, out, ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12, msg=name)


def test_rotation_input_changes_only_what_the_rotation_branch_sees():
    raw = trained_like("shared-0", torch.float64, {"model": {"rotation_input": "raw"}})
    cen = trained_like("shared-0", torch.float64, {"model": {"rotation_input": "centred"}})
    cen.load_state_dict(raw.state_dict())
    pts, cls = batch(torch.float64)
    with torch.no_grad():
        a, b = raw(pts, cls), cen(pts, cls)
        # centred input: the rotation does not move with the segment, the translation does
        shift = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
        b2 = cen(pts + shift, cls)
    torch.testing.assert_close(a.t, b.t)
    assert not torch.allclose(a.rot_raw, b.rot_raw)
    torch.testing.assert_close(b2.rot_raw, b.rot_raw)
    torch.testing.assert_close(b2.t, b.t + shift)


def test_rotation_centre_mean_gives_the_rotation_of_the_mean_and_the_translation_of_the_centre():
    """Same weights: with ``rotation_centre = "mean"`` the rotation is the mean-centred
    network's and the translation the trimmed-centre network's; folded the same."""
    settings = {"xyz_scale": 0.03, "rotation_input": "centred"}
    mean = trained_like("shared-0", torch.float64, {"model": settings})
    trimmed = trained_like("centre-trimmed", torch.float64, {"model": settings})
    both = trained_like("centre-trimmed-translation", torch.float64, {"model": settings})
    for net in (trimmed, both):
        net.load_state_dict(mean.state_dict())
    pts, cls = batch(torch.float64)
    pts[:, :6] += torch.tensor([0.0, 0.0, 0.15], dtype=torch.float64)  # background bled in
    with torch.no_grad():
        a, b, c = mean(pts, cls), trimmed(pts, cls), both(pts, cls)
    torch.testing.assert_close(c.rot_raw, a.rot_raw)
    torch.testing.assert_close(c.R, a.R)
    assert not torch.allclose(b.rot_raw, a.rot_raw)  # the trimmed centre's rotation moves
    torch.testing.assert_close(c.mu, b.mu)
    torch.testing.assert_close(c.t, b.t)
    assert not torch.allclose(c.mu, a.mu)
    folded = fold_for_inference(both)(pts, cls)
    for name, x, y in zip(c._fields, folded, c, strict=True):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-12, msg=name)


def test_fused_model_folds_the_same_and_paired_branches_are_used():
    model = trained_like("shared-0")
    pts, cls = batch(torch.float32)
    with torch.no_grad():
        ref = model(pts, cls)
    fused = fuse_model(trained_like("shared-0"))
    folded = fold_for_inference(fused)
    assert folded.mode == "pair" and folded.paired
    torch.testing.assert_close(folded(pts, cls).t, ref.t, rtol=2e-5, atol=2e-5)
    # one object and a single point
    one = folded(pts[:1, :1], cls[:1])
    with torch.no_grad():
        torch.testing.assert_close(one.R, model(pts[:1, :1], cls[:1]).R, rtol=2e-5, atol=2e-5)


def test_fold_bn_is_the_eval_composition():
    torch.manual_seed(3)
    lin, bn = nn.Linear(7, 5).double(), nn.BatchNorm1d(5).double()
    with torch.no_grad():
        bn.running_mean.normal_()
        bn.running_var.uniform_(0.1, 3.0)
        bn.weight.normal_()
        bn.bias.normal_()
    bn.eval()
    x = torch.randn(11, 7, dtype=torch.float64)
    w, b = fold_bn(lin, bn)
    torch.testing.assert_close(x @ w.T + b, bn(lin(x)).detach(), rtol=1e-12, atol=1e-12)
    w0, b0 = fold_bn(lin, None)
    torch.testing.assert_close(x @ w0.T + b0, lin(x).detach())


def test_folded_net_rejects_bad_input_and_non_posenets():
    folded = fold_for_inference(trained_like("shared-0"))
    assert isinstance(folded, FoldedPoseNet)
    with pytest.raises(ValueError, match="points"):
        folded(torch.zeros(2, 5, 4), torch.tensor([1, 2]))
    with pytest.raises(ValueError, match="class ids"):
        folded(torch.zeros(2, 5, 3), torch.tensor([0, 2]))
    with pytest.raises(ValueError, match="PoseNet"):
        fold_for_inference(nn.Linear(3, 3))  # type: ignore[arg-type]
