"""The fused last per-point layer + max pool against its slow twin, the plain PointLayerMaxPool."""

from __future__ import annotations

import copy

import pytest
import torch

from cloudpose.geometry.rotations import rotvec_to_rotmat
from cloudpose.models import PointLayerMaxPool, build_model
from cloudpose.models.fused import (
    FusedPointLayerMaxPool,
    fuse_model,
    fused_point_max_pool,
    unfuse_model,
)
from cloudpose.registry import resolve
from cloudpose.train.losses import pose_loss


def _randomise_bn(m: PointLayerMaxPool | FusedPointLayerMaxPool, seed: int) -> None:
    """Make BN's affine and running statistics non-trivial, including negative scales."""
    g = torch.Generator().manual_seed(seed)
    D = m.bn.num_features
    with torch.no_grad():
        m.bn.weight.copy_(torch.empty(D).uniform_(-1.5, 1.5, generator=g))
        m.bn.bias.copy_(torch.empty(D).uniform_(-0.5, 0.5, generator=g))
        m.bn.running_mean.copy_(torch.randn(D, generator=g))
        m.bn.running_var.copy_(torch.empty(D).uniform_(0.5, 2.0, generator=g))


def _features(B: int, n: int, C: int, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    """ReLU-like features with a non-zero mean, as the previous layer hands them over."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(B, n, C, generator=g, dtype=torch.float64)
    return (x.relu() + 0.3 * torch.randn(B, n, C, generator=g, dtype=torch.float64)).to(dtype)


def _pair(C: int, D: int, dtype: torch.dtype, momentum: float | None = 0.01, seed: int = 0):
    torch.manual_seed(seed)
    plain = PointLayerMaxPool(C, D, bn_momentum=0.01).to(dtype)
    plain.bn.momentum = momentum
    _randomise_bn(plain, seed)
    fused = FusedPointLayerMaxPool.from_plain(copy.deepcopy(plain), chunk_rows=700)
    return plain, fused


def _run(m, x: torch.Tensor, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    x = x.clone().requires_grad_(True)
    out = m(x)
    (out * g).sum().backward()
    return out.detach(), x.grad


def _close(actual: torch.Tensor, expected: torch.Tensor, rel: float, what: str = "") -> None:
    """Max abs difference within ``rel`` times the largest expected magnitude.

    Sums over thousands of points cancel, so a small entry carries the rounding error of the
    large ones; elementwise rtol would ask for more than float arithmetic gives either module.
    """
    assert actual.shape == expected.shape, what
    scale = expected.abs().max().clamp_min(1e-30)
    err = (actual - expected).abs().max()
    assert err <= rel * scale, f"{what}: max error {err:.3g} > {rel:.1g} * {scale:.3g}"


def _assert_same(plain, fused, rel: float) -> None:
    """Same parameter gradients and buffers.

    In training the Linear bias has gradient zero (BN subtracts the batch mean): the fused
    module returns exactly zero, the plain one rounding noise of a cancelling sum, so the bias
    is compared against the scale of the weight gradient.
    """
    for (name, a), (_, b) in zip(plain.named_parameters(), fused.named_parameters(), strict=True):
        if a.grad is None:
            assert b.grad is None, name
            continue
        if name == "linear.bias" and fused.training:
            assert torch.count_nonzero(b.grad) == 0, name
            scale = plain.linear.weight.grad.abs().max()
            assert a.grad.abs().max() <= 100 * rel * scale, name
            continue
        _close(b.grad, a.grad, rel, name)
    for (name, a), (_, b) in zip(plain.named_buffers(), fused.named_buffers(), strict=True):
        _close(b.double(), a.double(), rel, name)


@pytest.mark.parametrize("use_batch_stats", [True, False])
def test_gradcheck_float64(use_batch_stats: bool) -> None:
    g = torch.Generator().manual_seed(3)
    B, n, C, D = 3, 7, 5, 6
    x = torch.randn(B, n, C, generator=g, dtype=torch.float64).requires_grad_(True)
    w = torch.randn(D, C, generator=g, dtype=torch.float64).requires_grad_(True)
    b = torch.randn(D, generator=g, dtype=torch.float64).requires_grad_(True)
    gamma = torch.tensor([1.0, -0.5, 2.0, -1.0, 0.7, 0.3], dtype=torch.float64)
    gamma.requires_grad_(True)
    beta = torch.randn(D, generator=g, dtype=torch.float64).requires_grad_(True)
    rm = torch.randn(D, generator=g, dtype=torch.float64)
    rv = torch.rand(D, generator=g, dtype=torch.float64) + 0.5

    def f(*args):  # chunk_rows=14: two samples per chunk, the last chunk holds one
        return fused_point_max_pool(*args, rm, rv, use_batch_stats=use_batch_stats, chunk_rows=14)[
            0
        ]

    assert torch.autograd.gradcheck(f, (x, w, b, gamma, beta))


@pytest.mark.parametrize("training", [True, False])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_plain_module(training: bool, dtype: torch.dtype) -> None:
    B, n, C, D = 8, 256, 128, 1024
    plain, fused = _pair(C, D, dtype)
    plain.train(training)
    fused.train(training)
    x = _features(B, n, C, dtype)
    g = torch.randn(B, D, dtype=dtype, generator=torch.Generator().manual_seed(1))
    for _ in range(2):  # twice: running statistics are updated from updated ones
        out_p, dx_p = _run(plain, x, g)
        out_f, dx_f = _run(fused, x, g)
    rel = 1e-5 if dtype == torch.float32 else 1e-12
    _close(out_f, out_p, rel, "output")
    _close(dx_f, dx_p, rel, "input gradient")
    _assert_same(plain, fused, rel)
    if training:
        assert int(fused.bn.num_batches_tracked) == 2


def test_cumulative_average_momentum_none() -> None:
    plain, fused = _pair(16, 32, torch.float64, momentum=None)
    for seed in range(3):
        x = _features(4, 20, 16, torch.float64, seed=seed)
        plain(x)
        fused(x)
    _assert_same(plain, fused, 1e-12)


@pytest.mark.parametrize("training", [True, False])
def test_no_grad_path_matches(training: bool) -> None:
    plain, fused = _pair(32, 64, torch.float32)
    plain.train(training)
    fused.train(training)
    x = _features(5, 40, 32, torch.float32)
    with torch.no_grad():
        torch.testing.assert_close(fused(x), plain(x), rtol=1e-5, atol=1e-5)
    _assert_same(plain, fused, 1e-6)  # running statistics


def test_ties_give_the_same_parameter_gradients() -> None:
    """Repeated points (padding of small segments) tie in the max; parameters must not care."""
    plain, fused = _pair(16, 48, torch.float64)
    x = _features(4, 12, 16, torch.float64)
    x = torch.cat([x, x[:, :5]], dim=1)  # points 12..16 repeat points 0..4
    g = torch.randn(4, 48, dtype=torch.float64)
    out_p, dx_p = _run(plain, x, g)
    out_f, dx_f = _run(fused, x, g)
    torch.testing.assert_close(out_f, out_p)
    _assert_same(plain, fused, 1e-12)
    # The input gradient may be split differently among identical points; its sum may not.
    fold = lambda d: torch.cat([d[:, :5] + d[:, 12:], d[:, 5:12]], dim=1)  # noqa: E731
    _close(fold(dx_f), fold(dx_p), 1e-12, "summed input gradient")


def test_state_dict_interchanges() -> None:
    plain = PointLayerMaxPool(8, 24)
    _randomise_bn(plain, 5)
    fused = FusedPointLayerMaxPool(8, 24)
    assert list(fused.state_dict()) == list(plain.state_dict())
    fused.load_state_dict(plain.state_dict())
    back = PointLayerMaxPool(8, 24)
    back.load_state_dict(fused.state_dict())
    x = _features(3, 10, 8, torch.float32)
    for m in (plain, fused, back):
        m.eval()
    with torch.no_grad():
        torch.testing.assert_close(fused(x), plain(x))
        torch.testing.assert_close(back(x), plain(x))


def test_fuse_and_unfuse_model_swap_in_place() -> None:
    model = build_model(resolve("shared-5", "paper").model)  # the max pool sits in the trunk
    params = {id(p) for p in model.parameters()}
    keys = list(model.state_dict())
    assert fuse_model(model) is model
    fused = [m for m in model.modules() if isinstance(m, FusedPointLayerMaxPool)]
    assert len(fused) == 1
    assert not any(type(m) is PointLayerMaxPool for m in model.modules())
    assert {id(p) for p in model.parameters()} == params  # optimizers keep working
    assert list(model.state_dict()) == keys
    unfuse_model(model)
    assert not any(isinstance(m, FusedPointLayerMaxPool) for m in model.modules())
    assert {id(p) for p in model.parameters()} == params
    assert isinstance(fuse_model(PointLayerMaxPool(4, 8)), FusedPointLayerMaxPool)


def _loss_curve(
    variant: str,
    fused: bool,
    steps: int,
    B: int = 8,
    n: int = 64,
    n_batches: int = 4,
    preset: str = "paper-literal",
) -> torch.Tensor:
    """Float64 training losses of a fresh PoseNet on ``n_batches`` synthetic batches, cycled."""
    torch.manual_seed(0)
    model = build_model(resolve(variant, preset).model).double()
    if fused:
        fuse_model(model)
    opt = torch.optim.Adam(model.parameters(), lr=8e-4)
    g = torch.Generator().manual_seed(1)
    batches = []
    for _ in range(n_batches):
        t_gt = torch.randn(B, 3, generator=g, dtype=torch.float64) * 0.05
        t_gt[:, 2] += 0.8
        R_gt = rotvec_to_rotmat(torch.randn(B, 3, generator=g, dtype=torch.float64))
        model_pts = torch.randn(B, n, 3, generator=g, dtype=torch.float64) * 0.04
        pts = model_pts @ R_gt.mT + t_gt[:, None]
        batches.append((pts, torch.randint(1, 22, (B,), generator=g), R_gt, t_gt))
    losses = []
    for step in range(steps):
        pts, cls, R_gt, t_gt = batches[step % n_batches]
        out = model(pts, cls)
        loss = pose_loss(out.R, out.t, R_gt, t_gt).total
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return torch.tensor(losses, dtype=torch.float64)


@pytest.fixture
def one_thread():
    """Single-threaded: deterministic reductions, and immune to other jobs on a small machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("variant", ["shared-0", "shared-3", "shared-5"])
def test_posenet_loss_curve_float64(variant: str, one_thread) -> None:
    plain = _loss_curve(variant, fused=False, steps=20)
    fused = _loss_curve(variant, fused=True, steps=20)
    assert plain[-4:].sum() < plain[:4].sum()  # it trains (4 batches, cycled)
    torch.testing.assert_close(fused, plain, rtol=1e-10, atol=0)


@pytest.mark.slow
def test_posenet_loss_curve_float64_300_steps(one_thread) -> None:
    """300 steps on 300 distinct batches.

    Training amplifies any rounding difference (plain against itself with the learning rate
    changed by 1e-14 drifts by ~1e-10 here, and by percents over 300 steps on 4 cycled
    batches, where it overfits), so the bound is relative to that, not to machine epsilon.
    """
    kw = {"steps": 300, "B": 16, "n": 64, "n_batches": 300}
    plain = _loss_curve("shared-0", fused=False, **kw)
    fused = _loss_curve("shared-0", fused=True, **kw)
    torch.testing.assert_close(fused, plain, rtol=1e-8, atol=0)


def test_bf16_mode_is_close_and_off_by_default() -> None:
    plain, fused = _pair(16, 32, torch.float32)
    assert not fused.bf16
    fused.bf16 = True
    x = _features(4, 24, 16, torch.float32)
    g = torch.randn(4, 32)
    out_p, _ = _run(plain, x, g)
    out_f, _ = _run(fused, x, g)
    torch.testing.assert_close(out_f, out_p, rtol=0.05, atol=0.05)
    torch.testing.assert_close(fused.bn.running_mean, plain.bn.running_mean)  # stats stay fp32


def test_autocast_input_runs_in_float32() -> None:
    plain, fused = _pair(16, 32, torch.float32)
    x = _features(2, 10, 16, torch.float32)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = fused(x.bfloat16())
    assert out.dtype == torch.float32
    torch.testing.assert_close(out, plain(x.bfloat16().float()), rtol=1e-5, atol=1e-5)


def test_bad_input_raises() -> None:
    fused = FusedPointLayerMaxPool(8, 16)
    with pytest.raises(ValueError, match=r"\(B, n, 8\)"):
        fused(torch.randn(4, 8))
    with pytest.raises(ValueError, match="more than 1 value"):
        fused(torch.randn(1, 1, 8))


@pytest.mark.parametrize(
    ("kernel", "device", "fused"),
    [("fused", "cpu", True), ("fused", "cuda", False), ("plain", "cpu", False)],
)
def test_training_fuses_on_the_cpu_only(kernel: str, device: str, fused: bool) -> None:
    """The fused kernel is the CPU's; on a GPU training runs the plain modules (faster there)."""
    from cloudpose.train.loop import fused_kernel

    cfg = resolve("shared-0", "smoke", overrides={"train": {"kernel": kernel}})
    assert fused_kernel(cfg, torch.device(device)) is fused
