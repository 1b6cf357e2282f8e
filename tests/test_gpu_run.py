"""A run trained where MLflow and Open3D are missing, then adopted and finished here
(benchmarks/gpu_run.py), and the compiled synthesis path that needs no Open3D."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks import gpu_run
from tests.conftest import make_project

ROOT = Path(__file__).resolve().parents[1]

# The smoke data trained on line by synthesis version 3 (compiled, no Open3D), tiny epochs.
ONLINE = [
    "data.train_source=online",
    "data.online_version=3",
    "data.online_reuse=1",
    "data.online_workers=0",
    "data.online_epoch_segments=64",
    "train.epochs=2",
]


def test_training_and_compiled_synthesis_import_neither_open3d_nor_mlflow():
    """A GPU machine's image may lack both: training, on-line synthesis version 3 and the
    packaged surfaces import neither (a finder refuses them in a fresh interpreter)."""
    code = textwrap.dedent(
        """
        import sys

        class Refuse:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("open3d", "mlflow"):
                    raise ImportError(f"refused: {name}")

        sys.meta_path.insert(0, Refuse())
        import cloudpose.train.loop, cloudpose.data.synth.online, cloudpose.data.bop
        from cloudpose.data.synth.render import Renderer
        from cloudpose.data.synth.surfaces import load_packaged_models

        V, F = Renderer(load_packaged_models(), surface_version=2)._mesh_arrays(5)
        assert V.dtype == "float64" and F.dtype == "uint32" and len(F) > 1000, (V.shape, F.shape)
        print(sorted(m for m in sys.modules if m.split(".")[0] in ("open3d", "mlflow")))
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("version", [1, 2])
def test_surface_arrays_are_the_meshs(version):
    """The renderer's arrays (read without Open3D) are its Open3D mesh's vertices and triangles."""
    from cloudpose.data.synth.render import Renderer
    from cloudpose.data.synth.surfaces import load_packaged_models

    r = Renderer(load_packaged_models(), surface_version=version)
    for c in (1, 11, 14):
        V, F = r._mesh_arrays(c)
        m = r.mesh(c)
        np.testing.assert_array_equal(V, np.asarray(m.vertices))
        np.testing.assert_array_equal(F, np.asarray(m.triangles, dtype=np.uint32))


def test_split_and_join_restore_the_bytes(tmp_path):
    blob = np.random.default_rng(0).bytes(2 * gpu_run.PART_BYTES + 123)
    path = tmp_path / "last.pt"
    path.write_bytes(blob)
    parts = gpu_run.split(path)
    assert [p.name for p in parts] == ["last.pt.part0", "last.pt.part1", "last.pt.part2"]
    assert all(p.stat().st_size <= gpu_run.PART_BYTES for p in parts)
    path.unlink()
    assert gpu_run.join(tmp_path) == blob


def _model(folder: Path) -> dict[str, torch.Tensor]:
    return torch.load(folder / "model.pt", map_location="cpu", weights_only=False)["model"]


def test_a_run_cut_short_elsewhere_finishes_here_as_one_run(tmp_path, smoke_data, monkeypatch):
    """Trained for 3 of its 8 steps by ``train`` (a stand-in for the GPU machine), adopted and
    trained to its end here: one MLflow run, the machine's epochs and the rest logged, the same
    final weights as the run trained here at once, then evaluated as every run is."""
    from cloudpose.registry import parse_overrides, resolve
    from cloudpose.store import tracking
    from cloudpose.suite.pipeline import train_run

    proj = make_project(tmp_path / "proj", smoke_data, monkeypatch)
    monkeypatch.chdir(proj)
    assert gpu_run.main(["export", "--preset", "smoke", "--out", "val.npz", *_sets()]) == 0
    there = tmp_path / "there"
    args = ["--preset", "smoke", "--seed", "1", "--val", "val.npz", "--out", str(there)]
    assert gpu_run.main(["train", *args, "--max-steps", "3", *_sets()]) == 3
    info = json.loads((there / "train.json").read_text())
    assert (info["finished"], info["steps"], info["total_steps"]) == (False, 3, 8)
    assert not (there / "epochs.jsonl").exists()  # no epoch ended there

    assert (
        gpu_run.main(["adopt", "--preset", "smoke", "--seed", "1", "--from", str(there), *_sets()])
        == 0
    )
    client = tracking.setup(proj)
    (run,) = client.search_runs([e.experiment_id for e in client.search_experiments()])
    assert run.info.status == "FINISHED"
    assert run.data.params["device"] == "cpu, then cpu"
    assert run.data.params["train.machine_steps"] == "3"
    assert [m.step for m in client.get_metric_history(run.info.run_id, "train/loss")] == [1, 2]
    assert "test/ads_auc" in run.data.metrics and "real/ads_auc" in run.data.metrics

    cfg = resolve("shared-0", "smoke", 1, parse_overrides(ONLINE))
    # the run's folder, not its lock file beside it (a directory lists them in any order)
    (folder,) = [p for p in (proj / "runs" / "shared-0" / "smoke").iterdir() if p.is_dir()]
    adopted = _model(folder)
    other = make_project(tmp_path / "other", smoke_data, monkeypatch)
    at_once = _model(train_run(cfg, project_dir=other, progress=False).run_dir)
    for k, v in at_once.items():
        torch.testing.assert_close(adopted[k], v, rtol=1e-4, atol=1e-5, msg=k)


def test_adopt_refuses_another_config(tmp_path):
    (tmp_path / "train.json").write_text(json.dumps({"config": "0123456789abcdef"}))
    with pytest.raises(SystemExit, match="0123456789abcdef"):
        gpu_run.main(["adopt", "--preset", "smoke", "--from", str(tmp_path)])


def _sets() -> list[str]:
    return [a for kv in ONLINE for a in ("--set", kv)]
