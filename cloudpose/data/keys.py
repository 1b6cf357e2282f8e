"""The data key: a content hash that names the data a run was trained or evaluated on.

:func:`cloudpose.data.cache.cache_key` makes the key of one split's segments (20 hex digits:
frame ids, the content of their files and of the models, the segment settings);
:func:`cloudpose.data.dataset.data_fingerprint` combines the train and test keys into the key
of a run's data (16 hex digits). Either travels as a :data:`DataKey` named ``data_key``: it
names cache files and run folders and is the MLflow tag ``data`` of a run (``eval/NAME/data``
of an evaluation).
"""

from __future__ import annotations

from typing import NewType

DataKey = NewType("DataKey", str)
"""A content key of data (hex digits)."""

NO_DATA_KEY = DataKey("")
"""The key of segments built in memory, of no data file."""
