"""Which dataset a config means, made on first use, and the prepared data the stages share.

- :func:`dataset_root`: ``DataConfig.root``, or the synthetic default under the project folder
  (:func:`synthetic_root`, one folder per synthesis setting).
- :func:`prepare_data`: the (train, test) segments of a config as one :class:`Prepared`, what
  ``train`` and ``evaluate`` receive from the pipeline (:mod:`cloudpose.suite.pipeline`). The
  synthetic default is rendered or completed first (resumable), a real root is only read (its
  caches go to ``project_dir/data/cache``); the dataset is opened once and the object passed
  on to the caches, the class filter and the stages.
- :func:`data_fingerprint`: one content key for the train and test data and their settings
  (MLflow tag ``data``, part of a run's identity), without preparing anything.
- :func:`folder_segments`: the segments of a frame list of any other dataset folder (the
  ``--data`` of ``evaluate`` and ``baseline``), cached under the project.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cloudpose.config import DataConfig
from cloudpose.data.cache import SegmentSet, cache_key, load_segments, segments_for
from cloudpose.data.keys import DataKey
from cloudpose.data.layout import Dataset, as_dataset, open_dataset
from cloudpose.data.synth import synthesize

if TYPE_CHECKING:
    from cloudpose.config import DataConfig

__all__ = [
    "Prepared",
    "data_fingerprint",
    "dataset_root",
    "folder_segments",
    "only_classes",
    "prepare_data",
    "synthetic_root",
]


@dataclass(frozen=True)
class Prepared:
    """A config's data, ready for the stages.

    Attributes:
        train, test: the segments of the training set (image_sets/train.txt) and of the test
            set (keyframe.txt).
        data_key: the data key of both (:func:`data_fingerprint`).
        dataset: the opened dataset (models, class names and frames are read from it).
        cache_dir: where its segment caches are (other segment settings of the same frames
            go there too).
    """

    train: SegmentSet
    test: SegmentSet
    data_key: DataKey
    dataset: Dataset
    cache_dir: Path

    @property
    def root(self) -> Path:
        """The dataset root."""
        return self.dataset.root


def prepare_data(
    cfg: DataConfig,
    project_dir: str | Path | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> Prepared:
    """The (train, test) segments that ``cfg`` asks for, made on first use, with their data key.

    With ``cfg.root == ""`` the synthetic default (:func:`synthetic_root`) is rendered or
    completed to ``cfg.train_frames`` / ``cfg.test_frames`` (resumable); a real root is never
    written to (its caches go to ``project_dir/data/cache``). Train = image_sets/train.txt,
    test = keyframe.txt; both of the classes ``cfg.classes`` only (every class when empty).
    """
    project_dir = Path(project_dir or Path.cwd())
    root, cache_dir = _dataset_root(cfg, project_dir)
    if cfg.root == "":
        synthesize(
            root,
            cfg.train_frames,
            cfg.test_frames,
            seed=cfg.synth_seed,
            noise=cfg.noise,
            uniform_rotation=cfg.uniform_rotation,
            workers=workers,
            progress=progress,
            version=cfg.synth_version,
        )
    ds = open_dataset(root)
    train, test = (
        only_classes(
            load_segments(ds, split, cfg, cache_dir, workers=workers, progress=progress),
            ds,
            cfg.classes,
        )
        for split in ("train", "test")
    )
    return Prepared(train, test, _train_test_key(train.data_key, test.data_key), ds, cache_dir)


def _train_test_key(train: DataKey, test: DataKey) -> DataKey:
    """The data key of a run's data from those of its train and test segments."""
    return DataKey(hashlib.sha256(f"{train}+{test}".encode()).hexdigest()[:16])


def synthetic_root(cfg: DataConfig, project_dir: str | Path | None = None) -> Path:
    """The synthetic default root: ``project_dir/data/synth-seed{S}[-uniform][-nonoise][-vV]``.

    Generator version 1 has no suffix, every later version its own (``-v2``): frames of two
    versions never share a folder.
    """

    base = DataConfig()
    name = f"synth-seed{cfg.synth_seed}"
    if cfg.uniform_rotation != base.uniform_rotation:
        name += "-uniform"
    if cfg.noise != base.noise:
        name += "-nonoise"
    if cfg.synth_version != 1:
        name += f"-v{cfg.synth_version}"
    return Path(project_dir or Path.cwd()) / "data" / name


def _dataset_root(cfg: DataConfig, project_dir: Path) -> tuple[Path, Path]:
    if cfg.root == "":
        root = synthetic_root(cfg, project_dir)
        return root, root / "cache"
    root = Path(cfg.root)
    if not root.is_dir():
        raise FileNotFoundError(f"data.root {root}: dataset root not found")
    return root, project_dir / "data" / "cache"


def dataset_root(cfg: DataConfig, project_dir: str | Path | None = None) -> Path:
    """Dataset root of ``cfg``: ``cfg.root``, or the synthetic default (:func:`synthetic_root`)."""
    return _dataset_root(cfg, Path(project_dir or Path.cwd()))[0]


def only_classes(
    segs: SegmentSet, dataset: str | Path | Dataset, classes: tuple[str, ...]
) -> SegmentSet:
    """The segments of the named classes (``DataConfig.classes``); all of them when empty.

    Raises:
        ValueError: a name that is not in the dataset's ``classes.txt``.
    """
    if not classes:
        return segs
    ds = as_dataset(dataset)
    names = ds.classes
    unknown = [c for c in classes if c not in names]
    if unknown:
        raise ValueError(f"data.classes: unknown classes {unknown}; {ds.root} has {names}")
    ids = [names.index(c) + 1 for c in classes]
    return segs.subset(np.isin(segs.cls_id, ids))


def folder_segments(
    dataset: str | Path | Dataset,
    frames: str,
    cfg: DataConfig,
    project_dir: str | Path | None = None,
    progress: bool = True,
) -> SegmentSet:
    """The segments of the frame list ``frames`` of a dataset folder other than a run's own
    (``--data``), with ``cfg``'s segment settings and of its classes, cached in
    ``project_dir/data/cache`` (the folder is only read); ``.data_key`` is their data key."""
    ds = as_dataset(dataset)
    cache_dir = Path(project_dir or Path.cwd()) / "data" / "cache"
    segs = segments_for(ds, frames, cfg, cache_dir=cache_dir, progress=progress)
    return only_classes(segs, ds, cfg.classes)


def data_fingerprint(cfg: DataConfig, project_dir: str | Path | None = None) -> DataKey:
    """One data key for the train and test data and settings (MLflow tag ``data``); 16 hex
    digits: :attr:`Prepared.data_key`, computed without preparing (the data must exist)."""
    project_dir = Path(project_dir or Path.cwd())
    root, cache_dir = _dataset_root(cfg, project_dir)
    ds = open_dataset(root)
    return _train_test_key(*(cache_key(ds, s, cfg, memo_dir=cache_dir) for s in ("train", "test")))
