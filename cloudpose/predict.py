"""Pose estimation on one frame from loose files, with an overlay picture.

Input: a depth PNG, a label PNG (class ids; ground-truth or a segmentation network's output), an
optional color PNG, and intrinsics (a YCB-Video meta.mat, ``fx,fy,cx,cy``, or YCB-Video's camera
by default). Every labelled object is segmented, sampled and posed as in evaluation.

The overlay goes where ``--overlay`` says (:func:`overlay_path`): a folder (one that exists, or
a name ending in ``/``) holds :data:`OVERLAY_NAME`; a name without a suffix gets ``.png``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cloudpose.conventions import YCB_INTRINSICS, transform_points
from cloudpose.data.cache import SegmentSet
from cloudpose.data.segments import check_depth_scale, extract_segments
from cloudpose.data.ycb import YCBVideo, read_frame
from cloudpose.infer import estimate_poses, load_checkpoint
from cloudpose.refine import DepthView, ICPSettings, depth_agreement, refine_poses
from cloudpose.store.pretrained import is_pretrained
from cloudpose.store.runs import INFO, client_for, is_run_folder, local_checkpoint

OVERLAY_NAME = "prediction.png"
"""The overlay's file name in a folder that ``--overlay`` names (and in the current one by
default)."""


@dataclass(frozen=True)
class ObjectPose:
    """The estimated pose of one labelled object."""

    cls_id: int
    name: str
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,) metres
    points: int  # segment points after filtering
    fitness: float  # ICP fitness (NaN without ICP)
    coverage: float  # share of segment points within 1 cm of the posed model
    violation: float  # of posed model points on a depth reading, share > 1 cm in front of it

    def describe(self) -> str:
        """One line: class, translation in metres, rotation as axis-angle in degrees, and how
        the pose agrees with the depth (:func:`cloudpose.refine.depth_agreement`)."""
        from scipy.spatial.transform import Rotation

        rv = Rotation.from_matrix(self.R).as_rotvec()
        angle = np.degrees(np.linalg.norm(rv))
        axis = rv / max(np.linalg.norm(rv), 1e-12)
        t = ", ".join(f"{x:+.4f}" for x in self.t)
        ax = ", ".join(f"{x:+.3f}" for x in axis)
        return (
            f"{self.cls_id:2d} {self.name:<22} t = [{t}] m   R = {angle:6.1f} deg about [{ax}]"
            f"   ({self.points} points, ICP fitness {self.fitness:.2f}, coverage "
            f"{self.coverage:.2f}, in front of the depth {self.violation:.2f})"
        )


@dataclass(frozen=True)
class PredictResult:
    """Poses of every object with a usable segment, the labelled ones without, and the overlay
    written (None: none asked for)."""

    poses: list[ObjectPose]
    skipped: list[int]  # class ids with no usable segment point
    overlay: Path | None = None

    def notes(self, depth: Path, label: Path) -> list[str]:
        """Lines on the objects not posed, and what to check: none labelled in ``label``, or
        labelled ones without a usable point in ``depth``."""
        if not self.poses and not self.skipped:
            return [
                f"no object found: --label {label} labels no pixel (every one is 0, "
                "background); check that it is this frame's label image, class ids 1-21"
            ]
        if not self.skipped:
            return []
        ids = ", ".join(str(c) for c in self.skipped)
        head = "no object posed" if not self.poses else "not posed"
        return [
            f"{head}: class ids {ids} of --label {label} have no usable point in --depth "
            f"{depth}; check that the two are of one frame, and --depth-factor (or the meta's)"
        ]


def parse_intrinsics(text: str | None) -> np.ndarray:
    """``"fx,fy,cx,cy"`` -> (3, 3) K; None -> YCB-Video's camera."""
    if text is None:
        return YCB_INTRINSICS.copy()
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
    except ValueError as exc:
        raise ValueError(f"--intrinsics expects 'fx,fy,cx,cy' (4 numbers), got {text!r}") from exc
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


def overlay_path(overlay: str | Path) -> Path:
    """The file an ``--overlay`` value names: :data:`OVERLAY_NAME` inside a folder (one that
    exists, or a name ending in ``/``), ``NAME.png`` for a name without a suffix, else the
    ``.png`` file named.

    Raises:
        ValueError: a name with another suffix than ``.png``.
    """
    text = str(overlay)
    path = Path(text)
    if text.endswith(("/", "\\")) or path.is_dir():
        return path / OVERLAY_NAME
    if not path.suffix:
        return path.with_name(path.name + ".png")
    if path.suffix.lower() != ".png":
        raise ValueError(
            f"--overlay {text}: expected a .png file, a folder, or a name without a suffix "
            "(.png is added)"
        )
    return path


def load_model_for(checkpoint: str, device: str = "auto"):
    """(model, config) from a ``model.pt`` (or a compact store's ``model.f24.pt``), a run
    folder, an MLflow run id, a run name or a shipped network's name.

    Raises:
        ValueError: a name that is none of these, naming ``--checkpoint``.
        FileNotFoundError: a ``.pt`` file that does not exist.
    """
    path = Path(checkpoint)
    if path.is_file():
        return load_checkpoint(path, device)
    if path.suffix == ".pt":
        raise FileNotFoundError(f"--checkpoint {checkpoint}: no such file")
    if path.exists() and not is_run_folder(path):
        raise ValueError(
            f"--checkpoint {checkpoint}: a folder, but not a run folder (no {INFO}); expected a "
            "model.pt, a run folder, an MLflow run id or a run name"
        )
    client = client_for([checkpoint])  # None for the shipped network: no store is opened
    try:
        with local_checkpoint(client, checkpoint) as (_, ckpt):  # a download is removed
            return load_checkpoint(ckpt, device)
    except ValueError as exc:
        message = str(exc)
        if is_pretrained(checkpoint) or not message.startswith("--run "):
            raise
        # the resolver speaks of evaluate's --run; here the same value came as --checkpoint
        raise ValueError("--checkpoint " + message.removeprefix("--run ")) from exc


def predict(
    depth: Path,
    label: Path,
    checkpoint: str,
    *,
    color: Path | None = None,
    meta: Path | None = None,
    intrinsics: str | None = None,
    depth_factor: float = 10000.0,
    icp: bool = True,
    icp_overrides: dict[str, Any] | None = None,
    overlay: str | Path | None = None,
    seed: int = 0,
    device: str = "auto",
) -> PredictResult:
    """Estimate the pose of every labelled object in one frame (see the module doc).

    ``icp_overrides``: fields of :class:`~cloudpose.refine.ICPSettings` to change from the
    checkpoint's own ICP (as :func:`cloudpose.evaluate.evaluate`'s), e.g. the starts, their
    selection against this frame's depth, a wider first radius (``cloudpose predict`` passes
    the product's refinement, :data:`cloudpose.config.PRODUCT_REFINEMENT`). ``overlay``: where
    to draw the poses (:func:`overlay_path`; the result names the file written).

    Raises:
        ValueError: besides bad files, depth that looks like another unit than
            ``depth_factor`` says (:func:`cloudpose.data.segments.check_depth_scale`).
    """
    overlay = None if overlay is None else overlay_path(overlay)
    if overlay is not None:  # a folder that cannot be made is said before any work
        overlay.parent.mkdir(parents=True, exist_ok=True)
    model, cfg = load_model_for(checkpoint, device)
    K = None if meta is not None else parse_intrinsics(intrinsics)
    frame = read_frame(
        depth,
        label,
        meta_mat=meta,
        color_png=color,
        K=K,
        depth_factor=depth_factor,
        frame_id=Path(depth).stem,
    )
    segs = extract_segments(
        frame,
        n_fps=cfg.data.n_fps,
        outlier_radius=cfg.data.outlier_radius,
        rng=np.random.default_rng(seed),
        with_gt=False,
    )

    segs = SegmentSet.from_segments(segs)
    dataset = YCBVideo(Path(depth).parent)  # packaged classes and models unless the folder has them
    models_by_class = dataset.models()
    valid = np.flatnonzero(segs.valid)
    check_depth_scale(
        [segs.observed(i) for i in valid],
        [int(segs.cls_id[i]) for i in valid],
        models_by_class,
        str(depth),
        "--depth-factor" if meta is None else f"factor_depth in {meta}",
    )
    est = estimate_poses(model, segs, cfg.train.n_points, device=next(model.buffers()).device)
    fitness = np.full(len(segs), np.nan)
    view = DepthView(frame.depth, np.asarray(frame.K, dtype=np.float64))
    if icp:
        settings = ICPSettings.from_config(cfg.icp)
        settings = dataclasses.replace(settings, **(icp_overrides or {}))
        views = [view] * len(segs) if settings.select == "depth" else None
        est, stats = refine_poses(segs, est, models_by_class, settings, views=views)
        fitness = stats.fitness
    poses = []
    for i in np.flatnonzero(segs.valid):
        c = int(segs.cls_id[i])
        agree = depth_agreement(segs.observed(i), models_by_class[c], est.R[i], est.t[i], view)
        poses.append(
            ObjectPose(
                c,
                dataset.classes[c - 1],
                est.R[i],
                est.t[i],
                int(segs.count[i]),
                float(fitness[i]),
                agree.coverage,
                agree.violation,
            )
        )
    skipped = [int(c) for c in segs.cls_id[~segs.valid]]
    if overlay is not None:
        draw_overlay(frame, poses, models_by_class, overlay)
    return PredictResult(poses, skipped, overlay)


def draw_overlay(frame, poses: list[ObjectPose], models_by_class, path: Path) -> None:
    """Model points projected with each estimated pose, one colour per object, on the image,
    written to ``path`` as PNG (whatever its suffix)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, w = frame.depth.shape
    fig, ax = plt.subplots(figsize=(w / 100, h / 100), dpi=100)
    if frame.color is not None:
        ax.imshow(frame.color)
    else:
        ax.imshow(np.where(frame.depth > 0, frame.depth, np.nan), cmap="gray")
    cmap = plt.get_cmap("tab10")
    for k, p in enumerate(poses):
        pts = transform_points(models_by_class[p.cls_id], p.R, p.t)
        pts = pts[pts[:, 2] > 1e-3]
        uv = pts[:, :2] / pts[:, 2:] * [frame.K[0, 0], frame.K[1, 1]] + [
            frame.K[0, 2],
            frame.K[1, 2],
        ]
        ax.scatter(uv[:, 0], uv[:, 1], s=0.6, color=cmap(k % 10), alpha=0.7, label=p.name)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.axis("off")
    if poses:
        ax.legend(loc="lower left", fontsize=7, markerscale=8, framealpha=0.8)
    ax.set_title("cloudpose predict: model points at the estimated poses", fontsize=8)
    fig.tight_layout(pad=0.2)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    plt.close(fig)
