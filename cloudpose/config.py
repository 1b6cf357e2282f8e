"""The configuration schema: frozen dataclasses for the base system (the paper's network and
its training settings), their choices, and the fields a stored config may lack.

A variant or a preset changes some fields of it (:mod:`cloudpose.registry`); the result is one
:class:`Config` that every checkpoint and every MLflow run stores in full.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from typing import Any

ROTATIONS = ("axis_angle", "quaternion", "rot6d")
ROTATION_LOSSES = ("geodesic", "l2")
SHARED_CHOICES = (0, 1, 2, 3, 4, 5, "all")
PRECISIONS = ("fp32", "bf16")
ROTATION_INPUTS = ("raw", "centred")
CENTRES = ("mean", "median", "trimmed")
ROTATION_CENTRES = ("centre", "mean")
SAMPLERS = ("shuffle", "class_balanced")
LR_SCHEDULES = ("constant", "cosine")
TRAIN_SOURCES = ("frames", "online")
ONLINE_SCENES = ("all", "classes")
"""What on-line scenes hold when training keeps some classes (``DataConfig.online_scenes``)."""
ONLINE_SCENE_MIN_CLASSES = 3
"""Classes on-line scenes of the kept classes only need: a table scene holds at least this many
distinct objects (the scene sampler's ``N_OBJECTS[0]``, :mod:`cloudpose.data.synth.scenes`)."""
KERNELS = ("fused", "plain")
SEED_STREAMS = ("arithmetic", "purpose")
"""How training's random streams are seeded (``TrainConfig.seed_streams``,
:func:`cloudpose.train.seeds.seed_for`)."""

GENERATOR_VERSIONS = (1, 2)
"""The generators frames can be made with (``DataConfig.synth_version``; stored in
``synth.json``). A version's frames never change; a change that alters frames is a new version.

1. Surfaces that close through-holes (surface version 1), the Kinect noise model with
   edge and random dropout (:func:`~cloudpose.data.synth.sensor.add_sensor_noise`), objects
   only on the table.
2. Surfaces that keep through-holes (surface version 2); on object pixels missing depth
   fitted to real frames (:func:`~cloudpose.data.synth.sensor.add_sensor_noise_v2`); a share
   of objects resting on another (:data:`~cloudpose.data.synth.scenes.STACK_SHARE`); floating
   rotations from scipy's sampler.
"""

SYMMETRY_TABLE_VERSIONS = (1, 2)
"""The packaged symmetry tables (``LossConfig.symmetry_table``; ``cloudpose.geometry.symmetry``)."""
GENERATOR_VERSION = 2
"""The newest generator version (the default)."""


ONLINE_VERSIONS = (1, 2, 3)
"""How on-line synthesis makes its segments (``DataConfig.online_version``,
:class:`cloudpose.data.synth.online.OnlineSynth`): 1, Open3D ray casting and numpy (every
on-line run stored before this field existed); 2, the same scenes, draws and sensor by
compiled kernels (a z-buffer of the meshes; its segments per second against version 1's:
``online_v2_supply_ratio`` in reports/benchmarks.md): the same segments to float rounding, but
not bit for bit, so a stream of its own; 3, the same scenes and sensor model with draws of its
own (fewer, float32) and every object of a scene drawn, read and cut in a few compiled passes
(``online_v3_supply_ratio``): the same distribution, other segments."""

VERSION_3_SETTINGS = {
    "online_bleed": (1.0, ""),
    "online_smooth": (5.0, " pixels"),
    "online_noise_corr": (5.0, " pixels"),
}
"""The ``DataConfig`` fields only on-line synthesis version 3 has -> (largest value, unit of
the error message). Each is 0 by default, and a field at 0 is left out of a chunk store's key
(:func:`cloudpose.data.synth.chunks.store_settings`), so keys made before it existed stay."""


BLEED_BRANCHES = ("both", "translation", "translation-paired")
"""Which branch trains on bleeding masks (``DataConfig.online_bleed_branch``): both, or the
translation branch only (the rotation branch on the rendered masks of the same segments);
"translation-paired" as "translation" with the rendered form drawn as a run without bleeding
draws it (:data:`PAIRED_BRANCH`)."""

PAIRED_BRANCH = "translation-paired"
"""The bleed branch whose rotation branch trains on a plain run's segments: the rendered form's
noise, FPS starts and augmentation are the draws of a run without bleeding at the same seed,
the bleeding masks and their form's draws come from a stream of their own
(:meth:`cloudpose.data.synth.online.OnlineSynth.scene_segments`,
:func:`cloudpose.train.augment.augment_forms`). A translation-only run then differs from its
plain pair in the translation branch alone (rotation weights equal on one device: tested)."""


def check_online_version(version: int) -> int:
    """``version`` if it is one of :data:`ONLINE_VERSIONS`, else ValueError."""
    if version not in ONLINE_VERSIONS:
        raise ValueError(
            f"on-line synthesis version {version!r}: expected one of {ONLINE_VERSIONS} "
            "(data.online_version)"
        )
    return int(version)


def check_synth_version(version: int) -> int:
    """``version`` if it is one of :data:`GENERATOR_VERSIONS`, else ValueError."""
    if version not in GENERATOR_VERSIONS:
        raise ValueError(
            f"synthetic generator version {version!r}: expected one of {GENERATOR_VERSIONS} "
            "(data.synth_version)"
        )
    return int(version)


@dataclass(frozen=True)
class ModelConfig:
    """Network architecture (docs/design.md, "BaseNet" and "The pose networks").

    Attributes:
        shared_layers: 0-5 = how many leading per-point layers the rotation and translation
            branches share as one module; 5 also shares the pooled feature; "all" = one BaseNet
            with a 6- (or 7-, 9-) number output.
        width: multiplier on every hidden width (per-point MLP and regression head).
        rotation: rotation output: axis-angle (3), unit quaternion (4) or 6D (6).
        point_mlp: per-point MLP widths before the max pool.
        head: hidden widths of the regression MLP after the max pool.
        num_classes: k of the one-hot class input (21 for YCB-Video).
        bn_momentum: PyTorch BatchNorm momentum (the released code's decay 0.99 = 0.01).
        rotation_input: what the rotation branch of ``shared_layers = 0`` sees: "raw"
            camera-frame xyz (the paper) or "centred" xyz minus the segment mean (what every
            shared variant's trunk sees).
        xyz_scale: the networks see xyz divided by this length, metres (1.0 = metres, the
            paper). The one-hot class channels are 0/1; centred object points in metres are
            ~0.05, so at 1.0 the class term dominates every first-layer unit and the pooled
            features vary by a few percent between segments of one class (a class can then
            get stuck at a constant output). 0.1 (decimetres) puts both on one scale.
        centre: the point mu the segment is centred on and the translation is a residual to:
            "mean" (the paper), "median" (per coordinate) or "trimmed" (the mean of the
            points nearest the per-coordinate median, :data:`cloudpose.models.pose.TRIM_KEEP`
            of them). Points of a neighbour or the background that a mask lets in drag the
            mean sideways; the robust centres move less (docs/real-gap.md).
        rotation_centre: what the rotation branch's centred input (``rotation_input =
            "centred"``, ``shared_layers = 0``) is centred on: "centre" (``centre``, the
            point the translation is a residual to) or "mean" (the segment mean whatever
            ``centre`` is: a robust centre then serves the translation only).
    """

    shared_layers: int | str = 0
    width: float = 1.0
    rotation: str = "axis_angle"
    point_mlp: tuple[int, ...] = (64, 64, 64, 128, 1024)
    head: tuple[int, ...] = (512, 256)
    num_classes: int = 21
    bn_momentum: float = 0.01
    rotation_input: str = "raw"
    xyz_scale: float = 1.0
    centre: str = "mean"
    rotation_centre: str = "centre"

    def __post_init__(self) -> None:
        if self.centre not in CENTRES:
            raise ValueError(f"model.centre must be one of {CENTRES}, got {self.centre!r}")
        if self.rotation_centre not in ROTATION_CENTRES:
            raise ValueError(
                f"model.rotation_centre must be one of {ROTATION_CENTRES}, "
                f"got {self.rotation_centre!r}"
            )
        if self.rotation_centre == "mean" and (
            self.rotation_input != "centred" or self.shared_layers != 0
        ):
            raise ValueError(
                'model.rotation_centre = "mean" needs a rotation branch of its own on centred '
                'points: model.rotation_input = "centred" and model.shared_layers = 0, got '
                f"{self.rotation_input!r} and {self.shared_layers!r}"
            )
        if self.rotation_input not in ROTATION_INPUTS:
            raise ValueError(
                f"model.rotation_input must be one of {ROTATION_INPUTS}, "
                f"got {self.rotation_input!r}"
            )
        if self.shared_layers not in SHARED_CHOICES:
            raise ValueError(
                f"model.shared_layers must be one of {SHARED_CHOICES}, got {self.shared_layers!r}"
            )
        if self.rotation not in ROTATIONS:
            raise ValueError(f"model.rotation must be one of {ROTATIONS}, got {self.rotation!r}")
        if not self.xyz_scale > 0:
            raise ValueError(f"model.xyz_scale must be > 0, got {self.xyz_scale!r}")
        if not self.width > 0:
            raise ValueError(f"model.width must be > 0, got {self.width!r}")
        object.__setattr__(self, "point_mlp", tuple(self.point_mlp))
        object.__setattr__(self, "head", tuple(self.head))


@dataclass(frozen=True)
class LossConfig:
    """Training loss: ``alpha * l_t + l_r`` (paper eq. 6).

    Attributes:
        rotation: "geodesic" (angle between rotations, rad) or "l2" (|r - r_gt|_2 on axis-angle).
        alpha: weight of the translation loss (metres) against the rotation loss (radians).
        symmetric: take the rotation loss modulo each class's symmetries (the smallest loss
            over the equivalent ground truths of ``cloudpose.geometry.symmetry``).
        symmetry_table: which packaged symmetry table (``cloudpose.geometry.symmetry``, package
            doc) the loss modulo symmetry and every rotation error modulo symmetry the run
            logs use, so a run's loss and its metrics agree (a baseline on a preset takes the
            preset's). 1 finds only symmetries about the model axes (it misses the pudding
            and gelatin boxes' half turns, the clamps' and others' end-for-end turns); 2 finds
            them. 1 is every stored run's and the committed cpu results'.
    """

    rotation: str = "geodesic"
    alpha: float = 10.0
    symmetric: bool = False
    symmetry_table: int = 1

    def __post_init__(self) -> None:
        if self.rotation not in ROTATION_LOSSES:
            raise ValueError(
                f"loss.rotation must be one of {ROTATION_LOSSES}, got {self.rotation!r}"
            )
        if self.symmetry_table not in SYMMETRY_TABLE_VERSIONS:
            raise ValueError(
                f"loss.symmetry_table must be one of {SYMMETRY_TABLE_VERSIONS}, "
                f"got {self.symmetry_table!r}"
            )


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings; defaults are the paper's (Sec. V-A and the released code).

    Attributes:
        epochs: passes over the training segments.
        batch_size: segments per step.
        lr: Adam learning rate.
        n_points: network input points, the first n of the cached FPS order.
        val_fraction: share of training *frames* held out for per-epoch validation.
        precision: "fp32" or "bf16" (autocast; never on unless asked).
        device: "auto" (CUDA if available, else CPU), "cpu" or "cuda[:i]".
        kernel: "fused" = the last per-point layer, its BatchNorm, ReLU and the max pool as one
            exact autograd function (:mod:`cloudpose.models.fused`, same numerics, 2-2.5x the
            training throughput on CPU; on a GPU, where it is slower, the plain modules run
            instead: :func:`cloudpose.train.loop.fused_kernel`); "plain" = the textbook modules.
        bn_recalibrate: before each validation and before the final save, re-estimate every
            BatchNorm's running statistics as the plain average over this many training
            batches (no gradient step; 0 = keep the running averages). Fixes eval mode in
            short runs: with momentum 0.01 from step 0 the running variances (initialised to
            1) need thousands of steps to reach the real ones (~1e-3 in the first layer).
        sampler: "shuffle" (every segment once per epoch) or "class_balanced" (each batch
            draws classes uniformly, then a segment of the class; same steps per epoch).
        lr_schedule: "constant" or "cosine" (decay to 0 over the run's steps).
        augment_roll_deg: turn each training segment about the camera's optical axis by a
            uniform angle in +-this many degrees (points, R and t alike). Exact for depth
            data: a camera rolled about its optical axis sees the same surface points. 0 = off.
        augment_depth_noise_mm: move each training point along its viewing ray by a normal
            draw whose standard deviation is uniform in [0, this] mm, one level per segment
            (:func:`cloudpose.train.augment.jitter_along_rays`). 0 = off.
        threads: intra-op CPU threads of training (``torch.set_num_threads``), whatever the
            machine has. CPU kernels split their sums by thread (BatchNorm statistics, the
            reduction dimension of a GEMM), so the thread count changes a run's numbers: it is
            a setting, part of the run's identity, not the machine's core count. An on-line
            run leaves ``data.online_workers`` of them to its synthesis processes.
        seed_streams: how the random streams of training (initial weights, batch order,
            augmentations, BatchNorm re-estimation, probe) are seeded
            (:data:`SEED_STREAMS`, :mod:`cloudpose.train.seeds`): "purpose", one stream per
            purpose and index, none shared; "arithmetic", the seed arithmetic of every run
            stored before this field existed, whose streams overlap (epoch e's batch order is
            the roll augmentation's stream of epoch 0, step e). The default, and so every
            preset's, is "arithmetic": their runs keep their numbers and identity; a preset
            (or ``--set train.seed_streams=purpose``) opts in to "purpose".
    """

    epochs: int = 90
    batch_size: int = 128
    lr: float = 0.0008
    n_points: int = 256
    val_fraction: float = 0.1
    precision: str = "fp32"
    device: str = "auto"
    kernel: str = "fused"
    bn_recalibrate: int = 50
    sampler: str = "shuffle"
    lr_schedule: str = "constant"
    augment_roll_deg: float = 0.0
    augment_depth_noise_mm: float = 0.0
    threads: int = 2
    seed_streams: str = "arithmetic"

    def __post_init__(self) -> None:
        if self.seed_streams not in SEED_STREAMS:
            raise ValueError(
                f"train.seed_streams must be one of {SEED_STREAMS}, got {self.seed_streams!r}"
            )
        if self.threads < 1:
            raise ValueError(f"train.threads must be >= 1, got {self.threads}")
        if not self.augment_depth_noise_mm >= 0:
            raise ValueError(
                f"train.augment_depth_noise_mm must be >= 0, got {self.augment_depth_noise_mm}"
            )
        if self.epochs < 1:
            raise ValueError(f"train.epochs must be >= 1, got {self.epochs}")
        if self.n_points < 1:
            raise ValueError(f"train.n_points must be >= 1, got {self.n_points}")
        if not self.lr > 0:
            raise ValueError(f"train.lr must be > 0, got {self.lr}")
        if not 0 <= self.val_fraction < 1:
            raise ValueError(f"train.val_fraction must be in [0, 1), got {self.val_fraction}")
        if self.batch_size < 2:
            raise ValueError(f"train.batch_size must be >= 2 (BatchNorm), got {self.batch_size}")
        if self.sampler not in SAMPLERS:
            raise ValueError(f"train.sampler must be one of {SAMPLERS}, got {self.sampler!r}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(
                f"train.lr_schedule must be one of {LR_SCHEDULES}, got {self.lr_schedule!r}"
            )
        if self.bn_recalibrate < 0:
            raise ValueError(f"train.bn_recalibrate must be >= 0, got {self.bn_recalibrate}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"train.precision must be one of {PRECISIONS}, got {self.precision!r}")
        if self.kernel not in KERNELS:
            raise ValueError(f"train.kernel must be one of {KERNELS}, got {self.kernel!r}")


@dataclass(frozen=True)
class DataConfig:
    """Dataset and segment settings (docs/design.md, "Data flow" and "Data").

    Attributes:
        root: dataset root in YCB-Video layout; "" = the synthetic default under ``data/``.
        train_frames: synthetic training frames to render.
        test_frames: synthetic test frames to render (listed in its keyframe.txt).
        synth_seed: seed of the synthetic scenes (independent of the training seed).
        noise: apply the depth-sensor noise model when rendering.
        uniform_rotation: objects float in full SO(3) instead of resting on a table.
        synth_version: synthetic generator version (:data:`GENERATOR_VERSIONS`:
            1 = solid handles, Kinect edge dropout, table only; 2 = through-holes kept, missing
            depth fitted to real frames, stacked objects). Each version renders into its own
            default root.
        n_fps: points kept per segment by farthest point sampling.
        outlier_radius: drop segment points farther than this from the segment mean, metres.
        segmentation: where segment masks come from; "gt" = ground-truth labels.
        classes: train and test on these class names only (empty = every class). Instances
            of other classes are left out of training, validation and test sets alike.
        train_source: where training segments come from. "frames": the segment cache of the
            rendered training frames (``train_frames``), held-out frames validate. "online":
            synthesized fresh for every step (:mod:`cloudpose.data.synth.online`: the scenes,
            surfaces and sensor of ``synth_version``), none seen twice; the rendered training
            frames are then the validation set only.
        online_epoch_segments: with "online", segments per epoch (an epoch is then only the
            interval between validations and checkpoints).
        online_reuse: with "online", steps each synthesized segment is used in (a divisor of
            ``train.batch_size``): synthesis per step is ``batch_size / online_reuse``
            segments. Use it with ``train.augment_roll_deg`` so the uses differ.
        online_workers: with "online", synthesis processes beside training (0 = in the training
            process). The segments are the same for any count, but training runs on
            ``train.threads - online_workers`` threads (at least 1) while they do, so the count
            is part of a run's numbers (0 with a full chunk store: ``cpu-online-4x-2t``).
        online_scenes: with "online" and ``classes``, what the synthesized scenes hold
            (:data:`ONLINE_SCENES`): "all", objects of every class,
            the others as occluders, as in the test frames; "classes", the kept classes only
            (at least 3), which wastes no scene on segments it drops.
        online_version: with "online", how segments are synthesized
            (:data:`ONLINE_VERSIONS`): 1, ray casting (the committed on-line runs); 2, the
            compiled path, the same scenes and sensor to float rounding, several times faster;
            3, the scene-at-once compiled path, the same scenes and sensor model with draws
            of its own (the same distribution, other segments), faster again.
        online_bleed: with "online" version 3, masks that bleed by up to one pixel: each
            object's mask takes each pixel next to it (a 4-neighbour, background or another
            object) with a probability drawn per object and scene uniformly in
            [0, online_bleed], the pixel keeping the depth it has (the background's, or the
            other object's); 0 keeps the rendered masks. Real segmentation masks sit ~0.5 px
            out on the dilation axis of ``cloudpose stress`` (``docs/stress.md``).
        online_bleed_branch: with ``online_bleed``, which branch trains on the bleeding masks
            (:data:`BLEED_BRANCHES`): "both", every segment cut from them; "translation",
            each segment cut twice, from the rendered masks for the rotation branch and from
            the bleeding ones for the translation branch (the two forms of one object in one
            scene; needs a variant whose branches share no layer, ``model.shared_layers=0``);
            "translation-paired", as "translation" with the rendered form's draws those of a
            run without bleeding (:data:`PAIRED_BRANCH`).
        online_smooth: with "online" version 3, each object's depth readings replaced by their
            Gaussian average over the object's own readings (sigma in pixels; 0 keeps the
            sensor's independent per-pixel noise). Real depth errors are correlated over ~2
            pixels (a camera that matches over a window); real frames sit ~0.9 px out on the
            smoothing axis of ``cloudpose stress`` (``docs/stress.md``).
        online_noise_corr: with "online" version 3, the sensor's axial noise on each
            object's pixels off depth edges drawn again from a field correlated over this many
            pixels (a Gaussian's sigma), at the same per-pixel amount; readings on depth edges
            (flying pixels) kept; 0 keeps independent per-pixel noise. 2 px gives synthetic
            depth the ``depth_corr`` statistic of the real frames (~0.4,
            :func:`cloudpose.data.synth.sensor.correlate_readings`).
        segment_streams: how a frame's instances draw their FPS start points
            (:data:`cloudpose.data.segments.SEGMENT_STREAMS`): "instance", each from its own
            stream, so a missed or dropped instance changes no other; "frame", one stream per
            frame, as the segments of every run stored before this field existed were made
            (the presets of the committed cpu results keep it, so their runs stay current).
    """

    root: str = ""
    train_frames: int = 2000
    test_frames: int = 400
    synth_seed: int = 0
    noise: bool = True
    uniform_rotation: bool = False
    synth_version: int = 2
    n_fps: int = 1024
    outlier_radius: float = 0.2
    segmentation: str = "gt"
    classes: tuple[str, ...] = ()
    train_source: str = "frames"
    online_epoch_segments: int = 4096
    online_reuse: int = 4
    online_workers: int = 1
    online_scenes: str = "all"
    online_version: int = 1
    online_bleed: float = 0.0
    online_bleed_branch: str = "both"
    online_smooth: float = 0.0
    online_noise_corr: float = 0.0
    segment_streams: str = "instance"

    def __post_init__(self) -> None:
        object.__setattr__(self, "classes", tuple(self.classes))
        if self.segment_streams not in ("instance", "frame"):
            raise ValueError(
                f"data.segment_streams={self.segment_streams!r}: expected 'instance' or 'frame'"
            )
        if self.train_source not in TRAIN_SOURCES:
            raise ValueError(
                f"data.train_source={self.train_source!r}: expected one of {TRAIN_SOURCES}"
            )
        if self.online_scenes not in ONLINE_SCENES:
            raise ValueError(
                f"data.online_scenes={self.online_scenes!r}: expected one of {ONLINE_SCENES}"
            )
        few = 0 < len(self.classes) < ONLINE_SCENE_MIN_CLASSES
        if self.train_source == "online" and self.online_scenes == "classes" and few:
            raise ValueError(
                f"data.online_scenes='classes' needs at least {ONLINE_SCENE_MIN_CLASSES} classes "
                f"(a table scene holds {ONLINE_SCENE_MIN_CLASSES} or more distinct objects); "
                f"data.classes has {list(self.classes)}: add classes or use 'all'"
            )
        if self.online_epoch_segments < 1 or self.online_reuse < 1 or self.online_workers < 0:
            raise ValueError(
                "data.online_epoch_segments and data.online_reuse must be >= 1 and "
                f"data.online_workers >= 0; got {self.online_epoch_segments}, "
                f"{self.online_reuse}, {self.online_workers}"
            )
        check_synth_version(self.synth_version)
        check_online_version(self.online_version)
        for name, (high, unit) in VERSION_3_SETTINGS.items():
            value = getattr(self, name)
            if not 0.0 <= value <= high:
                raise ValueError(f"data.{name} must be in [0, {high:g}]{unit}, got {value}")
            if value and (self.train_source != "online" or self.online_version < 3):
                raise ValueError(
                    f"data.{name}={value} needs data.train_source='online' and "
                    f"data.online_version=3 (got {self.train_source!r}, {self.online_version})"
                )
            if value and self.noise and self.synth_version < 2:
                raise ValueError(
                    f"data.{name}={value} needs the sensor of data.synth_version >= 2 (version "
                    "1's sensor is applied to a whole window, by version 2's path of on-line "
                    "synthesis; got data.synth_version=1 with data.noise=true)"
                )
        if self.online_bleed_branch not in BLEED_BRANCHES:
            raise ValueError(
                f"data.online_bleed_branch={self.online_bleed_branch!r}: expected one of "
                f"{BLEED_BRANCHES}"
            )
        if self.online_bleed_branch != "both" and not self.online_bleed:
            raise ValueError(
                f"data.online_bleed_branch={self.online_bleed_branch!r} needs bleeding masks "
                "(data.online_bleed > 0)"
            )


START_GROUPS = {1: None, 12: "T", 24: "O", 60: "I"}
"""Number of ICP starts -> the rotation group (scipy's name) whose elements turn the estimate
(:func:`cloudpose.refine.start_rotations`)."""
PAPER_RADIUS = 0.01
"""The paper's first ICP correspondence distance, metres (docs/design.md "Refinement")."""
MAX_RADIUS = 0.5
"""The widest first ICP correspondence distance a setting may give, metres."""

REFINEMENTS: dict[str, dict[str, Any]] = {
    "paper": {"starts": 1, "select": "fitness", "radius": PAPER_RADIUS},
    "wide": {"starts": 24, "select": "depth", "radius": 0.18},
}
"""The named refinements (``--refine``): ``paper``, Open3D's point-to-point ICP on the paper's
schedule from the estimate alone (the refinement of the ablation tables, which reproduce the
paper); ``wide``, ICP from the estimate turned by each of the 24 rotations of the octahedral
group, from an 18 cm first radius, the start that agrees best with the frame's depth kept
(:func:`cloudpose.refine.depth_score`): the best measured on real frames (docs/ensemble.md)."""

PRODUCT_REFINEMENT = "wide"
"""The refinement of the commands that pose objects for a user (``predict``, ``showcase``,
``compare``'s second refinement); ``evaluate``, ``baseline`` and the sweeps keep a run's own."""


def refinement(
    name: str | None = None,
    starts: int | None = None,
    select: str | None = None,
    radius: float | None = None,
) -> dict[str, Any]:
    """``{"starts", "select", "radius"}`` of the named refinement (:data:`REFINEMENTS`), each
    field given replacing the recipe's; with no name only the fields given (None: not given).
    ``ValueError`` naming ``--refine`` for an unknown name."""
    if name is not None and name not in REFINEMENTS:
        raise ValueError(f"--refine {name!r}: expected one of {', '.join(REFINEMENTS)}")
    out = dict(REFINEMENTS[name]) if name is not None else {}
    given = {"starts": starts, "select": select, "radius": radius}
    return out | {k: v for k, v in given.items() if v is not None}


def describe_refinement(starts: int, select: str, radius: float) -> str:
    """A refinement in words, its recipe's name first where it is one (:data:`REFINEMENTS`),
    e.g. ``wide: ICP from 24 starts, the one that agrees best with the depth kept, first
    radius 18 cm``."""
    fields = {"starts": starts, "select": select, "radius": radius}
    named = [k for k, v in REFINEMENTS.items() if v == fields]
    if starts == 1:
        text = "ICP from the estimate"
    else:
        kept = "agrees best with the depth" if select == "depth" else "fits best"
        text = f"ICP from {starts} starts, the one that {kept} kept"
    text += f", first radius {radius * 100:g} cm"
    return f"{named[0]}: {text}" if named else text


@dataclass(frozen=True)
class ICPConfig:
    """The guard and the starts of ICP refinement after the network (the schedule:
    docs/design.md "Refinement", :class:`cloudpose.refine.ICPSettings`).

    Attributes:
        fallback: keep the network's pose when ICP's fitness (share of observed points within
            the last correspondence radius) is below ``fallback_min_fitness``. Off = the paper.
        fallback_min_fitness: the guard's threshold, 0..1
            (reports/diagnostics/icp_fallback.md measures it).
        starts: ICP from the estimate only (1, the paper) or also from it turned by each
            element of a rotation group (12, 24, 60), keeping the best fit
            (:mod:`cloudpose.refine`; reports/diagnostics/multi_start_icp_*.md measure it).
        start_margin: share of points by which another start's score must beat the
            estimate's own (0..1).
        select: how starts are scored: "fitness" (ICP's fitness) or "depth" (fitness,
            coverage and free-space violations against the frame's depth,
            :func:`cloudpose.refine.depth_score`).
        radius: the first correspondence distance, metres (0.01, the paper). A wider one
            adds iterations at the same 10% shrink until the paper's last radius is reached
            (:func:`cloudpose.refine.schedule_for`; reports/diagnostics/icp_radius_*.md
            measure it).
    """

    fallback: bool = False
    fallback_min_fitness: float = 0.1
    starts: int = 1
    start_margin: float = 0.02
    select: str = "fitness"
    radius: float = PAPER_RADIUS

    def __post_init__(self) -> None:
        if not PAPER_RADIUS <= self.radius <= MAX_RADIUS:
            raise ValueError(
                f"icp.radius must be in [{PAPER_RADIUS}, {MAX_RADIUS}] metres, got {self.radius!r}"
            )
        if self.select not in ("fitness", "depth"):
            raise ValueError(f"icp.select must be 'fitness' or 'depth', got {self.select!r}")
        if not 0 <= self.fallback_min_fitness <= 1:
            raise ValueError(
                f"icp.fallback_min_fitness must be in [0, 1], got {self.fallback_min_fitness!r}"
            )
        if self.starts not in START_GROUPS:
            raise ValueError(
                f"icp.starts must be one of {sorted(START_GROUPS)}, got {self.starts!r}"
            )
        if not 0 <= self.start_margin <= 1:
            raise ValueError(f"icp.start_margin must be in [0, 1], got {self.start_margin!r}")


@dataclass(frozen=True)
class Config:
    """Everything that determines a run. Stored whole with every checkpoint and MLflow run."""

    variant: str = "shared-0"
    preset: str = "paper"
    seed: int = 1
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    data: DataConfig = field(default_factory=DataConfig)
    icp: ICPConfig = field(default_factory=ICPConfig)

    def __post_init__(self) -> None:
        branch = self.data.online_bleed_branch
        if branch != "both" and self.model.shared_layers != 0:
            raise ValueError(
                f"data.online_bleed_branch={branch!r} trains each branch on its own form of "
                "a segment: it needs branches that share no layer (model.shared_layers=0), got "
                f"model.shared_layers={self.model.shared_layers!r} (variant {self.variant!r})"
            )
        if self.train.n_points > self.data.n_fps:
            raise ValueError(
                f"train.n_points={self.train.n_points} exceeds data.n_fps={self.data.n_fps} "
                "(the network's points are a prefix of each segment's FPS points)"
            )

    def to_dict(self) -> dict[str, Any]:
        """Nested plain dict (JSON/TOML-safe)."""
        return dataclasses.asdict(self)

    def fingerprint(self) -> str:
        """16 hex digits that change whenever any field changes (names, seed and settings).

        Keys a run's folder and its MLflow tag ``config``: a run made under an edited preset or
        variant, or with overrides, is never taken for (nor resumed as) a run of another config.
        A field of :data:`IMPLIED_FIELDS` at its implied value is left out, so a config stored
        without it keeps its fingerprint.
        """
        d = self.to_dict()
        for section, fields in IMPLIED_FIELDS.items():
            for name, value in fields.items():
                if d[section].get(name) == value:
                    del d[section][name]
            if not d[section]:  # a section that is all implied (icp) was never stored
                del d[section]
        text = json.dumps(d, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def flat(self) -> dict[str, Any]:
        """Flat ``section.field`` dict, as logged to MLflow params."""
        out: dict[str, Any] = {}
        for key, value in self.to_dict().items():
            if isinstance(value, dict):
                out.update({f"{key}.{k}": v for k, v in value.items()})
            else:
                out[key] = value
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Config:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        sections = {f.name: f.type for f in dataclasses.fields(cls)}
        kwargs: dict[str, Any] = {}
        for key, value in d.items():
            if key not in sections:
                raise ValueError(f"unknown config key {key!r}; expected one of {sorted(sections)}")
            if key in _SECTIONS:
                value = {**IMPLIED_FIELDS.get(key, {}), **value}
                value = _SECTIONS[key](**check_delta("config", {key: value})[key])
            kwargs[key] = value
        return cls(**kwargs)


_SECTIONS = {
    "model": ModelConfig,
    "loss": LossConfig,
    "train": TrainConfig,
    "data": DataConfig,
    "icp": ICPConfig,
}

IMPLIED_FIELDS: dict[str, dict[str, Any]] = {
    "data": {
        "synth_version": 1,
        "train_source": "frames",
        "online_epoch_segments": 4096,
        "online_reuse": 4,
        "online_workers": 1,
        "online_scenes": "all",
        "online_version": 1,
        "online_bleed": 0.0,
        "online_bleed_branch": "both",
        "online_smooth": 0.0,
        "online_noise_corr": 0.0,
        "segment_streams": "frame",
    },
    "icp": {
        "fallback": False,
        "fallback_min_fitness": 0.1,
        "starts": 1,
        "start_margin": 0.02,
        "select": "fitness",
        "radius": 0.01,
    },
    "train": {"threads": 2, "augment_depth_noise_mm": 0.0, "seed_streams": "arithmetic"},
    "loss": {"symmetry_table": 1},
    "model": {"centre": "mean", "rotation_centre": "centre"},
}
"""Fields that a stored config (checkpoint, run.json) without them had at a fixed value: the
synthetic frames of every run stored before ``data.synth_version`` existed are version 1, and
every run stored before the on-line source existed trained on frames, and on segments whose
instances drew from one stream per frame (an on-line run stored before ``data.online_scenes``
existed drew scenes of every class); every run stored before ``loss.symmetry_table``
existed used symmetry table 1; every run stored before
the ``icp`` section existed was refined without the guard, and every run stored before
``icp.starts`` existed from the estimate only, and every run stored before ``icp.radius``
existed with the paper's first radius; every run stored before
``train.threads`` existed trained on this project's 2-core machines with 2 threads, and
without depth-noise augmentation; every run stored before ``train.seed_streams`` existed drew
its random streams by the seed arithmetic; every run stored before ``model.centre`` existed
took the translation as a residual to the segment mean, and every run stored before
``model.rotation_centre`` existed centred its rotation input on that same point.
:meth:`Config.from_dict` fills them in, and :meth:`Config.fingerprint` leaves them out at that
value, so those runs keep their identity."""


def check_delta(where: str, delta: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """``delta`` ({section: {field: value}}) checked against the config's sections and
    fields; ValueError naming ``where`` and the unknown section or field."""
    out: dict[str, dict[str, Any]] = {}
    for section, fields in delta.items():
        if section not in _SECTIONS or not isinstance(fields, dict):
            raise ValueError(f"{where}: unknown section {section!r}; expected {sorted(_SECTIONS)}")
        valid = {f.name for f in dataclasses.fields(_SECTIONS[section])}
        for key in fields:
            if key not in valid:
                raise ValueError(f"{where}: unknown field {section}.{key}; valid: {sorted(valid)}")
        out[section] = dict(fields)
    return out
