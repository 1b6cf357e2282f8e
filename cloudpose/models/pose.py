"""Pose networks built from a variant: rotation and translation BaseNets, shared as asked.

Paper Sec. IV (docs/design.md "The pose networks" and "The ablation registry"):

- Rotation branch: raw camera-frame xyz + one-hot class -> rotation output (axis-angle 3,
  unit quaternion 4 or 6D 6 numbers) -> rotation matrix R. ``rotation_input = "centred"``
  gives it the translation branch's mean-centred xyz instead (learns rotation several times
  faster at small budgets; what every shared variant's trunk sees anyway).
- Translation branch: xyz - mu + one-hot -> residual dt; t = dt + mu. mu is the mean of the
  network's n input points (the paper's mean of X), not of the whole segment.
- ``shared_layers = k`` in 1..5: the first k per-point stages are ONE module (``trunk``) that
  both branches run through, computed once per forward. Our choice where the paper is silent
  (docs/design.md): the trunk takes the translation branch's input, the mean-centred points +
  one-hot, so for k >= 1 the rotation branch too sees centred points. k = 5 shares the whole
  per-point MLP and the pooled feature; the branches are then two regression heads.
- ``shared_layers = "all"``: one BaseNet on the centred input whose output is
  ``[dt (3), rotation output (3 | 4 | 6)]``.

Class ids are 1-based (0 = background); the one-hot uses ``id - 1`` (cloudpose.conventions).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, Protocol

import torch
import torch.nn.functional as F
from torch import nn

from cloudpose.config import ModelConfig
from cloudpose.geometry import normalize_quat, rot6d_to_rotmat, rotvec_to_rotmat, unitquat_to_rotmat
from cloudpose.models.basenet import BaseNet, point_stages
from cloudpose.registry import groups_of, resolve, variants

ROTATION_SIZES = {"axis_angle": 3, "quaternion": 4, "rot6d": 6}
"""Raw output size of each rotation representation."""


class PoseOutput(NamedTuple):
    """What a pose network returns for a batch of B segments.

    Attributes:
        R: (B, 3, 3) rotation, model -> camera.
        t: (B, 3) translation in metres, ``t_residual + mu``.
        rot_raw: (B, 3 | 4 | 6) raw rotation output: axis-angle in radians, an unnormalised
            XYZW quaternion, or the 6D vector (first two columns of R, unnormalised).
        t_residual: (B, 3) regressed translation residual to ``mu``, metres.
        mu: (B, 3) mean of the n input points, metres.
    """

    R: torch.Tensor
    t: torch.Tensor
    rot_raw: torch.Tensor
    t_residual: torch.Tensor
    mu: torch.Tensor


def raw_rotation_to_rotmat(rot_raw: torch.Tensor, rotation: str) -> torch.Tensor:
    """Rotation matrices from a network's raw rotation output.

    Args:
        rot_raw: (..., 3 | 4 | 6) raw output.
        rotation: "axis_angle" (exponential map), "quaternion" (normalised, XYZW) or "rot6d"
            (Gram-Schmidt on the first two columns, Zhou et al. 2019).

    Returns:
        (..., 3, 3) rotation matrices.
    """
    if rotation not in ROTATION_SIZES:
        raise ValueError(f"rotation must be one of {tuple(ROTATION_SIZES)}, got {rotation!r}")
    if rot_raw.shape[-1] != ROTATION_SIZES[rotation]:
        raise ValueError(
            f"{rotation} output must have last dimension {ROTATION_SIZES[rotation]}, "
            f"got shape {tuple(rot_raw.shape)}"
        )
    if rotation == "axis_angle":
        return rotvec_to_rotmat(rot_raw)
    if rotation == "quaternion":
        return unitquat_to_rotmat(normalize_quat(rot_raw))
    return rot6d_to_rotmat(rot_raw)


def branch_layout(cfg: ModelConfig) -> str:
    """How a pose network of ``cfg`` runs its branches: "all" (``shared_layers = "all"``: one
    BaseNet whose output is ``[dt, rotation]``), "trunk" (1..5: the shared per-point stages,
    then each branch's own) or "pair" (0: two branches of their own)."""
    if cfg.shared_layers == "all":
        return "all"
    return "trunk" if int(cfg.shared_layers) > 0 else "pair"


class PoseBranches(Protocol):
    """What :func:`pose_forward` asks of a network: its config and how its layers run.

    Each method takes xyz in metres, (B, n, 3), and the 1-based class ids (B,), and applies
    the network's layers to them (the xyz scale and the one-hot class are its business).
    """

    cfg: ModelConfig

    def run_all(self, xyz: torch.Tensor, cls_id: torch.Tensor) -> torch.Tensor:
        """Layout "all": the one network's output (B, 3 + rot), ``[dt, rotation]``."""
        ...

    def run_trunk(
        self, xyz: torch.Tensor, cls_id: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Layout "trunk": the trunk once, then both branches: rotation (B, rot), dt (B, 3)."""
        ...

    def run_pair(
        self, rot_xyz: torch.Tensor, trans_xyz: torch.Tensor, cls_id: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Layout "pair": each branch on its own input: rotation (B, rot), dt (B, 3).
        ``rot_xyz is trans_xyz`` when both branches see the same points."""
        ...


def pose_forward(
    net: PoseBranches,
    points: torch.Tensor,
    cls_id: torch.Tensor,
    trans_points: torch.Tensor | None = None,
) -> PoseOutput:
    """The forward pass of a pose network: the one used in training (:class:`PoseNet`) and
    at inference (:class:`~cloudpose.models.folded.FoldedPoseNet`).

    The points are centred on mu (their mean, or a robust centre: ``ModelConfig.centre``,
    :func:`segment_centre`); the translation branch (and a trunk) sees the
    centred points, the rotation branch of layout "pair" the centred or the raw points
    (``ModelConfig.rotation_input``; centred on mu or on the mean,
    ``ModelConfig.rotation_centre``); the rotation output becomes R, and ``t = dt + mu``.
    ``net`` supplies how its layers run (:class:`PoseBranches`).

    Args:
        net: the network.
        points: (B, n, 3) segment points in the camera frame, metres.
        cls_id: (B,) integer class ids, 1-based (1..num_classes).
        trans_points: (B, m, 3) another form of the same segments for the translation branch
            (layout "pair" only: training with ``data.online_bleed_branch = "translation"``):
            mu and the translation come from them, the rotation from ``points`` (centred, if
            centred, on their own centre). None: both branches see ``points``.

    Returns:
        PoseOutput with R (B, 3, 3), t (B, 3), rot_raw (B, 3|4|6), t_residual (B, 3),
        mu (B, 3).
    """
    cfg = net.cfg
    check_pose_inputs(points, cls_id, cfg.num_classes)
    layout = branch_layout(cfg)
    if trans_points is not None:
        check_pose_inputs(trans_points, cls_id, cfg.num_classes)
        if layout != "pair":
            raise ValueError(
                "a translation input of its own needs branches that share no layer "
                f"(model.shared_layers=0), got model.shared_layers={cfg.shared_layers!r}"
            )
    trans_in = points if trans_points is None else trans_points
    mu = segment_centre(trans_in, cfg.centre)  # (B, 3)
    centred = trans_in - mu[:, None, :]  # (B, n, 3)
    if layout == "all":
        out = net.run_all(centred, cls_id)  # (B, 3 + rot)
        t_residual, rot_raw = out[:, :3], out[:, 3:]
    elif layout == "trunk":
        rot_raw, t_residual = net.run_trunk(centred, cls_id)
    else:
        rot_xyz = points
        if cfg.rotation_input == "centred":  # on mu, or on the mean (ModelConfig)
            centre = "mean" if cfg.rotation_centre == "mean" else cfg.centre
            same = trans_points is None and centre == cfg.centre
            rot_xyz = centred if same else points - segment_centre(points, centre)[:, None, :]
        rot_raw, t_residual = net.run_pair(rot_xyz, centred, cls_id)
    R = raw_rotation_to_rotmat(rot_raw, cfg.rotation)  # (B, 3, 3)
    return PoseOutput(R, t_residual + mu, rot_raw, t_residual, mu)


TRIM_KEEP = 0.75
"""The share of a segment's points the "trimmed" centre averages: those nearest the
per-coordinate median."""


def segment_centre(points: torch.Tensor, centre: str = "mean") -> torch.Tensor:
    """The point (B, 3) a segment (B, n, 3) is centred on (``ModelConfig.centre``).

    "mean": the mean (the paper). "median": the per-coordinate median (for even n the lower of
    the two middle values, as :func:`torch.median`). "trimmed": the mean of the
    ``ceil(TRIM_KEEP * n)`` points nearest the per-coordinate median. Points a mask lets in
    from the background behind the object pull both robust centres far less than the mean;
    points of a neighbour right beside the rim are within the object's own spread and move
    the median about as much as the mean (its shift is then ~ the bled share times the
    object's spread, not times their distance).
    """
    if centre == "mean":
        return points.mean(dim=1)
    median = points.median(dim=1).values  # (B, 3)
    if centre == "median":
        return median
    if centre != "trimmed":
        raise ValueError(f"centre must be 'mean', 'median' or 'trimmed', got {centre!r}")
    n = points.shape[1]
    keep = max(1, math.ceil(TRIM_KEEP * n))
    d2 = ((points - median[:, None, :]) ** 2).sum(dim=-1)  # (B, n)
    idx = torch.topk(d2, keep, dim=1, largest=False).indices  # (B, keep)
    near = torch.gather(points, 1, idx[..., None].expand(-1, -1, 3))
    return near.mean(dim=1)


def check_pose_inputs(points: torch.Tensor, cls_id: torch.Tensor, num_classes: int) -> None:
    """Raise ``ValueError`` unless points are (B>0, n>0, 3) and cls_id (B,) ints in 1..k."""
    if points.ndim != 3 or points.shape[-1] != 3 or 0 in points.shape[:2]:
        raise ValueError(f"points must have shape (B>0, n>0, 3), got {tuple(points.shape)}")
    if cls_id.shape != points.shape[:1] or cls_id.is_floating_point():
        raise ValueError(
            f"cls_id must be an integer tensor of shape ({points.shape[0]},), "
            f"got {cls_id.dtype} {tuple(cls_id.shape)}"
        )
    # Range check only off-GPU: on CUDA it would force a host sync every step.
    k = num_classes
    if cls_id.device.type == "cpu" and (int(cls_id.min()) < 1 or int(cls_id.max()) > k):
        raise ValueError(f"cls_id must be 1-based class ids in 1..{k}, got {cls_id.tolist()}")


class PoseNet(nn.Module):
    """Rotation + translation regression from a point-cloud segment, built from a ModelConfig.

    Args:
        cfg: architecture (shared layers, width multiplier, rotation representation, widths,
            number of classes, BatchNorm momentum).

    Attributes:
        trunk: ``nn.Sequential`` of the shared per-point stages (empty for shared_layers 0 and
            "all"); one module, run once, whose parameters get gradients from both losses.
        rotation_net, translation_net: the branches' own BaseNets (stages after the trunk and
            the regression head); both ``None`` for "all".
        net: the single BaseNet of shared_layers "all" (``None`` otherwise).
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.rot_size = ROTATION_SIZES[cfg.rotation]
        in_channels = 3 + cfg.num_classes
        n_stages = len(cfg.point_mlp)
        common: dict[str, Any] = {
            "point_mlp": cfg.point_mlp,
            "head": cfg.head,
            "width": cfg.width,
            "bn_momentum": cfg.bn_momentum,
        }
        self.trunk = nn.Sequential()
        self.rotation_net: BaseNet | None = None
        self.translation_net: BaseNet | None = None
        self.net: BaseNet | None = None
        if cfg.shared_layers == "all":
            self.net = BaseNet(in_channels, 3 + self.rot_size, **common)
            return
        k = int(cfg.shared_layers)
        if k > n_stages:
            raise ValueError(
                f"model.shared_layers={k} exceeds the {n_stages} per-point layers of "
                f"model.point_mlp={cfg.point_mlp}"
            )
        if k > 0:
            stages = point_stages(in_channels, cfg.point_mlp, cfg.width, cfg.bn_momentum)
            self.trunk = nn.Sequential(*stages[:k])
        self.rotation_net = BaseNet(in_channels, self.rot_size, first_stage=k, **common)
        self.translation_net = BaseNet(in_channels, 3, first_stage=k, **common)

    def branch_modules(self, branch: str) -> list[nn.Module]:
        """The modules a branch's input passes through, in order (trunk stages first).

        Args:
            branch: "rotation" or "translation".

        Returns:
            Per-point stages, then the regression head. The first ``shared_layers`` entries
            (all of them for "all") are the same objects in both branches.
        """
        if branch not in ("rotation", "translation"):
            raise ValueError(f"branch must be 'rotation' or 'translation', got {branch!r}")
        net = self.net or (self.rotation_net if branch == "rotation" else self.translation_net)
        assert net is not None
        return [*self.trunk, *net.stages, net.head]

    def forward(
        self, points: torch.Tensor, cls_id: torch.Tensor, trans_points: torch.Tensor | None = None
    ) -> PoseOutput:
        """Regress the pose of each segment (:func:`pose_forward`).

        Args:
            points: (B, n, 3) segment points in the camera frame, metres.
            cls_id: (B,) integer class ids, 1-based (1..num_classes).
            trans_points: (B, m, 3) the translation branch's own form of the segments
                (layout "pair" only), or None.

        Returns:
            PoseOutput with R (B, 3, 3), t (B, 3), rot_raw (B, 3|4|6), t_residual (B, 3),
            mu (B, 3).
        """
        return pose_forward(self, points, cls_id, trans_points)

    def _encode(self, xyz: torch.Tensor, cls_id: torch.Tensor) -> torch.Tensor:
        """(B, n, 3 + k) network input: xyz (B, n, 3) times ``1 / xyz_scale``, then the
        one-hot class."""
        B, n, _ = xyz.shape
        k = self.cfg.num_classes
        onehot = F.one_hot(cls_id.long() - 1, k).to(xyz.dtype)  # (B, k)
        onehot = onehot[:, None, :].expand(B, n, k)  # (B, n, k)
        return torch.cat([xyz * (1.0 / self.cfg.xyz_scale), onehot], dim=-1)

    def run_all(self, xyz: torch.Tensor, cls_id: torch.Tensor) -> torch.Tensor:
        """See :class:`PoseBranches`."""
        assert self.net is not None
        return self.net(self._encode(xyz, cls_id))  # (B, 3 + rot)

    def run_trunk(
        self, xyz: torch.Tensor, cls_id: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """See :class:`PoseBranches`."""
        assert self.rotation_net is not None and self.translation_net is not None
        h = self.trunk(self._encode(xyz, cls_id))  # (B, n, C_k) or (B, C_L)
        return self.rotation_net(h), self.translation_net(h)

    def run_pair(
        self, rot_xyz: torch.Tensor, trans_xyz: torch.Tensor, cls_id: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """See :class:`PoseBranches`."""
        assert self.rotation_net is not None and self.translation_net is not None
        trans_in = self._encode(trans_xyz, cls_id)  # (B, n, 3+k)
        rot_in = trans_in if rot_xyz is trans_xyz else self._encode(rot_xyz, cls_id)
        return self.rotation_net(rot_in), self.translation_net(trans_in)


def build_model(cfg: ModelConfig) -> PoseNet:
    """The pose network a ModelConfig describes (see :class:`PoseNet`)."""
    return PoseNet(cfg)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters, each shared tensor counted once (BN buffers excluded)."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def variant_table() -> list[dict[str, Any]]:
    """One row per registered variant, for ``cloudpose variants``.

    Returns:
        Dicts with keys ``name``, ``groups`` (list of group names), ``changes``
        (``Variant.describe()``), ``why`` and ``parameters`` (trainable parameter count).
    """
    rows = []
    for name, variant in variants().items():
        model = build_model(resolve(name).model)
        rows.append(
            {
                "name": name,
                "groups": groups_of(name),
                "changes": variant.describe(),
                "why": variant.why,
                "parameters": count_parameters(model),
            }
        )
    return rows
