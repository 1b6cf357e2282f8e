"""One synthetic frame as a pure function of (seed, split, index): scene, render, noise."""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from cloudpose.config import GENERATOR_VERSION, check_synth_version
from cloudpose.conventions import IMAGE_SHAPE, YCB_INTRINSICS
from cloudpose.data.synth.render import Renderer
from cloudpose.data.synth.resting import resting_poses
from cloudpose.data.synth.scenes import (
    MIN_VISIBLE_PIXELS,
    N_OBJECTS,
    STACK_SHARE,
    Scene,
    _random_rotations,
    sample_floating_scene,
    sample_table_scene,
    uniform_rotations,
)
from cloudpose.data.synth.sensor import add_sensor_noise, add_sensor_noise_v2, background_depth
from cloudpose.data.synth.surfaces import load_packaged_models

SPLIT_CODES = {"train": 0, "test": 1}
SEQ_OFFSET = {"train": 0, "test": 1000}
FRAMES_PER_SEQ = 100


class SynthFrame(NamedTuple):
    """One generated frame.

    Attributes:
        frame_id: "SEQ/FRAME".
        depth: (H, W) float64 depth written to the PNG (noisy unless noise is off), metres.
        clean_depth: (H, W) float64 depth before noise, metres.
        label: (H, W) uint8 ground-truth class ids.
        cls_ids: (N,) int64 annotated classes.
        poses: (N, 3, 4) object->camera poses.
        alone_pixels: (N,) int64 pixels of each object rendered alone.
        visible_pixels: (N,) int64 pixels of each object in ``label``.
        scene: the sampled :class:`Scene`.
    """

    frame_id: str
    depth: np.ndarray
    clean_depth: np.ndarray
    label: np.ndarray
    cls_ids: np.ndarray
    poses: np.ndarray
    alone_pixels: np.ndarray
    visible_pixels: np.ndarray
    scene: Scene


def frame_id(split: str, index: int) -> str:
    """ "SEQ/FRAME" of frame ``index`` (0-based) of a split (train 0000/000001, test 1000/...)."""
    if split not in SPLIT_CODES:
        raise ValueError(f"unknown split {split!r}; expected one of {sorted(SPLIT_CODES)}")
    seq = SEQ_OFFSET[split] + index // FRAMES_PER_SEQ
    return f"{seq:04d}/{index % FRAMES_PER_SEQ + 1:06d}"


class _Generator:
    """Holds what every frame of a generator version needs (renderer with meshes, models,
    resting poses); build it with :func:`_generator` (one per process and version)."""

    def __init__(self, version: int = GENERATOR_VERSION) -> None:
        self.version = check_synth_version(version)
        self.models = load_packaged_models()
        self.renderer = Renderer(self.models, surface_version=self.version)
        self.resting = {c: resting_poses(p) for c, p in self.models.items()}


@functools.cache
def _generator(version: int = GENERATOR_VERSION) -> _Generator:
    return _Generator(version)


def generate_frame(
    split: str,
    index: int,
    seed: int = 0,
    noise: bool = True,
    uniform_rotation: bool = False,
    generator: _Generator | None = None,
    version: int = GENERATOR_VERSION,
) -> SynthFrame:
    """Generate frame ``index`` of ``split``; a pure function of (seed, split, index, flags,
    version).

    Objects with fewer than :data:`MIN_VISIBLE_PIXELS` visible pixels are taken out (with what
    rests on them) and the scene rendered again.

    Raises:
        ValueError: an unknown version, or a ``generator`` of another version.
    """
    gen = generator or _generator(check_synth_version(version))
    if gen.version != version:
        raise ValueError(f"generator of version {gen.version} asked for a version-{version} frame")
    rng = np.random.default_rng([seed, SPLIT_CODES[split], index])
    K, shape = YCB_INTRINSICS, IMAGE_SHAPE
    v1 = version == 1
    while True:
        if uniform_rotation:
            rotations = _random_rotations if v1 else uniform_rotations
            scene = sample_floating_scene(rng, gen.models, K, shape, rotations)
        else:
            stack = 0.0 if v1 else STACK_SHARE
            scene = sample_table_scene(rng, gen.models, gen.resting, K, shape, stack)
        for _ in range(8):
            r = gen.renderer.render(K, shape, scene.cls_ids, scene.poses())
            keep = scene.supported(r.visible_pixels >= MIN_VISIBLE_PIXELS)
            if keep.all() or keep.sum() < N_OBJECTS[0]:
                break
            scene = scene.subset(keep)
        if keep.all() and len(scene.cls_ids) >= N_OBJECTS[0]:
            break
    poses = scene.poses()
    alone = gen.renderer.alone_pixels(K, shape, scene.cls_ids, poses)
    bg = background_depth(K, shape, scene.world_to_camera, scene.background)
    obj = r.label > 0
    clean = np.where(obj, r.depth.astype(np.float64), bg)
    if not noise:
        depth = clean
    elif v1:
        depth = add_sensor_noise(clean, rng)
    else:
        depth = add_sensor_noise_v2(clean, r.label, K, rng)
    return SynthFrame(
        frame_id(split, index),
        depth,
        clean,
        r.label,
        scene.cls_ids,
        poses,
        alone,
        r.visible_pixels,
        scene,
    )
