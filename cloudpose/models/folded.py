"""Pose networks for inference: every BatchNorm folded into its Linear (inference speed).

In eval mode a BatchNorm is an affine map per channel, ``z = a * (y - mean) + beta`` with
``a = gamma / sqrt(running_var + eps)``, so ``BN(x W^T + b) = x (a W)^T + a (b - mean) + beta``:
one Linear. :func:`fold_for_inference` turns a trained :class:`~cloudpose.models.pose.PoseNet`
into a :class:`FoldedPoseNet` that computes the same eval-mode outputs. Its forward pass is the
network's own (:func:`~cloudpose.models.pose.pose_forward`: centring, what each branch sees,
R and t from the outputs); only its layers run differently, with

- no BatchNorm op: each (Linear, BN) pair is one ``addmm`` with folded weights, then ReLU in
  place;
- no one-hot input: the one-hot class channels of the first layer only add the weight column
  of the class, so the first layer is ``xyz W_xyz^T + (b + W_onehot[:, id - 1])``, a K = 3
  product with a per-sample bias instead of a (B, n, 3 + k) concatenation and a K = 3 + k
  product;
- the max pool before the bias and ReLU of the last per-point layer (``max_i relu(u_i + c) =
  relu(max_i u_i + c)``), so they touch (B, 1024) values instead of (B, n, 1024);
- both branches of a network with no shared layers (``shared-0``) run as one batched product
  per layer (``torch.baddbmm`` over a leading dimension of 2), halving the op count that
  dominates the cost of a single object.

Outputs equal the unfolded eval-mode network's up to float rounding (tests/test_folded.py:
float64 to ~1e-12, float32 to ~1e-5). The folded network has no training mode and no gradients
(its forward runs under ``torch.inference_mode``); fold again after changing the weights.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from cloudpose.models.basenet import BaseNet, PointLayer, PointLayerMaxPool, RegressionHead
from cloudpose.models.fused import FusedPointLayerMaxPool
from cloudpose.models.pose import PoseNet, PoseOutput, branch_layout, pose_forward

__all__ = ["FoldedPoseNet", "fold_bn", "fold_for_inference"]


def fold_bn(linear: nn.Linear, bn: nn.BatchNorm1d | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights of the Linear that equals ``bn(linear(x))`` in eval mode.

    Args:
        linear: the layer, weight (D, C) and optional bias (D,).
        bn: its BatchNorm1d (running statistics), or None for a bare Linear.

    Returns:
        weight (D, C) and bias (D,), new tensors (no autograd history).
    """
    with torch.no_grad():
        w = linear.weight.detach().clone()
        b = linear.bias.detach().clone() if linear.bias is not None else w.new_zeros(w.shape[0])
        if bn is None:
            return w, b
        if bn.running_mean is None or bn.running_var is None:
            raise ValueError("fold_bn: the BatchNorm has no running statistics to fold")
        a = torch.rsqrt(bn.running_var.to(w.dtype) + bn.eps)  # (D,)
        if bn.affine:
            a = a * bn.weight.detach()
        shift = bn.bias.detach() if bn.affine else torch.zeros_like(a)
        return w * a[:, None], a * (b - bn.running_mean.to(w.dtype)) + shift


class _FoldedStages(nn.Module):
    """A chain of folded per-point layers, the last one pooled if it is the max pool stage.

    Buffers ``w{i}`` (C_in, C_out) (transposed: the activations are the left operand) and
    ``b{i}`` (C_out,).
    """

    def __init__(self, stages: list[nn.Module]) -> None:
        super().__init__()
        self.n = len(stages)
        self.pooled = False
        for i, st in enumerate(stages):
            if isinstance(st, PointLayer):
                w, b = fold_bn(st.linear, st.bn)
            elif isinstance(st, (PointLayerMaxPool, FusedPointLayerMaxPool)):
                if i != len(stages) - 1:
                    raise ValueError("a max pool stage must be the last per-point stage")
                w, b = fold_bn(st.linear, st.bn)
                self.pooled = True
            else:
                raise ValueError(f"cannot fold per-point stage of type {type(st).__name__}")
            self.register_buffer(f"w{i}", w.T.contiguous())
            self.register_buffer(f"b{i}", b)

    def weight(self, i: int) -> torch.Tensor:
        return getattr(self, f"w{i}")

    def bias(self, i: int) -> torch.Tensor:
        return getattr(self, f"b{i}")

    def forward(self, x: torch.Tensor, first: int = 0) -> torch.Tensor:
        """Args: x (B, n, C) features entering stage ``first``. Returns (B, n, C') or (B, C')."""
        B, n, _ = x.shape
        h = x.reshape(B * n, -1)
        for i in range(first, self.n):
            if self.pooled and i == self.n - 1:
                u = (h @ self.weight(i)).view(B, n, -1).amax(dim=1)  # (B, D) max before bias
                return torch.relu_(u.add_(self.bias(i)))
            h = torch.relu_(torch.addmm(self.bias(i), h, self.weight(i)))  # (B*n, C_i)
        return h.view(B, n, -1)


class _FoldedHead(nn.Module):
    """A folded regression head: Linear (+BN folded) + ReLU per hidden layer, Linear out."""

    def __init__(self, head: RegressionHead) -> None:
        super().__init__()
        mods = list(head)
        pairs: list[tuple[nn.Linear, nn.BatchNorm1d | None]] = []
        i = 0
        while i < len(mods):
            lin = mods[i]
            if not isinstance(lin, nn.Linear):
                raise ValueError(f"cannot fold head module {type(lin).__name__}")
            bn = (
                mods[i + 1]
                if i + 1 < len(mods) and isinstance(mods[i + 1], nn.BatchNorm1d)
                else None
            )
            pairs.append((lin, bn))
            i += 3 if bn is not None else 1
        self.n = len(pairs)
        for k, (lin, bn) in enumerate(pairs):
            w, b = fold_bn(lin, bn)
            self.register_buffer(f"w{k}", w.T.contiguous())
            self.register_buffer(f"b{k}", b)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        for k in range(self.n):
            h = torch.addmm(getattr(self, f"b{k}"), h, getattr(self, f"w{k}"))
            if k < self.n - 1:
                h = torch.relu_(h)
        return h


class _FoldedBaseNet(nn.Module):
    """A folded BaseNet (or the part after a shared trunk)."""

    def __init__(self, net: BaseNet) -> None:
        super().__init__()
        self.stages = _FoldedStages(list(net.stages))
        self.head = _FoldedHead(net.head)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim == 2:  # the trunk already pooled (shared-5): only the head is left
            return self.head(x)
        return self.head(self.stages(x))


def _first_layer_split(
    stages: _FoldedStages, k: int, xyz_scale: float = 1.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """The first layer's xyz weights (3, C) for xyz in metres (``ModelConfig.xyz_scale``
    folded in) and its one-hot columns as (k, C) class biases."""
    if stages.n == 0 or (stages.n == 1 and stages.pooled):
        raise ValueError("fold_for_inference: the first per-point layer must not be the max pool")
    w = stages.weight(0)  # (3 + k, C)
    return (w[:3] / xyz_scale).contiguous(), w[3 : 3 + k].contiguous()


class FoldedPoseNet(nn.Module):
    """Eval-mode :class:`~cloudpose.models.pose.PoseNet` with BatchNorm folded (see module doc).

    Build it with :func:`fold_for_inference`. ``forward(points, cls_id)`` takes and returns what
    PoseNet's does.
    """

    def __init__(self, model: PoseNet) -> None:
        super().__init__()
        self.cfg = model.cfg
        self.k = model.cfg.num_classes
        self.mode = branch_layout(model.cfg)
        if self.mode == "all":
            assert model.net is not None
            self.net = _FoldedBaseNet(model.net)
            w3, wk = _first_layer_split(self.net.stages, self.k, self.cfg.xyz_scale)
            self.register_buffer("w_xyz", w3)
            self.register_buffer("w_cls", wk)
            return
        assert model.rotation_net is not None and model.translation_net is not None
        self.rot = _FoldedBaseNet(model.rotation_net)
        self.trans = _FoldedBaseNet(model.translation_net)
        if self.mode == "trunk":
            self.trunk = _FoldedStages(list(model.trunk))
            w3, wk = _first_layer_split(self.trunk, self.k, self.cfg.xyz_scale)
            self.register_buffer("w_xyz", w3)
            self.register_buffer("w_cls", wk)
            return
        # shared-0: stack the two branches layer by layer for batched products
        rs, ts = self.rot.stages, self.trans.stages
        same = (
            rs.n == ts.n
            and all(rs.weight(i).shape == ts.weight(i).shape for i in range(rs.n))
            and self.rot.head.n == self.trans.head.n
            and all(
                getattr(self.rot.head, f"w{i}").shape[0]
                == getattr(self.trans.head, f"w{i}").shape[0]
                for i in range(self.rot.head.n)
            )
        )
        self.paired = bool(same and rs.pooled and ts.pooled)
        for name, st in (("rot", rs), ("trans", ts)):
            w3, wk = _first_layer_split(st, self.k, self.cfg.xyz_scale)
            self.register_buffer(f"{name}_w_xyz", w3)
            self.register_buffer(f"{name}_w_cls", wk)
        if self.paired:
            self.register_buffer("p_w_xyz", torch.stack([self.rot_w_xyz, self.trans_w_xyz]))
            self.register_buffer("p_w_cls", torch.stack([self.rot_w_cls, self.trans_w_cls]))
            self.register_buffer("p_b0", torch.stack([rs.bias(0), ts.bias(0)]))
            for i in range(1, rs.n):
                self.register_buffer(f"p_w{i}", torch.stack([rs.weight(i), ts.weight(i)]))
                self.register_buffer(f"p_b{i}", torch.stack([rs.bias(i), ts.bias(i)]))
            rh, th = self.rot.head, self.trans.head
            for i in range(rh.n):
                wr, wt = getattr(rh, f"w{i}"), getattr(th, f"w{i}")
                br, bt = getattr(rh, f"b{i}"), getattr(th, f"b{i}")
                out = max(wr.shape[1], wt.shape[1])  # the outputs differ (rotation vs 3)
                self.register_buffer(
                    f"p_hw{i}",
                    torch.stack(
                        [F.pad(wr, (0, out - wr.shape[1])), F.pad(wt, (0, out - wt.shape[1]))]
                    ),
                )
                self.register_buffer(
                    f"p_hb{i}",
                    torch.stack(
                        [F.pad(br, (0, out - br.shape[0])), F.pad(bt, (0, out - bt.shape[0]))]
                    ),
                )
            self.n_stages, self.n_head = rs.n, rh.n
            self.rot_size = getattr(rh, f"w{rh.n - 1}").shape[1]

    def _first(
        self,
        stages: _FoldedStages,
        w_xyz: torch.Tensor,
        w_cls: torch.Tensor,
        xyz: torch.Tensor,
        cls0: torch.Tensor,
    ) -> torch.Tensor:
        """First per-point layer from xyz (B, n, 3) and 0-based classes (B,): (B, n, C)."""
        B, n, _ = xyz.shape
        bias = stages.bias(0) + w_cls[cls0]  # (B, C) the one-hot term is a class bias
        h = (xyz.reshape(B * n, 3) @ w_xyz).view(B, n, -1)  # (B, n, C)
        return torch.relu_(h.add_(bias[:, None, :]))

    @torch.inference_mode()
    def forward(self, points: torch.Tensor, cls_id: torch.Tensor) -> PoseOutput:
        """:func:`~cloudpose.models.pose.pose_forward` with the folded layers: the contract of
        :meth:`PoseNet.forward <cloudpose.models.pose.PoseNet.forward>`.

        Args:
            points: (B, n, 3) segment points in the camera frame, metres.
            cls_id: (B,) integer class ids, 1-based.

        Returns:
            PoseOutput with R (B, 3, 3), t (B, 3), rot_raw, t_residual (B, 3), mu (B, 3).
        """
        return pose_forward(self, points.to(self._dtype()), cls_id)

    def run_all(self, xyz: torch.Tensor, cls_id: torch.Tensor) -> torch.Tensor:
        """See :class:`~cloudpose.models.pose.PoseBranches`."""
        h = self._first(self.net.stages, self.w_xyz, self.w_cls, xyz, cls_id.long() - 1)
        return self.net.head(self.net.stages(h, first=1))

    def run_trunk(
        self, xyz: torch.Tensor, cls_id: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """See :class:`~cloudpose.models.pose.PoseBranches`."""
        h = self._first(self.trunk, self.w_xyz, self.w_cls, xyz, cls_id.long() - 1)
        h = self.trunk(h, first=1)
        return self.rot(h), self.trans(h)

    def run_pair(
        self, rot_xyz: torch.Tensor, trans_xyz: torch.Tensor, cls_id: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """See :class:`~cloudpose.models.pose.PoseBranches`; both branches as one batched
        product per layer where their shapes allow (:meth:`_paired`)."""
        cls0 = cls_id.long() - 1
        if self.paired:
            return self._paired(rot_xyz, trans_xyz, cls0)
        hr = self._first(self.rot.stages, self.rot_w_xyz, self.rot_w_cls, rot_xyz, cls0)
        ht = self._first(self.trans.stages, self.trans_w_xyz, self.trans_w_cls, trans_xyz, cls0)
        return self.rot.head(self.rot.stages(hr, first=1)), self.trans.head(
            self.trans.stages(ht, first=1)
        )

    def _dtype(self) -> torch.dtype:
        return next(iter(self.buffers())).dtype

    @staticmethod
    def _pooled_product(h: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """``(h @ w).amax(dim=2)`` of h (2, B, n, C) and w (2, C, D), one sample at a time.

        Each sample's (2, n, D) product (2 MiB at n = 256, D = 1024) is reduced while it is
        still in cache, instead of writing all B of them to memory and reading them back;
        the values are the same (each product element and each max are computed alike).
        """
        B, D = h.shape[1], w.shape[2]
        if B == 1:
            return torch.bmm(h[:, 0], w).amax(dim=1)[:, None, :]
        out = None
        for s in range(B):
            u = torch.bmm(h[:, s], w)  # (2, n, D); its dtype follows autocast where enabled
            if out is None:
                out = u.new_empty(B, 2, D)
            torch.amax(u, dim=1, out=out[s])
        return out.transpose(0, 1)

    def _paired(
        self, points: torch.Tensor, centred: torch.Tensor, cls0: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Both branches of shared-0 as one batched product per layer (leading dim 2)."""
        B, n, _ = points.shape
        x = torch.stack([points, centred]).view(2, B * n, 3)  # (2, B*n, 3)
        bias = self.p_b0[:, None, :] + self.p_w_cls[:, cls0]  # (2, B, C)
        h = torch.bmm(x, self.p_w_xyz).view(2, B, n, -1)  # (2, B, n, C)
        h = torch.relu_(h.add_(bias[:, :, None, :])).view(2, B * n, -1)
        last = self.n_stages - 1
        for i in range(1, last):
            h = torch.relu_(
                torch.baddbmm(getattr(self, f"p_b{i}")[:, None, :], h, getattr(self, f"p_w{i}"))
            )
        u = self._pooled_product(h.view(2, B, n, -1), getattr(self, f"p_w{last}"))  # (2, B, D)
        g = torch.relu_(u.add_(getattr(self, f"p_b{last}")[:, None, :]))
        for i in range(self.n_head):
            g = torch.baddbmm(getattr(self, f"p_hb{i}")[:, None, :], g, getattr(self, f"p_hw{i}"))
            if i < self.n_head - 1:
                g = torch.relu_(g)
        rot_raw = g[0, :, : self.rot_size]
        t_res = g[1, :, :3]
        return rot_raw, t_res


def fold_for_inference(model: PoseNet) -> FoldedPoseNet:
    """A :class:`FoldedPoseNet` computing ``model``'s eval-mode outputs (BatchNorm folded).

    Args:
        model: a pose network (plain or fused); its running statistics are used whatever its
            mode. Not modified.

    Returns:
        The folded network, on ``model``'s device and dtype.
    """
    if not isinstance(model, PoseNet):
        raise ValueError(f"fold_for_inference: expected a PoseNet, got {type(model).__name__}")
    return FoldedPoseNet(model)
