"""Whether a run's data is today's under another key (cloudpose.store.rekey.compare_test_segments,
`cloudpose same-data`)."""

from __future__ import annotations

import types

import numpy as np
import pandas as pd
import pytest

from cloudpose.data import keys
from cloudpose.store import rekey, tracking
from cloudpose.store.instances import write_table
from tests.store.segments import segment_set


def _segments(counts, classes, key="eeee0000"):
    m = len(counts)
    frames = [f"0000/{i:06d}" for i in range(m)]
    return segment_set(np.zeros((m, 4, 3)), classes, counts, frames, keys.DataKey(key))


@pytest.fixture
def run_with_table(tmp_path, monkeypatch):
    """A finished run whose test instance table has 4 segments of 1,000-4,000 points, and
    ``here(counts, classes)``: the segments its preset makes today."""
    client = tracking.setup(tmp_path)
    exp = client.create_experiment(f"{tracking.EXPERIMENT_PREFIX}shared")
    tags = {"preset": "smoke", "variant": "shared-0", "seed": "1", "data": "aaaa0000"}
    tags["eval/test/data"] = "bbbb0000"
    run = client.create_run(exp, tags=tags).info.run_id
    table = pd.DataFrame(
        {
            "frame_id": [f"0000/{i:06d}" for i in range(4)],
            "instance": list(range(4)),
            "cls_id": [1, 2, 3, 4],
            "points": [1000, 2000, 3000, 4000],
            "miss": [False] * 4,
            "net_ads": [0.01] * 4,
        }
    )
    out = tmp_path / "table"
    out.mkdir()
    write_table(table, out / "instances.parquet")
    client.log_artifact(run, str(out / "instances.parquet"), "eval/test")
    client.set_terminated(run)

    def here(counts, classes):
        prepared = types.SimpleNamespace(test=_segments(counts, classes), data_key="dddd0000")
        monkeypatch.setattr(
            "cloudpose.store.rekey.prepare_data", lambda *a, **k: prepared, raising=True
        )
        return rekey.compare_test_segments(run, tmp_path)

    return here


def test_a_point_of_thousands_is_the_same_data_and_names_the_entries(run_with_table):
    c = run_with_table([1000, 2001, 3000, 3999], [1, 2, 3, 4])
    assert c.same and c.other_count == 2 and c.unmatched == 0
    assert c.keys == {"data": ("aaaa0000", "dddd0000"), "test": ("bbbb0000", "eeee0000")}
    assert c.largest_share == pytest.approx(0.0005)
    entry = c.entry("checked")
    assert 'keys = ["aaaa0000", "dddd0000"]' in entry and 'kind = "segments"' in entry


@pytest.mark.parametrize(
    "counts, classes, what",
    [
        ([1000, 2100, 3000, 4000], [1, 2, 3, 4], "largest_share"),  # 5% of a segment
        ([1000, 2000, 3000, 4000], [1, 2, 3, 5], "other_class"),
        ([1000, 2000, 3000], [1, 2, 3], "unmatched"),
    ],
)
def test_other_segments_are_not_the_same_data(run_with_table, counts, classes, what):
    c = run_with_table(counts, classes)
    assert not c.same and getattr(c, what) > 0


def test_keys_already_listed_need_nothing_or_join_their_entry(
    run_with_table, tmp_path, monkeypatch
):
    same = tmp_path / "same_data.toml"
    same.write_text('[[same]]\nkeys = ["aaaa0000", "dddd0000"]\n')
    monkeypatch.setattr(keys, "SAME_DATA_FILE", same)
    c = run_with_table([1000, 2000, 3000, 4000], [1, 2, 3, 4])
    assert c.same and c.entry("checked").startswith('[[same]]\nkind = "segments"')
    other = tmp_path / "same_data_2.toml"  # read once per file and process
    other.write_text(
        '[[same]]\nkeys = ["aaaa0000", "cccc0000"]\n[[same]]\nkeys = ["bbbb0000", "eeee0000"]\n'
    )
    monkeypatch.setattr(keys, "SAME_DATA_FILE", other)
    entry = c.entry("checked")
    assert entry == 'add "dddd0000" to the keys of the entry that lists "aaaa0000"\n'
