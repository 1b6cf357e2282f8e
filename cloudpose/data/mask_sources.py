"""Segmentation sources by name: where the mask of an instance comes from
(``DataConfig.segmentation``).

"gt" is the ground-truth label image; the degraded masks of :mod:`cloudpose.data.masks`
("degraded-mild", "degraded-medium", "degraded-strong") imitate a segmentation network's
errors; ``posecnn:DIR`` reads PoseCNN's published labels (:mod:`cloudpose.data.posecnn`).
:func:`cloudpose.data.segments.extract_segments` takes a source by name; the occlusion factor
always uses the ground-truth labels.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cloudpose.data.masks import DEGRADATIONS, Degradation, degraded_mask
from cloudpose.data.posecnn import PoseCNNMasks

if TYPE_CHECKING:
    from cloudpose.data.ycb import Frame

__all__ = [
    "MASK_SOURCES",
    "MASK_SOURCE_FAMILIES",
    "MaskSource",
    "get_mask_source",
    "gt_mask",
    "mask_source_label",
    "register_mask_source",
    "register_mask_source_family",
]

MaskSource = Callable[["Frame", int], np.ndarray]
"""(frame, class id) -> (H, W) bool mask of that instance."""


def gt_mask(frame: Frame, cls_id: int) -> np.ndarray:
    """Ground-truth segmentation: pixels whose label is ``cls_id``."""
    return frame.label == cls_id


def _degraded(how: Degradation) -> MaskSource:
    return lambda frame, cls_id: degraded_mask(frame, cls_id, how)


MASK_SOURCES: dict[str, MaskSource] = {
    "gt": gt_mask,
    **{name: _degraded(how) for name, how in DEGRADATIONS.items()},
}
"""Segmentation sources by name (DataConfig.segmentation)."""

MASK_SOURCE_FAMILIES: dict[str, Callable[[str], MaskSource]] = {"posecnn": PoseCNNMasks}
"""Sources that take an argument, by prefix: ``posecnn:DIR`` -> ``factory("DIR")``. A source
may have a method ``content_files(frame_id) -> list[Path]``: the files it reads, which then
belong to the segments' cache key."""


def register_mask_source(name: str, source: MaskSource) -> None:
    """Add a segmentation source, e.g. "degraded-mild"."""
    MASK_SOURCES[name] = source


def register_mask_source_family(prefix: str, factory: Callable[[str], MaskSource]) -> None:
    """Add sources named ``PREFIX:ARG``, made by ``factory(ARG)`` on first use."""
    MASK_SOURCE_FAMILIES[prefix] = factory


def get_mask_source(name: str) -> MaskSource:
    """The segmentation source ``name``; unknown names raise with the list of valid ones."""
    if name not in MASK_SOURCES:
        family, sep, arg = name.partition(":")
        if sep and family in MASK_SOURCE_FAMILIES:
            MASK_SOURCES[name] = MASK_SOURCE_FAMILIES[family](arg)
    if name not in MASK_SOURCES:
        valid = [*MASK_SOURCES, *(f"{p}:DIR" for p in MASK_SOURCE_FAMILIES)]
        raise ValueError(f"unknown segmentation {name!r}; valid segmentations: {', '.join(valid)}")
    return MASK_SOURCES[name]


def mask_source_label(name: str) -> str:
    """A short name of a segmentation source for metric prefixes: the name, or for a source
    with an argument its prefix and the argument's last path part
    (``posecnn:/data/results_PoseCNN_RSS2018`` -> ``posecnn-results_PoseCNN_RSS2018``)."""
    family, sep, arg = name.partition(":")
    return f"{family}-{Path(arg).name or arg}" if sep else name
