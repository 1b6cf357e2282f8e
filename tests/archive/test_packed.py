"""Instance tables as the compact store packs them: shared data columns, poses on a grid."""

from __future__ import annotations

import hashlib

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from cloudpose.archive import packed
from cloudpose.store import instances
from tests.conftest import REPO

ROWS = 40


def _table(seed: int, points_offset: int = 0) -> pd.DataFrame:
    """An evaluation's table: the same instances whatever the seed, network and ICP poses
    (ICP a small change of the network's), errors, a miss, a symmetric class."""
    data = np.random.default_rng(0)
    rng = np.random.default_rng(seed)
    miss = np.arange(ROWS) == 3
    cls = data.integers(1, 22, ROWS)
    R = Rotation.random(ROWS, random_state=seed)
    R_icp = Rotation.from_rotvec(rng.normal(scale=0.05, size=(ROWS, 3))) * R
    t = rng.normal(scale=0.3, size=(ROWS, 3)) + np.array([0.0, 0.0, 1.0])
    t_icp = t + rng.normal(scale=0.003, size=(ROWS, 3))
    rot = np.where(miss, np.inf, rng.random(ROWS) * 180)
    sym = np.where(cls % 3 == 0, rot / 2, rot)  # classes without symmetry: the same error

    def text(rows):
        return [
            "" if m else " ".join(f"{v:.17g}" for v in r) for r, m in zip(rows, miss, strict=True)
        ]

    return pd.DataFrame(
        {
            "frame_id": [f"0048/{i // 4:06d}" for i in range(ROWS)],
            "instance": np.arange(ROWS) % 4,
            "cls_id": cls,
            "class": [f"class_{c}" for c in cls],
            "occlusion": np.where(np.arange(ROWS) == 5, np.nan, data.random(ROWS)),
            "points": data.integers(10, 30000, ROWS) + points_offset,
            "miss": miss,
            "net_ads": np.where(miss, np.inf, rng.random(ROWS) * 0.05),
            "net_rot_err_deg": rot,
            "net_R": text(R.as_matrix().reshape(-1, 9).astype(np.float32)),
            "net_t": text(t.astype(np.float32)),
            "net_rot_sym_err_deg": sym,
            "icp_R": text(R_icp.as_matrix().reshape(-1, 9)),
            "icp_t": text(t_icp),
        }
    )


def _arrow(df: pd.DataFrame, tmp_path, name: str = "t"):
    path = tmp_path / f"{name}.parquet"
    instances.write_table(df, path)
    return packed.read(path)


def _same(a, b) -> bool:
    return a.column_names == b.column_names and all(
        packed.same_column(x.combine_chunks().cast(y.type), y)
        for x, y in zip(a.columns, b.columns, strict=True)
    )


def test_a_packed_table_unpacks_to_its_reduced_table_and_reducing_again_changes_nothing(
    tmp_path,
):
    table = _arrow(_table(1), tmp_path)
    reduced = packed.reduce(table)
    shared = packed.shared_table(reduced)
    packed.write(packed.encode(reduced, shared, packed.shared_name(shared)), tmp_path / "p")
    back = packed.decode(packed.read(tmp_path / "p"), shared)
    assert _same(back, reduced)
    assert _same(packed.reduce(back), reduced)
    # the evaluation's form again: read as its CSV reads
    instances.write_arrow(back, tmp_path / "u.parquet")
    got, want = (
        instances.read_table(tmp_path / "u.parquet"),
        instances.read_table(tmp_path / "t.parquet"),
    )
    assert list(got.columns) == list(want.columns)
    for col in ("net_ads", "net_rot_err_deg", "net_rot_sym_err_deg", "occlusion"):
        np.testing.assert_array_equal(got[col], want[col])  # errors exactly (NaN, inf kept)
    assert got["points"].tolist() == want["points"].tolist()


@pytest.mark.parametrize("method", ["net", "icp"])
def test_poses_are_kept_within_the_grid(tmp_path, method):
    df = _table(2)
    table = _arrow(df, tmp_path)
    reduced = packed.reduce(table)
    instances.write_arrow(reduced, tmp_path / "r.parquet")
    got = instances.read_table(tmp_path / "r.parquet")
    miss = df["miss"].to_numpy()
    assert got[f"{method}_R"].isna().tolist() == miss.tolist()

    def poses(col, k):
        return np.array([v.split() for v in col[~miss]], float).reshape(-1, *k)

    R_got, R_want = poses(got[f"{method}_R"], (3, 3)), poses(df[f"{method}_R"], (3, 3))
    angle = Rotation.from_matrix(R_got @ R_want.transpose(0, 2, 1)).magnitude()
    assert np.degrees(angle).max() < packed.ROTATION_STEP_DEG
    t_got, t_want = poses(got[f"{method}_t"], (3,)), poses(df[f"{method}_t"], (3,))
    assert np.abs(t_got - t_want).max() < 0.5e-6 + 1e-7  # whole micrometres (float32)


def test_the_data_columns_are_shared_and_a_column_that_differs_stays_with_its_run(tmp_path):
    first = packed.reduce(_arrow(_table(1), tmp_path, "a"))
    other = packed.reduce(_arrow(_table(3, points_offset=1), tmp_path, "b"))
    assert packed.row_key(first) == packed.row_key(other)
    shared = packed.shared_table(first)
    ref = packed.shared_name(shared)
    assert ref.startswith(f"{packed.SHARED}/") and ref == packed.shared_name(shared)
    a = packed.encode(first, shared, ref)
    b = packed.encode(other, shared, ref)
    assert not set(packed.DATA_COLUMNS) & set(a.column_names)
    assert "points" in b.column_names and "frame_id" not in b.column_names
    assert packed.layout_of(b).shared == ref
    # rotation errors modulo symmetry equal to the plain ones are nulls: fewer values stored
    sym = a.column("net_rot_sym_err_deg")
    assert 0 < sym.null_count < len(sym)
    # ICP's translation is stored as its change from the network's
    assert packed.layout_of(a).difference_of == {"icp_t": "net_t"}
    assert _same(packed.decode(b, shared), other)


def test_a_packed_table_without_its_shared_table_is_refused(tmp_path):
    reduced = packed.reduce(_arrow(_table(1), tmp_path))
    shared = packed.shared_table(reduced)
    table = packed.encode(reduced, shared, packed.shared_name(shared))
    with pytest.raises(ValueError, match="shared table"):
        packed.decode(table, None)


COMMITTED = REPO / "reports" / "cpu-online" / "mlflow-store"
"""A compact store the checkout commits: its index names each file's SHA-256."""

PINNED = (
    "runs/006414627bb14b2290376ce815f98a01/artifacts/eval/real/instances.parquet",
    "027515160ab4c1b47c279526c42fecc72019fafa4f44749c501e12de8c3e36ae",
)
"""A committed packed table and the SHA-256 of its evaluation's form (decoded, written by
``instances.write_arrow``) as the evaluation's own writer wrote it before the compact store's
writer and it became one (issue 63)."""


def _sha256(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_the_one_parquet_writer_writes_the_committed_tables_to_their_bytes(tmp_path):
    """The store's one Parquet writer (``instances.write_arrow``; ``packed.write`` is it with
    brotli) writes a committed packed table read back to the bytes the store's index names, and
    the evaluation's form of one to the bytes it had (:data:`PINNED`): a change of the writer's
    settings (compression, which columns are split or dictionaries, the metadata) shows here.
    With another pyarrow than constraints.txt names the bytes may differ: pin them again only
    for a pyarrow change, and say so."""
    rows = [line.split("\t") for line in (COMMITTED / "index.tsv").read_text().splitlines()[1:]]
    listed = {rel: sha for rel, _, sha in rows}
    tables = [rel for rel in listed if rel.endswith(".parquet")]
    shared = [rel for rel in tables if rel.startswith(f"{packed.SHARED}/")]
    assert shared and PINNED[0] in listed, "the committed store lost the tables this test reads"
    for rel in [*shared, PINNED[0], *[r for r in tables if r not in shared][:2]]:
        packed.write(packed.read(COMMITTED / rel), tmp_path / "again.parquet")
        assert _sha256(tmp_path / "again.parquet") == listed[rel], rel
    table = packed.read(COMMITTED / PINNED[0])
    layout = packed.layout_of(table)
    base = packed.read(COMMITTED / layout.shared) if layout.from_shared else None
    instances.write_arrow(packed.decode(table, base), tmp_path / "instances.parquet")
    assert _sha256(tmp_path / "instances.parquet") == PINNED[1]
