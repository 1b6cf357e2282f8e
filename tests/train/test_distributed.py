"""One run across processes (gloo on CPU, 2 processes): the BatchNorm layers over the global
batch against one process holding the whole batch, then the real ``cloudpose train`` under
torchrun against one process."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp

from cloudpose.models.basenet import PointLayer, PointLayerMaxPool
from cloudpose.models.fused import FusedPointLayerMaxPool
from cloudpose.models.sync_bn import SyncBatchNorm1d, sync_batch_stats
from cloudpose.registry import resolve
from cloudpose.store import tracking
from cloudpose.store.runs import read_info
from cloudpose.suite.pipeline import train_run
from cloudpose.train.loop import TrainingInterrupted
from tests.conftest import make_project

WORLD = 2


def _layers(seed: int = 0) -> torch.nn.Module:
    """A plain per-point layer, a fused last layer and a BatchNorm over pooled features."""
    torch.manual_seed(seed)
    first = PointLayer(5, 16, bn_momentum=0.1)
    last = FusedPointLayerMaxPool.from_plain(PointLayerMaxPool(16, 32, bn_momentum=0.1))
    with torch.no_grad():  # non-trivial affine BN parameters, some negative scales
        for bn in (first.bn, last.bn):
            bn.weight.uniform_(-1.5, 1.5)
            bn.bias.uniform_(-0.5, 0.5)
    head = torch.nn.Sequential(torch.nn.Linear(32, 8), torch.nn.BatchNorm1d(8), torch.nn.ReLU())
    return torch.nn.Sequential(first, last, head)


def _batch(seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(8, 12, 5, generator=g, dtype=torch.float64) * 0.3 + 0.5  # (B, n, C)


def _step(model: torch.nn.Module, x: torch.Tensor) -> dict[str, torch.Tensor]:
    """Forward + backward of the batch-mean loss; the input and parameter gradients."""
    x = x.clone().requires_grad_(True)
    out = model(x)  # (B, 8)
    loss = (out * torch.linspace(-1, 1, 8, dtype=out.dtype)).sum(1).pow(2).mean()
    loss.backward()
    grads = {n: p.grad.clone() for n, p in model.named_parameters()}
    buffers = {n: b.clone() for n, b in model.named_buffers()}
    return {"out": out.detach(), "dx": x.grad, "grads": grads, "buffers": buffers}


def _worker(rank: int, init_file: str, results: dict) -> None:
    import torch.distributed as dist

    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=WORLD)
    model = sync_batch_stats(_layers().double().train(), dist.new_group())
    x = _batch()
    k = x.shape[0] // WORLD
    res = _step(model, x[rank * k : (rank + 1) * k])
    for g in res["grads"].values():  # what DDP does: the mean over processes
        dist.all_reduce(g)
        g /= WORLD
    results[rank] = res
    dist.destroy_process_group()


def test_batchnorm_over_two_processes_matches_one_process_whole_batch(tmp_path):
    ref = _step(_layers().double().train(), _batch())
    with mp.Manager() as manager:
        results = manager.dict()
        mp.spawn(_worker, args=(str(tmp_path / "init"), results), nprocs=WORLD, join=True)
        got = dict(results)
    k = _batch().shape[0] // WORLD
    for rank, res in got.items():
        rows = slice(rank * k, (rank + 1) * k)
        torch.testing.assert_close(res["out"], ref["out"][rows], rtol=1e-10, atol=1e-12)
        # each process's loss is its share's mean: WORLD times its rows' part of the whole
        torch.testing.assert_close(res["dx"], WORLD * ref["dx"][rows], rtol=1e-9, atol=1e-12)
        for name, g in ref["grads"].items():
            torch.testing.assert_close(res["grads"][name], g, rtol=1e-9, atol=1e-12, msg=name)
        for name, b in ref["buffers"].items():  # running statistics of the global batch
            torch.testing.assert_close(res["buffers"][name], b, rtol=1e-10, atol=1e-12, msg=name)
    assert set(got) == {0, 1}


def test_sync_batch_stats_keeps_parameters_and_is_plain_batchnorm_alone():
    model = _layers()
    params = {n: p for n, p in model.named_parameters()}
    sync_batch_stats(model, None)
    assert isinstance(model[2][1], SyncBatchNorm1d) and isinstance(model[0].bn, SyncBatchNorm1d)
    assert all(p is params[n] for n, p in model.named_parameters())
    assert set(model.state_dict()) == set(_layers().state_dict())
    x = _batch().float()
    torch.testing.assert_close(model(x), _layers()(x), rtol=0, atol=0)


def _free_port() -> int:
    """A free TCP port on 127.0.0.1 (18000-18999 first, then any)."""
    for port in [*range(18500, 18600), 0]:
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return s.getsockname()[1]
    raise RuntimeError("no free port")


def _curves(proj: Path, run_id: str, keys: tuple[str, ...]) -> dict[str, list[float]]:
    client = tracking.setup(proj)
    history = {k: client.get_metric_history(run_id, k) for k in keys}
    return {k: [m.value for m in sorted(h, key=lambda m: m.step)] for k, h in history.items()}


@pytest.mark.slow
def test_torchrun_two_processes_follow_one_process(tmp_path, smoke_data, monkeypatch):
    """One process trains 2 steps and is interrupted; ``torchrun --nproc_per_node 2 -m
    cloudpose.cli train`` (gloo, batch 16 split 8 + 8) resumes it from rank 0's checkpoint into
    the same MLflow run. Its loss curve is an uninterrupted one-process run's to float rounding
    (Adam amplifies rounding differences step by step, so later epochs drift further)."""
    cfg = resolve("shared-1", "smoke", seed=2)
    ref = train_run(cfg, project_dir=make_project(tmp_path / "one", smoke_data, monkeypatch))
    two = make_project(tmp_path / "two", smoke_data, monkeypatch)
    with pytest.raises(TrainingInterrupted):
        train_run(cfg, project_dir=two, progress=False, max_steps=2)
    cut = read_info(next((two / "runs").glob("shared-1/smoke/seed2-*")))
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env.update(CLOUDPOSE_NO_TCMALLOC="1", GLOO_SOCKET_IFNAME="lo")
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(WORLD)]
    torchrun += ["--master_addr", "127.0.0.1", "--master_port", str(_free_port())]
    train = ["train", "--variant", "shared-1", "--preset", "smoke", "--seed", "2", "--no-progress"]
    proc = subprocess.run(
        [*torchrun, "-m", "cloudpose.cli", *train], cwd=two, env=env, capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.count(f"run {cut['run_id']}") == 1  # the same run; rank 0 alone reports
    keys = ("train/loss", "train/loss_rot", "train/loss_trans")
    a, b = _curves(tmp_path / "one", ref.run_id, keys), _curves(two, cut["run_id"], keys)
    for k in keys:
        assert len(a[k]) == len(b[k]) == cfg.train.epochs, k
        np.testing.assert_allclose(b[k][0], a[k][0], rtol=5e-5, err_msg=k)  # first 3 steps
        np.testing.assert_allclose(b[k], a[k], rtol=1e-3, err_msg=k)
    runs = tracking.find_runs(tracking.setup(two), status=None)
    assert [r.info.status for r in runs] == ["FINISHED"]
    assert read_info(next((two / "runs").glob("shared-1/smoke/seed2-*")))["finished"]


def test_nproc_relaunches_the_same_command_under_torchrun(monkeypatch):
    import subprocess

    from cloudpose.train.distributed import relaunch_under_torchrun

    seen = {}

    def fake_run(cmd, check):
        seen["cmd"] = cmd
        return subprocess.CompletedProcess(cmd, 3)

    monkeypatch.setattr(subprocess, "run", fake_run)
    args = ["train", "--preset", "smoke", "--nproc", "2", "--seed", "4"]
    assert relaunch_under_torchrun(args, 2) == 3  # torchrun's exit code is the command's
    cmd = seen["cmd"]
    assert cmd[1:5] == ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node"]
    assert cmd[5] == "2" and cmd[6:8] == ["-m", "cloudpose.cli"]
    assert cmd[8:] == ["train", "--preset", "smoke", "--seed", "4"]  # --nproc 2 dropped
    assert args[3] == "--nproc"  # the caller's list is left as it was
