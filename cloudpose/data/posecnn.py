"""PoseCNN's released segmentation as a mask source: ``posecnn:DIR``.

The paper tests with PoseCNN's semantic segmentation, not ground truth. The YCB_Video_toolbox
ships PoseCNN's per-frame results as ``results_PoseCNN_RSS2018/NNNNNN.mat``, each holding

- ``labels``: (H, W) the predicted class id per pixel (0 = background);
- ``rois``: (K, 6) the detections, the class id in MATLAB's column 2 (``rois[:, 1]`` here).

File ``NNNNNN`` belongs to the frame on line ``NNNNNN`` of the toolbox's ``keyframe.txt``,
counted from 0: the toolbox's ``evaluate_poses_keyframe.m`` loads
``sprintf('results_PoseCNN_RSS2018/%06d.mat', i - 1)`` for its i-th keyframe (1-based), and
matches a ground-truth object to ``find(result.rois(:, 2) == cls_index)``. The list is
``DIR/keyframe.txt`` when the folder has one, else the toolbox's 2,949 keyframes that ship in
the package (``cloudpose/resources/keyframe.txt``). BOP-layout frames carry YCB-Video's frame
ids (:mod:`cloudpose.data.bop`), so the same results serve both layouts.

An instance's mask is the pixels PoseCNN labelled with its class, when a detection of that
class is among the ``rois`` (the toolbox's rule); otherwise it is empty, and the instance is a
miss in every metric (:func:`cloudpose.data.segments.extract_segments` keeps it as invalid).
Occlusion factors still come from the ground-truth labels. The ``.mat`` files are part of the
segments' cache key (:meth:`PoseCNNMasks.content_files`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cloudpose.conventions import resource_path
from cloudpose.data.ycb import _read_lines

if TYPE_CHECKING:
    from cloudpose.data.ycb import Frame

__all__ = ["PoseCNNMasks"]


class PoseCNNMasks:
    """The mask source ``posecnn:DIR`` (module doc): (frame, class id) -> (H, W) bool mask.

    Args:
        folder: the results folder (``results_PoseCNN_RSS2018``).

    Raises:
        FileNotFoundError: no such folder.
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise FileNotFoundError(
                f"{self.folder}: PoseCNN results folder not found (posecnn:DIR expects the "
                "YCB_Video_toolbox's results_PoseCNN_RSS2018 with NNNNNN.mat files)"
            )
        own = self.folder / "keyframe.txt"
        self.keyframes = own if own.is_file() else resource_path("keyframe.txt")
        self._index = {f: i for i, f in enumerate(_read_lines(self.keyframes, "keyframe list"))}
        self._last: tuple[str, np.ndarray, set[int]] | None = None

    def path(self, frame_id: str) -> Path:
        """The results file of a frame: ``DIR/NNNNNN.mat``, NNNNNN its 0-based keyframe line.

        Raises:
            ValueError: the frame is not in the keyframe list.
        """
        if frame_id not in self._index:
            raise ValueError(
                f"frame {frame_id} is not in {self.keyframes}: PoseCNN's results cover the "
                "listed keyframes only (evaluate with --frames keyframe)"
            )
        return self.folder / f"{self._index[frame_id]:06d}.mat"

    def content_files(self, frame_id: str) -> list[Path]:
        """The results file of a frame, for the segments' cache key.

        Raises:
            FileNotFoundError: it is missing.
        """
        path = self.path(frame_id)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: PoseCNN results of frame {frame_id} not found")
        return [path]

    def read(self, frame_id: str) -> tuple[np.ndarray, set[int]]:
        """(H, W) int64 predicted labels and the set of detected class ids of a frame.

        Raises:
            FileNotFoundError: no results file.
            ValueError: unreadable, or ``labels`` / ``rois`` of the wrong shape.
        """
        if self._last is not None and self._last[0] == frame_id:
            return self._last[1], self._last[2]
        import scipy.io

        (path,) = self.content_files(frame_id)
        try:
            mat = scipy.io.loadmat(path, variable_names=["labels", "rois"])
        except Exception as e:  # scipy raises several types on corrupt files
            raise ValueError(f"{path}: not a readable .mat file ({e})") from e
        for field in ("labels", "rois"):
            if field not in mat:
                raise ValueError(f"{path}: no field {field!r} (expected PoseCNN's results)")
        labels = np.asarray(mat["labels"])
        if labels.ndim != 2:
            raise ValueError(f"{path}: labels has shape {labels.shape}, expected (H, W)")
        rois = np.asarray(mat["rois"], dtype=np.float64)
        if rois.size and (rois.ndim != 2 or rois.shape[1] < 2):
            raise ValueError(f"{path}: rois has shape {rois.shape}, expected (K, 6)")
        detected = {int(c) for c in rois[:, 1]} if rois.size else set()
        labels = labels.astype(np.int64)
        self._last = (frame_id, labels, detected)
        return labels, detected

    def __call__(self, frame: Frame, cls_id: int) -> np.ndarray:
        """(H, W) bool: PoseCNN's pixels of ``cls_id`` if it detected the class, else empty."""
        labels, detected = self.read(frame.frame_id)
        if labels.shape != frame.label.shape:
            raise ValueError(
                f"{self.path(frame.frame_id)}: labels have shape {labels.shape}, expected the "
                f"frame's {frame.label.shape}"
            )
        if int(cls_id) not in detected:
            return np.zeros(labels.shape, dtype=bool)
        return labels == int(cls_id)
