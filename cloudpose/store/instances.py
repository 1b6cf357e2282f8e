"""Per-instance tables of an evaluation as files: Parquet with float32 columns, CSV read too.

An evaluation logs one row per test instance (``cloudpose.evaluate.instance_table``): ids, the
errors of each method, and each method's pose as numbers joined by spaces (``net_R``: the 9
entries of R row-major, ``net_t``: t in metres; empty for a miss). As CSV text at 17
significant digits such a table is ~0.8 kB a row; :func:`write_table` stores it as Parquet,
about a seventh of that: every float column as float32 and each pose column as a fixed-size
list of float32, all of them byte-stream-split (zstd), and each rotation column (``X_R``, 9
numbers) as the unit quaternion ``X_q`` (4 float32, XYZW: scalar last as in RoMa and scipy,
``w >= 0``), which gives the rotation to ~1e-7 rad as a float32 matrix does. The network
computes in float32, so its errors and translations lose nothing and its rotations stay within
:data:`ROTATION_TOLERANCE_DEG`; ICP's (float64) keep 7 significant digits.

:func:`read_table` reads either form into the same DataFrame as ``pd.read_csv`` of the CSV:
floats as float64, integers as int64, pose columns as space-joined numbers (NaN for a miss;
quaternions back as the 9 entries of their matrix), so every reader of the CSV reads the
Parquet form unchanged. A run's table is ``eval/{name}/instances.parquet`` (:data:`PARQUET`)
or, logged before, ``instances.csv`` (:data:`CSV`); :func:`artifact_names` lists both, the
Parquet one first.
"""

from __future__ import annotations

import contextlib
import json
import math
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from cloudpose.files import CorruptFileError, why
from cloudpose.geometry.rotations import normalize_quat, rotmat_to_unitquat, unitquat_to_rotmat
from cloudpose.store.tracking import download_artifact, metric_key

INSTANCE_COLUMNS = ("frame_id", "instance", "cls_id", "miss", "net_ads")
"""Columns every evaluation's instance table has (:func:`cloudpose.evaluate.instance_table`)."""

PARQUET = "instances.parquet"
"""File name of an instance table as evaluations write it."""

CSV = "instances.csv"
"""File name of an instance table logged as CSV (runs evaluated before :data:`PARQUET`)."""

_COMPRESSION = ("zstd", 9)

ROTATION_TOLERANCE_DEG = 1e-5
"""A rotation column is stored as quaternions only if every rotation read back is within this
angle of the matrix written (and within 1e-5 entry by entry: a rotation to float32
precision); else as its 9 numbers."""

QUATERNIONS_KEY = "cloudpose.unitquat_xyzw"
"""Parquet key-value metadata: JSON ``{"X_q": "X_R", ...}``, the quaternion columns of a table
and the rotation column each stands for."""


def artifact_names(name: str) -> tuple[str, str]:
    """``eval/{name}/instances.parquet`` and ``eval/{name}/instances.csv``: where a run keeps
    its instance table of evaluation ``name``, in the order to look for them."""
    return f"eval/{name}/{PARQUET}", f"eval/{name}/{CSV}"


def twins(rel: str) -> tuple[str, ...]:
    """The artifact paths to try for ``rel``: an instance table's Parquet and CSV names (either
    given), any other path alone."""
    folder, _, base = rel.rpartition("/")
    if base not in (PARQUET, CSV):
        return (rel,)
    pre = f"{folder}/" if folder else ""
    return f"{pre}{PARQUET}", f"{pre}{CSV}"


def _number_lists(values: pd.Series) -> np.ndarray | None:
    """(M, k) float32 of a column of numbers joined by spaces (NaN rows where empty), or None
    when the column is not such (any other text, or rows of differing counts, or k < 2)."""
    text = ["" if not isinstance(v, str) else v.strip() for v in values]
    filled = [t for t in text if t]
    if not filled:
        return None
    counts = {t.count(" ") + 1 for t in filled}
    if len(counts) != 1 or (k := counts.pop()) < 2:
        return None
    try:
        flat = np.array(" ".join(filled).split(), dtype=np.float64)
    except ValueError:
        return None
    if flat.size != k * len(filled):
        return None
    out = np.full((len(text), k), np.nan, dtype=np.float32)
    out[[i for i, t in enumerate(text) if t]] = flat.reshape(-1, k)
    return out


def to_arrow(df: pd.DataFrame):
    """``df`` as an Arrow table: floats float32, integers int32 where they fit, columns of
    space-joined numbers fixed-size float32 lists (null for an empty cell), text as strings;
    no pandas metadata (the bytes depend on the data alone)."""
    arrays, names = [], []
    for col in df.columns:
        s = df[col]
        if pd.api.types.is_bool_dtype(s):
            arr = pa.array(s.to_numpy(dtype=bool))
        elif pd.api.types.is_float_dtype(s):
            arr = pa.array(s.to_numpy(dtype=np.float32))
        elif pd.api.types.is_integer_dtype(s):
            v = s.to_numpy(dtype=np.int64)
            small = v.size == 0 or (v.min() >= -(2**31) and v.max() < 2**31)
            arr = pa.array(v.astype(np.int32) if small else v)
        elif (nums := _number_lists(s)) is not None:
            null = np.isnan(nums).all(axis=1)
            arr = pa.FixedSizeListArray.from_arrays(
                pa.array(np.nan_to_num(nums, nan=0.0).ravel()), nums.shape[1], mask=pa.array(null)
            )
        else:
            arr = pa.array([v if isinstance(v, str) else None for v in s], type=pa.string())
        arrays.append(arr)
        names.append(str(col))
    return pa.Table.from_arrays(arrays, names=names)


def _rotmat_to_quat32(R: np.ndarray) -> np.ndarray:
    """(M, 3, 3) matrices near rotations -> (M, 4) float32 unit quaternions XYZW, ``w >= 0``,
    of their nearest rotations (``U V^T`` of the SVD, in float64: a float32 network's matrix
    is orthonormal to ~1e-6 only, and the quaternion of the matrix as it is may be off by as
    much)."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    d = np.sign(np.linalg.det(U @ Vt))  # -1 for a reflection: the nearest rotation flips
    U[..., :, 2] *= d[..., None]
    q = rotmat_to_unitquat(torch.from_numpy(U @ Vt))
    return q.numpy().astype(np.float32)


def _quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(M, 4) quaternions XYZW (normalised here, in float64) -> (M, 3, 3) float64 rotations."""
    q64 = torch.from_numpy(np.asarray(q, dtype=np.float64))
    return unitquat_to_rotmat(normalize_quat(q64)).numpy()


def _angle_deg(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(M,) angle of ``A^T B`` in degrees from its skew part (accurate near 0, where the
    trace's arccos is not); for (M, 3, 3) matrices that are rotations to float precision."""
    M = np.swapaxes(A, -1, -2) @ B
    v = np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], 1)
    return np.degrees(np.arcsin(np.clip(np.linalg.norm(v, axis=1) / 2, 0.0, 1.0)))


def _quaternion_column(col):
    """A rotation column (fixed-size lists of 9 float32, R row-major, null for a miss) as
    fixed-size lists of 4 float32 (XYZW), or None when some row is not a rotation to float32
    precision (:data:`ROTATION_TOLERANCE_DEG`)."""
    col = col.combine_chunks() if hasattr(col, "combine_chunks") else col
    null = col.is_null().to_numpy(zero_copy_only=False)
    R = np.zeros((len(col), 3, 3), dtype=np.float64)
    R[~null] = col.flatten().to_numpy(zero_copy_only=False).reshape(-1, 3, 3)
    if not np.isfinite(R).all():
        return None
    q = _rotmat_to_quat32(R)
    back = _quat_to_rotmat(q)
    ok = ~null
    if ok.any() and (
        np.abs(back[ok] - R[ok]).max() > 1e-5
        or _angle_deg(R[ok], back[ok]).max() > ROTATION_TOLERANCE_DEG
    ):
        return None
    q[null] = 0.0
    return pa.FixedSizeListArray.from_arrays(pa.array(q.ravel()), 4, mask=pa.array(null))


def _with_quaternions(table) -> tuple[object, dict[str, str]]:
    """``table`` with each rotation column ``X_R`` (9 float32 a row) that holds rotations
    replaced in place by ``X_q`` (:func:`_quaternion_column`); and the names replaced."""
    names = list(table.column_names)
    replaced = {}
    for i, f in enumerate(table.schema):
        quat = f"{f.name[:-2]}_q"
        if not (
            f.name.endswith("_R")
            and pa.types.is_fixed_size_list(f.type)
            and f.type.list_size == 9
            and quat not in names
        ):
            continue
        arr = _quaternion_column(table.column(i))
        if arr is not None:
            table = table.set_column(i, quat, arr)
            replaced[quat] = f.name
    return table, replaced


def write_table(df: pd.DataFrame, path: str | Path) -> Path:
    """Write an instance table to ``path`` as Parquet (:func:`to_arrow`, rotations as
    quaternions; :func:`write_arrow`). The same table gives the same bytes (with one pyarrow
    version)."""
    table, replaced = _with_quaternions(to_arrow(df))
    if replaced:
        table = table.replace_schema_metadata(
            {QUATERNIONS_KEY: json.dumps(replaced, sort_keys=True)}
        )
    return write_arrow(table, path)


def write_arrow(table, path: str | Path, *, compression: tuple[str, int] = _COMPRESSION) -> Path:
    """Write an Arrow table as the store's Parquet: byte stream split for every float column
    and every list column (whatever its values), dictionaries for the others, ``compression``
    (codec, level; default zstd 9); no statistics, no stored schema, the schema's metadata as
    the file's key-value metadata. The one Parquet writer of the store: an instance table
    (quaternion columns named in its metadata, :data:`QUATERNIONS_KEY`) and the compact store's
    packed tables (:func:`cloudpose.archive.packed.write`, brotli) alike. The same table gives
    the same bytes (with one pyarrow version)."""
    meta = {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()}
    table = table.replace_schema_metadata(None)

    def is_list(t) -> bool:
        return pa.types.is_fixed_size_list(t) or pa.types.is_list(t)

    split = [f for f in table.schema if pa.types.is_floating(f.type) or is_list(f.type)]
    not_split = [n for n in table.column_names if n not in {f.name for f in split}]
    with pq.ParquetWriter(
        str(path),
        table.schema,
        compression=compression[0],
        compression_level=compression[1],
        use_dictionary=not_split,
        # a list column's values are its leaf, NAME.list.element
        use_byte_stream_split=[
            f"{f.name}.list.element" if is_list(f.type) else f.name for f in split
        ],
        write_statistics=False,
        store_schema=False,
    ) as writer:
        writer.write_table(table)
        if meta:
            writer.add_key_value_metadata(meta)
    return Path(path)


def _joined(values: np.ndarray, null: np.ndarray) -> list:
    """Rows of (M, k) numbers as space-joined text at 17 significant digits (as
    ``cloudpose.evaluate`` writes a pose), NaN where ``null``."""
    rows = values.astype(np.float64).tolist()
    fmt = " ".join(["%.17g"] * values.shape[1])
    return [np.nan if n else fmt % tuple(r) for r, n in zip(rows, null.tolist(), strict=True)]


def _list_text(arr) -> list:
    """A list column (Parquet reads back a fixed-size list as a list) as :func:`_joined` text:
    every non-null row holds the same count of numbers."""
    null = arr.is_null().to_numpy(zero_copy_only=False)
    flat = arr.flatten().to_numpy(zero_copy_only=False)  # the non-null rows' values
    k = flat.size // max(int((~null).sum()), 1)
    values = np.zeros((len(arr), k), dtype=flat.dtype)
    values[~null] = flat.reshape(-1, k)
    return _joined(values, null)


def _quaternion_text(arr) -> list:
    """A quaternion column (lists of 4, XYZW) as :func:`_joined` text of the 9 entries of each
    rotation matrix, row-major (NaN for a null)."""
    null = arr.is_null().to_numpy(zero_copy_only=False)
    q = np.zeros((len(arr), 4), dtype=np.float64)
    q[~null] = arr.flatten().to_numpy(zero_copy_only=False).reshape(-1, 4)
    q[null] = (0.0, 0.0, 0.0, 1.0)
    return _joined(_quat_to_rotmat(q).reshape(-1, 9), null)


def from_arrow(table) -> pd.DataFrame:
    """The DataFrame ``pd.read_csv`` gives for the same table written as CSV: floats float64,
    integers int64, list columns as space-joined numbers (NaN for a null), each quaternion
    column (:data:`QUATERNIONS_KEY`) as its rotation column."""

    meta = table.schema.metadata or {}
    quats = json.loads(meta.get(QUATERNIONS_KEY.encode(), b"{}"))
    cols, names = {}, []
    for name, col in zip(table.column_names, table.columns, strict=True):
        t = col.type
        if name in quats:
            name = quats[name]
            cols[name] = pd.Series(_quaternion_text(col.combine_chunks()), dtype="str")
        elif pa.types.is_list(t) or pa.types.is_fixed_size_list(t):
            cols[name] = pd.Series(_list_text(col.combine_chunks()), dtype="str")
        elif pa.types.is_floating(t):
            cols[name] = col.to_numpy().astype(np.float64)
        elif pa.types.is_integer(t):
            cols[name] = col.to_numpy().astype(np.int64)
        elif pa.types.is_string(t) or pa.types.is_large_string(t):
            cols[name] = pd.Series(col.to_pylist(), dtype="str")
        else:
            cols[name] = col.to_pandas()
        names.append(name)
    return pd.DataFrame(cols, columns=names)


def read_table(path: str | Path) -> pd.DataFrame:
    """An instance table from ``path``: Parquet (``.parquet``) or CSV (any other name).

    Raises:
        ValueError: the file is not a readable table of its kind (pyarrow's ``ArrowInvalid``,
            pandas' ``ParserError``, ``UnicodeDecodeError``); the caller names the run.
    """
    path = Path(path)
    if path.suffix != ".parquet":
        return pd.read_csv(path)

    return from_arrow(pq.read_table(str(path)))


def same_table(a: str | Path, b: str | Path) -> bool:
    """Whether two Parquet files hold the same table (values and column types), whatever
    pyarrow version wrote each."""
    try:
        return pq.read_table(str(a)).equals(pq.read_table(str(b)))
    except (OSError, ValueError):
        return False


def csv_to_parquet(src: str | Path, dst: str | Path) -> Path:
    """Write the CSV instance table ``src`` as Parquet to ``dst`` (:func:`write_table`)."""
    return write_table(pd.read_csv(src), dst)


@contextlib.contextmanager
def artifact_file(client, run, rel: str, missing_ok: bool = False) -> Iterator[Path | None]:
    """The file of a run's artifact ``rel`` for the block (an instance table's Parquet twin
    where the run has that instead of ``rel``, :func:`twins`): in place in a local store,
    else downloaded into a folder removed after the block
    (:func:`cloudpose.store.tracking.download_artifact`). With ``missing_ok``, None where the
    run has none of the names.

    Raises:
        FileNotFoundError: a local store has no such file (unless ``missing_ok``).
        MlflowException, OSError: a remote store has none (unless ``missing_ok``).
    """
    names = twins(rel)
    with tempfile.TemporaryDirectory() as tmp:
        path = None
        for r in names:
            try:
                path = download_artifact(client, run, r, tmp)
                break
            except Exception:  # not there (FileNotFoundError, MlflowException): the next name
                if r == names[-1] and not missing_ok:
                    raise
        yield path


def read_artifact_table(client, run, rel: str) -> pd.DataFrame:
    """A run's table artifact ``rel`` (CSV, or an instance table in either form: its Parquet
    twin is read where the run has that instead), read in place from a local store,
    downloaded from a remote one (:func:`artifact_file`)."""
    with artifact_file(client, run, rel) as path:
        return read_table(path)


def read_instance_table(
    path: str | Path,
    name: str,
    run_id: str,
    variant: str,
    seed: int,
    preset: str,
    count: float | None = None,
) -> pd.DataFrame:
    """An evaluation's instance table ``eval/{name}/instances.parquet`` or ``.csv`` of a run
    (:func:`read_table`), checked: whole (a CSV ends with a line end, as pandas writes every
    row; a Parquet file is read whole), with the columns an evaluation writes
    (:data:`INSTANCE_COLUMNS`) and, when the run logged its metric ``{name}/count``, as many
    rows.

    Raises:
        CorruptFileError: empty, cut short, unreadable, lacking columns or rows; the message
            names the file, the run and the command that writes the table anew.
    """
    path = Path(path)
    what = f"instance table of run {run_id} ({variant} seed {seed})"

    def damaged(problem: str) -> CorruptFileError:
        if variant.startswith("baseline-"):
            split = "" if name == "test" else f" --split {name}"
            command = (
                f"cloudpose baseline --method {variant.removeprefix('baseline-')} --preset "
                f"{preset} --seed {seed}{split} --rerun"
            )
        else:
            command = f"cloudpose evaluate --run {run_id}" + (" --real" if name == "real" else "")
        return CorruptFileError(
            path, f"{what} {problem}; evaluate the run again to write it anew: {command}"
        )

    raw = path.read_bytes()
    if not raw.strip():
        raise damaged("is empty")
    if path.suffix == ".csv" and not raw.endswith(b"\n"):
        raise damaged("is cut short in its last row")
    try:
        df = read_table(path)
    except (ValueError, OSError, pd.errors.ParserError, UnicodeDecodeError) as e:
        raise damaged(f"is unreadable ({why(e)})") from e
    missing = [c for c in INSTANCE_COLUMNS if c not in df.columns]
    if missing:
        raise damaged(f"lacks the columns {missing}")
    if count is not None and math.isfinite(count) and len(df) != int(count):
        raise damaged(f"has {len(df)} rows, where the run's metric {name}/count has {int(count)}")
    return df


def run_instance_table(client, run, name: str) -> pd.DataFrame:
    """The instance table ``eval/{name}/instances.parquet`` (or ``.csv``) of an MLflow
    ``run``, read in place from a local store or downloaded, and checked
    (:func:`read_instance_table`).

    Raises:
        FileNotFoundError, MlflowException: the run has no such table.
        CorruptFileError: as :func:`read_instance_table`.
    """
    tags = run.data.tags
    args = (
        name,
        run.info.run_id,
        tags.get("variant", "?"),
        int(tags.get("seed", 0)),
        tags.get("preset", "?"),
        run.data.metrics.get(metric_key(name, "count")),
    )
    with artifact_file(client, run, artifact_names(name)[0]) as path:
        return read_instance_table(path, *args)
