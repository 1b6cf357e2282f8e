"""A packed MLflow store unpacks anywhere and its runs' artifacts are read from there."""

from __future__ import annotations

import sqlite3
import tarfile

import pandas as pd
import pytest

from cloudpose import tracking
from cloudpose.store_archive import pack_store, unpack_store
from tests.conftest import cli, one_line_error


@pytest.fixture
def project(tmp_path, monkeypatch):
    """A project with two finished runs, each with an instance table and a checkpoint."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    root = tmp_path / "project"
    client = tracking.setup(root)
    exp = tracking.experiment_id(client, "shared", root)
    for seed in (1, 2):
        run = client.create_run(exp, run_name=f"shared-0/p/seed{seed}")
        src = tmp_path / f"src{seed}"
        (src / "eval" / "test").mkdir(parents=True)
        pd.DataFrame({"frame_id": ["0/1"], "ads": [0.001 * seed]}).to_csv(
            src / "eval" / "test" / "instances.csv", index=False
        )
        (src / "model.pt").write_bytes(b"weights" * 100)
        client.log_artifacts(run.info.run_id, str(src))
        client.set_terminated(run.info.run_id, "FINISHED")
    return root


def _uris(db):
    con = sqlite3.connect(db)
    try:
        return [u for (u,) in con.execute("SELECT artifact_uri FROM runs")]
    finally:
        con.close()


def _tables(root):
    client = tracking.setup(root)
    runs = tracking.find_runs(client)
    return {
        r.info.run_name: tracking.read_csv_artifact(client, r, "eval/test/instances.csv")
        for r in runs
    }


def test_a_packed_store_unpacks_elsewhere_with_its_artifacts(project, tmp_path):
    archive = tmp_path / "store.tar.xz"
    s = pack_store(project, archive, checkpoints=["shared-0/p/seed2"])
    assert (s.runs, s.files, s.checkpoints_kept, s.checkpoints_left_out) == (2, 3, 1, 1)
    with tarfile.open(archive) as tar:
        names = tar.getnames()
        tar.extract("mlflow.db", tmp_path / "peek", filter="data")
    assert sum(n.endswith("model.pt") for n in names) == 1
    # no address of the packing machine inside: relative to the project
    assert all(u.startswith("mlartifacts/shared/") for u in _uris(tmp_path / "peek" / "mlflow.db"))

    into = tmp_path / "elsewhere"
    assert unpack_store(archive, into) == 2
    root_uri = (into.resolve() / "mlartifacts").as_uri()
    assert all(u.startswith(root_uri + "/shared/") for u in _uris(into / "mlflow.db"))
    tables = _tables(into)
    assert sorted(tables) == ["shared-0/p/seed1", "shared-0/p/seed2"]
    assert tables["shared-0/p/seed2"]["ads"].tolist() == [0.002]
    assert len(list(into.rglob("model.pt"))) == 1


def test_an_archive_packed_by_hand_with_absolute_addresses_unpacks_too(project, tmp_path):
    archive = tmp_path / "by-hand.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:  # as `tar -cJf ... .` writes it: ./mlflow.db
        tar.add(project / "mlflow.db", arcname="./mlflow.db")
        tar.add(project / "mlartifacts", arcname="./mlartifacts")
    into = tmp_path / "copy"
    assert unpack_store(archive, into) == 2
    assert _tables(into)["shared-0/p/seed1"]["ads"].tolist() == [0.001]


def test_unpacking_never_replaces_a_store_and_names_a_foreign_archive(project, tmp_path):
    archive = tmp_path / "store.tar.xz"
    pack_store(project, archive)
    with pytest.raises(FileExistsError, match=r"mlflow\.db exists"):
        unpack_store(archive, project)
    foreign = tmp_path / "foreign.tar.xz"
    with tarfile.open(foreign, "w:xz") as tar:
        tar.add(project / "mlflow.db", arcname="mlflow.db")
        tar.add(project / "mlflow.db", arcname="notes/other.db")
    with pytest.raises(ValueError, match=r"'notes/other\.db' is neither"):
        unpack_store(foreign, tmp_path / "x")
    with pytest.raises(ValueError, match="no run with the id or name 'nope'"):
        pack_store(project, tmp_path / "y.tar.xz", checkpoints=["nope"])
    with pytest.raises(FileNotFoundError, match="no MLflow store to pack"):
        pack_store(tmp_path / "empty", tmp_path / "z.tar.xz")


def test_store_commands_pack_and_unpack(project, tmp_path, monkeypatch):
    monkeypatch.chdir(project)
    archive = tmp_path / "cli.tar.xz"
    res = cli("store-pack", str(archive))
    assert res.exit_code == 0, res.output
    assert "2 runs" in res.output and "2 left out" in res.output
    res = cli("store-unpack", str(archive), "--into", str(tmp_path / "there"))
    assert res.exit_code == 0 and "2 runs" in res.output
    one_line_error(cli("store-unpack", str(archive), "--into", str(project)), "mlflow.db exists")
