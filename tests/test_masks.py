"""Degraded segmentation masks (cloudpose.data.masks): imitated network errors, deterministic."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cloudpose.data.mask_sources import get_mask_source
from cloudpose.data.masks import DEGRADATIONS, Degradation, degraded_mask
from cloudpose.data.ycb import YCBVideo

REAL = Path(__file__).parent / "data" / "ycb_real"


@pytest.fixture(scope="module")
def frame():
    return YCBVideo(REAL).frame("0000/000001")


def test_degraded_masks_depart_from_gt_by_their_strength(frame):
    """Boundary error grows with the strength; the same frame always gives the same masks."""
    changed = []
    for name in DEGRADATIONS:
        src = get_mask_source(name)
        diff = 0
        for c in frame.cls_ids:
            gt = frame.label == c
            m = src(frame, int(c))
            assert np.array_equal(m, src(frame, int(c)))  # a pure function of (frame, class)
            diff += int((m ^ gt).sum())
        changed.append(diff)
    assert 0 < changed[0] <= changed[1] <= changed[2]


def test_bleeding_goes_into_touching_objects_only(frame):
    how = Degradation(boundary_px=0, bleed_px=6, miss_rate=0.0)
    for c in frame.cls_ids:
        gt = frame.label == c
        m = degraded_mask(frame, int(c), how)
        extra = m & ~gt
        assert (m & gt).sum() == gt.sum()  # nothing of the object lost
        assert not (extra & (frame.label == 0)).any()  # never into the background
        assert (frame.label[extra] != c).all()


def test_a_missed_detection_is_an_empty_mask(frame):
    always = Degradation(boundary_px=0, bleed_px=0, miss_rate=1.0)
    assert not degraded_mask(frame, int(frame.cls_ids[0]), always).any()


def test_unknown_segmentation_lists_the_valid_ones():
    with pytest.raises(ValueError, match="degraded-medium"):
        get_mask_source("posecnn-typo")


@pytest.mark.slow
def test_evaluate_under_degraded_masks_is_its_own_evaluation(smoke_project):
    """Evaluating under degraded masks logs beside, never over, the run's own results; the
    instances are the same, with the missed detections as misses."""
    from cloudpose.evaluate import evaluate
    from cloudpose.store import tracking

    proj, out = smoke_project
    own = evaluate(str(out.run_dir), progress=False, icp=False)
    ev = evaluate(str(out.run_dir), segmentation="degraded-strong", progress=False, icp=False)
    assert ev.name == "test-degraded-strong" and len(ev.table) == len(own.table)
    assert ev.table["miss"].sum() >= own.table["miss"].sum()
    metrics = tracking.setup(proj).get_run(out.run_id).data.metrics
    assert "test-degraded-strong/ads_auc" in metrics
    assert metrics["test/ads_auc"] == pytest.approx(own.metrics["test/ads_auc"])
