"""One optimiser step on its own (cloudpose.train.step.train_step): a tiny network fitted to a
handful of synthetic segments, the step against its textbook twin, a non-finite loss."""

from __future__ import annotations

import copy

import pytest
import torch

from cloudpose.config import LossConfig, ModelConfig
from cloudpose.models import build_model
from cloudpose.train.losses import pose_loss
from cloudpose.train.step import Batch, StepLoss, train_step

TINY = ModelConfig(
    point_mlp=(16, 32), head=(32,), num_classes=3, rotation_input="centred", xyz_scale=0.03
)


@pytest.fixture(autouse=True)
def one_thread():
    """One intra-op thread: a tiny network's steps gain nothing from more, and on a loaded
    machine a second thread's waits cost seconds."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _segments(n: int = 8, points: int = 48, seed: int = 0) -> Batch:
    """``n`` segments of 3 classes (one elongated point cloud per class, metres) posed at
    random rotations about 0.8 m in front of the camera."""
    g = torch.Generator().manual_seed(seed)
    models = torch.randn(3, points, 3, generator=g) * torch.tensor([0.06, 0.03, 0.015])
    cls_id = torch.arange(n) % 3 + 1
    R = torch.linalg.qr(torch.randn(n, 3, 3, generator=g))[0]
    R = R * torch.det(R)[:, None, None]  # proper rotations
    t = torch.tensor([0.0, 0.0, 0.8]) + 0.05 * torch.randn(n, 3, generator=g)
    pts = models[cls_id - 1] @ R.mT + t[:, None]  # (n, points, 3)
    return Batch(pts.float(), cls_id, R.float(), t.float())


def _net(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return build_model(TINY).train()


def test_steps_on_a_batch_fit_it():
    """Forty steps on one batch: the loss falls to under a quarter of its start, both terms fall,
    every parameter moves and the BatchNorm statistics follow the batches."""
    batch, net, loss = _segments(), _net(), LossConfig()
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    before = {k: v.clone() for k, v in net.state_dict().items()}
    losses = [train_step(net, opt, batch, loss) for _ in range(40)]
    assert all(isinstance(s, StepLoss) for s in losses)
    assert losses[-1].loss < 0.25 * losses[0].loss, [round(s.loss, 3) for s in losses]
    assert losses[-1].rot < losses[0].rot and losses[-1].trans < losses[0].trans
    for name, p in net.named_parameters():
        assert not torch.equal(p.detach(), before[name]), f"{name} did not move"
    bn = [k for k in before if k.endswith("running_mean")]
    assert bn and all(not torch.equal(net.state_dict()[k], before[k]) for k in bn)


def test_a_step_is_the_textbook_step():
    """The loss returned is the batch's before the step, and the step is forward, the pose
    loss, backward and Adam, as written out by hand on a twin of the network."""
    batch, loss = _segments(seed=1), LossConfig(alpha=10.0, symmetric=False)
    net = _net(1)
    twin = copy.deepcopy(net)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    opt_twin = torch.optim.Adam(twin.parameters(), lr=1e-3)

    got = train_step(net, opt, batch, loss)

    out = twin(batch.points, batch.cls_id)
    terms = pose_loss(out.R, out.t, batch.R, batch.t, rotation="geodesic", alpha=10.0)
    opt_twin.zero_grad()
    terms.total.backward()
    opt_twin.step()
    terms = type(terms)(*(x.detach() for x in terms))
    assert got.loss == pytest.approx(float(terms.total), rel=1e-6)
    assert got.rot == pytest.approx(float(terms.rotation), rel=1e-6)
    assert got.trans == pytest.approx(float(terms.translation), rel=1e-6)
    assert got.loss == pytest.approx(10.0 * got.trans + got.rot, rel=1e-6)
    for (name, a), b in zip(net.state_dict().items(), twin.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7, msg=name)


def test_a_zero_learning_rate_keeps_the_weights():
    batch, net = _segments(), _net()
    opt = torch.optim.Adam(net.parameters(), lr=0.0)
    before = [p.detach().clone() for p in net.parameters()]
    train_step(net, opt, batch, LossConfig())
    for p, q in zip(net.parameters(), before, strict=True):
        assert torch.equal(p.detach(), q)


def test_a_non_finite_loss_is_an_error():
    batch, net = _segments(), _net()
    bad = batch._replace(points=batch.points.clone().index_fill_(0, torch.tensor([2]), torch.nan))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    with pytest.raises(FloatingPointError, match="loss became nan"):
        train_step(net, opt, bad, LossConfig())


@pytest.mark.parametrize("rotation_input", ["raw", "centred"])
def test_a_translation_input_of_its_own_trains_each_branch_as_alone(rotation_input):
    """With ``trans_points`` (``data.online_bleed_branch = "translation"``), a step trains the
    rotation branch exactly as a step on ``points`` alone does, and the translation branch
    exactly as a step on ``trans_points`` alone: branches that share no layer, each loss on
    its own branch, Adam per parameter. So a network trained on two forms of its segments is
    the rotation branch of one run beside the translation branch of another."""
    from dataclasses import replace

    cfg = replace(TINY, rotation_input=rotation_input)
    batch = _segments()
    g = torch.Generator().manual_seed(5)
    other = batch.points + 0.004 * torch.randn(batch.points.shape, generator=g)  # another form
    runs = []
    for points, trans_points in ((batch.points, other), (batch.points, None), (other, None)):
        torch.manual_seed(0)
        net = build_model(cfg).train()
        opt = torch.optim.Adam(net.parameters(), lr=3e-3)
        for _ in range(3):
            train_step(
                net, opt, batch._replace(points=points, trans_points=trans_points), LossConfig()
            )
        runs.append(net.state_dict())
    both, rot_alone, trans_alone = runs
    for name, value in both.items():
        alone = rot_alone if name.startswith("rotation_net.") else trans_alone
        assert name.split(".")[0] in ("rotation_net", "translation_net"), name
        torch.testing.assert_close(value, alone[name], rtol=1e-5, atol=1e-6, msg=name)
    net = build_model(cfg).eval()
    with torch.no_grad():  # at inference, each branch's output is its input's
        out = net(batch.points, batch.cls_id, other)
        torch.testing.assert_close(out.R, net(batch.points, batch.cls_id).R)
        torch.testing.assert_close(out.t, net(other, batch.cls_id).t)
    shared = build_model(replace(cfg, shared_layers=1))
    with pytest.raises(ValueError, match="share no layer"):
        shared(batch.points, batch.cls_id, other)
