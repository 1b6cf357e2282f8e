"""The synthetic frames' fidelity to real ones: the side-by-side report (``cloudpose synth
--compare-real``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cloudpose.conventions import YCB_INTRINSICS
from cloudpose.data.ycb import Frame
from cloudpose.report import fidelity

DATA = Path(__file__).parent / "data"


def test_frame_set_stats_on_a_drawn_frame():
    label = np.zeros((40, 40), np.uint8)
    label[10:30, 10:30] = 5
    depth = np.where(label > 0, 1.0, 2.0).astype(np.float32)
    depth[10, 10:30] = 0.0  # the top row of the mask: 20 of 400 pixels, all on the edge
    f = Frame("x", depth, label, YCB_INTRINSICS, np.array([5]), None, None)
    rendered = np.where(label > 0, 1.001, 0.0)
    s = fidelity.frame_set_stats([f], [rendered], [np.array([800])])
    assert s.missing == pytest.approx(20 / 400)
    assert s.missing_inside == 0 and s.missing_edge == pytest.approx(20 / (400 - 16 * 16))
    assert s.points == 380 and s.occlusion == pytest.approx(0.5)
    assert s.noise_std == pytest.approx(0.0, abs=1e-6)
    # 19 missing pixels have a missing right neighbour; the 20 below them are not missing
    assert s.missing_next == pytest.approx(19 / 39)


@pytest.mark.slow
def test_compare_real_command(tmp_path):
    from typer.testing import CliRunner

    from cloudpose.cli import app

    out = tmp_path / "renderer_vs_real.md"
    args = ["synth", "--compare-real", str(DATA / "ycb_real"), "--compare-real"]
    args += [str(DATA / "demo_no_gt"), "--compare-frames", "1", "--report", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    text = out.read_text()
    assert text.startswith("# Synthetic frames against real ones")
    assert (
        "cloudpose synth --compare-real" in text
        and "| real | synthetic v1 | synthetic v2 |" in text
    )
    rows = [r for r in text.splitlines() if r.startswith("| 0000/000001 |")]
    assert [r.split(" | ")[1] for r in rows] == ["009_gelatin_box", "025_mug", "061_foam_brick"]
    for r in rows:
        assert min(float(x) for x in r.split(" | ")[2:4]) >= 0.97  # IoU v1, v2
