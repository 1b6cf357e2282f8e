"""Prediction on a frame without poses (the real demo frame) and its intrinsics option."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cloudpose.predict import parse_intrinsics, predict

DATA = Path(__file__).parent / "data"


@pytest.mark.slow
def test_predict_on_a_real_frame_without_poses(smoke_project, tmp_path):
    _, out = smoke_project
    overlay = tmp_path / "overlay.png"
    res = predict(
        DATA / "demo_no_gt" / "depth.png",
        DATA / "demo_no_gt" / "label.png",
        str(out.checkpoint),
        color=DATA / "demo_no_gt" / "color.png",
        overlay=overlay,
    )
    assert sorted(p.cls_id for p in res.poses) == [2, 4, 5, 10, 15]
    for p in res.poses:
        np.testing.assert_allclose(p.R @ p.R.T, np.eye(3), atol=1e-6)
        assert 0.3 < p.t[2] < 2.0  # in front of the camera, at table distance
    from PIL import Image

    img = Image.open(overlay)
    assert (
        img.size[0] >= 600
        and len(np.unique(np.asarray(img.convert("RGB")).reshape(-1, 3), axis=0)) > 100
    )


def test_parse_intrinsics():
    K = parse_intrinsics("1066.8,1067.5,313.0,241.3")
    assert K[0, 0] == 1066.8 and K[1, 2] == 241.3 and K[2, 2] == 1
    with pytest.raises(ValueError, match="fx,fy,cx,cy"):
        parse_intrinsics("1,2,3")


def test_predict_keeps_the_start_that_agrees_best_with_this_frames_depth():
    """Starts turned by the 12-element group and scored against the frame's own depth: every
    object keeps a pose that agrees with the depth at least as well as the paper's one start
    (which is among the starts), and each pose reports that agreement."""
    from cloudpose.refine import DepthAgreement, depth_score
    from cloudpose.store.pretrained import PRETRAINED

    frame = DATA / "ycb_real" / "data" / "0000" / "000001"
    files = (Path(f"{frame}-depth.png"), Path(f"{frame}-label.png"), PRETRAINED)
    kw = dict(meta=Path(f"{frame}-meta.mat"), device="cpu")
    paper = predict(*files, **kw)
    turned = predict(*files, icp_overrides={"starts": 12, "select": "depth"}, **kw)
    assert [p.cls_id for p in turned.poses] == [p.cls_id for p in paper.poses] != []

    def score(p):
        return depth_score(p.fitness, DepthAgreement(p.coverage, p.violation))

    for a, b in zip(paper.poses, turned.poses, strict=True):
        assert 0 <= b.coverage <= 1 and 0 <= b.violation <= 1
        assert score(b) >= score(a) - 1e-9, (a.name, score(a), score(b))
        assert "coverage" in b.describe()
