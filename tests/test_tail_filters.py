"""reports/diagnostics/tail_filters.py: the depth-continuity filter keeps an object's body and
drops the rim pixels that read the background behind it."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import diagnostic_script


@pytest.fixture(scope="module")
def tails():
    return diagnostic_script("tail_filters")


def test_bled_ring_is_dropped_and_a_sloped_body_kept(tails):
    depth = np.full((40, 40), 1.30)  # the background
    body = np.zeros((40, 40), bool)
    body[10:30, 10:30] = True
    # a surface sloping 2 mm a pixel: continuous, though 38 mm deep over its width
    depth[body] = 1.0 + 0.002 * np.broadcast_to(np.arange(40), (40, 40))[body]
    mask = np.zeros_like(body)
    mask[9:31, 9:31] = True  # the label bled one pixel into the background all round
    kept = tails.depth_components(mask, depth)
    assert (kept == body).all()


def test_regions_of_a_quarter_of_the_largest_survive_and_holes_are_no_points(tails):
    depth = np.zeros((20, 40))
    mask = np.zeros((20, 40), bool)
    mask[:, :20] = True
    depth[:, :20] = 1.0  # 400 px
    mask[:, 25:30] = True
    depth[:, 25:30] = 0.8  # 100 px, a quarter: kept (a handle in front of the body)
    mask[0:3, 35:38] = True
    depth[0:3, 35:38] = 1.2  # 9 px: dropped
    mask[5, 5] = True
    depth[5, 5] = 0.0  # no reading: never a point
    kept = tails.depth_components(mask, depth)
    assert kept[:, :20].sum() == 399 and not kept[5, 5]
    assert kept[:, 25:30].all() and not kept[0:3, 35:38].any()
    assert not tails.depth_components(np.zeros_like(mask), depth).any()
