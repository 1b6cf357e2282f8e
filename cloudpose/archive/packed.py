"""Instance tables as a compact store keeps them: fewer bytes, the same rendered numbers.

An evaluation's instance table (:mod:`cloudpose.store.instances`, float32 Parquet) is ~100 kB
for the 2,053 synthetic test instances of the default preset; a store of a hundred runs holds
two hundred such tables. The compact form (:mod:`cloudpose.archive.compact`) stores each one
*packed*, and unpacking writes it back as the evaluation's form:

- **The data's columns once**: ``frame_id``, ``instance``, ``cls_id``, ``class``,
  ``occlusion`` and ``points`` describe the test set, not the run. The runs whose tables have
  the same rows (the same ``frame_id``, ``instance``, ``cls_id``, ``class``) share one table of
  them, ``shared/SHA.parquet`` (named by the SHA-256 of its values, made from the first such
  run), and a run's file keeps only the ones that differ from it (``points`` of a config that
  samples other points).
- **Rotation errors modulo symmetry** equal to the plain rotation errors (every instance of a
  class without symmetry) are stored as nulls: ``X_rot_sym_err_deg`` is ``X_rot_err_deg``
  there, exactly.
- **Poses on a grid**: each unit quaternion as its three smallest components (int16, in steps
  of 1 / (32767 sqrt 2)) and the index of the largest, which gives the rotation within
  :data:`ROTATION_STEP_DEG`; each translation in whole micrometres (int32), and ICP's as its
  difference from the network's where both have one.
- brotli (level 11) where the evaluation's form uses zstd.

Errors and every other float column stay float32 as written: the reports print medians and
areas under curves to six significant digits, which a shorter mantissa changes. Only the poses
lose digits, which no report reads; :func:`reduce` puts a table's poses on the grid, and a
packed table unpacks to exactly the reduced one (:func:`decode`), so a store packed again
after unpacking writes the same values. Every report renders the same tables from the reduced
store as from the full one (docs/store-format.md).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from cloudpose.store import instances
from cloudpose.store.instances import QUATERNIONS_KEY

PACKED_KEY = "cloudpose.packed"
"""Parquet key-value metadata of a packed table: JSON (:class:`Layout`)."""

SHARED = "shared"
"""Folder of a compact store that holds the data's columns shared by runs' tables."""

DATA_COLUMNS = ("frame_id", "instance", "cls_id", "class", "occlusion", "points")
"""Columns that describe the evaluated instances rather than the run (stored once)."""

ROW_KEY = ("frame_id", "instance", "cls_id", "class")
"""The columns that identify a table's rows: tables alike in these share their data columns."""

QUAT_SCALE = 32767 * np.sqrt(2.0)
"""Integer steps per unit of a quaternion's three smallest components (each at most 1/sqrt 2)."""

TRANSLATION_STEP = 1e-6
"""Metres per integer step of a packed translation."""

ROTATION_STEP_DEG = 0.005
"""A packed rotation is within this angle of the one written (the grid's worst case is
~0.004 degrees); a column that would move further stays float32."""

_COMPRESSION = ("brotli", 11)

LARGEST = "__largest"
"""Suffix of the column that holds the index of a packed quaternion's largest component."""


@dataclass(frozen=True)
class Layout:
    """How a packed table maps back to the evaluation's table (stored as :data:`PACKED_KEY`)."""

    columns: list[str]
    """The evaluation's column names, in order."""
    shared: str = ""
    """``shared/SHA.parquet``: the table of the data's columns the run shares, or ''."""
    from_shared: tuple[str, ...] = ()
    """Columns read from :attr:`shared` (absent from the packed file)."""
    same_as: dict[str, str] | None = None
    """Column -> column whose value a null stands for."""
    quaternions: tuple[str, ...] = ()
    """Quaternion columns stored as three int16 (and ``NAME.largest``, int8)."""
    micrometres: tuple[str, ...] = ()
    """Translation columns stored as int32 micrometres."""
    difference_of: dict[str, str] | None = None
    """Translation column -> the column it is stored as a difference from (where that has a
    value)."""

    def to_json(self) -> str:
        d = {k: v for k, v in self.__dict__.items() if v}
        return json.dumps({k: list(v) if isinstance(v, tuple) else v for k, v in d.items()})

    @staticmethod
    def from_json(text: str | bytes) -> Layout:
        d = json.loads(text)
        for k in ("from_shared", "quaternions", "micrometres"):
            if k in d:
                d[k] = tuple(d[k])
        return Layout(**d)


# ------------------------------------------------------------------------------ helpers


def _lists(col, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(M, k) float64 values of a list column (zeros for a null row) and its (M,) null mask."""
    col = col.combine_chunks() if hasattr(col, "combine_chunks") else col
    null = col.is_null().to_numpy(zero_copy_only=False)
    out = np.zeros((len(col), k), dtype=np.float64)
    flat = col.flatten().to_numpy(zero_copy_only=False)
    if flat.size:
        out[~null] = flat.reshape(-1, k)
    return out, null


def _list_array(values: np.ndarray, null: np.ndarray):
    """A fixed-size list column of (M, k) ``values`` (their dtype), null where ``null``."""
    v = np.where(null[:, None], 0, values).astype(values.dtype)
    return pa.FixedSizeListArray.from_arrays(
        pa.array(v.ravel()), values.shape[1], mask=pa.array(null)
    )


def _width(col) -> int:
    """Numbers per row of a list column (0 when every row is null)."""
    col = col.combine_chunks() if hasattr(col, "combine_chunks") else col
    filled = len(col) - col.null_count
    return len(col.flatten()) // filled if filled else 0


def same_column(a, b) -> bool:
    """Whether two columns hold the same values of the same type (floats bit for bit, so NaN
    equals NaN)."""
    a = a.combine_chunks() if hasattr(a, "combine_chunks") else a
    b = b.combine_chunks() if hasattr(b, "combine_chunks") else b
    if a.type != b.type or len(a) != len(b) or a.null_count != b.null_count:
        return False
    if pa.types.is_floating(a.type) and not a.null_count:
        x, y = a.to_numpy(zero_copy_only=False), b.to_numpy(zero_copy_only=False)
        return bool((x.view(np.uint8) == y.view(np.uint8)).all())
    return a.equals(b)


def _quat_encode(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 4) unit quaternions -> (M, 3) int16 (the three smallest components of the one of
    ``q`` and ``-q`` whose largest component is positive) and (M,) int8 index of the largest."""
    a = np.argmax(np.abs(q), axis=1)
    rows = np.arange(len(q))
    sign = np.where(q[rows, a] < 0, -1.0, 1.0)
    rest = np.stack([np.delete(r, i) for r, i in zip(q * sign[:, None], a, strict=True)])
    rest = rest if len(q) else np.zeros((0, 3))
    return np.round(rest * QUAT_SCALE).astype(np.int16), a.astype(np.int8)


def _quat_decode(ints: np.ndarray, largest: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_quat_encode`: (M, 4) float32 unit quaternions, ``w >= 0``."""
    rest = ints.astype(np.float64) / QUAT_SCALE
    big = np.sqrt(np.clip(1.0 - (rest**2).sum(axis=1), 0.0, None))
    q = np.zeros((len(ints), 4))
    for i in range(4):
        at = largest == i
        cols = [j for j in range(4) if j != i]
        q[np.ix_(at, cols)] = rest[at]
        q[at, i] = big[at]
    q /= np.linalg.norm(q, axis=1, keepdims=True).clip(1e-300)
    q[q[:, 3] < 0] *= -1.0
    return q.astype(np.float32)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M,) angle in degrees between the rotations of (M, 4) quaternions, from the chord
    (accurate near 0, where the arccos of the dot product is not)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    a = a / np.linalg.norm(a, axis=1, keepdims=True).clip(1e-300)
    b = b / np.linalg.norm(b, axis=1, keepdims=True).clip(1e-300)
    b = np.where(((a * b).sum(axis=1) < 0)[:, None], -b, b)
    return np.degrees(4 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=1) / 2, 0.0, 1.0)))


def _settled_quaternions(q: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The grid point of each quaternion that decodes and encodes to itself, or None when
    some row does not settle or moves by more than :data:`ROTATION_STEP_DEG`."""
    ints, largest = _quat_encode(q)
    for _ in range(4):
        again, big_again = _quat_encode(_quat_decode(ints, largest).astype(np.float64))
        moved = (again != ints).any(axis=1) | (big_again != largest)
        if not moved.any():
            if len(q) and _angle_deg(_quat_decode(ints, largest), q).max() > ROTATION_STEP_DEG:
                return None
            return ints, largest
        ints, largest = again, big_again
    return None


def _settled_micrometres(t: np.ndarray) -> np.ndarray | None:
    """(M, 3) int32 micrometres of float32 translations in metres that read back (float32)
    to the same integers, or None (a value beyond the float32 grid of 1 micrometre)."""
    if not np.isfinite(t).all() or np.abs(t).max(initial=0.0) > 1e3:
        return None
    ints = np.round(t / TRANSLATION_STEP).astype(np.int64)
    back = (ints * TRANSLATION_STEP).astype(np.float32).astype(np.float64)
    if (np.round(back / TRANSLATION_STEP).astype(np.int64) != ints).any():
        return None
    return ints.astype(np.int32)


def _quaternion_names(table) -> dict[str, str]:
    meta = table.schema.metadata or {}
    return json.loads(meta.get(QUATERNIONS_KEY.encode(), b"{}"))


# ------------------------------------------------------------------------------ reduce


def reduce(table):
    """``table`` (an instance table in the evaluation's form, as Arrow) with the precision a
    packed table keeps: quaternions and translations on their grids (a column whose rows do
    not all fit stays as it is), every other column as it is. Reducing twice changes nothing
    more."""
    quats = _quaternion_names(table)
    cols = []
    for f, col in zip(table.schema, table.columns, strict=True):
        col = col.combine_chunks()
        if f.name in quats and _width(col) == 4:
            q, null = _lists(col, 4)
            settled = _settled_quaternions(q[~null])
            if settled is not None:
                q[~null] = _quat_decode(*settled)
            col = _list_array(q.astype(np.float32), null)
        elif f.name.endswith("_t") and _width(col) == 3:
            t, null = _lists(col, 3)
            ints = _settled_micrometres(t[~null])
            if ints is not None:
                t[~null] = ints * TRANSLATION_STEP
            col = _list_array(t.astype(np.float32), null)
        elif pa.types.is_list(f.type) or pa.types.is_fixed_size_list(f.type):
            v, null = _lists(col, _width(col))
            col = _list_array(v.astype(np.float32), null)
        cols.append(col)
    out = pa.Table.from_arrays(cols, names=table.column_names)
    return out.replace_schema_metadata(table.schema.metadata)


# ------------------------------------------------------------------------------ shared


def shared_table(table):
    """The data's columns (:data:`DATA_COLUMNS` that ``table`` has) of a reduced table."""
    return table.select([c for c in DATA_COLUMNS if c in table.column_names])


def _digest(table, columns) -> str:
    h = hashlib.sha256()
    for name in columns:
        col = table.column(name)
        h.update(f"{name}\t{col.type}\n".encode())
        h.update(json.dumps(col.to_pylist()).encode())
    return h.hexdigest()


def row_key(table) -> str | None:
    """SHA-256 of the columns that identify ``table``'s rows (:data:`ROW_KEY`), or None when
    it lacks one of them."""
    if not all(c in table.column_names for c in ROW_KEY):
        return None
    return _digest(table, ROW_KEY)


def shared_name(shared) -> str:
    """``shared/SHA.parquet`` of a shared table: the SHA-256 of its values (16 hex digits)."""
    return f"{SHARED}/{_digest(shared, shared.column_names)[:16]}.parquet"


# ------------------------------------------------------------------------------ encode


def encode(reduced, shared=None, shared_ref: str = ""):
    """The packed form of a reduced table (:func:`reduce`), given the shared table of its rows
    (or None): an Arrow table whose metadata holds its :class:`Layout`."""
    quats = _quaternion_names(reduced)
    names = reduced.column_names
    from_shared = ()
    if shared is not None:
        from_shared = tuple(
            c
            for c in shared.column_names
            if c in names and same_column(reduced.column(c), shared.column(c))
        )
    same_as, q_cols, um_cols, diff_of = {}, [], [], {}
    arrays, out_names = [], []
    ints_of = {}
    for f, col in zip(reduced.schema, reduced.columns, strict=True):
        name = f.name
        col = col.combine_chunks()
        if name in from_shared:
            continue
        plain = name.replace("_rot_sym_err_deg", "_rot_err_deg")
        if name.endswith("_rot_sym_err_deg") and plain in names:
            a = col.to_numpy(zero_copy_only=False)
            b = reduced.column(plain).to_numpy()
            same = (a == b) | (np.isnan(a) & np.isnan(b))
            arrays.append(pa.array(a, mask=same))
            out_names.append(name)
            same_as[name] = plain
            continue
        if name in quats and _width(col) == 4:
            q, null = _lists(col, 4)
            settled = _settled_quaternions(q[~null])
            if settled is not None and np.array_equal(
                _quat_decode(*settled).astype(np.float64), q[~null]
            ):
                ints = np.zeros((len(q), 3), np.int16)
                big = np.zeros(len(q), np.int8)
                ints[~null], big[~null] = settled
                arrays += [_list_array(ints, null), pa.array(big, mask=null)]
                out_names += [name, f"{name}{LARGEST}"]
                q_cols.append(name)
                continue
        if name.endswith("_t") and _width(col) == 3:
            t, null = _lists(col, 3)
            ints = _settled_micrometres(t[~null])
            if ints is not None and np.array_equal(
                (ints.astype(np.float64) * TRANSLATION_STEP).astype(np.float32), t[~null]
            ):
                full = np.zeros((len(t), 3), np.int32)
                full[~null] = ints
                ints_of[name] = (full, null)
                base = f"net{name[3:]}" if name.startswith("icp_") else ""
                if base in ints_of:
                    # ICP refines the network's pose: its translation as the change, smaller
                    have = ~ints_of[base][1]
                    diff = np.where(have[:, None], full.astype(np.int64) - ints_of[base][0], full)
                    if np.abs(diff).max(initial=0) < 2**31:
                        full = diff.astype(np.int32)
                        diff_of[name] = base
                arrays.append(_list_array(full.astype(np.int32), null))
                out_names.append(name)
                um_cols.append(name)
                continue
        arrays.append(col)
        out_names.append(name)
    layout = Layout(
        columns=list(names),
        shared=shared_ref if from_shared else "",
        from_shared=from_shared,
        same_as=same_as or None,
        quaternions=tuple(q_cols),
        micrometres=tuple(um_cols),
        difference_of=diff_of or None,
    )
    meta = dict(reduced.schema.metadata or {})
    meta[PACKED_KEY.encode()] = layout.to_json().encode()
    return pa.Table.from_arrays(arrays, names=out_names).replace_schema_metadata(meta)


def layout_of(table) -> Layout | None:
    """The :class:`Layout` of a packed table, None for a table in the evaluation's form."""
    raw = (table.schema.metadata or {}).get(PACKED_KEY.encode())
    return None if raw is None else Layout.from_json(raw)


def decode(packed, shared=None):
    """The reduced table a packed one stands for (the evaluation's form, as Arrow); ``shared``
    is the table its layout names (None when it names none)."""
    layout = layout_of(packed)
    if layout is None:
        return packed
    if layout.from_shared and shared is None:
        raise ValueError(f"the packed table needs its shared table {layout.shared}")
    have = {n: packed.column(n).combine_chunks() for n in packed.column_names}
    out = {}
    for name in layout.from_shared:
        out[name] = shared.column(name).combine_chunks()
    for name in layout.quaternions:
        ints, null = _lists(have[name], 3)
        big = have[f"{name}{LARGEST}"].fill_null(0).to_numpy(zero_copy_only=False)
        q = _quat_decode(ints.astype(np.int16), big.astype(np.int8))
        out[name] = _list_array(q, null)
    for name in layout.micrometres:
        ints, null = _lists(have[name], 3)
        ints = ints.astype(np.int64)
        base = (layout.difference_of or {}).get(name)
        if base:
            b_ints, b_null = _lists(have[base], 3)
            ints = np.where(~b_null[:, None], ints + b_ints.astype(np.int64), ints)
        out[name] = _list_array((ints * TRANSLATION_STEP).astype(np.float32), null)
    for name, plain in (layout.same_as or {}).items():
        a = have[name]
        null = a.is_null().to_numpy(zero_copy_only=False)
        v = a.fill_null(0).to_numpy(zero_copy_only=False).astype(np.float32)
        v[null] = have[plain].to_numpy(zero_copy_only=False)[null]
        out[name] = pa.array(v)
    for name in layout.columns:
        if name not in out:
            out[name] = have[name]
    meta = {k: v for k, v in (packed.schema.metadata or {}).items() if k != PACKED_KEY.encode()}
    table = pa.Table.from_arrays([out[n] for n in layout.columns], names=layout.columns)
    return table.replace_schema_metadata(meta or None)


# ------------------------------------------------------------------------------ files


def write(table, path) -> None:
    """Write a packed (or shared) table as Parquet: the store's writer
    (:func:`cloudpose.store.instances.write_arrow`: byte stream split for float and list
    columns, the integer lists too, dictionaries for the rest; no statistics), brotli."""
    instances.write_arrow(table, path, compression=_COMPRESSION)


def read(path):
    """A packed or shared table as Arrow (its metadata kept)."""
    return pq.read_table(str(path))
