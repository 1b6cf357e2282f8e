"""Keys of the same data made on other CPUs (cloudpose.data.keys, registry/same_data.toml)."""

from __future__ import annotations

import pytest

from cloudpose.data import keys


@pytest.fixture
def same_file(tmp_path, monkeypatch):
    """Point the package at a same-data file written by the test."""

    def write(text: str):
        path = tmp_path / "same_data.toml"
        path.write_text(text)
        monkeypatch.setattr(keys, "SAME_DATA_FILE", path)
        return path

    return write


def test_the_packaged_file_reads_and_names_each_key_once():
    listed = keys._same_data_classes(keys.SAME_DATA_FILE)
    assert listed, "the packaged file lists the default preset's keys"
    for key, group in listed.items():
        assert key in group and keys.canonical_key(key) == group[0]
        assert all(keys.same_data(key, other) for other in group)


def test_listed_keys_are_the_same_data_and_others_only_themselves(same_file):
    same_file('[[same]]\nkind = "data"\nkeys = ["aaaa", "bbbb", "cccc"]\n')
    assert keys.same_data_keys("bbbb") == ("aaaa", "bbbb", "cccc")
    assert keys.canonical_key("cccc") == "aaaa" and keys.same_data("bbbb", "cccc")
    assert keys.same_data_keys("dddd") == ("dddd",) and keys.canonical_key("dddd") == "dddd"
    assert not keys.same_data("aaaa", "dddd") and keys.same_data("dddd", "dddd")


@pytest.mark.parametrize(
    "text, match",
    [
        ('[[same]]\nkeys = ["aaaa"]\n', "entry 1 .*two or more hex"),
        ('[[same]]\nkeys = ["aaaa", "XYZ"]\n', "entry 1 .*hex"),
        ('[[same]]\nkeys = ["aa", "bb"]\n[[same]]\nkeys = ["bb", "cc"]\n', "bb is listed in two"),
    ],
)
def test_a_bad_file_is_named_with_what_was_expected(same_file, text, match):
    path = same_file(text)
    with pytest.raises(ValueError, match=match) as err:
        keys.same_data_keys("aa")
    assert str(path) in str(err.value)


def test_every_committed_run_of_the_synthetic_presets_is_on_one_data():
    """The committed sweep's runs of cpu-online, cpu-online-4x and gpu were trained on machines
    of several kinds; a run on a key that no same-data entry joins to the others would be left
    out of every report (``cloudpose same-data --run RUN`` checks a key and prints its entry)."""
    import json
    from pathlib import Path

    store = Path(__file__).resolve().parents[1] / "reports" / "cpu-online" / "mlflow-store"
    found: dict[str, set[str]] = {}
    for path in sorted(store.glob("runs/*/run.json")):
        tags = json.loads(path.read_text()).get("tags", {})
        data = tags.get("data", "")
        if tags.get("preset") in ("cpu-online", "cpu-online-4x", "gpu") and data:
            found.setdefault(keys.canonical_key(data), set()).add(data)
    assert len(found) == 1, f"the committed runs fall into {len(found)} data: {found}"
