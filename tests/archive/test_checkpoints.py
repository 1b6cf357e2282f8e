"""Checkpoints in a compact store: fewer bytes only where the poses stay, float32 when unpacked,
the same files when packed again; and what a pack records of runs (relative run folders, dead
runs KILLED)."""

from __future__ import annotations

import dataclasses
import json
import sqlite3
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from cloudpose.archive import checkpoints
from cloudpose.archive import pack as store_archive
from cloudpose.archive.checkpoints import FLOAT32, FORM_KEY, PoseCheck
from cloudpose.archive.compact import INDEX, RUNS
from cloudpose.archive.pack import pack_store, unpack_store
from cloudpose.data.segment_set import SegmentSet
from cloudpose.models.stored import FLOAT16, FLOAT24
from cloudpose.store import tracking
from tests.store.segments import segment_set


def _config():
    from cloudpose.registry import resolve

    cfg = resolve("shared-0", "smoke")
    model = dataclasses.replace(cfg.model, point_mlp=(8, 8, 8, 8, 16), head=(16, 8))
    return dataclasses.replace(cfg, model=model)


def _checkpoint(seed: int = 0, scale: float = 1.0) -> dict:
    """A tiny shared-0 network's checkpoint (random weights, trained BatchNorm statistics);
    ``scale`` multiplies the last layer of both heads (a network with huge outputs)."""
    from cloudpose.models import build_model

    cfg = _config()
    torch.manual_seed(seed)
    state = build_model(cfg.model).state_dict()
    for key, value in state.items():
        if key.endswith("running_var"):
            state[key] = torch.rand_like(value) + 0.5
        elif key.endswith("running_mean"):
            state[key] = torch.randn_like(value) * 0.1
        elif key.endswith("num_batches_tracked"):
            state[key] = torch.tensor(1000)
    last = max(int(k.split(".")[2]) for k in state if ".head." in k)
    for key in state:
        if f".head.{last}." in key:
            state[key] = state[key] * scale
    return {"model": state, "config": cfg.to_dict()}


def _segments(n: int = 16) -> SegmentSet:
    cfg = _config()
    rng = np.random.default_rng(0)
    pts = rng.normal(scale=0.03, size=(n, cfg.data.n_fps, 3)).astype(np.float32)
    pts[..., 2] += 0.8
    return segment_set(pts, np.arange(n) % 21 + 1)


@pytest.fixture(scope="module")
def check():
    return PoseCheck(segments=_segments(), name="noise")


def _save(ckpt: dict, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(checkpoints.to_bytes(ckpt))
    return path


@pytest.mark.parametrize("form", [FLOAT16, FLOAT24])
def test_a_round_trip_keeps_keys_and_dtypes_and_rounds_once(form):
    ckpt = _checkpoint()
    ckpt["model"]["extra.double"] = torch.randn(3, dtype=torch.float64)
    packed = checkpoints.encode(ckpt, form)
    back = checkpoints.decode(packed)
    assert list(back) == list(ckpt) and list(back["model"]) == list(ckpt["model"])
    assert back["config"] == ckpt["config"]
    for key, value in ckpt["model"].items():
        got = back["model"][key]
        assert got.dtype == value.dtype and got.shape == value.shape, key
        if value.dtype != torch.float32:
            assert torch.equal(got, value), key  # integer buffers, float64: as they were
            assert torch.equal(packed["model"][key], value), key
        else:
            np.testing.assert_allclose(got, value, rtol=2**-11 if form == FLOAT16 else 2**-16)
    floats = {packed["model"][k].dtype for k in packed[FORM_KEY]["keys"]}
    assert floats == {torch.float16 if form == FLOAT16 else torch.uint8}
    again = checkpoints.round_trip(back, form)  # rounding what was rounded changes nothing
    assert checkpoints.state_digest(again) == checkpoints.state_digest(back)
    assert checkpoints.to_bytes(checkpoints.encode(back, form)) == checkpoints.to_bytes(packed)


def test_float24_rounds_to_nearest_and_keeps_what_is_not_finite():
    x = torch.tensor([1.0, 1.0 + 2**-16, 1.0 + 2**-17, -3.5, 0.0, float("inf"), 2**-140])
    back = checkpoints.decode(checkpoints.encode({"model": {"w": x}, "config": {}}, FLOAT24))
    got = back["model"]["w"]
    assert got[0] == 1.0 and got[3] == -3.5 and got[4] == 0.0 and torch.isinf(got[5])
    assert got[1] == 1.0 + 2**-15  # 15 mantissa bits: half a step up rounds up
    assert got[2] == 1.0
    assert abs(got[6] - x[6]) <= 2**-148  # a subnormal keeps its high bits


def test_the_first_form_within_the_tolerances_is_chosen(check, monkeypatch):
    ckpt = _checkpoint()
    form, changes, n = checkpoints.choose_form(ckpt, check)
    assert n == 16 and form in (FLOAT16, FLOAT24, FLOAT32)
    tried = list(changes)
    assert tried == list(checkpoints.REDUCED)[: len(tried)]
    assert all(not checkpoints.within(c) for c in list(changes.values())[:-1])
    assert checkpoints.within(changes[form]) if form != FLOAT32 else True
    monkeypatch.setattr(checkpoints, "TOLERANCE_DEG", 180.0)
    monkeypatch.setattr(checkpoints, "TOLERANCE_MM", 1e9)
    assert checkpoints.choose_form(ckpt, check)[0] == FLOAT16


def test_poses_that_move_too_much_keep_the_checkpoint_float32(check, monkeypatch, tmp_path):
    """A network whose heads end in huge weights moves its poses under any rounding; so does
    every network at a tolerance of 0: it stays float32, with the changes recorded."""
    src = _save(_checkpoint(scale=1e4), tmp_path / "huge" / "model.pt")
    out = checkpoints.pack_checkpoint(src, tmp_path / "out", check, shipped=set())
    assert out.record["stored_as"] == FLOAT32 and out.file == "model.pt"
    assert (tmp_path / "out" / "model.pt").read_bytes() == src.read_bytes()
    for change in out.record["max_pose_change"].values():
        assert change["rot_deg"] > 0.01 or change["trans_mm"] > 0.01
    monkeypatch.setattr(checkpoints, "TOLERANCE_DEG", 0.0)
    monkeypatch.setattr(checkpoints, "TOLERANCE_MM", 0.0)
    form, changes, _ = checkpoints.choose_form(_checkpoint(), check)
    assert form == FLOAT32 and set(changes) == {FLOAT16, FLOAT24}
    assert all(c[1] > 0 for c in changes.values())  # float16 and float24 move translations


def test_pack_unpack_and_pack_again_write_the_same_files(check, monkeypatch, tmp_path):
    monkeypatch.setattr(checkpoints, "TOLERANCE_MM", 1e9)
    monkeypatch.setattr(checkpoints, "TOLERANCE_DEG", 180.0)
    ckpt = _checkpoint()
    src = _save(ckpt, tmp_path / "run" / "model.pt")
    first = checkpoints.pack_checkpoint(src, tmp_path / "packed", check, shipped=set())
    assert first.file == "model.fp16.pt" and first.record["stored_as"] == FLOAT16
    assert not (tmp_path / "packed" / "model.pt").exists()
    record = json.loads((tmp_path / "packed" / "model.precision.json").read_text())
    assert record == first.record and record["check_set"] == {"frames": "noise", "segments": 16}
    change = record["max_pose_change"][FLOAT16]
    assert change["rot_deg"] >= 0 and change["trans_mm"] >= 0

    unpacked = tmp_path / "unpacked"
    unpacked.mkdir()
    target = checkpoints.unpack_checkpoint(tmp_path / "packed" / first.file, unpacked / "model.pt")
    (unpacked / "model.precision.json").write_bytes(
        (tmp_path / "packed" / "model.precision.json").read_bytes()
    )
    back = torch.load(target, weights_only=True)
    assert list(back) == list(ckpt) and FORM_KEY not in back
    assert {k: v.dtype for k, v in back["model"].items()} == {
        k: v.dtype for k, v in ckpt["model"].items()
    }
    assert checkpoints.state_digest(back) == record["unpacked_digest"]
    from cloudpose.infer import load_checkpoint

    load_checkpoint(target)  # every reader's way in

    class NoCheck(PoseCheck):
        def poses(self, ckpt):
            raise AssertionError("a checkpoint its record describes is not checked again")

    again = checkpoints.pack_checkpoint(target, tmp_path / "again", NoCheck(), shipped=set())
    for name in ("model.fp16.pt", "model.precision.json"):
        assert (tmp_path / "again" / name).read_bytes() == (tmp_path / "packed" / name).read_bytes()
    assert again.record == first.record


def test_a_shipped_network_and_a_foreign_file_are_copied_as_they_are(check, tmp_path):
    src = _save(_checkpoint(), tmp_path / "run" / "model.pt")
    sha = checkpoints._sha256(src.read_bytes())
    out = checkpoints.pack_checkpoint(src, tmp_path / "a", check, shipped={sha})
    assert out.record is None and sorted(p.name for p in (tmp_path / "a").iterdir()) == ["model.pt"]
    assert (tmp_path / "a" / "model.pt").read_bytes() == src.read_bytes()
    foreign = tmp_path / "run2" / "model.pt"
    foreign.parent.mkdir()
    foreign.write_bytes(b"not a checkpoint" * 10)
    out = checkpoints.pack_checkpoint(foreign, tmp_path / "b", check, shipped=set())
    assert out.record is None and (tmp_path / "b" / "model.pt").read_bytes() == foreign.read_bytes()
    assert checkpoints.shipped_digests()  # the package ships one network


# -- a whole store ---------------------------------------------------------------------------

HOUR_MS = 3600 * 1000


def _run(client, exp, root, name, seed, *, status, start_ms, ckpt=None, run_dir=None):
    run = client.create_run(
        exp,
        run_name=name,
        start_time=start_ms,
        tags={"variant": "shared-0", "preset": "p", "seed": str(seed), "config": "c"},
    )
    rid = run.info.run_id
    client.log_metric(rid, "train/loss", 0.5, step=0, timestamp=start_ms + 1000)
    if run_dir is not None:
        client.set_tag(rid, "run_dir", str(run_dir))
    if ckpt is not None:
        src = _save(ckpt, root.parent / f"src-{name.replace('/', '-')}" / "model.pt")
        client.log_artifact(rid, str(src))
    if status != "RUNNING":
        client.set_terminated(rid, status, end_time=start_ms + 2000)
    return rid


@pytest.fixture
def store(tmp_path, monkeypatch, check):
    """A project: a finished run with a checkpoint and an absolute run folder inside the
    project; a run left RUNNING 10 hours ago; a RUNNING run whose folder's lock a live process
    holds; a run started now, RUNNING; a run whose folder is on another machine."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.setattr(store_archive, "PoseCheck", lambda project: check)  # as pack_store calls it
    root = tmp_path / "project"
    client = tracking.setup(root)
    exp = tracking.experiment_id(client, "shared", root)
    now = int(time.time() * 1000)
    locked_dir = root / "runs" / "shared-0" / "p" / "seed3-k-c"
    locked_dir.mkdir(parents=True)
    ids = {
        "finished": _run(
            client,
            exp,
            root,
            "shared-0/p/seed1",
            1,
            status="FINISHED",
            start_ms=now - 20 * HOUR_MS,
            ckpt=_checkpoint(),
            run_dir=root / "runs" / "shared-0" / "p" / "seed1-k-c",
        ),
        "dead": _run(
            client, exp, root, "shared-0/p/seed2", 2, status="RUNNING", start_ms=now - 10 * HOUR_MS
        ),
        "locked": _run(
            client,
            exp,
            root,
            "shared-0/p/seed3",
            3,
            status="RUNNING",
            start_ms=now - 10 * HOUR_MS,
            run_dir=locked_dir,
        ),
        "live": _run(client, exp, root, "shared-0/p/seed4", 4, status="RUNNING", start_ms=now),
        "elsewhere": _run(
            client,
            exp,
            root,
            "shared-0/p/seed5",
            5,
            status="FINISHED",
            start_ms=now - HOUR_MS,
            run_dir="/other/machine/runs/shared-0/p/seed5-k-c",
        ),
    }
    return root, ids, locked_dir


def _records(folder: Path) -> dict[str, dict]:
    return {p.parent.name: json.loads(p.read_text()) for p in (folder / RUNS).glob("*/run.json")}


def _files(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


def test_a_pack_writes_run_folders_relative_and_dead_runs_killed(store, tmp_path):
    from filelock import FileLock

    from cloudpose.store.liveness import KILLED_TAG
    from cloudpose.store.runs import lock_path

    root, ids, locked_dir = store
    with FileLock(str(lock_path(locked_dir))):
        s = pack_store(root, tmp_path / "packed", checkpoints=["shared-0/p/seed1"])
    assert [name for name, _ in s.killed] == ["shared-0/p/seed2"]
    rec = _records(tmp_path / "packed")
    assert rec[ids["finished"]]["tags"]["run_dir"] == "runs/shared-0/p/seed1-k-c"
    assert rec[ids["locked"]]["tags"]["run_dir"] == "runs/shared-0/p/seed3-k-c"
    assert rec[ids["elsewhere"]]["tags"]["run_dir"] == "runs/shared-0/p/seed5-k-c"
    dead = rec[ids["dead"]]
    assert dead["run"]["status"] == "KILLED" and dead["run"]["end_time"] is not None
    assert "nothing logged since" in dead["tags"][KILLED_TAG]
    for alive in ("locked", "live"):
        assert rec[ids[alive]]["run"]["status"] == "RUNNING", alive
        assert KILLED_TAG not in rec[ids[alive]]["tags"]
    assert rec[ids["finished"]]["run"]["status"] == "FINISHED"
    exps = json.loads((tmp_path / "packed" / "experiments.json").read_text())["experiments"]
    assert all(not Path(e["artifact_location"]).is_absolute() for e in exps)
    # the project's own store is left as it was
    con = sqlite3.connect(root / "mlflow.db")
    status = con.execute("SELECT status FROM runs WHERE run_uuid = ?", (ids["dead"],)).fetchone()
    con.close()
    assert status == ("RUNNING",)


def test_a_packed_store_unpacks_float32_and_packs_again_to_the_same_files(
    store, tmp_path, monkeypatch
):
    root, ids, _ = store
    monkeypatch.setattr(checkpoints, "TOLERANCE_MM", 1e9)
    monkeypatch.setattr(checkpoints, "TOLERANCE_DEG", 180.0)
    packed = tmp_path / "packed"
    s = pack_store(root, packed, checkpoints=["shared-0/p/seed1"])
    assert [(rid, r["stored_as"]) for rid, r in s.checked] == [(ids["finished"], FLOAT16)]
    art = packed / RUNS / ids["finished"] / "artifacts"
    assert sorted(p.name for p in art.iterdir()) == ["model.fp16.pt", "model.precision.json"]
    assert (packed / INDEX).read_text().startswith("# cloudpose MLflow store, compact form 3")

    into = tmp_path / "unpacked"
    unpack_store(packed, into)
    client = tracking.setup(into)
    run = client.get_run(ids["finished"])
    ckpt = tracking.local_artifact(run.info.artifact_uri, "model.pt", client.tracking_uri)
    back = torch.load(ckpt, weights_only=True)
    original = _checkpoint()
    assert {k: v.dtype for k, v in back["model"].items()} == {
        k: v.dtype for k, v in original["model"].items()
    }
    assert checkpoints.state_digest(back) == checkpoints.state_digest(
        checkpoints.round_trip(original, FLOAT16)
    )
    assert client.get_run(ids["dead"]).info.status == "KILLED"

    before = _files(packed)
    again = pack_store(into, packed, checkpoints=["shared-0/p/seed1"], force=True)
    assert _files(packed) == before and not again.killed
    fresh = tmp_path / "fresh"
    pack_store(into, fresh, checkpoints=["shared-0/p/seed1"])
    assert _files(fresh) == before


def test_store_pack_prints_the_form_and_the_runs_it_killed(store, tmp_path, monkeypatch):
    from tests.conftest import cli

    root, ids, _ = store
    monkeypatch.chdir(root)
    res = cli("store-pack", str(tmp_path / "out"), "--checkpoint", "shared-0/p/seed1")
    assert res.exit_code == 0, res.output
    assert "recorded KILLED: shared-0/p/seed2" in res.output
    assert f"checkpoint model.pt of run {ids['finished'][:8]}: stored as" in res.output
    res = cli(
        "store-pack", str(tmp_path / "full"), "--checkpoint", "shared-0/p/seed1", "--full-precision"
    )
    assert res.exit_code == 0, res.output
    art = tmp_path / "full" / RUNS / ids["finished"] / "artifacts"
    assert sorted(p.name for p in art.iterdir()) == ["model.pt"]
