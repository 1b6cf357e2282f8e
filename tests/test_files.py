"""Atomic file writes (cloudpose.files): the target holds the old or the whole new file."""

from __future__ import annotations

import numpy as np
import pytest

from cloudpose.files import atomic_text, atomic_write


def test_atomic_write_makes_the_folder_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "a" / "b" / "run.json"
    assert atomic_write(target, lambda tmp: tmp.write_text("{}")) == target
    assert target.read_text() == "{}"
    assert sorted(p.name for p in target.parent.iterdir()) == ["run.json"]


def test_a_failed_write_keeps_the_old_file_and_removes_the_temporary(tmp_path):
    target = atomic_text(tmp_path / "model.pt", "old")

    def half(tmp):
        tmp.write_text("ne")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(target, half)
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["model.pt"]


def test_the_suffix_serves_writers_that_append_one(tmp_path):
    """``np.savez`` appends ``.npz`` to a name without it: the suffix gives the temporary one."""
    target = tmp_path / "segments.npz"
    atomic_write(target, lambda tmp: np.savez(tmp, x=np.arange(3)), ".npz")
    with np.load(target) as z:
        np.testing.assert_array_equal(z["x"], [0, 1, 2])
    assert [p.name for p in tmp_path.iterdir()] == ["segments.npz"]


def test_atomic_text_replaces_the_whole_file(tmp_path):
    target = tmp_path / "notes.md"
    atomic_text(target, "a long first version\n")
    atomic_text(target, "short\n")
    assert target.read_text() == "short\n"
