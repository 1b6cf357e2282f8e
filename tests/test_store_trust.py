"""A packed store is trusted only as far as it is checked: an index that does not match its
folder, a damaged checkpoint, a run left RUNNING, an artifact folder already there, a name
that matches no run, data that is missing: each is said in one line, and nothing is lost."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from cloudpose.archive import checkpoints
from cloudpose.archive.compact import INDEX, METRICS_FILE, RUN_FILE, RUNS
from cloudpose.archive.pack import pack_store, unpack_store
from cloudpose.models.stored import FLOAT24
from cloudpose.store import tracking
from cloudpose.store.liveness import KILLED_TAG
from cloudpose.store.rekey import rekey_runs
from cloudpose.store.runs import lock_path
from tests.conftest import cli, one_line_error


def _finished_run(client, exp: str, name: str, src: Path) -> str:
    """A finished run with a metric and two small artifacts (logged from ``src``)."""
    run = client.create_run(exp, run_name=name, tags={"variant": "shared-0", "seed": "1"})
    rid = run.info.run_id
    client.log_metric(rid, "train/loss", 0.5, step=0)
    (src / "eval").mkdir(parents=True)
    (src / "config.json").write_text("{}\n")
    (src / "eval" / "notes.txt").write_text(f"{name}\n")
    client.log_artifacts(rid, str(src))
    client.set_terminated(rid, "FINISHED")
    return rid


@pytest.fixture
def project(tmp_path, empty_store, monkeypatch) -> Path:
    """A project with two finished runs, each with two artifacts."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    root = tmp_path / "project"
    root.mkdir()
    shutil.copy(empty_store, root / tracking.STORE_DB)
    client = tracking.setup(root)
    exp = tracking.experiment_id(client, "shared", root)
    for seed in (1, 2):
        _finished_run(client, exp, f"shared-0/p/seed{seed}", tmp_path / f"src{seed}")
    return root


def _tree(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


def _rows(folder: Path) -> list[str]:
    return (folder / INDEX).read_text().splitlines()


def _write_rows(folder: Path, rows: list[str]) -> None:
    (folder / INDEX).write_text("\n".join(rows) + "\n")


def _row(folder: Path, rel: str) -> str:
    data = (folder / rel).read_bytes()
    return f"{rel}\t{len(data)}\t{hashlib.sha256(data).hexdigest()}"


# -- 1. the index against the folder ------------------------------------------------------


@pytest.mark.parametrize("change", ["row of run.json dropped", "stray file", "record gone"])
def test_an_index_that_does_not_match_its_folder_is_one_line_and_nothing_is_unpacked(
    project, tmp_path, monkeypatch, change
):
    packed = tmp_path / "packed"
    pack_store(project, packed)
    rows = _rows(packed)
    run_file = next(r.split("\t")[0] for r in rows if r.split("\t")[0].endswith(f"/{RUN_FILE}"))
    if change == "row of run.json dropped":  # a hand-merged index after a git conflict
        named = run_file
        _write_rows(packed, [r for r in rows if not r.startswith(f"{run_file}\t")])
    elif change == "stray file":
        named = f"{RUNS}/{run_file.split('/')[1]}/artifacts/stray.txt"
        (packed / named).write_text("not packed\n")
    else:  # the record and its row gone, the run's other files still listed
        named = run_file
        (packed / run_file).unlink()
        _write_rows(packed, [r for r in rows if not r.startswith(f"{run_file}\t")])
    monkeypatch.chdir(tmp_path)
    into = tmp_path / "into"
    res = cli("store-unpack", str(packed), "--into", str(into))
    one_line_error(res, named, str(packed / INDEX), "nothing unpacked")
    assert not into.exists()
    # an existing folder is left as it was
    into.mkdir()
    (into / "keep.txt").write_text("mine\n")
    with pytest.raises((ValueError, FileNotFoundError), match="nothing unpacked"):
        unpack_store(packed, into)
    assert _tree(into) == {"keep.txt": b"mine\n"}


def test_a_listed_file_that_is_missing_names_it_and_the_index(project, tmp_path):
    packed = tmp_path / "packed"
    pack_store(project, packed)
    victim = next(packed.rglob(METRICS_FILE))
    victim.unlink()
    with pytest.raises(FileNotFoundError) as exc:
        unpack_store(packed, tmp_path / "into")
    assert str(victim) in str(exc.value) and str(packed / INDEX) in str(exc.value)
    assert not (tmp_path / "into").exists()


# -- 2. runs left RUNNING --------------------------------------------------------------------


def _hold_lock(path: Path) -> subprocess.Popen:
    """A process that holds the file lock ``path`` (as training holds its run folder's) until
    it is killed; returns once it holds it."""
    code = (
        "import sys, time\nfrom filelock import FileLock\n"
        "lock = FileLock(sys.argv[1])\nlock.acquire()\nprint('held', flush=True)\n"
        "time.sleep(120)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], stdout=subprocess.PIPE)
    assert proc.stdout.readline().strip() == b"held"
    return proc


def test_store_pack_records_a_run_whose_process_was_killed_and_names_a_live_one(
    project, tmp_path, monkeypatch
):
    client = tracking.setup(project)
    exp = tracking.experiment_id(client, "shared", project)
    now = int(time.time() * 1000)
    ids, procs = {}, {}
    for seed in (3, 4):
        folder = project / "runs" / "shared-0" / "p" / f"seed{seed}-k-c"
        folder.mkdir(parents=True)
        run = client.create_run(
            exp,
            run_name=f"shared-0/p/seed{seed}",
            start_time=now - 60_000,
            tags={"variant": "shared-0", "preset": "p", "seed": str(seed), "run_dir": str(folder)},
        )
        ids[seed] = run.info.run_id
        (folder / "run.json").write_text(json.dumps({"run_id": ids[seed]}))  # as training's
        client.log_metric(ids[seed], "train/loss", 0.5, step=7, timestamp=now - 1000)
        procs[seed] = _hold_lock(lock_path(folder))
    try:
        os.kill(procs[3].pid, signal.SIGKILL)  # seed 3's training killed a second ago
        procs[3].wait(timeout=10)
        monkeypatch.chdir(project)
        res = cli("store-pack", str(tmp_path / "packed"))
        assert res.exit_code == 0, res.output
        assert "recorded KILLED: shared-0/p/seed3 (" in res.output
        assert "no process holds its run folder's lock" in res.output
        alive = [line for line in res.output.splitlines() if "shared-0/p/seed4" in line]
        assert len(alive) == 1 and alive[0].startswith("still running: shared-0/p/seed4"), alive
        assert "packed RUNNING" in alive[0] and "step 7" in alive[0]
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
            proc.wait(timeout=10)
    records = {
        rid: json.loads((tmp_path / "packed" / RUNS / rid / RUN_FILE).read_text())
        for rid in ids.values()
    }
    killed, live = records[ids[3]], records[ids[4]]
    assert killed["run"]["status"] == "KILLED" and killed["run"]["end_time"] == now - 1000
    assert "no process holds" in killed["tags"][KILLED_TAG]
    assert live["run"]["status"] == "RUNNING" and KILLED_TAG not in live["tags"]


def test_a_run_whose_folder_lock_is_released_is_dead_at_once_and_a_held_one_never():
    from cloudpose.store.liveness import dead_reason, dead_runs

    now = 100 * 3600 * 1000
    assert dead_reason(now - 1000, now) is None  # a second of silence says nothing
    assert "no process holds its run folder's lock" in dead_reason(
        now - 1000, now, lock_released=True
    )
    assert dead_reason(now - 1000, now, folder_locked=True, lock_released=True) is None
    runs = [(name, "RUNNING", now - 5000, ("v", name)) for name in ("gone", "held", "unknown")]
    dead = dead_runs(
        runs, now, lambda r: now - 1000, lambda r: r == "held", lambda r: r != "unknown"
    )
    assert [(d.run, d.lock_released) for d in dead] == [("gone", True)]
    assert dead_runs(runs, now, lambda r: now - 1000, lambda r: False) == []  # not asked


# -- 3. a damaged packed checkpoint ----------------------------------------------------------


@pytest.mark.parametrize("damage", ["truncated", "not float24 planes"])
def test_a_damaged_float24_checkpoint_that_its_index_row_matches_is_one_line(
    project, tmp_path, monkeypatch, damage
):
    packed = tmp_path / "packed"
    pack_store(project, packed)
    ckpt = {"model": {"w": torch.linspace(-1, 1, 64)}, "config": {}}
    good = checkpoints.to_bytes(checkpoints.encode(ckpt, FLOAT24))
    if damage == "truncated":
        data = good[: len(good) // 2]
    else:  # a float24 entry whose tensor is not three byte planes
        bad = {**ckpt, checkpoints.FORM_KEY: {"form": FLOAT24, "keys": ["w"]}}
        data = checkpoints.to_bytes(bad)
    rid = next((packed / RUNS).iterdir()).name
    rel = f"{RUNS}/{rid}/artifacts/model.f24.pt"
    (packed / rel).write_bytes(data)
    _write_rows(packed, [*_rows(packed), _row(packed, rel)])
    monkeypatch.chdir(tmp_path)
    res = cli("store-unpack", str(packed), "--into", str(tmp_path / "into"))
    one_line_error(res, str(packed / rel), "float24", "nothing unpacked")
    assert not (tmp_path / "into").exists()


# -- 4. a run name that matches no run -------------------------------------------------------


def test_store_pack_checkpoint_of_no_run_names_the_option_and_the_store(
    project, tmp_path, monkeypatch
):
    monkeypatch.chdir(project)
    res = cli("store-pack", str(tmp_path / "packed"), "--checkpoint", "UNKNOWN")
    line = one_line_error(res, "--checkpoint 'UNKNOWN'", str(project / tracking.STORE_DB))
    assert "cloudpose-store-pack-" not in line and "shared-0/p/seed" in line  # a name to give
    assert not (tmp_path / "packed").exists()


# -- 5. unpacking over an artifact folder already there -------------------------------------


def test_unpacking_over_an_artifact_folder_replaces_each_runs_artifacts(project, tmp_path):
    client = tracking.setup(project)
    exp = tracking.experiment_id(client, "shared", project)
    bare = client.create_run(exp, run_name="shared-0/p/report").info.run_id  # no artifacts
    client.set_terminated(bare, "FINISHED")
    packed = tmp_path / "packed"
    pack_store(project, packed)
    into = tmp_path / "into"
    unpack_store(packed, into)
    client = tracking.setup(into)
    folders = {r.info.run_id: into / r.info.artifact_uri for r in tracking.find_runs(client)}
    want = {rid: _tree(folder) for rid, folder in folders.items()}
    assert want[bare] == {} and all(want[rid] for rid in folders if rid != bare)
    first, second = sorted(rid for rid in folders if rid != bare)
    (folders[first] / "stray.txt").write_text("left from before\n")
    (folders[first] / "eval" / "notes.txt").write_text("an older version\n")
    shutil.rmtree(folders[second])  # gone: it comes back
    folders[bare].mkdir(parents=True)
    (folders[bare] / "model.pt").write_text("not this run's\n")
    other = into / "mlartifacts" / "shared" / "not-a-run-of-the-store" / "artifacts"
    other.mkdir(parents=True)
    (other / "kept.txt").write_text("another run's\n")
    (into / tracking.STORE_DB).unlink()

    with pytest.warns(UserWarning, match="2 runs.*replaced"):
        assert unpack_store(packed, into) == 3
    assert {rid: _tree(folder) for rid, folder in folders.items()} == want
    assert _tree(other) == {"kept.txt": b"another run's\n"}  # not a run of the store: left


# -- 6. rekeying without the data -------------------------------------------------------------


def test_rekeying_without_the_data_says_why_it_needs_it(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(FileNotFoundError) as info:
        rekey_runs("smoke", ["0123456789"], tmp_path, dry_run=True)
    said = " ".join(str(info.value).split())
    for needle in ("today's keys", "cloudpose prepare --preset smoke", "not found"):
        assert needle in said, said
    assert list(tmp_path.iterdir()) == []
