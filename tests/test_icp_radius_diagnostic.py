"""reports/diagnostics/icp_radius.py: the rule that chooses the radius, and the control that
refines no estimate."""

from __future__ import annotations

import numpy as np
import pandas as pd

from tests.conftest import diagnostic_script


def _runs(ads_by_radius: dict[float, list[float]]) -> list[dict]:
    """Fake refined runs whose instance tables give each radius one ADS AUC per run: four
    instances at one ADS distance d (the toolbox's VOCap of four equal distances is
    1 - 7.5 d: its first step already counts the first instance)."""
    n_runs = len(next(iter(ads_by_radius.values())))
    runs = []
    for k in range(n_runs):
        tables = {}
        for radius, aucs in ads_by_radius.items():
            d = (1 - aucs[k] / 100) / 7.5
            tables[radius] = pd.DataFrame(
                {
                    "frame_id": ["0000/000001"] * 4,
                    "instance": range(4),
                    "miss": False,
                    "cls_id": 1,
                    **{f"{p}_ad": d for p in ("net", "icp")},
                    **{f"{p}_rot_err_deg": 1.0 for p in ("net", "icp")},
                    **{f"{p}_ads": d for p in ("net", "icp")},
                    **{f"{p}_rot_sym_err_deg": 1.0 for p in ("net", "icp")},
                    **{f"{p}_trans_err": 0.001 for p in ("net", "icp")},
                }
            )
        runs.append({"tables": tables})
    return runs


def test_the_rule_takes_the_smallest_radius_within_a_tenth_of_the_best():
    mod = diagnostic_script("icp_radius")
    radii = [0.01, 0.05, 0.12, 0.25]
    means = {0.01: [93.0, 93.2], 0.05: [95.0, 95.2], 0.12: [95.35, 95.45], 0.25: [95.5, 95.46]}
    chosen, got = mod.choose(_runs(means), radii)
    np.testing.assert_allclose(got, [93.1, 95.1, 95.4, 95.48], atol=0.02)
    assert chosen == 0.12  # 95.40 is within 0.1 of 95.48; 95.1 is not
