"""The report commands read a preset's committed store when the project's own lacks its runs."""

from __future__ import annotations

import os
import shutil

import pytest

from cloudpose.archive.pack import pack_store
from cloudpose.report.committed import STORES, committed_store, use_committed_store
from tests.conftest import cli


@pytest.fixture
def clone_with_a_committed_store(smoke_run, tmp_path, monkeypatch):
    """A folder like a fresh clone: no store of its own, the smoke runs packed where a
    committed preset keeps them (reports/smoke/mlflow-store.tar.xz)."""
    from cloudpose.archive.pack import unpack_store
    from cloudpose.evaluate import evaluate

    proj, out = smoke_run
    # a sweep of its own: the session's smoke store, unpacked (artifacts rewritten to point
    # here), its data copied, the run evaluated with ICP as a sweep does
    src = tmp_path / "sweep"
    pack_store(proj, tmp_path / "session.tar.xz", checkpoints=[out.run_id])
    unpack_store(tmp_path / "session.tar.xz", src)
    shutil.copytree(proj / "data", src / "data", symlinks=True)
    monkeypatch.chdir(src)
    evaluate(out.run_id, project_dir=src, progress=False)
    clone = tmp_path / "clone"
    (clone / "reports" / "smoke").mkdir(parents=True)
    pack_store(src, clone / "reports" / "smoke" / "mlflow-store.tar.xz")
    monkeypatch.chdir(clone)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    return clone


@pytest.mark.slow
def test_occlusion_report_renders_from_the_committed_store(clone_with_a_committed_store):
    clone = clone_with_a_committed_store
    try:
        res = cli("occlusion-report", "--preset", "smoke", "--seeds", "1", "--out", "out")
        assert res.exit_code == 0, res.output
        assert "reading the committed store (unpacked from reports/smoke/" in res.output
        # rendered from the committed run, and only the occlusion plot and its table
        assert sorted(p.name for p in (clone / "out").iterdir()) == [
            "occlusion.csv",
            "occlusion.png",
        ], res.output
        assert (clone / STORES / "smoke" / "mlflow.db").is_file()
        assert not (clone / "mlflow.db").exists()  # the project's own store is not made
        # a second call reads the unpacked copy in place
        os.environ.pop("MLFLOW_TRACKING_URI", None)
        res = cli("occlusion-report", "--preset", "smoke", "--seeds", "1", "--out", "out")
        assert res.exit_code == 0 and f"in {STORES}/smoke/;" in res.output, res.output
    finally:
        os.environ.pop("MLFLOW_TRACKING_URI", None)  # the command set it for its process


@pytest.fixture
def clone_with_an_archive(tmp_path):
    """A folder with a committed archive in place (its content is not read by these tests)."""
    (tmp_path / "reports" / "smoke").mkdir(parents=True)
    (tmp_path / "reports" / "smoke" / "mlflow-store.tar.xz").write_bytes(b"")
    return tmp_path


def test_a_named_store_or_one_that_holds_the_runs_is_used_as_it_is(
    clone_with_an_archive, monkeypatch
):
    clone = clone_with_an_archive
    said = []
    (clone / "mlflow.db").write_bytes(b"")  # a store of its own, which lacking() asks about
    assert not use_committed_store("smoke", clone, lambda: False, said.append)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{clone / 'own.db'}")
    assert not use_committed_store("smoke", clone, lambda: True, said.append)
    assert said == [] and not (clone / STORES).exists()
    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    assert not use_committed_store("cpu-online", clone, lambda: True, said.append)  # none here


def test_a_preset_without_a_committed_store_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="commits no store for preset 'smoke'"):
        committed_store("smoke", tmp_path)


def test_an_unpacked_committed_store_is_read_in_place(clone_with_an_archive, monkeypatch):
    """Once unpacked, the store in stores/PRESET is used as it is (the archive, here empty, is
    not opened again)."""
    clone = clone_with_an_archive
    folder = clone / STORES / "smoke"
    folder.mkdir(parents=True)
    (folder / "mlflow.db").write_bytes(b"")
    assert committed_store("smoke", clone) == folder
    said = []
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    try:
        assert use_committed_store("smoke", clone, lambda: True, said.append)
        assert os.environ["MLFLOW_TRACKING_URI"] == f"sqlite:///{(folder / 'mlflow.db').resolve()}"
        assert said and f"in {STORES}/smoke/;" in said[0]
    finally:
        os.environ.pop("MLFLOW_TRACKING_URI", None)


@pytest.mark.slow
def test_mlflow_ui_opens_on_the_committed_sweep(clone_with_a_committed_store, monkeypatch):
    """A fresh clone's `make mlflow-ui`: the default preset's committed runs, unpacked once,
    with the project's own store one switch away."""
    clone = clone_with_a_committed_store
    monkeypatch.setattr("cloudpose.registry.DEFAULT_PRESET", "smoke")
    (clone / "mlflow.db").write_bytes(b"")  # a store of its own (a demo run's), not browsed
    try:
        res = cli("mlflow-ui", "--no-serve", "--port", "5124")
        assert res.exit_code == 0, res.output
        first = res.output.splitlines()[0]
        assert first.startswith(f"store: {STORES}/smoke/mlflow.db (unpacked now from reports/")
        assert "--backend sqlite:///mlflow.db" in first
        assert (clone / STORES / "smoke" / "mlflow.db").stat().st_size > 0
        assert "no cloudpose run" not in res.output and "smoke" in res.output
    finally:
        os.environ.pop("MLFLOW_TRACKING_URI", None)
