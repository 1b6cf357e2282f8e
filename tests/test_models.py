"""BaseNet and the pose networks: every registered variant builds, has the right shapes and
parameter count, overfits a tiny fixed batch; shared layers are one module trained by both
losses; the networks are invariant to the order of the input points."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest
import torch
from torch import nn

from cloudpose.config import ModelConfig
from cloudpose.conventions import resource_path
from cloudpose.geometry import rotvec_to_rotmat
from cloudpose.models import (
    BaseNet,
    PointLayer,
    PointLayerMaxPool,
    PoseNet,
    build_model,
    count_parameters,
    raw_rotation_to_rotmat,
    scaled_width,
    segment_centre,
    variant_table,
)
from cloudpose.registry import get_variant, groups_of, resolve, variants
from cloudpose.train.losses import pose_loss

VARIANTS = list(variants())
K = 21  # YCB-Video classes
B, N = 8, 32  # tiny fixed batch: 8 segments of 32 points


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def batch() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Eight real YCB object point sets (classes 1..8), posed in front of the camera.

    Returns points (B, N, 3) m, class ids (B,), R_gt (B, 3, 3), t_gt (B, 3) m. Rotation angles
    lie in [0.2, 1.4] rad, away from the axis-angle seam at pi.
    """
    rng = np.random.default_rng(0)
    names = resource_path("classes.txt").read_text().split()
    clouds = []
    for name in names[:B]:
        pts = np.loadtxt(resource_path("models", name, "points.xyz"))
        clouds.append(pts[rng.choice(len(pts), N, replace=False)])
    model_pts = torch.tensor(np.stack(clouds), dtype=torch.float32)  # (B, N, 3)
    axis = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(B, 3))), dim=-1)
    angle = torch.tensor(rng.uniform(0.2, 1.4, size=(B, 1)))
    R_gt = rotvec_to_rotmat(axis * angle).float()
    t_gt = torch.tensor(rng.normal([0.0, 0.0, 0.9], [0.1, 0.1, 0.1], size=(B, 3))).float()
    points = model_pts @ R_gt.mT + t_gt[:, None, :]  # p_cam = R p + t
    cls_id = torch.arange(1, B + 1)
    return points, cls_id, R_gt, t_gt


# --- analytic parameter counts, from the layer widths of docs/design.md ------------------------


def _linear(c_in: int, c_out: int) -> int:
    return c_in * c_out + c_out


def _bn(c: int) -> int:
    return 2 * c  # weight and bias; running statistics are buffers


def _expected_parameters(shared: int | str, width: float, rot_size: int) -> int:
    w = lambda c: round(c * width)  # noqa: E731 - the documented width rule
    point = [24, w(64), w(64), w(64), w(128), w(1024)]  # 3 + 21 input channels
    point_layers = [_linear(a, b) + _bn(b) for a, b in pairwise(point)]

    def head(out: int) -> int:
        h = [w(1024), w(512), w(256)]
        return (
            _linear(h[0], h[1]) + _bn(h[1]) + _linear(h[1], h[2]) + _bn(h[2]) + _linear(h[2], out)
        )

    if shared == "all":
        return sum(point_layers) + head(3 + rot_size)
    own = sum(point_layers[shared:])
    return sum(point_layers[:shared]) + 2 * own + head(rot_size) + head(3)


def _rot_size(rotation: str) -> int:
    return {"axis_angle": 3, "quaternion": 4, "rot6d": 6}[rotation]


# --- every registered variant ------------------------------------------------------------------


@pytest.mark.parametrize("name", VARIANTS)
def test_variant_builds_with_right_shapes(name, batch):
    points, cls_id, _, _ = batch
    cfg = resolve(name).model
    torch.manual_seed(0)
    model = build_model(cfg)
    for train in (True, False):
        model.train(train)
        with torch.no_grad():
            out = model(points, cls_id)
        assert out.R.shape == (B, 3, 3)
        assert out.t.shape == (B, 3)
        assert out.rot_raw.shape == (B, _rot_size(cfg.rotation))
        assert out.t_residual.shape == (B, 3)
        torch.testing.assert_close(out.mu, segment_centre(points, cfg.centre))
        torch.testing.assert_close(out.t, out.t_residual + out.mu)
        eye = torch.eye(3).expand(B, 3, 3)
        torch.testing.assert_close(out.R @ out.R.mT, eye, atol=1e-5, rtol=0)
        torch.testing.assert_close(torch.linalg.det(out.R), torch.ones(B), atol=1e-5, rtol=0)
        torch.testing.assert_close(out.R, raw_rotation_to_rotmat(out.rot_raw, cfg.rotation))


@pytest.mark.parametrize("name", VARIANTS)
def test_variant_parameter_count(name):
    cfg = resolve(name).model
    expected = _expected_parameters(cfg.shared_layers, cfg.width, _rot_size(cfg.rotation))
    assert count_parameters(build_model(cfg)) == expected


@pytest.mark.parametrize("name", VARIANTS)
def test_variant_overfits_tiny_batch(name, batch):
    """Adam on one fixed batch, BN in train mode: the loss falls tenfold within 300 steps."""
    points, cls_id, R_gt, t_gt = batch
    cfg = resolve(name)
    torch.manual_seed(0)
    model = build_model(cfg.model).train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    rotvec = cfg.model.rotation == "axis_angle"
    first = None
    for _ in range(300):
        out = model(points, cls_id)
        terms = pose_loss(
            out.R,
            out.t,
            R_gt,
            t_gt,
            cfg.loss.rotation,
            cfg.loss.alpha,
            rotvec_pred=out.rot_raw if rotvec else None,
        )
        if first is None:
            first = terms
        if terms.total < first.total / 10:
            break
        opt.zero_grad()
        terms.total.backward()
        opt.step()
    assert terms.total < first.total / 10, f"{name}: {first.total:.3f} -> {terms.total:.3f}"
    # Both parts learned, not only the (initially dominant) translation term.
    assert terms.rotation < first.rotation / 5
    assert terms.translation < first.translation / 5


def test_parameter_budget_of_wide_variants():
    count = {n: count_parameters(build_model(resolve(n).model)) for n in VARIANTS}
    separate = count["shared-0"]
    # The paper calls its double-width "all" variant equal in size; doubling gives ~2x.
    assert 1.8 < count["shared-all-2x"] / separate < 2.2
    matched = [n for n in VARIANTS if n.startswith("shared-all-") and n != "shared-all-2x"]
    assert len(matched) == 1
    assert abs(count[matched[0]] / separate - 1) < 0.01
    # ... and its width is the 2-decimal width that matches best.
    width = resolve(matched[0]).model.width
    for other in (width - 0.01, width + 0.01):
        params = _expected_parameters("all", other, 3)
        assert abs(params - separate) > abs(count[matched[0]] - separate)
    assert matched[0] == f"shared-all-{width:.2f}x"


# --- shared layers are one module --------------------------------------------------------------


@pytest.mark.parametrize("shared", [0, 1, 2, 3, 4, 5, "all"])
def test_shared_layers_are_one_module(shared, batch):
    points, cls_id, R_gt, t_gt = batch
    torch.manual_seed(0)
    model = PoseNet(ModelConfig(shared_layers=shared))
    rot, trans = model.branch_modules("rotation"), model.branch_modules("translation")
    assert len(rot) == len(trans) == 6  # 5 per-point stages + head
    k = 6 if shared == "all" else shared
    for i in range(6):
        assert (rot[i] is trans[i]) == (i < k), f"stage {i}"
    shared_params = {p for m in rot[:k] for p in m.parameters()}
    own_rot = {p for m in rot[k:] for p in m.parameters()}
    own_trans = {p for m in trans[k:] for p in m.parameters()}
    assert not shared_params & own_rot and not shared_params & own_trans
    # one set of parameters: nothing is counted twice, nothing is left out
    assert set(model.parameters()) == shared_params | own_rot | own_trans
    assert count_parameters(model) == sum(p.numel() for p in shared_params | own_rot | own_trans)

    model.train()
    for loss_part, own, other in (
        ("rotation", own_rot, own_trans),
        ("translation", own_trans, own_rot),
    ):
        model.zero_grad(set_to_none=True)
        out = model(points, cls_id)
        getattr(pose_loss(out.R, out.t, R_gt, t_gt), loss_part).backward()
        for p in shared_params:
            assert p.grad is not None and p.grad.abs().sum() > 0, f"{loss_part}: shared param"
        for p in own:
            assert p.grad is not None
        for p in other:
            assert p.grad is None, f"{loss_part} loss reached the other branch"
    if shared == "all":
        # the single output layer: rows 0-2 are the translation residual, 3-5 the rotation
        out_layer = model.net.head[-1]
        model.zero_grad(set_to_none=True)
        out = model(points, cls_id)
        pose_loss(out.R, out.t, R_gt, t_gt).rotation.backward()
        assert out_layer.weight.grad[:3].abs().sum() == 0
        assert out_layer.weight.grad[3:].abs().sum() > 0


def test_shared_trunk_sees_centred_points(batch):
    """docs/design.md: a shared trunk takes the translation branch's (mean-centred) input, so the
    output does not change when the whole segment is shifted, except t by the shift."""
    points, cls_id, _, _ = batch
    shift = torch.tensor([0.3, -0.2, 0.5])
    for shared in (1, 5, "all"):
        model = PoseNet(ModelConfig(shared_layers=shared)).eval()
        with torch.no_grad():
            a, b = model(points, cls_id), model(points + shift, cls_id)
        torch.testing.assert_close(a.R, b.R, atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(a.t + shift, b.t, atol=1e-5, rtol=1e-4)
    # shared-0's rotation net sees raw camera-frame xyz: its rotation depends on the position
    model = PoseNet(ModelConfig(shared_layers=0)).eval()
    with torch.no_grad():
        a, b = model(points, cls_id), model(points + shift, cls_id)
    assert not torch.allclose(a.R, b.R, atol=1e-4)


# --- BaseNet -----------------------------------------------------------------------------------


@pytest.mark.parametrize("train", [False, True])
def test_basenet_permutation_invariant(train):
    torch.manual_seed(0)
    net = BaseNet(24, 3).double().train(train)
    x = torch.randn(4, 50, 24, dtype=torch.float64)
    perm = torch.randperm(50)
    y1, y2 = net(x), net(x[:, perm])
    torch.testing.assert_close(y1, y2, atol=1e-10, rtol=1e-10)
    assert y1.shape == (4, 3)


@pytest.mark.parametrize("shared", [0, 3, "all"])
def test_posenet_permutation_invariant(shared, batch):
    points, cls_id, _, _ = batch
    torch.manual_seed(0)
    model = PoseNet(ModelConfig(shared_layers=shared)).double()
    pts = points.double()
    perm = torch.randperm(N)
    for train in (False, True):
        model.train(train)
        a, b = model(pts, cls_id), model(pts[:, perm], cls_id)
        for x, y in zip(a, b, strict=True):
            torch.testing.assert_close(x, y, atol=1e-10, rtol=1e-10)


def test_basenet_layout():
    """docs/design.md: 64-64-64-128-1024 per point, max pool, FC 512-256-out; BN everywhere but the
    output layer; no dropout; BN momentum from the config."""
    net = BaseNet(24, 7, bn_momentum=0.01)
    linears = [m for m in net.modules() if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [
        (24, 64),
        (64, 64),
        (64, 64),
        (64, 128),
        (128, 1024),
        (1024, 512),
        (512, 256),
        (256, 7),
    ]
    bns = [m for m in net.modules() if isinstance(m, nn.BatchNorm1d)]
    assert [m.num_features for m in bns] == [64, 64, 64, 128, 1024, 512, 256]
    assert all(m.momentum == 0.01 for m in bns)
    assert not any(isinstance(m, nn.Dropout) for m in net.modules())
    assert isinstance(net.stages[-1], PointLayerMaxPool)
    assert all(isinstance(m, PointLayer) for m in net.stages[:-1])
    # BN momentum travels from ModelConfig into every BN of a pose network
    model = PoseNet(ModelConfig(shared_layers=2, bn_momentum=0.1))
    assert all(m.momentum == 0.1 for m in model.modules() if isinstance(m, nn.BatchNorm1d))


def test_width_multiplier_rounds_each_width():
    assert scaled_width(64, 1.42) == 91  # round(90.88)
    assert scaled_width(1024, 1.42) == 1454  # round(1454.08)
    assert scaled_width(64, 0.001) == 1
    net = BaseNet(24, 6, width=1.42)
    outs = [m.out_features for m in net.modules() if isinstance(m, nn.Linear)]
    assert outs == [91, 91, 91, 182, 1454, 727, 364, 6]


def test_point_layer_equals_conv1x1():
    """Slow twin: a Linear on (B*n, C) + BN1d is the paper's 1x1 convolution + BN on (B, C, n)."""
    torch.manual_seed(0)
    layer = PointLayer(24, 64).double().train()
    conv = nn.Conv1d(24, 64, kernel_size=1).double()
    bn = nn.BatchNorm1d(64, momentum=0.01).double().train()
    with torch.no_grad():
        conv.weight.copy_(layer.linear.weight[:, :, None])
        conv.bias.copy_(layer.linear.bias)
    x = torch.randn(3, 40, 24, dtype=torch.float64)
    ref = torch.relu(bn(conv(x.mT))).mT  # (B, n, C)
    torch.testing.assert_close(layer(x), ref)
    torch.testing.assert_close(layer.bn.running_mean, bn.running_mean)


def test_point_layer_max_pool_matches_loop():
    """Slow twin of PointLayerMaxPool (eval-mode BN): per segment, per point, then a max."""
    torch.manual_seed(0)
    layer = PointLayerMaxPool(5, 7).double()
    with torch.no_grad():
        layer.bn.running_mean.uniform_(-1, 1)
        layer.bn.running_var.uniform_(0.5, 2)
        layer.bn.weight.uniform_(0.5, 2)
        layer.bn.bias.uniform_(-1, 1)
    layer.eval()
    x = torch.randn(3, 11, 5, dtype=torch.float64)
    W, b = layer.linear.weight, layer.linear.bias
    bn = layer.bn
    ref = torch.empty(3, 7, dtype=torch.float64)
    for s in range(3):
        feats = []
        for p in range(11):
            z = W @ x[s, p] + b
            z = (z - bn.running_mean) / torch.sqrt(bn.running_var + bn.eps) * bn.weight + bn.bias
            feats.append(torch.clamp(z, min=0))
        ref[s] = torch.stack(feats).max(dim=0).values
    torch.testing.assert_close(layer(x), ref)
    assert set(layer.state_dict()) == {
        "linear.weight",
        "linear.bias",
        "bn.weight",
        "bn.bias",
        "bn.running_mean",
        "bn.running_var",
        "bn.num_batches_tracked",
    }


def test_rotation_outputs_convert():
    q = torch.tensor([[0.1, -0.2, 0.3, 0.9]])
    torch.testing.assert_close(
        raw_rotation_to_rotmat(q, "quaternion"), raw_rotation_to_rotmat(5 * q, "quaternion")
    )
    torch.testing.assert_close(
        raw_rotation_to_rotmat(torch.zeros(1, 3), "axis_angle"), torch.eye(3)[None]
    )
    R = rotvec_to_rotmat(torch.tensor([[0.3, -1.0, 0.5]]))
    x6 = torch.cat([2 * R[..., :, 0], R[..., :, 1] + 0.5 * R[..., :, 0]], -1)  # columns, skewed
    torch.testing.assert_close(raw_rotation_to_rotmat(x6, "rot6d"), R, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="quaternion"):
        raw_rotation_to_rotmat(torch.zeros(2, 3), "quaternion")


def test_bad_input_raises(batch):
    points, cls_id, _, _ = batch
    model = PoseNet(ModelConfig()).eval()
    with pytest.raises(ValueError, match="points"):
        model(points[..., :2], cls_id)
    with pytest.raises(ValueError, match="cls_id"):
        model(points, cls_id[:3])
    with pytest.raises(ValueError, match="1-based"):
        model(points, cls_id - 1)  # a 0 = background id
    with pytest.raises(ValueError, match="1-based"):
        model(points, torch.full((B,), K + 1))
    with pytest.raises(ValueError, match=r"\(B, n, 24\)"):
        BaseNet(24, 3)(torch.zeros(2, 10, 3))
    with pytest.raises(ValueError, match="point_mlp"):
        PoseNet(ModelConfig(shared_layers=4, point_mlp=(64, 128, 256)))


def test_variant_table_lists_every_variant():
    rows = variant_table()
    assert [r["name"] for r in rows] == VARIANTS
    for r in rows:
        assert r["groups"] == groups_of(r["name"]) and r["groups"]
        assert r["changes"] == get_variant(r["name"]).describe()
        assert r["why"]
        cfg = resolve(r["name"]).model
        assert r["parameters"] == _expected_parameters(
            cfg.shared_layers, cfg.width, _rot_size(cfg.rotation)
        )


def test_robust_centres_move_less_than_the_mean_under_background_bled_in():
    """A half-visible object's surface plus 8% of points bled in from the background 15 cm
    behind its rim: the mean moves by ~1 cm, the trimmed mean by under half that, the median
    by less than the mean. On the clean segment all three lie near the mean; each is a (B, 3) point."""
    g = torch.Generator().manual_seed(0)
    n, n_bled = 256, 20
    surface = torch.randn(2, n, 3, generator=g) * torch.tensor([0.03, 0.03, 0.005])
    surface[..., 2] += 0.8
    bled = surface.clone()
    rim = torch.tensor([0.04, 0.0, 0.95])
    bled[:, :n_bled] = rim + 0.005 * torch.randn(2, n_bled, 3, generator=g)
    for centre in ("mean", "median", "trimmed"):
        assert segment_centre(surface, centre).shape == (2, 3)
        clean_gap = (segment_centre(surface, centre) - surface.mean(dim=1)).norm(dim=-1)
        assert bool((clean_gap < 0.006).all()), (centre, clean_gap)
    shift = {
        c: (segment_centre(bled, c) - segment_centre(surface, c)).norm(dim=-1).max().item()
        for c in ("mean", "median", "trimmed")
    }
    assert shift["mean"] > 0.01, shift
    # the per-coordinate median still moves by the bled share times the object's lateral spread
    assert shift["median"] < 0.75 * shift["mean"], shift
    assert shift["trimmed"] < 0.5 * shift["mean"], shift
    with pytest.raises(ValueError, match="centre"):
        segment_centre(surface, "mode")
