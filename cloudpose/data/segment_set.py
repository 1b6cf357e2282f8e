"""Segments as columnar arrays (:class:`SegmentSet`), and the depth unit check over them.

A :class:`SegmentSet` stacks the :class:`~cloudpose.data.segments.Segment` objects of many
frames into arrays: the format of the segment cache (:mod:`cloudpose.data.cache`), of training
and of evaluation. :func:`unit_stats` measures, per scene, what the depth unit check looks at;
:func:`check_units` stops on a scene whose segments are a tenth or ten times their model's size
(the segment cache and the BOP export run it).
"""

from __future__ import annotations

import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cloudpose.data.keys import NO_DATA_KEY, DataKey
from cloudpose.data.segments import (
    Segment,
    depth_scale_problem,
    depth_scale_stats,
    report_depth_scale,
)
from cloudpose.files import UNREADABLE, CorruptFileError, atomic_write, read_npz, why

__all__ = ["UNIT_SAMPLE", "SegmentSet", "check_units", "unit_stats"]

_NPY_HEADERS = {
    (1, 0): np.lib.format.read_array_header_1_0,
    (2, 0): np.lib.format.read_array_header_2_0,
}


@dataclass
class SegmentSet:
    """Segments as columnar arrays (M segments).

    Attributes:
        points: (M, n_fps, 3) float32 camera-frame points, metres, FPS order.
        count: (M,) int32 true point count after the outlier filter.
        cls_id: (M,) int16 1-based class ids.
        R: (M, 3, 3) float32 ground-truth rotations (NaN without ground truth).
        t: (M, 3) float32 ground-truth translations, metres (NaN without ground truth).
        occlusion: (M,) float32 occlusion factors in [0, 1] (NaN when unknown).
        frame_id: (M,) str "SEQ/FRAME".
        instance: (M,) int16 instance index within its frame.
        valid: (M,) bool; False = no usable point (a miss at test time).
        data_key: the data key of the frames and settings
            (:func:`cloudpose.data.cache.cache_key`; :data:`~cloudpose.data.keys.NO_DATA_KEY` when
            built in memory).
    """

    points: np.ndarray
    count: np.ndarray
    cls_id: np.ndarray
    R: np.ndarray
    t: np.ndarray
    occlusion: np.ndarray
    frame_id: np.ndarray
    instance: np.ndarray
    valid: np.ndarray
    data_key: DataKey = NO_DATA_KEY

    _ARRAYS = ("points", "count", "cls_id", "R", "t", "occlusion", "frame_id", "instance", "valid")

    def __len__(self) -> int:
        return len(self.count)

    def observed(self, i: int) -> np.ndarray:
        """Segment ``i``'s distinct points: the first ``count`` of its FPS order, camera frame
        (a segment of fewer points than ``n_fps`` repeats its FPS order after them)."""
        return self.points[i, : min(int(self.count[i]), self.points.shape[1])]

    def subset(self, index: np.ndarray | slice) -> SegmentSet:
        """The segments selected by a bool mask (M,), an index array or a slice."""
        parts = {name: getattr(self, name)[index] for name in self._ARRAYS}
        return SegmentSet(**parts, data_key=self.data_key)

    @classmethod
    def from_segments(cls, segments: list[Segment], n_fps: int = 1024) -> SegmentSet:
        """Stack :class:`Segment` objects (frames without ground truth get NaN poses)."""
        m = len(segments)
        nan_R, nan_t = np.full((3, 3), np.nan, np.float32), np.full(3, np.nan, np.float32)
        if m == 0:
            points = np.zeros((0, n_fps, 3), np.float32)
        else:
            points = np.stack([s.points for s in segments]).astype(np.float32)
        return cls(
            points=points,
            count=np.array([s.count for s in segments], dtype=np.int32),
            cls_id=np.array([s.cls_id for s in segments], dtype=np.int16),
            R=np.array([nan_R if s.R is None else s.R for s in segments], np.float32).reshape(
                m, 3, 3
            ),
            t=np.array([nan_t if s.t is None else s.t for s in segments], np.float32).reshape(m, 3),
            occlusion=np.array([s.occlusion for s in segments], dtype=np.float32),
            frame_id=np.array([s.frame_id for s in segments], dtype=str),
            instance=np.array([s.instance for s in segments], dtype=np.int16),
            valid=np.array([s.valid for s in segments], dtype=bool),
        )

    @classmethod
    def concatenate(cls, sets: list[SegmentSet]) -> SegmentSet:
        """Join sets (keys dropped)."""
        if not sets:
            raise ValueError("concatenate needs at least one SegmentSet")
        return cls(**{n: np.concatenate([getattr(s, n) for s in sets]) for n in cls._ARRAYS})

    def save(self, path: str | Path, extra: dict[str, np.ndarray] | None = None) -> None:
        """Write one uncompressed ``.npz`` (atomically: temporary name, then rename), with the
        arrays ``extra`` beside the segments' (:meth:`load` leaves them out)."""
        arrays = {**(extra or {}), **{n: getattr(self, n) for n in self._ARRAYS}}
        arrays["frame_id"] = np.asarray(self.frame_id, dtype=str)
        atomic_write(path, lambda tmp: np.savez(tmp, key=np.array(self.data_key), **arrays), ".npz")

    @classmethod
    def load(cls, path: str | Path) -> SegmentSet:
        """Read a set written by :meth:`save`, every array whole (a damaged one fails its CRC).

        Raises:
            FileNotFoundError: no such file.
            CorruptFileError: (a ``ValueError``) the file is empty, truncated or garbled, lacks
                a field, or a field has the wrong shape.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: segment cache not found")
        parts = read_npz(path, (*cls._ARRAYS, "key"), "segment cache")
        data_key = DataKey(str(parts.pop("key")))
        _check_shapes(path, {n: a.shape for n, a in parts.items()})
        return cls(**parts, data_key=data_key)

    @classmethod
    def check(cls, path: str | Path) -> None:
        """Check a file written by :meth:`save` without reading its arrays: every field is there
        with the shape the others imply, and each array's stored bytes are as many as its header
        declares (a zero-byte or truncated file fails here). Garbled bytes inside an array are
        found by :meth:`load`, which reads them.

        Raises:
            CorruptFileError: as :meth:`load`.
        """
        path = Path(path)
        shapes: dict[str, tuple[int, ...]] = {}
        try:
            with zipfile.ZipFile(path) as z:
                members = {i.filename: i for i in z.infolist()}
                missing = [n for n in (*cls._ARRAYS, "key") if f"{n}.npy" not in members]
                if missing:
                    raise CorruptFileError(path, f"segment cache lacks fields {missing}")
                for n in cls._ARRAYS:
                    info = members[f"{n}.npy"]
                    with z.open(info) as f:
                        version = np.lib.format.read_magic(f)
                        read_header = _NPY_HEADERS.get(version)
                        if read_header is None:  # a later format: read it all
                            cls.load(path)
                            return
                        shape, _, dtype = read_header(f)
                        header = f.tell()
                    if header + math.prod(shape) * dtype.itemsize != info.file_size:
                        raise CorruptFileError(
                            path,
                            f"segment cache array {n} holds {info.file_size - header} bytes, its "
                            f"header declares {math.prod(shape) * dtype.itemsize}",
                        )
                    shapes[n] = shape
        except CorruptFileError:
            raise
        except UNREADABLE as e:
            raise CorruptFileError(path, f"segment cache is unreadable ({why(e)})") from e
        _check_shapes(path, shapes)


def _check_shapes(path: Path, shapes: dict[str, tuple[int, ...]]) -> None:
    """The fields of a stored set agree: M rows each, points (M, n_fps, 3), R (M, 3, 3),
    t (M, 3), the others (M,)."""
    count = shapes["count"]
    if len(count) != 1:
        raise CorruptFileError(path, f"segment cache field count has shape {count}, expected (M,)")
    m = count[0]
    n_fps = shapes["points"][1] if len(shapes["points"]) == 3 else "n_fps"
    expected = {n: (m,) for n in SegmentSet._ARRAYS}
    expected.update(points=(m, n_fps, 3), R=(m, 3, 3), t=(m, 3))
    for n, want in expected.items():
        if shapes[n] != want:
            raise CorruptFileError(
                path, f"segment cache field {n} has shape {shapes[n]}, expected {want}"
            )


# --------------------------------------------------------------------------- units

UNIT_SAMPLE = 64
"""Segments per scene that the depth unit check measures (evenly spaced over its valid ones)."""


def unit_stats(segs: SegmentSet, models_by_class: dict[int, np.ndarray]) -> dict[str, np.ndarray]:
    """Per scene (the ``SEQ`` of ``SEQ/FRAME``), what the depth unit check looks at
    (:func:`~cloudpose.data.segments.depth_scale_stats`: median extent / model diameter, median
    depth in metres), from up to :data:`UNIT_SAMPLE` of its valid segments.

    Returns:
        ``unit_scene`` (S,) str and ``unit_stats`` (S, 2) float64 (NaN: no usable segment), as
        the segment cache stores them.
    """
    scene = np.array([str(f).split("/", 1)[0] for f in segs.frame_id], dtype=str)
    names = np.unique(scene)
    stats = np.full((len(names), 2), np.nan)
    for k, name in enumerate(names):
        idx = np.flatnonzero((scene == name) & np.asarray(segs.valid, dtype=bool))
        if len(idx) > UNIT_SAMPLE:
            idx = idx[np.linspace(0, len(idx) - 1, UNIT_SAMPLE).round().astype(np.int64)]
        points = [segs.observed(i) for i in idx]
        found = depth_scale_stats(points, [int(segs.cls_id[i]) for i in idx], models_by_class)
        if found is not None:
            stats[k] = found
    return {"unit_scene": names, "unit_stats": stats}


def check_units(dataset, unit: dict[str, np.ndarray]) -> None:
    """The depth unit check of a dataset's segments (:func:`unit_stats`): the first scene that
    looks like depth in another unit stops it with one line naming the scene folder and the
    setting to fix (the count of other such scenes added), or warns where
    :data:`cloudpose.data.segments.UNIT_CHECK_OFF` is set."""
    bad = [
        (str(scene), float(ratio), float(depth))
        for scene, (ratio, depth) in zip(unit["unit_scene"], unit["unit_stats"], strict=True)
        if not np.isnan(ratio) and depth_scale_problem(ratio, depth, "", "") is not None
    ]
    if not bad:
        return
    scene, ratio, depth = bad[0]
    where, setting, meaning = dataset.depth_unit_setting(scene)
    if len(bad) > 1:
        where += f" (and {len(bad) - 1} more scenes alike)"
    report_depth_scale(depth_scale_problem(ratio, depth, where, setting, meaning))
