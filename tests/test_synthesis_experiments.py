"""reports/diagnostics/synthesis_experiments.py: each synthesis setting against the same seeds
without it, with intervals over seeds and instances (synthetic) or object poses (real)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.conftest import diagnostic_script


@pytest.fixture(scope="module")
def synthesis():
    return diagnostic_script("synthesis_experiments")


def _table(frames: list[str], trans_m: np.ndarray, rot_deg: np.ndarray) -> pd.DataFrame:
    """One instance a frame, class by frame index mod 2; ADS = translation error."""
    n = len(frames)
    cols = {
        "frame_id": frames,
        "instance": np.zeros(n, int),
        "cls_id": np.arange(n) % 2 + 1,
        "class": [f"c{i % 2}" for i in range(n)],
    }
    for prefix in ("net_", "icp_"):
        cols[prefix + "ad"] = trans_m
        cols[prefix + "ads"] = trans_m
        cols[prefix + "trans_err"] = trans_m
        cols[prefix + "rot_err_deg"] = rot_deg
        cols[prefix + "rot_sym_err_deg"] = rot_deg
    return pd.DataFrame(cols)


@dataclass
class _Run:
    """What the script reads of a run: its id and its instance tables."""

    run_id: str
    tables: dict = field(default_factory=dict)

    def instances(self, name: str):
        return self.tables.get(name)


def _runs(n: int, good: float, bad: float, seed: int):
    """A run whose first half of instances is off by ``good`` metres and second by ``bad``;
    the real frames are two videos of two object poses each."""
    trans = np.r_[np.full(n // 2, good), np.full(n - n // 2, bad)]
    rot = np.r_[np.full(n // 2, 5.0), np.full(n - n // 2, 30.0)]
    synth = _table([f"synth/{i:06d}" for i in range(n)], trans, rot)
    real_frames = [f"{v}/{i:06d}" for v in ("0000", "0001") for i in range(n // 2)]
    real = _table(real_frames, trans, rot)
    return _Run(f"run{seed}-{good}-{bad}", {"test": synth, "real": real})


def test_measure_pairs_seeds_and_reports_each_figure(synthesis):
    runs = {
        "none": {1: _runs(8, 0.005, 0.02, 1), 2: _runs(8, 0.005, 0.02, 2)},
        "bleed 1": {
            1: _runs(8, 0.005, 0.005, 1),
            2: _runs(8, 0.005, 0.005, 2),
            3: _runs(8, 0.1, 0.1, 3),
        },
    }
    table = synthesis.measure("p", runs, replicates=50)
    # one setting x two sets x two stages x three figures; seed 3 has no run without it
    assert len(table) == 12
    assert set(table["seeds"]) == {"1 2"}
    trans = table[(table["figure"] == "translation < 1 cm") & (table["stage"] == "network")]
    # half the instances move from 2 cm to 5 mm: +50 points on both sets
    np.testing.assert_allclose(trans["difference"], 50.0)
    assert list(trans["per_seed"]) == ["50.0 -> 100.0; 50.0 -> 100.0"] * 2
    rot = table[table["figure"] == "rot < 10 deg mod sym"]
    np.testing.assert_allclose(rot["difference"], 0.0)


def test_real_interval_resamples_object_poses_not_instances(synthesis):
    """Two videos x two classes = four poses: the pose bootstrap's interval is wider than
    one over 16 independent instances would be, and it contains the mean."""
    rng = np.random.default_rng(0)
    n = 16
    poses = np.array([f"{v}/c{i % 2}" for v in ("0000", "0001") for i in range(n // 2)])
    # the gain is all in one pose: a clustered effect
    gain = (poses == "0000/c0").astype(float)
    b = {s: rng.uniform(0, 1, n) for s in (1, 2, 3)}
    a = {s: b[s] - 0.5 * gain for s in (1, 2, 3)}  # smaller errors where gained
    stat = synthesis.share_below(0.5)
    mean, low, high = synthesis.cluster_bootstrap(a, b, stat, poses, replicates=400)
    exact = np.mean([stat(a[s][None])[0] - stat(b[s][None])[0] for s in (1, 2, 3)])
    assert mean == pytest.approx(exact)
    assert low <= mean <= high
    # drawing the gaining pose zero times happens in (3/4)^4 = 32% of replicates
    assert low == pytest.approx(0.0, abs=1e-12)


def test_tables_of_other_instances_are_refused(synthesis):
    a = _runs(8, 0.005, 0.005, 1)
    b = _runs(8, 0.005, 0.02, 1)
    b.tables["test"] = b.tables["test"].iloc[1:]
    with pytest.raises(ValueError, match="differ in instances"):
        synthesis.measure("p", {"none": {1: b}, "bleed 1": {1: a}}, replicates=10)


def test_markdown_names_runs_and_intervals(synthesis):
    runs = {"none": {1: _runs(8, 0.005, 0.02, 1)}, "smooth 1 px": {1: _runs(8, 0.005, 0.005, 1)}}
    table = synthesis.measure("p", runs, replicates=20)
    text = synthesis.markdown(table, {"p": runs}, ["synthesis_experiments.py", "--preset", "p"])
    assert "## p: smooth 1 px against none (seeds 1)" in text
    assert "seed 1 `run1-0.0`" in text
    assert (
        "| real development frames | network | translation < 1 cm | 50.0 -> 100.0 | +50.0" in text
    )


def _sweep(folder: Path, checkpoint: str, trans_m: dict[float, float], run_id: str = "") -> Path:
    """A `cloudpose stress` results folder: the network of ``checkpoint`` (of MLflow run
    ``run_id``, where given) under dilation, every instance's translation off by
    ``trans_m[level]``."""
    from cloudpose.studies.stress import result_path

    folder.mkdir(parents=True)
    method = {"checkpoint": checkpoint, "limit": None} | ({"run_id": run_id} if run_id else {})
    meta = {
        "sources": {"real": "x"},
        "methods": {"net-seed1": method},
        "perturbations": {"dilate": sorted(trans_m)},
    }
    (folder / "sweep.json").write_text(json.dumps(meta))
    for level, t in trans_m.items():
        table = _table([f"0000/{i:06d}" for i in range(4)], np.full(4, t), np.zeros(4))
        table["seconds"] = 0.01
        path = result_path(folder, "real", "dilate", level, "net-seed1")
        path.parent.mkdir(parents=True, exist_ok=True)
        table.to_csv(path, index=False)
    return folder


def test_stress_sweeps_are_matched_to_runs_by_their_folder(synthesis, tmp_path):
    folders = {"seed1-aaaa": ("p", "none", 1), "seed1-bbbb": ("p", "bleed 1", 1)}
    plain = _sweep(tmp_path / "plain", "runs/shared-0/p/seed1-aaaa/model.pt", {0: 0.004, 2: 0.02})
    bled = _sweep(tmp_path / "bled", "runs/shared-0/p/seed1-bbbb/model.pt", {0: 0.005, 2: 0.008})
    rows = synthesis.stress_rows([plain, bled], folders, "dilate")
    assert set(zip(rows["setting"], rows["seed"], strict=True)) == {("none", 1), ("bleed 1", 1)}
    text = "\n".join(synthesis.stress_markdown(rows, "dilate"))
    assert "## p: under dilate, bleed 1 against none (seeds 1" in text
    assert "| real | 2 | 20.0 -> 8.0 | 20.0 -> 8.0 | 0.0 -> 100.0 |" in text
    other = _sweep(tmp_path / "other", "runs/shared-0/p/seed1-cccc/model.pt", {0: 0.004})
    with pytest.raises(ValueError, match="none of the runs found"):
        synthesis.stress_rows([other], folders, "dilate")
    # a run's checkpoint downloaded to a temporary folder: matched by the run id kept
    folders["f00d"] = ("p", "bleed 1", 2)
    copy = _sweep(tmp_path / "copy", "/tmp/cloudpose-x/model.pt", {0: 0.004}, run_id="f00d")
    rows = synthesis.stress_rows([copy], folders, "dilate")
    assert set(zip(rows["setting"], rows["seed"], strict=True)) == {("bleed 1", 2)}


def test_stress_summaries_read_back_from_their_csv(synthesis, tmp_path):
    """The curves of ``*_stress.csv`` render as the sweeps they came from; a sweep given again
    replaces its run's rows; a CSV of another kind is refused."""
    folders = {"seed1-aaaa": ("p", "none", 1), "seed1-bbbb": ("p", "bleed 1", 1)}
    plain = _sweep(tmp_path / "plain", "runs/shared-0/p/seed1-aaaa/model.pt", {0: 0.004, 2: 0.02})
    bled = _sweep(tmp_path / "bled", "runs/shared-0/p/seed1-bbbb/model.pt", {0: 0.005, 2: 0.008})
    rows = synthesis.stress_rows([plain, bled], folders, "dilate")
    csv = tmp_path / "x_stress.csv"
    rows.to_csv(csv, index=False, float_format="%.5f")
    back = synthesis.merge_stress([pd.read_csv(csv)], pd.DataFrame(), "dilate")
    assert synthesis.stress_markdown(back, "dilate") == synthesis.stress_markdown(rows, "dilate")
    again = _sweep(tmp_path / "again", "runs/shared-0/p/seed1-bbbb/model.pt", {2: 0.004})
    merged = synthesis.merge_stress(
        [pd.read_csv(csv)], synthesis.stress_rows([again], folders, "dilate"), "dilate"
    )
    assert len(merged) == len(rows)
    text = "\n".join(synthesis.stress_markdown(merged, "dilate"))
    assert "| real | 2 | 20.0 -> 4.0 |" in text
    assert synthesis.merge_stress([pd.read_csv(csv)], pd.DataFrame(), "erode").empty
    with pytest.raises(ValueError, match="lacks the columns"):
        synthesis.merge_stress([pd.DataFrame({"level": [0.0]})], pd.DataFrame(), "dilate")


def test_one_seed_still_has_an_instance_interval(synthesis):
    runs = {"none": {1: _runs(8, 0.005, 0.02, 1)}, "bleed 1": {1: _runs(8, 0.005, 0.005, 1)}}
    table = synthesis.measure("p", runs, replicates=200)
    trans = table[(table["figure"] == "translation < 1 cm") & (table["set"].str.startswith("syn"))]
    assert (trans["low"] < trans["difference"]).all() and (trans["high"] >= 50.0).all()
