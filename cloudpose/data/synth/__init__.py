"""Synthetic YCB-Video scenes rendered from the 21 real model point sets (``cloudpose synth``).

The output is a dataset root in the real YCB-Video layout (docs/design.md, "Data"), so one reader
(:class:`cloudpose.data.ycb.YCBVideo`) and one segment pipeline serve real and synthetic data::

    ROOT/classes.txt                        the 21 YCB-Video classes (copy of the package's)
    ROOT/models/NAME/points.xyz             copies of the 21 packaged model point sets
    ROOT/data/SEQ/FRAME-{depth,label}.png   depth uint16 (10000 per metre), label uint8
    ROOT/data/SEQ/FRAME-meta.mat            cls_indexes, poses, intrinsic_matrix, factor_depth,
                                            and ``alone_pixels`` (see below)
    ROOT/image_sets/train.txt, test.txt     the requested frame counts (rewritten each call)
    ROOT/keyframe.txt                       = image_sets/test.txt, as in YCB-Video
    ROOT/synth.json                         the generator settings (checked when resuming)

Frame i of a split is a pure function of ``(seed, split, i)`` and the generator version
(:data:`GENERATOR_VERSIONS`, ``DataConfig.synth_version``): its random generator is
``np.random.default_rng([seed, split_code, i])``. Asking for more frames later only adds frames,
and a smaller preset uses a prefix of a bigger one. Train frames live in sequences 0000, 0001,
..., test frames in 1000, 1001, ..., :data:`FRAMES_PER_SEQ` frames each.

Scenes (default): 3 to 8 distinct objects resting on a table in stable poses (faces of each
model's convex hull on which its centre of mass rests, drawn with probability proportional to
their solid angle from the centre of mass, plus a random yaw), packed in a cluster without
interpenetration (a 2D footprint check), seen by a camera 0.5-1.3 m from the look-at point
(the scene centre) looking down 20-70 degrees. In version 2 a share of the objects
(:data:`STACK_SHARE`) rest on the top of an object standing on the table instead, where their
centre of mass lies over the contact region and nothing else is in the way. The table (label 0) and the floor below it are
rendered in depth, as real frames have background depth. With ``uniform_rotation`` the objects
float in front of a wall in rotations drawn uniformly from SO(3).

Sensor noise (on by default; never changes the label image): Kinect-like axial Gaussian noise
``sigma(z) = 1.2 mm + 1.9 mm/m^2 (z - 0.4 m)^2`` (Nguyen et al., 3DIMPVT 2012), disparity
quantisation to 1/8 pixel (focal 580 px, baseline 7.5 cm: 2.9 mm steps at 1 m), missing and
"flying" (mixed foreground/background) pixels at depth edges, and a small random dropout.
Pixels without a reading have depth 0.
Version 2 replaces the dropout on object pixels by :data:`REAL_DROPOUT`, a model fitted to the
real frames (edges, grazing angles, a rate per class, in blobs), and renders surfaces that keep
through-holes (:mod:`cloudpose.data.synth.surfaces`, surface version 2). ``cloudpose synth
--compare-real`` (:mod:`~cloudpose.report.fidelity`) measures both versions against real
frames.

Runs on the same root may overlap (e.g. parallel training runs that each ensure the data): a
frame is written by renaming whole files, so two runs rendering the same frame leave identical,
complete files. ``synth.json`` records the generator version and the surface settings: a root
holding frames of another version, or of other surfaces, is refused.

``alone_pixels``: each meta also stores, per instance, the pixel count of the object rendered
alone at its pose (the occlusion factor's nu, docs/design.md "Metrics"). The real dataset has
no such field; the segment pipeline renders it when it is absent.
Modules: ``scenes`` (resting poses, table and floating arrangements, stacking), ``sensor``
(background depth, noise, missing depth), ``sensor_fit`` (the missing-depth model fitted to
real frames), ``frames`` (one frame from its seed and version),
``write`` (the resumable writer, :func:`synthesize`), ``compare`` (against real frames).
"""

from cloudpose.config import GENERATOR_VERSION, GENERATOR_VERSIONS
from cloudpose.data.synth.frames import (
    FRAMES_PER_SEQ,
    SEQ_OFFSET,
    SPLIT_CODES,
    SynthFrame,
    frame_id,
    generate_frame,
)
from cloudpose.data.synth.resting import RestingPoses, resting_poses
from cloudpose.data.synth.scenes import (
    CAMERA_DISTANCE,
    CAMERA_ELEVATION_DEG,
    MAX_RANGE,
    MIN_IN_IMAGE,
    MIN_VISIBLE_PIXELS,
    N_OBJECTS,
    STACK_SHARE,
    Plane,
    Scene,
    look_at_camera,
    sample_floating_scene,
    sample_table_scene,
    uniform_rotations,
)
from cloudpose.data.synth.sensor import (
    REAL_DROPOUT,
    DropoutModel,
    NoiseModel,
    add_sensor_noise,
    add_sensor_noise_v2,
    background_depth,
)
from cloudpose.data.synth.write import SynthSummary, synthesize

__all__ = [
    "CAMERA_DISTANCE",
    "CAMERA_ELEVATION_DEG",
    "FRAMES_PER_SEQ",
    "GENERATOR_VERSION",
    "GENERATOR_VERSIONS",
    "MAX_RANGE",
    "MIN_IN_IMAGE",
    "MIN_VISIBLE_PIXELS",
    "N_OBJECTS",
    "REAL_DROPOUT",
    "SEQ_OFFSET",
    "SPLIT_CODES",
    "STACK_SHARE",
    "DropoutModel",
    "NoiseModel",
    "Plane",
    "RestingPoses",
    "Scene",
    "SynthFrame",
    "SynthSummary",
    "add_sensor_noise",
    "add_sensor_noise_v2",
    "background_depth",
    "frame_id",
    "generate_frame",
    "look_at_camera",
    "resting_poses",
    "sample_floating_scene",
    "sample_table_scene",
    "synthesize",
    "uniform_rotations",
]
