"""Segment sets for the store's tests: points and classes given, no ground-truth pose."""

from __future__ import annotations

import numpy as np

from cloudpose.data.keys import NO_DATA_KEY, DataKey
from cloudpose.data.segment_set import SegmentSet


def segment_set(
    points: np.ndarray,
    cls_id,
    count=None,
    frame_id=None,
    data_key: DataKey = NO_DATA_KEY,
) -> SegmentSet:
    """A :class:`SegmentSet` of ``points`` (M, n, 3) and classes ``cls_id``: every point
    counted unless ``count`` says otherwise, pose and occlusion NaN, all in frame
    ``0000/000001`` (instances 0..M-1) unless ``frame_id`` names each segment's frame."""
    m = len(points)
    return SegmentSet(
        points=np.asarray(points, np.float32),
        count=np.full(m, points.shape[1], np.int32)
        if count is None
        else np.asarray(count, np.int32),
        cls_id=np.asarray(cls_id, np.int16),
        R=np.full((m, 3, 3), np.nan, np.float32),
        t=np.full((m, 3), np.nan, np.float32),
        occlusion=np.full(m, np.nan, np.float32),
        frame_id=np.array(["0000/000001"] * m) if frame_id is None else np.asarray(frame_id),
        instance=np.arange(m, dtype=np.int16),
        valid=np.ones(m, bool),
        data_key=data_key,
    )
