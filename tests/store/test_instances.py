"""Instance tables as Parquet: rotations as float32 unit quaternions, byte stream split."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from scipy.spatial.transform import Rotation

from cloudpose.geometry.rigid import rotation_error_deg
from cloudpose.store import instances

ROWS = 64


def _float32_rotations(seed: int) -> np.ndarray:
    """(ROWS, 3, 3) float32 matrices as a float32 network gives them: rotations orthonormal
    to ~1e-6 only (Gram-Schmidt in float32 of noisy columns)."""
    rng = np.random.default_rng(seed)
    R = Rotation.random(ROWS, random_state=seed).as_matrix()
    R = (R + rng.normal(scale=1e-3, size=R.shape)).astype(np.float32)
    a, b = R[..., 0], R[..., 1]
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b - (a * b).sum(-1, keepdims=True) * a
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    R = np.stack([a, b, np.cross(a, b)], axis=-1).astype(np.float32)
    R[0] = np.eye(3, dtype=np.float32)  # angle 0
    R[1] = np.diag([1.0, -1.0, -1.0]).astype(np.float32)  # angle pi (w = 0)
    return R


def _text(rows: np.ndarray, missing: np.ndarray) -> list:
    return [
        np.nan if m else " ".join(f"{v:.17g}" for v in r.ravel())
        for r, m in zip(rows.astype(np.float64), missing, strict=True)
    ]


def _matrices(column: pd.Series) -> np.ndarray:
    return np.array([np.array(v.split(), dtype=np.float64) for v in column]).reshape(-1, 3, 3)


def _table(seed: int = 0) -> tuple[pd.DataFrame, np.ndarray]:
    R = _float32_rotations(seed)
    missing = np.zeros(ROWS, dtype=bool)
    missing[[3, 10, 11]] = True
    df = pd.DataFrame(
        {
            "frame_id": [f"0000/{i:06d}" for i in range(ROWS)],
            "cls_id": np.arange(ROWS) % 21 + 1,
            "miss": missing,
            "net_rot_err_deg": np.where(missing, np.inf, np.linspace(0, 180, ROWS)),
        }
    )
    df["net_R"] = _text(R.reshape(ROWS, 9), missing)
    df["net_t"] = _text(np.full((ROWS, 3), 0.25, dtype=np.float32), missing)
    return df, R


def test_rotations_are_stored_as_quaternions_and_read_back_as_the_float32_matrices(tmp_path):
    df, R = _table()
    df.to_csv(tmp_path / "t.csv", index=False)
    csv = pd.read_csv(tmp_path / "t.csv")
    instances.write_table(csv, tmp_path / "t.parquet")
    stored = pq.read_table(tmp_path / "t.parquet")
    assert "net_q" in stored.column_names and "net_R" not in stored.column_names
    got = instances.read_table(tmp_path / "t.parquet")
    # every consumer sees the columns (names, order, dtypes) that the CSV gives
    assert list(got.columns) == list(csv.columns)
    assert got.dtypes.to_dict() == csv.dtypes.to_dict()
    assert got["net_R"].isna().tolist() == csv["net_R"].isna().tolist()
    ok = ~df["miss"].to_numpy()
    angle = rotation_error_deg(R[ok].astype(np.float64), _matrices(got["net_R"][ok]))
    assert angle.max() < instances.ROTATION_TOLERANCE_DEG
    np.testing.assert_allclose(_matrices(got["net_R"][ok]), R[ok], rtol=0, atol=2e-6)
    # the quaternions are XYZW (scalar last), w >= 0, as scipy's of the same rotations
    q = np.array([v if v is not None else [np.nan] * 4 for v in stored["net_q"].to_pylist()])
    assert np.isnan(q[~ok]).all()
    want = Rotation.from_matrix(R[ok].astype(np.float64)).as_quat()
    want *= np.where(want[:, 3:] < 0, -1.0, 1.0)
    q_ok = q[ok]
    flip = (q_ok * want).sum(1) < 0  # the rotation by pi has w = 0: either sign is right
    q_ok[flip] *= -1
    np.testing.assert_allclose(q_ok, want, atol=1e-6)
    assert (q[ok][:, 3] >= 0).all()


def test_float_columns_are_byte_stream_split_and_the_others_dictionaries(tmp_path):
    df, _ = _table()
    instances.write_table(df, tmp_path / "t.parquet")
    meta = pq.ParquetFile(tmp_path / "t.parquet").metadata.row_group(0)
    enc = {meta.column(i).path_in_schema: meta.column(i).encodings for i in range(meta.num_columns)}
    for col in ("net_rot_err_deg", "net_q.list.element", "net_t.list.element"):
        assert "BYTE_STREAM_SPLIT" in enc[col], (col, enc[col])
    for col in ("frame_id", "cls_id"):
        assert "RLE_DICTIONARY" in enc[col], (col, enc[col])
    assert meta.column(0).compression == "ZSTD"


def test_a_matrix_column_that_holds_no_rotations_stays_as_its_numbers(tmp_path):
    df, R = _table()
    scaled = R.reshape(ROWS, 9) * np.float32(2.0)
    df["net_R"] = _text(scaled, df["miss"].to_numpy())
    instances.write_table(df, tmp_path / "t.parquet")
    assert "net_R" in pq.read_table(tmp_path / "t.parquet").column_names
    got = instances.read_table(tmp_path / "t.parquet")
    ok = ~df["miss"].to_numpy()
    np.testing.assert_array_equal(_matrices(got["net_R"][ok]), scaled[ok].reshape(-1, 3, 3))
    assert got["net_R"].isna().tolist() == (~ok).tolist()


def test_the_same_table_gives_the_same_bytes_and_a_reread_table_the_same_rotations(tmp_path):
    df, _ = _table(1)
    a = instances.write_table(df, tmp_path / "a.parquet")
    b = instances.write_table(df, tmp_path / "b.parquet")
    assert a.read_bytes() == b.read_bytes()
    # written again from what the reader gives: the same quaternions
    c = instances.write_table(instances.read_table(a), tmp_path / "c.parquet")
    qa = np.array([v or [0.0] * 4 for v in pq.read_table(a)["net_q"].to_pylist()])
    qc = np.array([v or [0.0] * 4 for v in pq.read_table(c)["net_q"].to_pylist()])
    np.testing.assert_allclose(qc, qa, atol=1e-7)


class _RemoteStore:
    """A client of a remote artifact store holding ``files`` (artifact path -> bytes); it
    records the downloads it serves, in order."""

    tracking_uri = "http://tracking.invalid"

    def __init__(self, files: dict[str, bytes]):
        self.files = files
        self.served: list[str] = []

    def download_artifacts(self, run_id: str, rel: str, dst: str) -> str:
        if rel not in self.files:
            raise OSError(f"run {run_id} has no artifact {rel}")
        path = Path(dst) / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(self.files[rel])
        self.served.append(rel)
        return str(path)


def _run(artifact_uri: str):
    return SimpleNamespace(info=SimpleNamespace(run_id="r1", artifact_uri=artifact_uri))


def test_an_instance_table_is_read_from_its_parquet_twin_in_place_or_downloaded(tmp_path):
    df, _ = _table(2)
    local = tmp_path / "artifacts"
    (local / "eval" / "test").mkdir(parents=True)
    parquet = instances.write_table(df, local / "eval" / "test" / "instances.parquet")
    client = SimpleNamespace(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
    # asked by its CSV name, read in place from the Parquet file the run has
    with instances.artifact_file(client, _run(local.as_uri()), "eval/test/instances.csv") as p:
        assert p == parquet
    pd.testing.assert_frame_equal(
        instances.read_artifact_table(client, _run(local.as_uri()), "eval/test/instances.csv"),
        instances.read_table(parquet),
    )
    # a remote store: the Parquet name first, then the CSV one; the download is gone after
    csv = df.to_csv(index=False).encode()
    remote = _RemoteStore({"eval/test/instances.csv": csv})
    with instances.artifact_file(
        remote, _run("mlflow-artifacts:/1/r1"), "eval/test/instances.parquet"
    ) as p:
        assert p.read_bytes() == csv
        fetched = p
    assert remote.served == ["eval/test/instances.csv"]
    assert not fetched.exists()
    # neither name: None where that is allowed, else the store's own error
    with instances.artifact_file(
        _RemoteStore({}), _run("mlflow-artifacts:/1/r1"), "eval/test/instances.csv", missing_ok=True
    ) as p:
        assert p is None
    with pytest.raises(OSError, match=r"instances\.csv"):
        instances.read_artifact_table(
            _RemoteStore({}), _run("mlflow-artifacts:/1/r1"), "eval/test/instances.csv"
        )
    with pytest.raises(FileNotFoundError, match=r"instances\.csv"):
        instances.read_artifact_table(
            client, _run((tmp_path / "none").as_uri()), "eval/test/instances.csv"
        )
