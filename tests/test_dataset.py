"""Which dataset a config means and its segments (cloudpose.data.dataset)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cloudpose.config import DataConfig
from cloudpose.data.dataset import (
    data_fingerprint,
    dataset_root,
    folder_segments,
    only_classes,
    prepare_data,
    synthetic_root,
)
from cloudpose.data.layout import open_dataset
from cloudpose.registry import resolve
from tests.conftest import make_project

REAL = Path(__file__).parent / "data" / "ycb_real"


@pytest.fixture
def project(tmp_path, smoke_data, monkeypatch) -> Path:
    return make_project(tmp_path / "proj", smoke_data, monkeypatch)


def test_synthetic_root_names_the_generator_settings(tmp_path):
    base = DataConfig()
    assert synthetic_root(base, tmp_path) == tmp_path / "data" / "synth-seed0-v2"
    other = dataclasses.replace(
        base, synth_seed=3, uniform_rotation=not base.uniform_rotation, noise=False, synth_version=1
    )
    assert synthetic_root(other, tmp_path).name == "synth-seed3-uniform-nonoise"
    assert dataset_root(base, tmp_path) == synthetic_root(base, tmp_path)


def test_a_real_root_is_the_dataset_and_must_exist(tmp_path):
    assert dataset_root(DataConfig(root=str(REAL)), tmp_path) == REAL
    with pytest.raises(FileNotFoundError, match="dataset root not found"):
        dataset_root(DataConfig(root=str(tmp_path / "missing")), tmp_path)


def test_prepare_data_reads_the_rendered_set_and_keys_it(project):
    cfg = resolve("shared-0", "smoke").data
    frames = sorted((project / "data").rglob("*-depth.png"))
    prep = prepare_data(cfg, project, progress=False)
    assert sorted((project / "data").rglob("*-depth.png")) == frames  # nothing rendered again
    assert prep.root == synthetic_root(cfg, project) and prep.cache_dir == prep.root / "cache"
    assert len(prep.train) > 0 and len(prep.test) > 0
    assert set(np.char.partition(prep.test.frame_id.astype(str), "/")[:, 0]) <= {"1000"}
    assert prep.data_key == data_fingerprint(cfg, project) and len(prep.data_key) == 16
    again = prepare_data(cfg, project, progress=False)
    assert (again.train.data_key, again.test.data_key, again.data_key) == (
        prep.train.data_key,
        prep.test.data_key,
        prep.data_key,
    )
    # another segment setting is other data, with another key
    assert (
        data_fingerprint(dataclasses.replace(cfg, n_fps=cfg.n_fps // 2), project) != prep.data_key
    )


def test_only_classes_keeps_the_named_classes(project):
    cfg = resolve("shared-0", "smoke").data
    prep = prepare_data(cfg, project, progress=False)
    names = open_dataset(prep.root).classes
    cls = int(prep.test.cls_id[0])
    sub = only_classes(prep.test, prep.root, (names[cls - 1],))
    assert len(sub) == int(np.sum(prep.test.cls_id == cls)) and set(sub.cls_id.tolist()) == {cls}
    assert only_classes(prep.test, prep.root, ()) is prep.test
    with pytest.raises(ValueError, match="unknown classes"):
        only_classes(prep.test, prep.root, ("999_not_a_class",))
    narrowed = dataclasses.replace(cfg, classes=(names[cls - 1],))
    test = prepare_data(narrowed, project, progress=False).test
    assert set(test.cls_id.tolist()) == {cls}


def test_prepare_data_opens_the_dataset_once_and_passes_it_on(project, monkeypatch):
    import cloudpose.data.dataset as dataset_module
    import cloudpose.data.layout as layout

    opened = []
    real_open = layout.open_dataset

    def counting(root):
        opened.append(Path(root))
        return real_open(root)

    monkeypatch.setattr(layout, "open_dataset", counting)
    monkeypatch.setattr(dataset_module, "open_dataset", counting)
    import cloudpose.data.cache as cache_module

    monkeypatch.setattr(cache_module, "open_dataset", counting)
    cfg = dataclasses.replace(resolve("shared-0", "smoke").data, classes=("006_mustard_bottle",))
    prep = prepare_data(cfg, project, progress=False)
    assert opened == [prep.root]
    assert prep.dataset.root == prep.root and "006_mustard_bottle" in prep.dataset.classes


def test_folder_segments_are_of_the_configured_classes_and_cached_under_the_project(tmp_path):
    cfg = DataConfig(n_fps=64)
    every = folder_segments(REAL, "all", cfg, tmp_path, progress=False)
    assert len(every) == 3 and len(every.data_key) == 20
    assert list((tmp_path / "data" / "cache").glob("*.npz"))
    names = open_dataset(REAL).classes
    one = names[int(every.cls_id[0]) - 1]
    few = folder_segments(REAL, "all", dataclasses.replace(cfg, classes=(one,)), tmp_path, False)
    assert few.cls_id.tolist() == [int(every.cls_id[0])] and few.data_key == every.data_key
