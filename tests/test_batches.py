"""The network's tensors of a segment set: valid segments only, the FPS prefix, the targets."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from cloudpose.data.batches import Batchable


def _segments(m: int = 5, n_fps: int = 16) -> SimpleNamespace:
    rng = np.random.default_rng(0)
    return SimpleNamespace(
        points=rng.normal(size=(m, n_fps, 3)),
        cls_id=np.arange(1, m + 1),
        R=np.tile(np.eye(3), (m, 1, 1)),
        t=rng.normal(size=(m, 3)),
        valid=np.array([True, False, True, True, False][:m]),
    )


def test_from_segments_keeps_the_valid_segments_and_their_point_prefix():
    segs = _segments()
    b = Batchable.from_segments(segs, n_points=8)
    assert len(b) == 3 and b.points.shape == (3, 8, 3) and b.points.dtype == torch.float32
    np.testing.assert_allclose(b.points.numpy(), segs.points[segs.valid, :8].astype(np.float32))
    assert b.cls_id.tolist() == [1, 3, 4] and b.cls_id.dtype == torch.int64
    np.testing.assert_allclose(b.t.numpy(), segs.t[segs.valid].astype(np.float32))
    sub = b.subset(torch.tensor([2, 0]))
    assert sub.cls_id.tolist() == [4, 1] and torch.equal(sub.points[1], b.points[0])


def test_more_points_than_cached_are_refused_naming_the_setting():
    with pytest.raises(ValueError, match=r"train.n_points=32 exceeds the 16 cached FPS points"):
        Batchable.from_segments(_segments(), n_points=32)
