"""The data key: a content hash that names the data a run was trained or evaluated on.

:func:`cloudpose.data.cache.cache_key` makes the key of one split's segments (20 hex digits:
frame ids, the content of their files and of the models, the segment settings);
:func:`cloudpose.data.dataset.data_fingerprint` combines the train and test keys into the key
of a run's data (16 hex digits). Either travels as a :data:`DataKey` named ``data_key``: it
names cache files and run folders and is the MLflow tag ``data`` of a run (``eval/NAME/data``
of an evaluation).

Synthetic frames rendered on two kinds of CPU can differ in a few edge pixels, so one dataset can
have a key per kind of machine; :data:`SAME_DATA_FILE` lists the keys checked to name the same
data, and :func:`same_data` is how runs and reports compare keys.
"""

from __future__ import annotations

import functools
import tomllib
from pathlib import Path
from typing import NewType

from cloudpose.conventions import resource_path

DataKey = NewType("DataKey", str)
"""A content key of data (hex digits)."""

NO_DATA_KEY = DataKey("")
"""The key of segments built in memory, of no data file."""

_HEX = frozenset("0123456789abcdef")


SAME_DATA_FILE = resource_path("registry", "same_data.toml")
"""The keys known to name the same data made on other CPUs (the file says when to add one)."""


@functools.cache
def _same_data_classes(path: Path) -> dict[str, tuple[DataKey, ...]]:
    """Each key listed in ``path`` -> every key of its entry, the entry's first key first."""
    raw = tomllib.loads(path.read_text())
    out: dict[str, tuple[DataKey, ...]] = {}
    for i, entry in enumerate(raw.get("same", [])):
        keys = entry.get("keys")
        if (
            not isinstance(keys, list)
            or len(keys) < 2
            or not all(isinstance(k, str) and k and all(c in _HEX for c in k) for k in keys)
        ):
            raise ValueError(
                f"{path}: entry {i + 1} ([[same]]): expected `keys`, a list of two or "
                f"more hex data keys, got {keys!r}"
            )
        for k in keys:
            if k in out:
                raise ValueError(f"{path}: key {k} is listed in two entries")
            out[k] = tuple(DataKey(x) for x in keys)
    return out


def same_data_keys(key: str) -> tuple[DataKey, ...]:
    """Every key of the data that ``key`` names: itself alone, or the keys of its entry of
    :data:`SAME_DATA_FILE` (the entry's first key first)."""
    return _same_data_classes(SAME_DATA_FILE).get(key, (DataKey(key),))


def canonical_key(key: str) -> DataKey:
    """The key reports name ``key``'s data by: the first of :func:`same_data_keys`."""
    return same_data_keys(key)[0]


def same_data(a: str, b: str) -> bool:
    """``a`` and ``b`` name the same data (equal, or listed together in :data:`SAME_DATA_FILE`)."""
    return a == b or canonical_key(a) == canonical_key(b)
