"""The version-2 sensor's missing-depth fit: it recovers a known model, and the shipped model
is the fit on the real frames the repository carries."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cloudpose.data.synth import sensor, sensor_fit
from cloudpose.report import fidelity

DATA = Path(__file__).parent / "data"


def test_fit_dropout_recovers_a_known_model():
    truth = sensor.DropoutModel(0.45, 3.0, 0.15, 0.06, ((2, 0.0), (15, 0.1)), 0.05)
    rng = np.random.default_rng(0)
    n = 100_000
    edge = 1.0 + np.floor(rng.exponential(8.0, n))
    cos = rng.uniform(0.0, 1.0, n)
    cls = rng.choice([2, 15], n)
    missing = rng.random(n) < truth.probability(edge, cos, cls)
    fit = sensor_fit.fit_dropout(sensor_fit.PixelSamples(missing, edge, cos, cls))
    assert abs(fit.edge_rate - 0.45) < 0.03 and abs(fit.edge_scale - 3.0) < 0.3
    assert abs(fit.graze_cos - 0.15) < 0.02 and abs(fit.graze_width - 0.06) < 0.015
    assert abs(fit.class_rate(15) - 0.1) < 0.01 and fit.class_rate(2) < 0.01


@pytest.mark.slow
def test_shipped_dropout_is_the_fit_on_the_real_frames():
    real = fidelity.read_real_frames([DATA / "ycb_real", DATA / "demo_no_gt"])
    fit = sensor_fit.fit_dropout(sensor_fit.object_pixels(real))
    shipped = sensor.REAL_DROPOUT
    for name in ("edge_rate", "edge_scale", "graze_cos", "graze_width", "default_rate"):
        assert getattr(fit, name) == pytest.approx(getattr(shipped, name), abs=2e-3), name
    for c, r in fit.class_rates:
        assert r == pytest.approx(shipped.class_rate(c), abs=2e-3), c
