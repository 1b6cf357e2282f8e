"""BaseNet: PointNet without the spatial transformers (paper Sec. IV-A, docs/design.md "BaseNet").

    (B, n, 3 + k) -> per-point MLP 64-64-64-128-1024 (Linear + BN + ReLU on every point)
                  -> max pool over the n points -> (B, 1024)
                  -> FC 512 + BN + ReLU -> FC 256 + BN + ReLU -> FC out (no BN, no activation)

The per-point MLP is a list of *stages*, one module per layer, so that a pose network can hand
its first stages to both branches as one module (``cloudpose.models.pose``). The last stage,
:class:`PointLayerMaxPool`, holds the last per-point layer together with the max pool: it is
the unit a fused implementation may replace (same ``linear`` / ``bn`` parameters and
state_dict), since it is where the largest per-point activation, (B, n, 1024), lives.

Hidden widths are scaled by a multiplier ``width``: a layer of nominal width ``c`` gets
``max(1, round(c * width))`` channels (Python's ``round``). Input and output widths are never
scaled. BatchNorm uses the config's momentum (0.01 = the released code's decay 0.99); there is
no dropout.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise

import torch
from torch import nn


def scaled_width(channels: int, width: float) -> int:
    """The channel count of a nominal-``channels`` layer under the width multiplier.

    Args:
        channels: nominal width of the layer (e.g. 1024).
        width: multiplier (1.0 = the paper's widths).

    Returns:
        ``max(1, round(channels * width))``.
    """
    return max(1, round(channels * width))


class PointLayer(nn.Module):
    """One per-point layer: Linear + BatchNorm1d + ReLU applied to every point alike.

    Equivalent to the paper's 1x1 convolution; BatchNorm statistics are taken over all B * n
    points of the batch.
    """

    def __init__(self, in_channels: int, out_channels: int, bn_momentum: float = 0.01) -> None:
        super().__init__()
        self.linear = nn.Linear(in_channels, out_channels)
        self.bn = nn.BatchNorm1d(out_channels, momentum=bn_momentum)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Args: x (B, n, C_in). Returns: (B, n, C_out) per-point features."""
        B, n, _ = x.shape
        y = self.bn(self.linear(x.reshape(B * n, -1)))  # (B*n, C_out)
        return torch.relu(y).reshape(B, n, -1)


class PointLayerMaxPool(nn.Module):
    """The last per-point layer and the max pool: Linear + BatchNorm1d + ReLU, max over points.

    Its parameters are a plain ``nn.Linear`` (``linear``) and ``nn.BatchNorm1d`` (``bn``), so a
    faster implementation of the same computation can load this module's state_dict.
    """

    def __init__(self, in_channels: int, out_channels: int, bn_momentum: float = 0.01) -> None:
        super().__init__()
        self.linear = nn.Linear(in_channels, out_channels)
        self.bn = nn.BatchNorm1d(out_channels, momentum=bn_momentum)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Args: x (B, n, C_in). Returns: (B, C_out) global feature, the max over the n points."""
        B, n, _ = x.shape
        y = torch.relu(self.bn(self.linear(x.reshape(B * n, -1))))  # (B*n, C_out)
        return y.reshape(B, n, -1).amax(dim=1)  # (B, C_out)


def point_stages(
    in_channels: int,
    point_mlp: Sequence[int],
    width: float = 1.0,
    bn_momentum: float = 0.01,
) -> list[nn.Module]:
    """The per-point MLP as a list of stages: ``PointLayer`` ... ``PointLayer``, ``PointLayerMaxPool``.

    Args:
        in_channels: channels of each input point (3 + k).
        point_mlp: nominal widths of the per-point layers, e.g. (64, 64, 64, 128, 1024).
        width: width multiplier applied to every entry of ``point_mlp``.
        bn_momentum: BatchNorm momentum.

    Returns:
        ``len(point_mlp)`` new modules; stage i maps (B, n, C_{i-1}) to (B, n, C_i), the last
        one maps (B, n, C_{L-1}) to (B, C_L).
    """
    if not point_mlp:
        raise ValueError("model.point_mlp must list at least one per-point layer width")
    widths = [in_channels] + [scaled_width(c, width) for c in point_mlp]
    stages: list[nn.Module] = [
        PointLayer(c_in, c_out, bn_momentum) for c_in, c_out in pairwise(widths[:-1])
    ]
    stages.append(PointLayerMaxPool(widths[-2], widths[-1], bn_momentum))
    return stages


class RegressionHead(nn.Sequential):
    """FC + BN + ReLU for each hidden width, then a plain FC output: (B, C_in) -> (B, C_out)."""

    def __init__(
        self,
        in_channels: int,
        hidden: Sequence[int],
        out_channels: int,
        bn_momentum: float = 0.01,
    ) -> None:
        layers: list[nn.Module] = []
        c = in_channels
        for h in hidden:
            layers += [nn.Linear(c, h), nn.BatchNorm1d(h, momentum=bn_momentum), nn.ReLU()]
            c = h
        layers.append(nn.Linear(c, out_channels))
        super().__init__(*layers)


class BaseNet(nn.Module):
    """PointNet without spatial transformers: per-point MLP, max pool, regression MLP.

    Args:
        in_channels: channels of each input point, 3 + k (xyz + one-hot class).
        out_channels: size of the regression output (3 for axis-angle or a translation).
        point_mlp: nominal per-point widths, (64, 64, 64, 128, 1024) in the paper.
        head: nominal hidden widths of the regression MLP, (512, 256) in the paper.
        width: multiplier on every hidden width (``point_mlp`` and ``head``).
        bn_momentum: BatchNorm momentum.
        first_stage: the net owns per-point stages ``first_stage ..`` only, so its input is the
            output of stage ``first_stage - 1`` of the same layout; the earlier stages live
            elsewhere (a shared trunk). 0 = a complete BaseNet taking (B, n, in_channels);
            ``len(point_mlp)`` = the regression head alone, taking the pooled (B, C_L).

    Attributes:
        stages: ``nn.Sequential`` of the owned per-point stages (the last is the max pool).
        head: the regression MLP.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        point_mlp: Sequence[int] = (64, 64, 64, 128, 1024),
        head: Sequence[int] = (512, 256),
        width: float = 1.0,
        bn_momentum: float = 0.01,
        first_stage: int = 0,
    ) -> None:
        super().__init__()
        if not 0 <= first_stage <= len(point_mlp):
            raise ValueError(f"first_stage must be in 0..{len(point_mlp)}, got {first_stage}")
        all_stages = point_stages(in_channels, point_mlp, width, bn_momentum)
        self.stages = nn.Sequential(*all_stages[first_stage:])
        self.head = RegressionHead(
            scaled_width(point_mlp[-1], width),
            [scaled_width(h, width) for h in head],
            out_channels,
            bn_momentum,
        )
        self.in_channels = in_channels if first_stage == 0 else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Regress from points (or from a trunk's features when ``first_stage > 0``).

        Args:
            x: (B, n, 3 + k) points: xyz in metres and the one-hot class. For
                ``first_stage > 0``, the trunk's (B, n, C) features or (B, C) pooled feature.

        Returns:
            (B, out_channels) regression output.
        """
        if self.in_channels is not None and (x.ndim != 3 or x.shape[-1] != self.in_channels):
            raise ValueError(
                f"BaseNet input must have shape (B, n, {self.in_channels}), got {tuple(x.shape)}"
            )
        return self.head(self.stages(x))  # (B, out)
