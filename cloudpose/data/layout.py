"""Which layout a dataset folder has, and the dataset object that reads it.

Every command that takes ``--data`` takes either layout: the original YCB-Video layout
(:class:`~cloudpose.data.ycb.YCBVideo`: ``data/SEQ/FRAME-*``, ``keyframe.txt``; the synthetic
sets use it too) or BOP's ``ycbv`` layout (:class:`~cloudpose.data.bop.BOPYcbv`:
``test/SCENE/scene_gt.json``, ``test_targets_bop19.json``). :func:`open_dataset` tells them
apart from the folder; both read into the same frames, so segments, caches, training and
evaluation do not know which it was. Results name their frame list with
:func:`describe_split`, because "keyframe" means YCB-Video's 2,949 keyframes in one layout and
BOP's 900 target images in the other.
"""

from __future__ import annotations

from pathlib import Path

from cloudpose.conventions import resource_path
from cloudpose.data.bop import BOPYcbv, is_bop_root
from cloudpose.data.ycb import YCBVideo

__all__ = [
    "Dataset",
    "as_dataset",
    "describe_split",
    "detect_layout",
    "open_dataset",
    "real_dev_root",
]

Dataset = YCBVideo | BOPYcbv
"""An opened dataset of either layout: what the data stages read frames, models and frame
lists from (open a folder once with :func:`open_dataset` and pass the object on)."""


def detect_layout(root: str | Path) -> str:
    """ "bop" or "ycb": the layout of the dataset folder ``root``.

    BOP: a ``test_targets_bop19.json`` or a scene with ``scene_gt.json`` under ``test/`` or
    ``train_real/``. YCB-Video: a ``data/`` folder, ``keyframe.txt``, ``image_sets/`` or
    ``classes.txt``.

    Raises:
        FileNotFoundError: ``root`` is not a folder.
        ValueError: it is neither, naming the folder and what each layout holds.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: dataset root not found")
    if is_bop_root(root):
        return "bop"
    if any((root / p).exists() for p in ("data", "keyframe.txt", "image_sets", "classes.txt")):
        return "ycb"
    raise ValueError(
        f"{root}: neither a YCB-Video layout (data/SEQ/FRAME-meta.mat, keyframe.txt) nor a BOP "
        "ycbv layout (test/SCENE/scene_gt.json, test_targets_bop19.json)"
    )


def open_dataset(root: str | Path) -> YCBVideo | BOPYcbv:
    """The dataset object of ``root``, in the layout :func:`detect_layout` finds."""
    if detect_layout(root) == "bop":
        return BOPYcbv(root)
    return YCBVideo(root)


def as_dataset(data: str | Path | Dataset) -> Dataset:
    """``data`` itself when it is an opened dataset, else :func:`open_dataset` of the folder."""
    return data if isinstance(data, (YCBVideo, BOPYcbv)) else open_dataset(data)


def describe_split(data: str | Path | Dataset, frames: str) -> str:
    """The frame list ``frames`` of ``data`` (a folder or an opened dataset) in words, with its size: ``YCB-Video keyframe
    (2949 frames)``, ``BOP19 ycbv test targets (900 images)``, ``synthetic YCB-Video-layout
    keyframe (150 frames)``. Every evaluation names its data this way (printed and in
    MLflow), so results of different frame lists are not mixed up."""
    ds = as_dataset(data)
    name = "keyframe" if frames == "test" else frames
    n = len(ds.image_set(name))
    if isinstance(ds, BOPYcbv):
        what = {
            "keyframe": "BOP19 ycbv test targets",
            "all": "BOP ycbv test",
            "train": "BOP ycbv train_real",
        }.get(name, f"BOP ycbv {name}")
        return f"{what} ({n} images)"
    kind = "synthetic YCB-Video-layout" if (ds.root / "synth.json").is_file() else "YCB-Video"
    return f"{kind} {name} ({n} frames)"


def real_dev_root() -> Path:
    """The 61 real YCB-Video frames with ground truth that ship in the package (frames
    000001-000020 of training videos 0000-0002 and 0003/000138; 14 classes, 4 scenes), in the
    YCB-Video layout: the sim-to-real check of every run. Test videos are not among them."""
    return resource_path("real_dev")
