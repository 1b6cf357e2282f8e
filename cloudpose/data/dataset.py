"""Which dataset a config means, made on first use, and the prepared data the stages share.

- :func:`dataset_root`: ``DataConfig.root``, or the synthetic default under the project folder
  (:func:`synthetic_root`, one folder per synthesis setting).
- :func:`ensure_dataset`: the (train, test) segments of a config; the synthetic default is
  rendered or completed first (resumable), a real root is only read (its caches go to
  ``project_dir/data/cache``).
- :func:`data_fingerprint`: one content key for the train and test data and their settings
  (MLflow tag ``data``, part of a run's identity).
- :func:`prepare_data`: all of the above as one :class:`Prepared`, what ``train`` and
  ``evaluate`` receive from the pipeline (:mod:`cloudpose.pipeline`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cloudpose.data.cache import SegmentSet, cache_key, prepare

if TYPE_CHECKING:
    from cloudpose.config import DataConfig

__all__ = [
    "Prepared",
    "data_fingerprint",
    "dataset_root",
    "ensure_dataset",
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
        key: :func:`data_fingerprint` of both.
        root: the dataset root (models and class names are read from it).
        cache_dir: where its segment caches are (other segment settings of the same frames
            go there too).
    """

    train: SegmentSet
    test: SegmentSet
    key: str
    root: Path
    cache_dir: Path


def prepare_data(
    cfg: DataConfig, project_dir: str | Path | None = None, progress: bool = True
) -> Prepared:
    """The data of ``cfg``, made on first use (:func:`ensure_dataset`), with its key."""
    project_dir = Path(project_dir or Path.cwd())
    train, test = ensure_dataset(cfg, project_dir=project_dir, progress=progress)
    root, cache_dir = _dataset_root(cfg, project_dir)
    return Prepared(train, test, data_fingerprint(cfg, project_dir), root, cache_dir)


def synthetic_root(cfg: DataConfig, project_dir: str | Path | None = None) -> Path:
    """The synthetic default root: ``project_dir/data/synth-seed{S}[-uniform][-nonoise][-vV]``.

    Generator version 1 has no suffix, every later version its own (``-v2``): frames of two
    versions never share a folder.
    """
    from cloudpose.config import DataConfig

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


def ensure_dataset(
    cfg: DataConfig,
    project_dir: str | Path | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> tuple[SegmentSet, SegmentSet]:
    """The (train, test) segments that ``cfg`` asks for, made on first use.

    With ``cfg.root == ""`` the synthetic default (:func:`synthetic_root`) is rendered or
    completed to ``cfg.train_frames`` / ``cfg.test_frames`` (resumable); a real root is never
    written to (its caches go to ``project_dir/data/cache``). Train = image_sets/train.txt,
    test = keyframe.txt.
    """
    project_dir = Path(project_dir or Path.cwd())
    root, cache_dir = _dataset_root(cfg, project_dir)
    if cfg.root == "":
        from cloudpose.data.synth import synthesize

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
    sets = []
    for split in ("train", "test"):
        path = prepare(root, split, cfg, cache_dir, workers=workers, progress=progress)
        sets.append(only_classes(SegmentSet.load(path), root, cfg.classes))
    return sets[0], sets[1]


def only_classes(segs: SegmentSet, root: str | Path, classes: tuple[str, ...]) -> SegmentSet:
    """The segments of the named classes (``DataConfig.classes``); all of them when empty.

    Raises:
        ValueError: a name that is not in the dataset's ``classes.txt``.
    """
    if not classes:
        return segs
    from cloudpose.data.layout import open_dataset

    names = open_dataset(root).classes
    unknown = [c for c in classes if c not in names]
    if unknown:
        raise ValueError(f"data.classes: unknown classes {unknown}; {root} has {names}")
    ids = [names.index(c) + 1 for c in classes]
    return segs.subset(np.isin(segs.cls_id, ids))


def data_fingerprint(cfg: DataConfig, project_dir: str | Path | None = None) -> str:
    """One key for the train and test data and settings (for MLflow params); 16 hex digits.

    Needs the data to exist (call after :func:`ensure_dataset`).
    """
    project_dir = Path(project_dir or Path.cwd())
    root, cache_dir = _dataset_root(cfg, project_dir)
    keys = [cache_key(root, split, cfg, memo_dir=cache_dir) for split in ("train", "test")]
    return hashlib.sha256("+".join(keys).encode()).hexdigest()[:16]
