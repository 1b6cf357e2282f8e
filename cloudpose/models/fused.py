"""The last per-point layer and the max pool as one autograd function (training speed).

One algorithm (its forward, its hand-written backward, and the module swap that uses it), so
one file of ~500 lines.

:class:`~cloudpose.models.basenet.PointLayerMaxPool` computes, for input points x (B, n, C)::

    y = x W^T + b            (B*n, D)   D = 1024, 87% of the network's FLOPs
    z = BN(y)                (B*n, D)   batch statistics over all B*n points in training
    out = max_points relu(z) (B, D)

and so forms, saves and backpropagates through several (B*n, D) tensors (128 MiB each at
B = 128, n = 256). :class:`FusedPointLayerMaxPool` computes exactly the same function, with the
same parameters and state_dict, without keeping any (B*n, D) tensor:

- Statistics. In training BN uses the batch mean and biased variance of y. Both follow from the
  C x C covariance of x: ``mean_y = W mean_x + b`` and ``var_y = diag(W Cov_x W^T)``.
- Max before the affine. ``z = a * (y - mean_y) + beta`` with ``a = gamma / sqrt(var_y + eps)``.
  ReLU is monotone, so it commutes with the max; and ``max_i a*u_i = |a| * max_i s*u_i`` with
  ``s = sign(gamma) = sign(a)``. So one GEMM with the sign-folded weights ``s * W``, in chunks
  of points, feeds a max/argmax reduction and is then dropped: only (B, D) values and indices
  survive.
- Backward. The gradient of the max reaches one point per (sample, channel), so dL/dz is a sparse
  matrix S with B*D entries. The BN statistics couple every point, but only through rank-one
  and C x C terms (derivation in :meth:`_FusedPointMaxPoolFn.backward`)::

      dL/dx = S W - 1 (k1^T W) - x_c (W^T diag(k2) W)             (B*n, C)
      dL/dW = S^T x_c - N diag(k2) W Cov_x                         (D, C)
      dL/db = 0  (training: BN removes the bias)

  ``S W`` and ``S^T x_c`` touch B*D rows of length C (an ``index_add_`` and an
  ``embedding_bag``); the rest is (B*n, C) x (C, C) work. The backward never recomputes y.

FLOPs of the 128 -> 1024 layer, fwd + bwd: plain 3 GEMMs of 2*N*C*D; fused one such GEMM plus
two of 2*N*C*C (covariance, ``x_c @ M``), i.e. 1.25 / 3 of the plain count.

Eval mode (running statistics) folds BN into the Linear and takes ``amax`` of ``x W'^T + b'``.

Across processes (one batch split over the processes of a distributed run,
:mod:`cloudpose.models.sync_bn`): the mean of x, then its centred scatter, are all-reduced, so BN
normalises with the whole batch's statistics; the backward all-reduces ``dbeta`` and ``dgamma``
(the two (D,) sums the statistics' gradient needs), as a synchronised BatchNorm does.

Ties: the plain module's ``amax`` shares the gradient equally among tied points; this module
sends it to the one index ``torch.max`` returns. Tied points have identical features (e.g. the
repeated points that pad a small segment), and every parameter gradient is a sum over points of
a function of the point's features, so parameter gradients agree; only the split of the input
gradient among identical points differs. A channel with ``gamma == 0`` exactly makes all points
tie; its ``gamma`` gradient then differs from the plain module's (measure zero in practice).

Slow twin: :class:`~cloudpose.models.basenet.PointLayerMaxPool` itself (tests/test_fused.py).
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import nn
from torch.autograd.function import once_differentiable

from cloudpose.models.basenet import PointLayerMaxPool
from cloudpose.models.sync_bn import GroupBatchStats, all_reduce_sum, global_mean

__all__ = [
    "DEFAULT_CHUNK_ROWS",
    "FusedPointLayerMaxPool",
    "fuse_model",
    "fused_point_max_pool",
    "unfuse_model",
]

DEFAULT_CHUNK_ROWS = 2048
"""Points per chunk of the forward GEMM: a (D, rows) buffer of 8 MiB at D = 1024 in float32."""


def _max_argmax_chunked(
    xin: torch.Tensor, ws: torch.Tensor, chunk_rows: int, bf16: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per sample and channel, the max over points of ``xin @ ws^T`` and where it is.

    Args:
        xin: (B, n, C) point features.
        ws: (D, C) weights.
        chunk_rows: points per GEMM chunk (whole samples; at least one sample per chunk).
        bf16: run the GEMM in bfloat16 (values then rounded to bfloat16).

    Returns:
        umax (D, B) maxima in ``xin``'s dtype and idx (D, B) int64 point indices in 0..n-1.
    """
    B, n, C = xin.shape
    D = ws.shape[0]
    bc = max(1, min(B, chunk_rows // n))
    gemm_dtype = torch.bfloat16 if bf16 else xin.dtype
    w = ws.to(gemm_dtype)
    dev = xin.device
    buf = torch.empty(D * bc * n, dtype=gemm_dtype, device=dev)  # reused by every chunk
    mask_buf = torch.empty(D * bc * n, dtype=xin.dtype, device=dev) if bf16 else buf
    # Point i scores i + n; one match sums to [n, 2n), two or more to >= 2n + 1.
    score = torch.arange(n, 2 * n, dtype=xin.dtype, device=dev)  # (n,)
    umax = torch.empty(D, B, dtype=xin.dtype, device=dev)
    idx = torch.empty(D, B, dtype=torch.long, device=dev)
    for s in range(0, B, bc):
        k = min(bc, B - s)
        u = buf[: D * k * n].view(D, k, n)
        torch.mm(w, xin[s : s + k].reshape(k * n, C).to(gemm_dtype).T, out=u.view(D, k * n))
        vals = u.amax(dim=2)  # (D, k)
        # torch.max(dim) finds the index with a scalar loop (~4x the cost of the rest); a
        # vectorised compare and a matrix-vector product find it instead.
        mask = mask_buf[: D * k * n].view(D, k, n)
        torch.ge(u, vals[:, :, None], out=mask)  # (D, k, n) 1.0 at the maxima
        hit = mask.view(D * k, n) @ score  # (D*k,)
        tied = hit >= 2 * n
        if bool(tied.any()):  # several points share the max: take the first one
            rows = tied.nonzero().squeeze(1)
            hit[rows] = mask.view(D * k, n)[rows].argmax(dim=1).to(hit.dtype) + n
        umax[:, s : s + k] = vals
        # No match only with NaN; clamp keeps the index valid (NaN propagates via vals).
        idx[:, s : s + k] = (hit - n).clamp_(0, n - 1).view(D, k).long()
    return umax, idx


def _amax_chunked(
    x: torch.Tensor, wf: torch.Tensor, bf: torch.Tensor, chunk_rows: int, bf16: bool
) -> torch.Tensor:
    """``relu(max over points of x @ wf^T + bf)`` in chunks, no indices (no-grad path).

    Args:
        x: (B, n, C) point features.
        wf: (D, C) folded weights (BN scale applied).
        bf: (D,) folded bias.
        chunk_rows: points per GEMM chunk.
        bf16: run the GEMM in bfloat16.

    Returns:
        (B, D) pooled features.
    """
    B, n, C = x.shape
    D = wf.shape[0]
    bc = max(1, min(B, chunk_rows // n))
    gemm_dtype = torch.bfloat16 if bf16 else x.dtype
    w = wf.to(gemm_dtype)
    buf = torch.empty(bc * n * D, dtype=gemm_dtype, device=x.device)
    out = torch.empty(B, D, dtype=x.dtype, device=x.device)
    for s in range(0, B, bc):
        k = min(bc, B - s)
        u = buf[: k * n * D].view(k * n, D)
        torch.mm(x[s : s + k].reshape(k * n, C).to(gemm_dtype), w.T, out=u)  # (k*n, D)
        out[s : s + k] = u.view(k, n, D).amax(dim=1)
    return torch.relu_(out.add_(bf))


def _batch_stats(
    xf: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, group: Any = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, int]:
    """BN batch statistics of ``y = xf W^T + b`` from the covariance of ``xf``.

    Args:
        xf: (N, C) inputs, N = B*n points.
        weight: (D, C), bias: (D,).
        group: a process group whose processes' points together make the batch (the mean,
            then the centred scatter, all-reduced: :mod:`cloudpose.models.sync_bn`); None = this
            process's points alone.

    Returns:
        mean_y (D,), biased var_y (D,), centred inputs x_c (N, C), mean_x (C,), W Cov_x (D, C),
        and the number of points the statistics are over.
    """
    if group is None:
        N = xf.shape[0]
        mean_x = xf.mean(dim=0)  # (C,)
        xc = xf - mean_x  # (N, C)
        cov = (xc.T @ xc).div_(N)  # (C, C), biased
    else:
        mean_x, N = global_mean(xf, group)  # (C,), points of every process
        xc = xf - mean_x  # (N_r, C)
        cov = all_reduce_sum(xc.T @ xc, group).div_(N)  # (C, C), biased
    w_cov = weight @ cov  # (D, C)
    var_y = (w_cov * weight).sum(dim=1).clamp_(min=0)  # (D,) = diag(W Cov W^T)
    mean_y = torch.addmv(bias, weight, mean_x)  # (D,)
    return mean_y, var_y, xc, mean_x, w_cov, N


class _FusedPointMaxPoolFn(torch.autograd.Function):
    """Linear + BatchNorm1d + ReLU + max over points, forward and backward without (B*n, D)."""

    @staticmethod
    def forward(
        ctx: Any,
        x: torch.Tensor,
        weight: torch.Tensor,
        bias: torch.Tensor,
        gamma: torch.Tensor,
        beta: torch.Tensor,
        running_mean: torch.Tensor | None,
        running_var: torch.Tensor | None,
        use_batch_stats: bool,
        eps: float,
        bf16: bool,
        chunk_rows: int,
        group: Any = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Returns out (B, D), and the (non-differentiable) batch mean_y and biased var_y (D,)."""
        B, n, C = x.shape
        N = B * n
        with torch.autocast(device_type=x.device.type, enabled=False):
            xf = x.reshape(N, C)
            if use_batch_stats:
                mean_y, var_y, xin, _, w_cov, n_all = _batch_stats(xf, weight, bias, group)
                offset = torch.zeros_like(bias)  # y - mean_y = x_c W^T
            else:
                assert running_mean is not None and running_var is not None
                mean_y, var_y = running_mean.clone(), running_var.clone()
                xin, w_cov, n_all = xf, None, N
                offset = bias - running_mean  # y - mean_y = x W^T + offset
            inv_std = torch.rsqrt(var_y + eps)  # (D,)
            a = gamma * inv_std  # (D,) BN scale
            sign = torch.where(gamma < 0, -1.0, 1.0).to(x.dtype)  # (D,) = sign(a)
            umax, idx = _max_argmax_chunked(
                xin.view(B, n, C), weight * sign[:, None], chunk_rows, bf16
            )  # (D, B) max of s * (x W^T) and its point
            yhat = (sign[:, None] * umax + offset[:, None]) * inv_std[:, None]  # (D, B)
            zmax = gamma[:, None] * yhat + beta[:, None]  # (D, B) BN output at the max
            out = torch.relu(zmax).T.contiguous()  # (B, D)

        ctx.use_batch_stats = use_batch_stats
        ctx.shape = (B, n, C)
        ctx.group = group if use_batch_stats else None
        ctx.n_all = n_all
        ctx.save_for_backward(xin, weight, a, inv_std, yhat, zmax, idx, w_cov)
        ctx.mark_non_differentiable(mean_y, var_y)
        return out, mean_y, var_y

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, g_out: torch.Tensor, *_: Any) -> tuple[torch.Tensor | None, ...]:
        """Gradients w.r.t. x, W, b, gamma, beta.

        With G = dL/dz (sparse: one point per sample and channel), the BN backward is
        ``dL/dy = a * (G - mean_points(G) - yhat * mean_points(G * yhat))``. Here
        ``mean_points(G) = dbeta / N`` and ``mean_points(G * yhat) = dgamma / N``, and
        ``yhat = x_c W^T diag(inv_std)``, so ``dL/dy = S - 1 k1^T - x_c W^T diag(k2)`` with
        ``S = a * G``, ``k1 = a * dbeta / N``, ``k2 = a * dgamma * inv_std / N``. Multiplying by
        W and by x gives the formulas of the module docstring (``S^T 1 = N k1`` cancels the
        mean_x terms of dL/dW). In eval mode the statistics are constants: ``k1 = k2 = 0``.

        Across processes (``group``): dbeta and dgamma of every process's points are
        all-reduced into k1 and k2 (over the global count), so dL/dx is the gradient of the
        whole batch's loss; each process's dL/dW takes its own points' ``S^T x_c`` and its
        share N_r of the covariance term, and these sum to the whole batch's dL/dW (DDP sums
        the processes' parameter gradients). dL/dgamma and dL/dbeta are this process's sums.
        """
        xin, weight, a, inv_std, yhat, zmax, idx, w_cov = ctx.saved_tensors
        B, n, C = ctx.shape
        N = B * n
        D = weight.shape[0]
        need_x, need_w, need_b, need_g, need_beta = ctx.needs_input_grad[:5]
        with torch.autocast(device_type=xin.device.type, enabled=False):
            gz = g_out.T.to(xin.dtype) * (zmax > 0)  # (D, B) dL/dz at the max points
            dbeta = gz.sum(dim=1)  # (D,)
            dgamma = (gz * yhat).sum(dim=1)  # (D,)
            v = a[:, None] * gz  # (D, B) the entries of S
            offsets = torch.arange(B, device=idx.device) * n
            flat = idx + offsets  # (D, B) row of each entry in the (N, C) input
            dx = dw = db = None
            if ctx.use_batch_stats:
                if ctx.group is None:
                    k1 = a * dbeta / N  # (D,)
                    k2 = a * dgamma * inv_std / N  # (D,)
                else:
                    sums = torch.stack([dbeta, dgamma])  # (2, D) this process's points
                    n_all = ctx.n_all
                    sums = all_reduce_sum(sums, ctx.group)  # every process's points
                    k1 = a * sums[0] / n_all  # (D,)
                    k2 = a * sums[1] * inv_std / n_all  # (D,)
                if need_x:
                    m = weight.T @ (k2[:, None] * weight)  # (C, C)
                    dx = torch.addmm((k1 @ weight).neg_().expand(N, C), xin, m, alpha=-1)
                if need_w:
                    dw = w_cov * (k2 * -N)[:, None]  # (D, C)
                if need_b:
                    db = torch.zeros_like(dbeta)
            else:
                if need_x:
                    dx = torch.zeros(N, C, dtype=xin.dtype, device=xin.device)
                if need_w:
                    dw = torch.zeros(D, C, dtype=xin.dtype, device=xin.device)
                if need_b:
                    db = v.sum(dim=1)
            if dx is not None:
                # S W: row flat[d, b] of dx gets v[d, b] * W[d]; in channel chunks of ~4 MiB.
                # v in row-major order: a (D, B) view of the transposed g_out would make each
                # chunk's product permuted, and its reshape a copy of the chunk.
                dc = max(1, (1 << 20) // max(1, B * C))
                vc = v.contiguous()
                for s in range(0, D, dc):
                    src = vc[s : s + dc, :, None] * weight[s : s + dc, None, :]  # (dc, B, C)
                    dx.index_add_(0, flat[s : s + dc].reshape(-1), src.reshape(-1, C))
                dx = dx.view(B, n, C)
            if dw is not None:
                # S^T x_c: per channel, the v-weighted sum of the B max points' inputs.
                dw += F.embedding_bag(flat, xin, per_sample_weights=v, mode="sum")  # (D, C)
        return (
            dx,
            dw,
            db,
            dgamma if need_g else None,
            dbeta if need_beta else None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
        )


def fused_point_max_pool(
    x: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor,
    gamma: torch.Tensor,
    beta: torch.Tensor,
    running_mean: torch.Tensor | None = None,
    running_var: torch.Tensor | None = None,
    *,
    use_batch_stats: bool = True,
    eps: float = 1e-5,
    bf16: bool = False,
    chunk_rows: int = DEFAULT_CHUNK_ROWS,
    group: Any = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``max_points relu(BN(x W^T + b))`` without forming the (B*n, D) activation.

    Differentiable w.r.t. x, weight, bias, gamma and beta (first order). Running statistics are
    read (``use_batch_stats=False``), never written: the caller updates them from the returned
    batch statistics (see :class:`FusedPointLayerMaxPool`).

    Args:
        x: (B, n, C) point features.
        weight: (D, C) Linear weight; bias: (D,) Linear bias.
        gamma, beta: (D,) BN affine parameters.
        running_mean, running_var: (D,) BN running statistics, used when not
            ``use_batch_stats``.
        use_batch_stats: BN training behaviour (statistics of this batch over all B*n points).
        eps: BN epsilon.
        bf16: the main GEMM in bfloat16 (statistics and backward stay in x's dtype).
        chunk_rows: points per chunk of the main GEMM.
        group: with batch statistics, the process group whose processes' points together
            make the batch (:mod:`cloudpose.models.sync_bn`); None = this call's points alone.

    Returns:
        out (B, D); mean_y (D,) and biased var_y (D,), the statistics BN normalised with.
    """
    if x.ndim != 3 or x.shape[-1] != weight.shape[1]:
        raise ValueError(
            f"fused_point_max_pool: x must have shape (B, n, {weight.shape[1]}), "
            f"got {tuple(x.shape)}"
        )
    if use_batch_stats and x.shape[0] * x.shape[1] < 2:
        raise ValueError(
            "fused_point_max_pool: batch statistics need more than 1 value per channel, "
            f"got x of shape {tuple(x.shape)}"
        )
    if not use_batch_stats and (running_mean is None or running_var is None):
        raise ValueError("fused_point_max_pool: use_batch_stats=False needs running statistics")
    return _FusedPointMaxPoolFn.apply(
        x,
        weight,
        bias,
        gamma,
        beta,
        running_mean,
        running_var,
        use_batch_stats,
        eps,
        bf16,
        chunk_rows,
        group,
    )


class FusedPointLayerMaxPool(GroupBatchStats, nn.Module):
    """Drop-in, exact replacement of :class:`~cloudpose.models.basenet.PointLayerMaxPool`.

    Same submodules (``linear``: nn.Linear, ``bn``: nn.BatchNorm1d), hence the same parameters,
    buffers and state_dict keys; running statistics follow nn.BatchNorm1d exactly (momentum, or
    the cumulative average when momentum is None; unbiased variance; ``num_batches_tracked``).

    Args:
        in_channels: C of the (B, n, C) input.
        out_channels: D of the (B, D) output.
        bn_momentum: BatchNorm momentum.
        bf16: run the main GEMM in bfloat16 (an approximation; never on by default).
        chunk_rows: points per chunk of the main GEMM (memory ~ 4 * D * chunk_rows bytes).

    Attributes:
        process_group: None, or in training the process group whose processes each hold an
            equal share of the batch: BatchNorm then uses the whole batch's statistics
            (:func:`cloudpose.models.sync_bn.sync_batch_stats` sets it).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        bn_momentum: float = 0.01,
        *,
        bf16: bool = False,
        chunk_rows: int = DEFAULT_CHUNK_ROWS,
    ) -> None:
        super().__init__()
        self.linear = nn.Linear(in_channels, out_channels)
        self.bn = nn.BatchNorm1d(out_channels, momentum=bn_momentum)
        self.bf16 = bf16
        self.chunk_rows = chunk_rows

    @classmethod
    def from_plain(
        cls, plain: PointLayerMaxPool, *, bf16: bool = False, chunk_rows: int = DEFAULT_CHUNK_ROWS
    ) -> FusedPointLayerMaxPool:
        """A fused module that shares (not copies) ``plain``'s ``linear`` and ``bn``.

        Parameters stay the same tensor objects, so an optimizer built before fusing keeps
        working.
        """
        fused = cls.__new__(cls)
        nn.Module.__init__(fused)
        fused.linear = plain.linear
        fused.bn = plain.bn
        fused.bf16 = bf16
        fused.chunk_rows = chunk_rows
        fused.train(plain.training)
        return fused

    def to_plain(self) -> PointLayerMaxPool:
        """The plain module sharing this one's ``linear`` and ``bn``."""
        plain = PointLayerMaxPool.__new__(PointLayerMaxPool)
        nn.Module.__init__(plain)
        plain.linear = self.linear
        plain.bn = self.bn
        plain.train(self.training)
        return plain

    def extra_repr(self) -> str:
        return f"bf16={self.bf16}, chunk_rows={self.chunk_rows}"

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Args: x (B, n, C_in). Returns: (B, C_out) global feature, the max over the n points."""
        lin, bn = self.linear, self.bn
        if x.ndim != 3 or x.shape[-1] != lin.in_features:
            raise ValueError(
                f"FusedPointLayerMaxPool input must have shape (B, n, {lin.in_features}), "
                f"got {tuple(x.shape)}"
            )
        x = x.to(lin.weight.dtype)  # autocast may hand in bfloat16 features
        B, n, _ = x.shape
        use_batch_stats = self.training or bn.running_mean is None
        update = self.training and bn.track_running_stats
        group = self.process_group if self.training else None
        if use_batch_stats and B * n < 2:
            raise ValueError(
                f"Expected more than 1 value per channel when training, got input {tuple(x.shape)}"
            )
        bias = lin.bias if lin.bias is not None else torch.zeros_like(lin.weight[:, 0])
        gamma = bn.weight if bn.affine else torch.ones_like(lin.weight[:, 0])
        beta = bn.bias if bn.affine else torch.zeros_like(lin.weight[:, 0])
        params = (x, lin.weight, bias, gamma, beta)
        if torch.is_grad_enabled() and any(t.requires_grad for t in params):
            out, mean_y, var_y = fused_point_max_pool(
                x,
                lin.weight,
                bias,
                gamma,
                beta,
                bn.running_mean,
                bn.running_var,
                use_batch_stats=use_batch_stats,
                eps=bn.eps,
                bf16=self.bf16,
                chunk_rows=self.chunk_rows,
                group=group,
            )
        else:
            with torch.no_grad(), torch.autocast(device_type=x.device.type, enabled=False):
                if use_batch_stats:
                    mean_y, var_y, *_ = _batch_stats(x.reshape(B * n, -1), lin.weight, bias, group)
                else:
                    mean_y, var_y = bn.running_mean, bn.running_var
                a = gamma * torch.rsqrt(var_y + bn.eps)  # (D,)
                wf = lin.weight * a[:, None]  # (D, C) BN folded into the Linear
                bf = a * (bias - mean_y) + beta  # (D,)
                out = _amax_chunked(x, wf, bf, self.chunk_rows, self.bf16)
        if update:
            count = B * n
            if group is not None:  # equal shares: the trainer splits every batch evenly
                count *= torch.distributed.get_world_size(group)
            self._update_running_stats(mean_y.detach(), var_y.detach(), count)
        return out

    @torch.no_grad()
    def _update_running_stats(self, mean_y: torch.Tensor, var_y: torch.Tensor, N: int) -> None:
        bn = self.bn
        assert bn.running_mean is not None and bn.running_var is not None
        assert bn.num_batches_tracked is not None
        bn.num_batches_tracked.add_(1)
        if bn.momentum is None:
            factor = 1.0 / float(bn.num_batches_tracked)
        else:
            factor = bn.momentum
        bn.running_mean.lerp_(mean_y.to(bn.running_mean.dtype), factor)
        unbiased = var_y * (N / (N - 1))
        bn.running_var.lerp_(unbiased.to(bn.running_var.dtype), factor)


def fuse_model(
    model: nn.Module, *, bf16: bool = False, chunk_rows: int = DEFAULT_CHUNK_ROWS
) -> nn.Module:
    """Replace, in place, every plain ``PointLayerMaxPool`` of ``model`` by the fused module.

    The fused modules share the plain ones' parameters and buffers, so outputs, gradients,
    running statistics, state_dict and optimizer state carry over unchanged. A module used at
    several places (a shared trunk) is replaced by one fused module used at the same places.

    Args:
        model: any module tree.
        bf16: bfloat16 main GEMM in the fused modules (an approximation; off by default).
        chunk_rows: points per GEMM chunk.

    Returns:
        ``model`` itself (a bare ``PointLayerMaxPool`` comes back as a new fused module).
    """
    return _swap(
        model,
        lambda m: type(m) is PointLayerMaxPool,
        lambda m: FusedPointLayerMaxPool.from_plain(m, bf16=bf16, chunk_rows=chunk_rows),
    )


def unfuse_model(model: nn.Module) -> nn.Module:
    """Undo :func:`fuse_model`: every ``FusedPointLayerMaxPool`` back to a plain module."""
    return _swap(model, lambda m: isinstance(m, FusedPointLayerMaxPool), lambda m: m.to_plain())


def _swap(model: nn.Module, match, make) -> nn.Module:
    if match(model):
        return make(model)
    done: dict[int, nn.Module] = {}
    for parent in list(model.modules()):
        for name, child in list(parent.named_children()):
            if match(child):
                if id(child) not in done:
                    done[id(child)] = make(child)
                setattr(parent, name, done[id(child)])
    return model
