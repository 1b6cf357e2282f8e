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


def test_segments_in_two_forms_recalibrate_each_branch_on_its_own():
    """With the translation branch's own form (``Batchable.trans_points``), recalibration
    re-estimates the rotation branch's statistics on ``points`` and the translation branch's on
    ``trans_points``, each as recalibrating on that form alone does; validation runs both."""
    import math

    from cloudpose.config import Config, ModelConfig
    from cloudpose.data.batches import Batchable
    from cloudpose.models import build_model
    from cloudpose.train.validation import recalibrate_bn, validate

    torch.manual_seed(0)
    model = build_model(ModelConfig(point_mlp=(16, 32), head=(32,), num_classes=3))
    (pts, cls_id), (other, _) = _tiny_batches(2)
    R, t = torch.eye(3).expand(64, 3, 3).clone(), torch.tensor([0.0, 0.0, 0.9]).expand(64, 3)
    far = other + torch.tensor([0.0, 0.0, 0.05])  # a translation form unlike the rotation one

    def stats(data: Batchable, branch: str) -> list[torch.Tensor]:
        recalibrate_bn(model, data, 4, 16, seed=3, device="cpu")
        net = getattr(model, f"{branch}_net")
        return [b.running_mean.clone() for b in net.modules() if hasattr(b, "running_mean")]

    both = Batchable(pts, cls_id, R, t, trans_points=far)
    for branch, alone in (("rotation", pts), ("translation", far)):
        got, want = stats(both, branch), stats(Batchable(alone, cls_id, R, t), branch)
        assert got and all(torch.allclose(a, b) for a, b in zip(got, want, strict=True)), branch
    assert both.subset(torch.arange(5)).trans_points.shape == (5, 32, 3)
    models = {c: torch.randn(50, 3).numpy() * 0.03 for c in (1, 2, 3)}
    cfg = Config()
    with_form = validate(model, both, models, cfg, "cpu", class_names=None)
    without = validate(model, Batchable(pts, cls_id, R, t), models, cfg, "cpu")
    assert math.isfinite(with_form["val/loss"])
    assert with_form["val/trans_err_median_mm"] != without["val/trans_err_median_mm"]
