"""A packed MLflow store unpacks anywhere and its runs' artifacts are read from there."""

from __future__ import annotations

import sqlite3
import tarfile

import pandas as pd
import pytest

from cloudpose.archive.pack import pack_store, unpack_store
from cloudpose.store import instances, tracking
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
        r.info.run_name: instances.read_artifact_table(client, r, "eval/test/instances.csv")
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
    assert all(u.startswith("mlartifacts/shared/") for u in _uris(into / "mlflow.db"))
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


def _texts(db) -> list[str]:
    """Every text value of every table of a SQLite database."""
    con = sqlite3.connect(db)
    try:
        out = []
        for (table,) in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'"):
            for row in con.execute(f'SELECT * FROM "{table}"'):
                out += [v for v in row if isinstance(v, str)]
        return out
    finally:
        con.close()


@pytest.mark.parametrize("form", ["store.tar.xz", "compact"])
def test_an_unpacked_store_can_move_and_is_read_from_any_directory(
    project, tmp_path, monkeypatch, form
):
    """Unpacked into one folder, moved to another, read from a third current directory: the
    runs' artifacts (instance table, config, checkpoint, listing) are found under the store's
    folder, a new run's artifacts are written there, and nothing in mlflow.db names the folder
    it was unpacked into."""
    import shutil

    from cloudpose.store.runs import resolve_run

    client = tracking.setup(project)
    run = tracking.newest_run_named(client, "shared-0/p/seed1")
    client.set_tag(run.info.run_id, "run_dir", "/elsewhere/runs/shared-0/p/seed1-abc-def")
    client.log_text(run.info.run_id, '{"seed": 1}', "config.json")
    pack_store(project, tmp_path / form, checkpoints=["shared-0/p/seed1"])
    first = tmp_path / "first-folder"
    unpack_store(tmp_path / form, first)
    assert not [t for t in _texts(first / "mlflow.db") if str(first) in t]
    moved = tmp_path / "moved" / "store"
    moved.parent.mkdir()
    shutil.move(first, moved)
    other = tmp_path / "other-cwd"
    other.mkdir()
    monkeypatch.chdir(other)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{moved / 'mlflow.db'}")
    client = tracking.setup()
    run = tracking.newest_run_named(client, "shared-0/p/seed1")
    assert run.data.tags["run_dir"] == "runs/shared-0/p/seed1-abc-def"
    assert tracking.store_path(run.data.tags["run_dir"], client.tracking_uri) == (
        moved / "runs/shared-0/p/seed1-abc-def"
    )
    table = instances.read_artifact_table(client, run, "eval/test/instances.csv")
    assert table["ads"].tolist() == pytest.approx([0.001], rel=1e-6)
    config = tracking.download_artifact(client, run, "config.json")
    assert config.is_relative_to(moved) and config.read_text() == '{"seed": 1}'
    assert "model.pt" in {f.path for f in client.list_artifacts(run.info.run_id)}
    _, ckpt = resolve_run(client, run.info.run_id, download_to=tmp_path / "dl")
    assert ckpt.read_bytes() == b"weights" * 100
    # a new run of the moved store writes its artifacts under it, not the current directory
    exp = tracking.experiment_id(client, "shared")
    new = client.create_run(exp, run_name="shared-0/p/seed3")
    assert new.info.artifact_uri.startswith("mlartifacts/shared/")
    client.log_text(new.info.run_id, "x", "note.txt")
    assert (moved / new.info.artifact_uri / "note.txt").read_text() == "x"
    assert not list(other.iterdir())
    assert client.download_artifacts(new.info.run_id, "note.txt").endswith("note.txt")


def test_unpacking_never_replaces_a_store_and_names_a_foreign_archive(project, tmp_path):
    archive = tmp_path / "store.tar.xz"
    pack_store(project, archive)
    with pytest.raises(FileExistsError, match=r"mlflow\.db exists"):
        unpack_store(archive, project)
    foreign = tmp_path / "foreign.tar.xz"
    with tarfile.open(foreign, "w:xz") as tar:
        tar.add(project / "mlflow.db", arcname="mlflow.db")
        tar.add(project / "mlflow.db", arcname="notes/other.db")
    with pytest.raises(
        ValueError, match=r"'notes/other\.db' is not mlflow\.db or under mlartifacts/"
    ):
        unpack_store(foreign, tmp_path / "x")
    with pytest.raises(ValueError, match=r"--checkpoint 'nope': no run of .* has that id or name"):
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


def _entries(folder):
    """Every path under ``folder`` (hidden ones too), relative, as strings."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) if folder.exists() else []


def test_an_unpack_stopped_midway_leaves_no_store_and_a_rerun_unpacks(
    project, tmp_path, monkeypatch
):
    """Killed (Ctrl-C, SIGTERM) between extraction and the rewrite of its addresses, an unpack
    leaves no mlflow.db pointing at the source project: the rerun is not refused."""
    from cloudpose.archive import pack as store_archive

    archive = tmp_path / "store.tar.xz"
    pack_store(project, archive)
    rewrite = store_archive._rewrite

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(store_archive, "_rewrite", stopped)
    into = tmp_path / "there"
    with pytest.raises(KeyboardInterrupt):
        unpack_store(archive, into)
    assert not (into / "mlflow.db").exists()
    assert not [e for e in _entries(into) if e.startswith(".")], _entries(into)
    monkeypatch.setattr(store_archive, "_rewrite", rewrite)
    assert unpack_store(archive, into) == 2
    assert all(u.startswith("mlartifacts/shared/") for u in _uris(into / "mlflow.db"))
    assert sorted(_tables(into)) == ["shared-0/p/seed1", "shared-0/p/seed2"]


@pytest.mark.parametrize("kind", ["dotdot", "absolute-link", "outside-link"])
def test_an_archive_reaching_outside_is_refused_in_one_line_and_leaves_nothing(
    project, tmp_path, monkeypatch, kind
):
    import io

    archive = tmp_path / f"{kind}.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:
        tar.add(project / "mlflow.db", arcname="mlflow.db")
        if kind == "dotdot":
            data = b"pwned"
            info = tarfile.TarInfo("mlartifacts/../../evil.txt")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
        else:
            info = tarfile.TarInfo("mlartifacts/shared/link")
            info.type = tarfile.SYMTYPE
            info.linkname = "/etc/passwd" if kind == "absolute-link" else "../../../../outside"
            tar.addfile(info)
    into = tmp_path / "target"
    into.mkdir()
    monkeypatch.chdir(tmp_path)
    line = one_line_error(cli("store-unpack", str(archive), "--into", str(into)), str(archive))
    assert "outside" in line and "nothing unpacked" in line
    assert _entries(into) == []
    assert not (tmp_path / "evil.txt").exists()


def test_a_store_whose_artifacts_lie_outside_mlartifacts_is_packed_with_them(tmp_path, monkeypatch):
    """MLFLOW_TRACKING_URI=sqlite:///.../mlflow.db puts artifacts in MLflow's ./mlruns: the pack
    follows each run's artifact folder, checkpoints included, and the unpacked store has them."""
    root = tmp_path / "proj"
    root.mkdir()
    monkeypatch.chdir(root)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{root / 'mlflow.db'}")
    client = tracking.setup(root)
    exp = tracking.experiment_id(client, "shared", root)
    run = client.create_run(exp, run_name="shared-0/p/seed1")
    src = tmp_path / "src"
    (src / "eval" / "test").mkdir(parents=True)
    pd.DataFrame({"frame_id": ["0/1"], "ads": [0.5]}).to_csv(
        src / "eval" / "test" / "instances.csv", index=False
    )
    (src / "model.pt").write_bytes(b"weights" * 100)
    client.log_artifacts(run.info.run_id, str(src))
    client.set_terminated(run.info.run_id, "FINISHED")
    assert "/mlartifacts/" not in client.get_run(run.info.run_id).info.artifact_uri

    archive = tmp_path / "store.tar.xz"
    s = pack_store(root, archive, checkpoints=["shared-0/p/seed1"])
    assert (s.runs, s.files, s.checkpoints_kept, s.checkpoints_left_out) == (1, 2, 1, 0)
    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    into = tmp_path / "elsewhere"
    assert unpack_store(archive, into) == 1
    assert _tables(into)["shared-0/p/seed1"]["ads"].tolist() == [0.5]
    assert len(list(into.rglob("model.pt"))) == 1


def test_a_store_whose_artifacts_it_cannot_read_is_refused(project, tmp_path):
    con = sqlite3.connect(project / "mlflow.db")
    with con:
        con.execute("UPDATE runs SET artifact_uri = 's3://bucket/x/artifacts'")
    con.close()
    with pytest.raises(ValueError, match=r"s3://bucket/x/artifacts.*cannot"):
        pack_store(project, tmp_path / "s.tar.xz")
    assert not (tmp_path / "s.tar.xz").exists()


def test_packing_never_replaces_an_archive_without_force(project, tmp_path, monkeypatch):
    archive = tmp_path / "store.tar.xz"
    archive.write_bytes(b"an older store")
    with pytest.raises(FileExistsError, match=r"store\.tar\.xz exists.*--force"):
        pack_store(project, archive)
    assert archive.read_bytes() == b"an older store"
    monkeypatch.chdir(project)
    one_line_error(cli("store-pack", str(archive)), "exists", "--force")
    assert archive.read_bytes() == b"an older store"
    res = cli("store-pack", str(archive), "--force")
    assert res.exit_code == 0, res.output
    with tarfile.open(archive) as tar:
        assert "mlflow.db" in tar.getnames()


def test_a_pack_stopped_by_sigterm_leaves_no_temporary_file(project, tmp_path):
    """SIGTERM mid-pack: neither the hidden archive beside the target nor the temporary folder
    of the database copy stays behind."""
    import os
    import signal
    import subprocess
    import sys

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    code = (
        "import os, signal, tarfile\n"
        "from pathlib import Path\n"
        "from cloudpose.archive.pack import pack_store\n"
        "add = tarfile.TarFile.add\n"
        "def add_then_stop(self, *a, **k):\n"
        "    add(self, *a, **k)\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "tarfile.TarFile.add = add_then_stop\n"
        f"pack_store(Path({str(project)!r}), Path({str(out / 's.tar.xz')!r}))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env["TMPDIR"] = str(tmp)
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert proc.returncode != 0
    assert proc.returncode != -signal.SIGTERM, "the pack was killed, not stopped"
    assert _entries(out) == [] and _entries(tmp) == []


def test_a_run_whose_artifact_folder_is_gone_is_named(project, tmp_path, monkeypatch):
    import shutil

    client = tracking.setup(project)
    run = tracking.find_runs(client)[0]
    shutil.rmtree(tracking.local_artifact(run.info.artifact_uri, ""))
    monkeypatch.chdir(project)
    res = cli("store-pack", str(tmp_path / "s.tar.xz"))
    assert res.exit_code == 0, res.output
    assert f"1 of 2 runs have no artifact folder (e.g. run {run.info.run_id})" in res.output


def test_what_a_killed_pack_or_unpack_left_is_removed_by_the_next(project, tmp_path):
    """kill -9 runs no clean-up: the next pack or unpack removes what a dead process left."""
    import subprocess

    proc = subprocess.Popen(["true"])
    proc.wait()
    dead = proc.pid
    archive = tmp_path / "s.tar.xz"
    stale_tmp = tmp_path / f".s.tar.xz.{dead}.tmp.tar.xz"
    stale_tmp.write_bytes(b"half an archive")
    pack_store(project, archive)
    assert not stale_tmp.exists() and archive.is_file()
    into = tmp_path / "into"
    stale_dir = into / f".store-unpack-{dead}-abcd"
    (stale_dir / "mlartifacts").mkdir(parents=True)
    assert unpack_store(archive, into) == 2
    assert not stale_dir.exists()


def test_a_full_disk_while_packing_is_one_line(project, tmp_path, monkeypatch):
    import errno

    from cloudpose.archive import pack as store_archive

    def full(path, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(store_archive, "atomic_write", full)
    monkeypatch.chdir(project)
    archive = tmp_path / "s.tar.xz"
    line = one_line_error(cli("store-pack", str(archive)), str(archive), "no space left")
    assert "free there" in line and not archive.exists()


def test_a_full_disk_while_packing_or_unpacking_a_compact_store_names_it(project, tmp_path):
    """Packing into a compact folder and unpacking one say a full disk as the archive does:
    the folder and what to do once space is free."""
    import errno

    from cloudpose.archive import pack as store_archive
    from cloudpose.failures import DiskFullError

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    folder = tmp_path / "compact"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(store_archive, "write_compact", full)
        with pytest.raises(DiskFullError, match=r"writing .*compact.*store-pack .* --force"):
            pack_store(project, folder)
    pack_store(project, folder)
    into = tmp_path / "into"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(store_archive, "extract_compact", full)
        with pytest.raises(DiskFullError, match=r"writing .*into.*unpack again"):
            unpack_store(folder, into)
    assert not into.exists()  # nothing left where the unpack failed
    assert unpack_store(folder, into) == 2
