"""Per-instance tables of an evaluation as files: Parquet with float32 columns, CSV read too.

An evaluation logs one row per test instance (``cloudpose.evaluate.instance_table``): ids, the
errors of each method, and each method's pose as numbers joined by spaces (``net_R``: the 9
entries of R row-major, ``net_t``: t in metres; empty for a miss). As CSV text at 17
significant digits such a table is ~0.8 kB a row; :func:`write_table` stores it as Parquet,
every float column as float32 and each pose column as a fixed-size list of float32 (byte
stream split, zstd), about a fifth of that. The network computes in float32, so its poses and
errors lose nothing; ICP's (float64) keep 7 significant digits.

:func:`read_table` reads either form into the same DataFrame as ``pd.read_csv`` of the CSV:
floats as float64, integers as int64, pose columns as space-joined numbers (NaN for a miss),
so every reader of the CSV reads the Parquet form unchanged. A run's table is
``eval/{name}/instances.parquet`` (:data:`PARQUET`) or, logged before, ``instances.csv``
(:data:`CSV`); :func:`artifact_names` lists both, the Parquet one first.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

PARQUET = "instances.parquet"
"""File name of an instance table as evaluations write it."""

CSV = "instances.csv"
"""File name of an instance table logged as CSV (runs evaluated before :data:`PARQUET`)."""

_COMPRESSION = ("zstd", 9)


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
    import pyarrow as pa

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


def write_table(df: pd.DataFrame, path: str | Path) -> Path:
    """Write an instance table to ``path`` as Parquet (:func:`to_arrow`; byte stream split for
    the float columns, zstd). The same table gives the same bytes (with one pyarrow version)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = to_arrow(df)
    floats = [
        f.name
        for f in table.schema
        if pa.types.is_floating(f.type) or pa.types.is_fixed_size_list(f.type)
    ]
    pq.write_table(
        table,
        str(path),
        compression=_COMPRESSION[0],
        compression_level=_COMPRESSION[1],
        use_dictionary=[n for n in table.column_names if n not in floats],
        use_byte_stream_split=floats,
        write_statistics=False,
        store_schema=False,
    )
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


def from_arrow(table) -> pd.DataFrame:
    """The DataFrame ``pd.read_csv`` gives for the same table written as CSV: floats float64,
    integers int64, list columns as space-joined numbers (NaN for a null)."""
    import pyarrow as pa

    cols = {}
    for name, col in zip(table.column_names, table.columns, strict=True):
        t = col.type
        if pa.types.is_list(t) or pa.types.is_fixed_size_list(t):
            cols[name] = pd.Series(_list_text(col.combine_chunks()), dtype="str")
        elif pa.types.is_floating(t):
            cols[name] = col.to_numpy().astype(np.float64)
        elif pa.types.is_integer(t):
            cols[name] = col.to_numpy().astype(np.int64)
        elif pa.types.is_string(t) or pa.types.is_large_string(t):
            cols[name] = pd.Series(col.to_pylist(), dtype="str")
        else:
            cols[name] = col.to_pandas()
    return pd.DataFrame(cols, columns=table.column_names)


def read_table(path: str | Path) -> pd.DataFrame:
    """An instance table from ``path``: Parquet (``.parquet``) or CSV (any other name).

    Raises:
        ValueError: the file is not a readable table of its kind (pyarrow's ``ArrowInvalid``,
            pandas' ``ParserError``, ``UnicodeDecodeError``); the caller names the run.
    """
    path = Path(path)
    if path.suffix != ".parquet":
        return pd.read_csv(path)
    import pyarrow.parquet as pq

    return from_arrow(pq.read_table(str(path)))


def same_table(a: str | Path, b: str | Path) -> bool:
    """Whether two Parquet files hold the same table (values and column types), whatever
    pyarrow version wrote each."""
    import pyarrow.parquet as pq

    try:
        return pq.read_table(str(a)).equals(pq.read_table(str(b)))
    except (OSError, ValueError):
        return False


def csv_to_parquet(src: str | Path, dst: str | Path) -> Path:
    """Write the CSV instance table ``src`` as Parquet to ``dst`` (:func:`write_table`)."""
    return write_table(pd.read_csv(src), dst)


def local_table(artifact_uri: str, name: str) -> Path | None:
    """The file of evaluation ``name``'s instance table in a local artifact folder: the
    Parquet one if present, else the CSV one (which may not exist either); None for a remote
    store (:func:`cloudpose.store.tracking.local_artifact`)."""
    from cloudpose.store.tracking import local_artifact

    paths = [local_artifact(artifact_uri, rel) for rel in artifact_names(name)]
    if paths[0] is None:
        return None
    return next((p for p in paths if p.is_file()), paths[-1])


def read_artifact_table(client, run, rel: str) -> pd.DataFrame:
    """A run's table artifact ``rel`` (CSV, or an instance table in either form: its Parquet
    twin is read where the run has that instead), read in place from a local store,
    downloaded from a remote one."""
    from cloudpose.store.tracking import local_artifact

    names = twins(rel)
    local = [local_artifact(run.info.artifact_uri, r) for r in names]
    if local[0] is not None:
        return read_table(next((p for p in local if p.is_file()), local[-1]))
    with tempfile.TemporaryDirectory() as tmp:
        for r in names[:-1]:
            try:
                return read_table(client.download_artifacts(run.info.run_id, r, tmp))
            except Exception:  # not there (MlflowException, OSError): try the CSV name
                continue
        return read_table(client.download_artifacts(run.info.run_id, names[-1], tmp))
