"""CUDA against CPU: a training step, inference and a whole smoke run give the CPU's numbers
within float tolerance. Marked ``gpu``: skipped where torch sees no CUDA device (conftest)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from cloudpose.geometry import random_rotmat
from cloudpose.geometry.symmetry import SymmetryTensors, symmetries_for
from cloudpose.models import build_model
from cloudpose.models.folded import fold_for_inference
from cloudpose.models.fused import fuse_model
from cloudpose.registry import resolve
from cloudpose.train.losses import pose_loss

pytestmark = pytest.mark.gpu

DEVICE = "cuda"
"""Where the tests run what they compare with the CPU."""

TOL = {"rtol": 1e-4, "atol": 1e-5}
"""float32 on two devices: the same maths in another summation order."""


@pytest.fixture(autouse=True)
def _full_float32():
    """No TF32 products on the GPU: the comparison is of float32 with float32."""
    before = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("highest")
    yield
    torch.set_float32_matmul_precision(before)


def _batch(num_classes: int, B: int = 32, n: int = 64):
    """Points near 0.8 m, class ids, and ground-truth poses (B segments of n points)."""
    g = torch.Generator().manual_seed(3)
    pts = torch.randn(B, n, 3, generator=g) * 0.05 + torch.tensor([0.1, -0.1, 0.8])
    cls_id = torch.randint(1, num_classes + 1, (B,), generator=g)
    R_gt = random_rotmat(B, generator=g)
    t_gt = pts.mean(dim=1) + 0.01 * torch.randn(B, 3, generator=g)
    return pts, cls_id, R_gt, t_gt


def _step(model, cfg, batch, device: str):
    """One training step as :func:`cloudpose.train.loop.train` takes it: outputs, the loss, the
    gradients, then the weights and BatchNorm statistics after Adam's update."""
    pts, cls_id, R_gt, t_gt = (x.to(device) for x in batch)
    symmetry = None
    if cfg.loss.symmetric:
        symmetry = SymmetryTensors(symmetries_for(_class_names())).to(device)
    model = model.to(device).train()
    opt = torch.optim.Adam(model.parameters(), lr=cfg.train.lr)
    out = model(pts, cls_id)
    terms = pose_loss(
        out.R,
        out.t,
        R_gt,
        t_gt,
        rotation=cfg.loss.rotation,
        alpha=cfg.loss.alpha,
        rotvec_pred=out.rot_raw,
        symmetry=symmetry,
        cls_id=cls_id,
    )
    opt.zero_grad(set_to_none=True)
    terms.total.backward()
    grads = {k: p.grad.detach().cpu() for k, p in model.named_parameters() if p.grad is not None}
    opt.step()
    return {
        "R": out.R.detach().cpu(),
        "t": out.t.detach().cpu(),
        "loss": terms.total.detach().cpu(),
        "grads": grads,
        "state": {k: v.detach().cpu() for k, v in model.state_dict().items()},
    }


def _class_names() -> list[str]:
    from cloudpose.conventions import resource_path
    from cloudpose.data.ycb import load_classes

    return list(load_classes(resource_path("classes.txt")))


def _close(a, b, what: str, **tol) -> None:
    if isinstance(a, dict):
        assert a.keys() == b.keys(), what
        for k in a:
            _close(a[k], b[k], f"{what}/{k}", **tol)
        return
    if a.dtype in (torch.int64, torch.int32):  # num_batches_tracked
        assert torch.equal(a, b), what
        return
    torch.testing.assert_close(a, b, msg=what, **(tol or TOL))


@pytest.mark.parametrize("variant", ["shared-0", "shared-3", "shared-all", "quaternion", "l2"])
@pytest.mark.parametrize("kernel", ["plain", "fused"])
def test_training_step_on_cuda_matches_cpu(variant, kernel):
    cfg = resolve(variant, "smoke")
    torch.manual_seed(0)
    model = build_model(cfg.model)
    if kernel == "fused":
        fuse_model(model)
    batch = _batch(cfg.model.num_classes)
    cpu = _step(copy.deepcopy(model), cfg, batch, "cpu")
    dev = _step(copy.deepcopy(model), cfg, batch, DEVICE)
    for key in ("R", "t", "loss"):
        _close(dev[key], cpu[key], key)
    # gradients of a max pool and a BatchNorm: a few float32 roundings more than the outputs
    _close(dev["grads"], cpu["grads"], "grad", rtol=1e-3, atol=1e-5)
    _close_after_adam(dev, cpu)


GRAD_FLOOR = 1e-4
"""Gradients above this have the same sign on both devices (they agree to 1e-5 + 0.1%)."""


def _close_after_adam(dev: dict, cpu: dict) -> None:
    """Weights and BatchNorm statistics after the step. Adam's first step moves a weight by
    about ``lr * sign(grad)``, so a gradient at rounding level moves it by up to ``lr`` either
    way: a Linear bias followed by BatchNorm has an exactly zero gradient in exact arithmetic,
    and float32 leaves noise whose sign differs between devices. Those entries are left out;
    every other weight and every buffer is compared, and they are most of the network."""
    compared = total = 0
    for name, a in dev["state"].items():
        b, grad = cpu["state"][name], cpu["grads"].get(name)
        if grad is not None:
            keep = grad.abs() > GRAD_FLOOR
            compared, total = compared + int(keep.sum()), total + keep.numel()
            a, b = a[keep], b[keep]
        _close(a, b, f"state/{name}", rtol=1e-3, atol=1e-5)
    assert compared > 0.5 * total, f"only {compared} of {total} weights have a clear gradient"


@pytest.mark.parametrize("variant", ["shared-0", "shared-2", "shared-all", "rot6d"])
def test_inference_on_cuda_matches_cpu(variant):
    """The eval-mode network and its folded form on CUDA give the CPU's poses."""
    cfg = resolve(variant, "smoke")
    torch.manual_seed(0)
    model = build_model(cfg.model)
    pts, cls_id, _, _ = _batch(cfg.model.num_classes, B=64, n=256)
    with torch.no_grad():  # running statistics that are not the initial ones
        model.train()(pts, cls_id)
    model.eval()
    with torch.no_grad():
        ref = model(pts, cls_id)
    on_dev = copy.deepcopy(model).to(DEVICE)
    with torch.no_grad():
        out = on_dev(pts.to(DEVICE), cls_id.to(DEVICE))
    folded = fold_for_inference(on_dev)(pts.to(DEVICE), cls_id.to(DEVICE))
    for name in ("R", "t", "rot_raw"):
        _close(getattr(out, name).cpu(), getattr(ref, name), f"eval {name}")
        _close(getattr(folded, name).cpu(), getattr(ref, name), f"folded {name}")


@pytest.mark.slow
def test_smoke_run_on_cuda_matches_cpu(tmp_path, smoke_data, monkeypatch):
    """shared-0 on the smoke preset, trained and evaluated with ``train.device`` cuda and cpu
    on the same data (same initial weights, batches and augmentation, all drawn on the CPU): close
    training losses, and close poses on the run's own test segments. Adam's steps amplify
    rounding in near-zero gradients, so the weights themselves are not compared."""
    from cloudpose.data.dataset import prepare_data
    from cloudpose.infer import estimate_poses, load_checkpoint
    from cloudpose.suite.pipeline import train_run
    from tests.conftest import make_project

    outcomes, test = [], None
    for i, device in enumerate(("cpu", DEVICE)):
        proj = make_project(tmp_path / f"{i}-{device}", smoke_data, monkeypatch)
        cfg = resolve("shared-0", "smoke", seed=1, overrides={"train": {"device": device}})
        outcomes.append(train_run(cfg, project_dir=proj, progress=False))
        test = prepare_data(cfg.data, project_dir=proj, progress=False).test
    cpu, dev = outcomes
    for key in ("train/loss", "train/loss_rot", "train/loss_trans"):
        assert dev.metrics[key] == pytest.approx(cpu.metrics[key], rel=1e-2), key
    est = []
    for device, o in zip(("cpu", DEVICE), outcomes, strict=True):
        model, cfg = load_checkpoint(o.checkpoint, device=device)
        est.append(estimate_poses(model, test, cfg.train.n_points, device=device))
    ok = np.isfinite(est[0].t).all(axis=1)
    assert ok.any()
    np.testing.assert_allclose(est[1].t[ok], est[0].t[ok], atol=5e-3)  # metres
    np.testing.assert_allclose(est[1].R[ok], est[0].R[ok], atol=5e-2)
