"""A full disk as one line; SIGTERM as Ctrl-C."""

from __future__ import annotations

import errno
import os
import signal

import pytest

from cloudpose.failures import DiskFullError, disk_full, is_disk_full, sigterm_as_interrupt


def test_a_full_disk_names_the_file_the_space_it_needs_and_what_is_free(tmp_path):
    exc = OSError(errno.ENOSPC, "No space left on device")
    full = disk_full(exc, tmp_path / "last.pt", 6_500_000, then="rerun the same command")
    assert isinstance(full, DiskFullError) and full.errno == errno.ENOSPC
    text = str(full)
    assert "\n" not in text
    assert text.startswith(f"no space left on the device writing {tmp_path / 'last.pt'}")
    assert "it needs 6.5 MB" in text and "MB free there" in text
    assert text.endswith("free some space and rerun the same command")
    # an OSError's own file name wins: it is the file the write failed on
    named = OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "x.csv"))
    assert str(tmp_path / "x.csv") in str(disk_full(named, tmp_path))


def test_only_a_full_disk_is_taken_for_one():
    assert disk_full(OSError(errno.EACCES, "Permission denied"), "/x") is None
    assert disk_full(RuntimeError("boom"), "/x") is None
    assert is_disk_full(OSError(errno.EDQUOT, "Disk quota exceeded"))
    sqlite = RuntimeError("(sqlite3.OperationalError) database or disk is full")
    assert is_disk_full(sqlite)
    try:
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError as inner:
            raise RuntimeError("the store could not write") from inner
    except RuntimeError as outer:
        assert is_disk_full(outer)


def test_sigterm_raises_keyboard_interrupt_inside_the_block_only():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt, match="SIGTERM"), sigterm_as_interrupt():
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # the handler runs between bytecodes
            pass
    assert signal.getsignal(signal.SIGTERM) is before
