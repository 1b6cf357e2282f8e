"""reports/diagnostics/stress_budget.py: networks of several sweeps scored on the instances a
baseline ran on."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cloudpose.studies.stress import result_path
from tests.conftest import diagnostic_script


@pytest.fixture(scope="module")
def stress_budget():
    return diagnostic_script("stress_budget")


def _results(n: int, trans_m: float, start: int = 0) -> pd.DataFrame:
    """``n`` instances, every rotation exact and every translation off by ``trans_m``."""
    rows = []
    for i in range(start, start + n):
        row = {
            "frame_id": f"0000/{i:06d}",
            "instance": 0,
            "cls_id": 1,
            "class": "002_master_chef_can",
        }
        for stage in ("net", "icp"):
            row |= {
                f"{stage}_ad": trans_m,
                f"{stage}_ads": trans_m,
                f"{stage}_rot_err_deg": 0.0,
                f"{stage}_rot_sym_err_deg": 0.0,
                f"{stage}_trans_err": trans_m,
            }
        rows.append(row)
    return pd.DataFrame(rows)


def _sweep(folder: Path, tables: dict[tuple[float, str], pd.DataFrame]) -> Path:
    (folder).mkdir(parents=True)
    meta = {"sources": {"real": "x"}, "perturbations": {"dilate": [0, 2]}}
    (folder / "sweep.json").write_text(json.dumps(meta))
    for (level, method), table in tables.items():
        path = result_path(folder, "real", "dilate", level, method)
        path.parent.mkdir(parents=True, exist_ok=True)
        table.to_csv(path, index=False)
    return folder


def test_each_network_is_scored_on_the_baselines_instances_only(stress_budget, tmp_path):
    base = _sweep(
        tmp_path / "base",
        {(0, "fpfh"): _results(4, 0.004), (2, "fpfh"): _results(4, 0.006)},
    )
    # the network ran on 8 instances: 4 shared with the baseline (2 mm off), 4 more (9 cm off)
    net = pd.concat([_results(4, 0.002), _results(4, 0.09, start=4)])
    a = _sweep(tmp_path / "a", {(0, "net-seed1"): net, (2, "net-seed1"): net})
    df = stress_budget.paired({"a": a}, base, "dilate", "net-seed1")
    got = df[(df["method"] == "a") & (df["stage"] == "net")]
    assert list(got["count"]) == [4.0, 4.0]
    np.testing.assert_allclose(got["trans_median_mm"], [2.0, 2.0], atol=1e-9)
    fpfh = df[(df["method"] == "fpfh") & (df["stage"] == "icp")]
    np.testing.assert_allclose(fpfh["trans_median_mm"], [4.0, 6.0], atol=1e-9)
    text = stress_budget.markdown(df, {"dilate": 0.5}, "python stress_budget.py ...")
    assert "Real frames' level: 0.5 px." in text
    assert "| real | 2 | 6.0 / 6.0 | 2.0 / 2.0 |" in text  # median translation (mm)


def test_a_network_missing_some_of_the_baselines_instances_is_refused(stress_budget, tmp_path):
    base = _sweep(
        tmp_path / "base", {(0, "fpfh"): _results(4, 0.004), (2, "fpfh"): _results(4, 0.004)}
    )
    a = _sweep(
        tmp_path / "a", {(0, "net-seed1"): _results(3, 0.002), (2, "net-seed1"): _results(4, 0.002)}
    )
    with pytest.raises(ValueError, match="lacks some of fpfh's 4 instances"):
        stress_budget.paired({"a": a}, base, "dilate", "net-seed1")
