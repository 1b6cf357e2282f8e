"""The MLflow store: safe first use under concurrency, a broken store said in one line."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from cloudpose.store import tracking


def test_concurrent_first_use_of_a_new_store(tmp_path, monkeypatch):
    """Four processes open one fresh SQLite store at once; every one of them and a later one
    can use it (without the lock, two concurrent migrations break the store for good)."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    script = textwrap.dedent(
        """
        import sys
        from pathlib import Path
        from cloudpose.store import tracking
        client = tracking.setup(Path(sys.argv[1]))
        tracking.experiment_id(client, "g" + sys.argv[2], Path(sys.argv[1]))
        """
    )
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", script, str(tmp_path), str(i)], stderr=subprocess.PIPE, text=True
        )
        for i in range(4)
    ]
    errors = [p.communicate(timeout=300)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0, 0, 0], errors
    client = tracking.setup(tmp_path)
    names = {e.name for e in client.search_experiments()}
    assert {f"{tracking.EXPERIMENT_PREFIX}g{i}" for i in range(4)} <= names


def test_broken_store_is_one_line_with_the_fix(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    (tmp_path / "mlflow.db").write_bytes(b"this is not a database" * 100)
    with pytest.raises(tracking.StoreError, match=r"cannot be opened.*mv .*mlflow\.db") as info:
        tracking.setup(tmp_path)
    assert "\n" not in str(info.value)


def test_cli_says_a_broken_store_in_one_line(tmp_path):
    (tmp_path / "mlflow.db").write_bytes(b"this is not a database" * 100)
    env = {k: v for k, v in __import__("os").environ.items() if k != "MLFLOW_TRACKING_URI"}
    env["CLOUDPOSE_NO_TCMALLOC"] = "1"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "cloudpose.cli",
            "experiments",
            "--group",
            "shared",
            "--out",
            "log.md",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert out.returncode == 2, out.stderr
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "mlflow.db" in lines[0] and "mv " in lines[0], out.stderr
    assert not any(Path(tmp_path).glob("mlruns"))


def test_a_group_that_is_not_one_plain_name_is_refused(tmp_path):
    """A group names an experiment (``cloudpose-{group}``) and a folder (``mlartifacts/{group}``):
    a path in it would write outside the project folder."""
    client = tracking.setup(tmp_path)
    for bad in ["../../x", "/abs/path", "a/b", "", ".", "..", ".hidden", "-x", "a b", "x" * 101]:
        with pytest.raises(ValueError, match=r"group .*: expected 1-100 letters, digits"):
            tracking.check_name("group", bad)
        with pytest.raises(ValueError, match="group"):
            tracking.experiment_id(client, bad, tmp_path)
    assert [e.name for e in client.search_experiments()] == ["Default"]
    assert not (tmp_path / "mlartifacts").exists()
    for good in ("shared", "my-group_2.1", "G"):
        assert tracking.check_name("group", good) == good


def test_server_command_keeps_its_default_store_in_one_folder(tmp_path):
    from cloudpose.store.tracking import SERVER_FOLDER, server_command

    server = server_command(root=tmp_path, port=5123)
    folder = tmp_path / SERVER_FOLDER
    assert folder.is_dir() and server.backend == f"sqlite:///{folder / 'mlflow.db'}"
    argv = server.argv
    assert argv[argv.index("--backend-store-uri") + 1] == server.backend
    assert argv[argv.index("--artifacts-destination") + 1] == str(folder / "artifacts")
    assert argv[argv.index("--port") + 1] == "5123"
    assert server.env == {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    # a given store and artifact root are used as they are, and no folder is made for them
    other = server_command("postgresql://u:p@db/runs", "s3://bucket/x", root=tmp_path / "elsewhere")
    assert other.backend == "postgresql://u:p@db/runs" and not (tmp_path / "elsewhere").exists()
    with pytest.raises(ValueError, match="SQLAlchemy URI"):
        server_command("runs.db", root=tmp_path)


def test_git_commit_is_the_tree_when_the_process_first_asked(tmp_path):
    """A sweep process trains with the code it imported: later commits do not restamp it."""

    def git(*args):
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    git("init", "-q")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty", "-m", "a")
    first = tracking.git_commit(tmp_path)
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty", "-m", "b")
    assert first != "unknown" and tracking.git_commit(tmp_path) == first


def test_command_line_writes_paths_inside_the_working_folder_relative(tmp_path, monkeypatch):
    """A provenance line names the project's files, not one machine's folders: absolute paths
    under the working folder (bare or as ``--opt=PATH``) are written relative, others as given."""
    monkeypatch.chdir(tmp_path)
    outside = tmp_path.parent / "elsewhere" / "x.md"
    monkeypatch.setattr(
        sys,
        "argv",
        [
            "/usr/bin/cloudpose",
            "report",
            "--out",
            str(tmp_path / "reports" / "a b"),
            f"--readme={tmp_path / 'reports' / 'README.md'}",
            str(outside),
            "--seeds=3",
        ],
    )
    assert tracking.command_line() == (
        f"cloudpose report --out 'reports/a b' --readme=reports/README.md {outside} --seeds=3"
    )
