"""reports/diagnostics/real_twins.py: the pieces its new conditions and its translation table
stand on."""

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from tests.conftest import diagnostic_script


@pytest.fixture(scope="module")
def twins():
    return diagnostic_script("real_twins")


def test_offset_from_model_recovers_a_shift_of_the_readings(twins):
    """Readings of a posed model moved by d: the translation-only fit gives d back (to the
    sampling of the model), and 0 for readings on the model."""
    rng = np.random.default_rng(0)
    model = rng.uniform(-0.05, 0.05, (4000, 3))
    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    t = np.array([0.05, -0.02, 0.9])
    seen = model[:1500] @ R.T + t
    d = np.array([0.004, -0.003, 0.006])
    tree = cKDTree(model)
    np.testing.assert_allclose(twins._offset_from_model(seen + d, R, t, tree), d, atol=5e-4)
    np.testing.assert_allclose(twins._offset_from_model(seen, R, t, tree), 0.0, atol=1e-12)


def test_correlated_depth_changes_object_readings_only(twins):
    """``_correlated``: the object's readings off its step redrawn (other values, the same
    pixels with depth), the background and the readings on the step kept."""
    K = np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]])
    clean = np.full((480, 640), 2.0)
    label = np.zeros((480, 640), dtype=np.uint8)
    label[200:260, 300:380] = 5
    clean[label == 5] = 0.9
    clean[200:260, 340:380] = 0.85
    depth = clean + 0.002 * np.random.default_rng(0).standard_normal(clean.shape)
    out = twins._correlated(depth, clean, label, K, 2.0, np.random.default_rng(1))
    obj = label == 5
    np.testing.assert_array_equal(out[~obj], depth[~obj])
    np.testing.assert_array_equal(out > 0, depth > 0)
    step = obj & np.isin(np.arange(640), [339, 340])[None, :]
    np.testing.assert_array_equal(out[step], depth[step])
    assert np.mean(out[obj & ~step] != depth[obj & ~step]) > 0.9
