"""Validation's BatchNorm statistics: re-estimated running statistics match train mode."""

from __future__ import annotations

import pytest
import torch


def _tiny_batches(n_batches: int, seed: int = 0):
    """Random (points, cls_id) batches in metres: segments of 3 classes around z = 0.9 m."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(n_batches):
        cls_id = torch.randint(1, 4, (64,), generator=g)
        pts = torch.randn(64, 32, 3, generator=g) * 0.04 + torch.tensor([0.0, 0.0, 0.9])
        out.append((pts, cls_id))
    return out


@pytest.mark.parametrize("kernel", ["plain", "fused"])
def test_recalibrated_bn_makes_eval_mode_match_train_mode(kernel):
    from cloudpose.config import ModelConfig
    from cloudpose.data.batches import Batchable
    from cloudpose.models import build_model
    from cloudpose.models.fused import fuse_model
    from cloudpose.train.validation import recalibrate_bn

    torch.manual_seed(0)
    model = build_model(ModelConfig(bn_momentum=0.01, point_mlp=(16, 32, 64), head=(32,)))
    if kernel == "fused":
        fuse_model(model)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    batches = _tiny_batches(20)
    for pts, cls_id in batches:  # a short run: momentum 0.01 leaves the running stats at init
        loss = model(pts, cls_id).t_residual.square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    pts, cls_id = batches[0]
    with torch.no_grad():
        model.train()
        # train mode updates the running stats: evaluate on a copy
        import copy

        train_out = copy.deepcopy(model)(pts, cls_id).t
        model.eval()
        stale = model(pts, cls_id).t
    gap_before = float((stale - train_out).norm(dim=1).mean())
    data = Batchable(
        points=torch.cat([p for p, _ in batches]),
        cls_id=torch.cat([c for _, c in batches]),
        R=torch.eye(3).expand(1280, 3, 3).clone(),
        t=torch.zeros(1280, 3),
    )
    bn0 = model.translation_net.stages[0].bn
    with torch.no_grad():
        lin0 = model.translation_net.stages[0].linear
        x0 = torch.cat(
            [
                data.points - data.points.mean(1, keepdim=True),
                torch.nn.functional.one_hot(data.cls_id - 1, 21)[:, None].expand(-1, 32, -1),
            ],
            dim=-1,
        )
        true_var = lin0(x0.reshape(-1, 24)).var(0)
    assert (bn0.running_var / true_var).median() > 3  # still near its initial 1
    recalibrate_bn(model, data, batches=40, batch_size=64, seed=1, device=torch.device("cpu"))
    ratio = bn0.running_var / true_var
    assert torch.allclose(ratio, torch.ones_like(ratio), atol=0.1), ratio
    assert not model.training
    with torch.no_grad():
        fresh = model(pts, cls_id).t
    gap_after = float((fresh - train_out).norm(dim=1).mean())
    assert gap_after < 0.5 * gap_before, (gap_before, gap_after)
    # the momenta are restored for further training
    assert all(
        bn.momentum == 0.01 for bn in model.modules() if isinstance(bn, torch.nn.BatchNorm1d)
    )
