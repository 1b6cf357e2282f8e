"""The compact form of a store: one folder per run, rebuilt into an MLflow store anywhere."""

from __future__ import annotations

import sqlite3

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from cloudpose.archive import compact, packed
from cloudpose.archive.compact import INDEX, METRICS_FILE, RUNS
from cloudpose.archive.pack import pack_store, unpack_store
from cloudpose.report.committed import COMPACT, STORES, committed_archive, use_committed_store
from cloudpose.store import instances, tracking
from tests.conftest import cli, one_line_error

ROWS = 6


def _table(seed: int) -> pd.DataFrame:
    """An instance table as an evaluation writes it: the test set's instances (the same for
    every seed but ``points``, which seed 2 samples otherwise), a miss (infinite errors, empty
    pose), float64 errors, poses as 17-digit text."""
    data = np.random.default_rng(0)
    rng = np.random.default_rng(seed)
    R = Rotation.random(ROWS, random_state=seed).as_matrix()
    t = rng.normal(size=(ROWS, 3))
    miss = np.arange(ROWS) == 2
    points = data.integers(10, 30000, ROWS)
    df = pd.DataFrame(
        {
            "frame_id": [f"0000/{i:06d}" for i in range(ROWS)],
            "instance": np.arange(ROWS),
            "cls_id": data.integers(1, 22, ROWS),
            "class": [f"class_{i}" for i in range(ROWS)],
            "occlusion": data.random(ROWS).astype(np.float32),
            "points": points + (seed == 2),
            "miss": miss,
            "net_ads": np.where(miss, np.inf, rng.random(ROWS) * 0.05),
        }
    )
    df["net_R"] = [
        "" if m else " ".join(f"{v:.17g}" for v in r.ravel()) for r, m in zip(R, miss, strict=True)
    ]
    df["net_t"] = [
        "" if m else " ".join(f"{v:.17g}" for v in x) for x, m in zip(t, miss, strict=True)
    ]
    return df


def _log_run(client, exp: str, name: str, seed: int, src) -> str:
    run = client.create_run(exp, run_name=name, tags={"variant": "shared-0", "seed": str(seed)})
    rid = run.info.run_id
    client.log_param(rid, "train.epochs", "3")
    for step, loss in enumerate((0.9, 0.5, 0.25 + 0.01 * seed)):
        client.log_metric(rid, "train/loss", loss, step=step, timestamp=1000 + step)
    client.log_metric(rid, "test/ads_auc", 0.5 + 0.1 * seed, timestamp=2000)
    client.log_metric(rid, "ads_auc", 0.5 + 0.1 * seed, timestamp=2000)
    (src / "eval" / "test").mkdir(parents=True)
    _table(seed).to_csv(src / "eval" / "test" / instances.CSV, index=False)
    (src / "config.json").write_text(f'{{"seed": {seed}}}\n')
    (src / "model.pt").write_bytes(bytes(range(256)) * 4 * seed)
    client.log_artifacts(rid, str(src))
    client.set_terminated(rid, "FINISHED")
    return rid


@pytest.fixture
def project(tmp_path, monkeypatch):
    """A project with two finished runs: params, tags, a metric history, headline metrics,
    an instance table (CSV, as logged before Parquet) and a checkpoint each."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    root = tmp_path / "project"
    client = tracking.setup(root)
    exp = tracking.experiment_id(client, "shared", root)
    client.set_experiment_tag(exp, "mlflow.note.content", "shared\n\n| a | b |")
    for seed in (1, 2):
        _log_run(client, exp, f"shared-0/p/seed{seed}", seed, tmp_path / f"src{seed}")
    return root


def _dump(db) -> dict[str, list]:
    """Every row a store keeps of its runs, but the machine-dependent artifact addresses."""
    con = sqlite3.connect(db)
    try:
        out = {}
        for table, cols in (
            (
                "runs",
                "run_uuid, name, status, start_time, end_time, lifecycle_stage, experiment_id",
            ),
            ("tags", "*"),
            ("params", "*"),
            ("metrics", "key, value, timestamp, run_uuid, step, is_nan"),
            ("latest_metrics", "key, value, timestamp, step, is_nan, run_uuid"),
            ("experiments", "experiment_id, name, lifecycle_stage, creation_time"),
            ("experiment_tags", "*"),
        ):
            out[table] = sorted(con.execute(f"SELECT {cols} FROM {table}").fetchall(), key=repr)
        return out
    finally:
        con.close()


def _poses(column: pd.Series, k: int) -> np.ndarray:
    return np.array(
        [v.split() if isinstance(v, str) and v else [np.nan] * k for v in column], float
    )


def test_a_compact_store_rebuilds_the_same_runs_and_tables(project, tmp_path):
    out = tmp_path / "reports" / COMPACT
    s = pack_store(project, out, checkpoints=["shared-0/p/seed2"])
    assert (s.runs, s.checkpoints_kept, s.checkpoints_left_out) == (2, 1, 1)
    assert (out / INDEX).is_file() and not list(out.rglob(instances.CSV))
    assert len(list(out.rglob(instances.PARQUET))) == 2
    assert len(list((out / packed.SHARED).iterdir())) == 1  # one test set: its columns once

    into = tmp_path / "elsewhere"
    assert unpack_store(out, into) == 2
    before, after = _dump(project / "mlflow.db"), _dump(into / "mlflow.db")
    for table in before:
        assert after[table] == before[table], table  # ids, params, tags, every metric step
    assert len(list(into.rglob("model.pt"))) == 1

    client = tracking.setup(into)
    runs = {r.info.run_name: r for r in tracking.find_runs(client)}
    assert sorted(runs) == ["shared-0/p/seed1", "shared-0/p/seed2"]
    for name, run in runs.items():
        assert run.info.artifact_uri.startswith("mlartifacts/shared/")  # relative to `into`
        assert [m.value for m in client.get_metric_history(run.info.run_id, "train/loss")][:2] == [
            0.9,
            0.5,
        ]
        seed = int(name[-1])
        want = _table(seed)
        got = instances.read_artifact_table(client, run, "eval/test/instances.csv")  # the twin
        assert list(got.columns) == list(want.columns)
        pd.testing.assert_series_equal(got["frame_id"], want["frame_id"], check_dtype=False)
        assert got["miss"].tolist() == want["miss"].tolist()
        assert (got["points"].to_numpy() == want["points"].to_numpy()).all()
        np.testing.assert_allclose(got["net_ads"], want["net_ads"], rtol=1e-7)  # inf kept
        np.testing.assert_allclose(got["occlusion"], want["occlusion"], rtol=0)
        assert got["net_R"].isna().tolist() == want["miss"].tolist()
        R_got = _poses(got["net_R"], 9)[~want["miss"]].reshape(-1, 3, 3)
        R_want = _poses(want["net_R"], 9)[~want["miss"]].reshape(-1, 3, 3)
        angle = Rotation.from_matrix(R_got @ R_want.transpose(0, 2, 1)).magnitude()
        assert np.degrees(angle.max()) < packed.ROTATION_STEP_DEG  # poses on the store's grid
        np.testing.assert_allclose(
            _poses(got["net_t"], 3), _poses(want["net_t"], 3), rtol=0, atol=0.6e-6
        )


def test_an_instance_table_reads_back_as_its_csv_reads(tmp_path):
    df = _table(3)
    df.to_csv(tmp_path / "t.csv", index=False)
    csv = pd.read_csv(tmp_path / "t.csv")
    instances.write_table(df, tmp_path / "t.parquet")
    got = instances.read_table(tmp_path / "t.parquet")
    assert got.dtypes.to_dict() == csv.dtypes.to_dict()
    assert got["net_R"].isna().tolist() == csv["net_R"].isna().tolist()
    np.testing.assert_allclose(got["net_ads"], csv["net_ads"], rtol=1e-7)
    # a table read from CSV packs to the same bytes as the one the evaluation made
    instances.write_table(csv, tmp_path / "from-csv.parquet")
    assert (tmp_path / "from-csv.parquet").read_bytes() == (tmp_path / "t.parquet").read_bytes()


def test_a_repack_rewrites_only_what_changed_and_a_new_run_adds_its_own_files(project, tmp_path):
    out = tmp_path / COMPACT
    pack_store(project, out)
    first = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(FileExistsError, match="--force"):
        pack_store(project, out)
    client = tracking.setup(project)
    exp = tracking.experiment_id(client, "shared", project)
    new = _log_run(client, exp, "shared-0/p/seed3", 3, tmp_path / "src3")
    pack_store(project, out, force=True)
    second = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    changed = {p for p in first if second.get(p) != first[p]}
    added = set(second) - set(first)
    assert changed == {out.joinpath(INDEX).relative_to(out)}  # nothing of the old runs
    assert added and all(p.parts[:2] == (RUNS, new) for p in added)
    assert unpack_store(out, tmp_path / "again") == 3


def test_an_update_keeps_the_checkpoints_the_folder_held_unless_one_is_dropped(project, tmp_path):
    """Repacking a compact folder without naming its checkpoints again keeps them (a repack
    that adds a run must not lose the shipped network's); --drop-checkpoint is how one goes."""
    out = tmp_path / COMPACT
    pack_store(project, out, checkpoints=["shared-0/p/seed2"])
    seed2 = {p.parts[-3] for p in out.rglob("*.pt")}
    assert len(seed2) == 1
    s = pack_store(project, out, force=True)
    assert (s.checkpoints_kept, s.held) == (1, tuple(seed2))
    assert {p.parts[-3] for p in out.rglob("*.pt")} == seed2
    with pytest.raises(ValueError, match="--drop-checkpoint 'shared-0/p/seed9': no run"):
        pack_store(project, out, force=True, drop_checkpoints=["shared-0/p/seed9"])
    with pytest.raises(ValueError, match="both name run"):
        pack_store(project, out, ["shared-0/p/seed2"], True, drop_checkpoints=["shared-0/p/seed2"])
    assert {p.parts[-3] for p in out.rglob("*.pt")} == seed2  # a refused call changes nothing
    s = pack_store(project, out, force=True, drop_checkpoints=["shared-0/p/seed2"])
    assert (s.checkpoints_kept, s.held) == (0, ())
    assert not list(out.rglob("*.pt"))


@pytest.mark.parametrize("damage", ["missing", "damaged"])
def test_a_missing_or_damaged_file_is_named_in_one_line_and_nothing_is_unpacked(
    project, tmp_path, monkeypatch, damage
):
    out = tmp_path / COMPACT
    pack_store(project, out)
    if damage == "missing":
        victim = next(out.rglob(METRICS_FILE))
        victim.unlink()
    else:
        victim = next(out.rglob(instances.PARQUET))
        raw = bytearray(victim.read_bytes())
        raw[len(raw) // 2] ^= 0xFF
        victim.write_bytes(bytes(raw))
    monkeypatch.chdir(tmp_path)
    res = cli("store-unpack", str(out), "--into", "copy")
    line = one_line_error(res, str(victim), damage)
    assert "git checkout --" in line
    if damage == "damaged":  # same size: the checksum is what differs, and it says so
        assert "SHA-256" in line and "same size" in line and "bytes, not the" not in line
    assert not (tmp_path / "copy").exists()


def test_a_folder_that_is_no_compact_store_is_refused_in_one_line(tmp_path, monkeypatch):
    (tmp_path / "empty").mkdir()
    monkeypatch.chdir(tmp_path)
    one_line_error(cli("store-unpack", "empty", "--into", "copy"), "index.tsv", "missing")
    (tmp_path / "empty" / INDEX).write_text("hello\n")
    one_line_error(cli("store-unpack", "empty", "--into", "copy"), "index.tsv", "'hello'")
    assert not (tmp_path / "copy").exists()


def test_the_committed_compact_store_is_read_before_an_archive_and_a_change_is_noted(
    project, tmp_path, monkeypatch
):
    clone = tmp_path / "clone"
    (clone / "reports" / "p").mkdir(parents=True)
    (clone / "reports" / "p" / "mlflow-store.tar.xz").write_bytes(b"")  # not opened
    pack_store(project, clone / "reports" / "p" / COMPACT)
    assert committed_archive("p", clone) == clone / "reports" / "p" / COMPACT
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    said = []
    try:
        assert use_committed_store("p", clone, lambda: True, said.append)
        assert f"unpacked from reports/p/{COMPACT} into {STORES}/p/" in said[0]
        assert len(tracking.find_runs(tracking.setup(clone))) == 2
        # a pull brings a new round: the copy in stores/ is read as it is, and said to be old
        client = tracking.setup(project)
        exp = tracking.experiment_id(client, "shared", project)
        _log_run(client, exp, "shared-0/p/seed3", 3, tmp_path / "src3")
        pack_store(project, clone / "reports" / "p" / COMPACT, force=True)
        monkeypatch.delenv("MLFLOW_TRACKING_URI")
        said.clear()
        assert use_committed_store("p", clone, lambda: True, said.append)
        assert len(said) == 2 and f"remove {STORES}/p/" in said[1]
    finally:
        monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)


def test_a_store_of_the_first_compact_form_still_unpacks(project, tmp_path):
    """Form 1 kept each instance table in the evaluation's form and had no shared tables."""
    out = tmp_path / COMPACT
    pack_store(project, out)
    for path in out.rglob(instances.PARQUET):
        table = packed.read(path)
        layout = packed.layout_of(table)
        base = packed.read(out / layout.shared) if layout.from_shared else None
        instances.write_arrow(packed.decode(table, base), path)
    for f in (out / packed.SHARED).iterdir():
        f.unlink()
    (out / packed.SHARED).rmdir()
    files = sorted(
        p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file() and p.name != INDEX
    )
    lines = [compact.FORMATS[0]]
    lines += [f"{f}\t{(out / f).stat().st_size}\t{compact._sha256(out / f)}" for f in files]
    (out / INDEX).write_text("\n".join(lines) + "\n")

    into = tmp_path / "old"
    assert unpack_store(out, into) == 2
    client = tracking.setup(into)
    for run in tracking.find_runs(client):
        got = instances.read_artifact_table(client, run, "eval/test/instances.parquet")
        want = _table(int(run.info.run_name[-1]))
        assert got["points"].tolist() == want["points"].tolist()
        np.testing.assert_allclose(got["net_ads"], want["net_ads"], rtol=1e-7)
