"""Atomic file writes, and checked reads of the files the suite writes itself.

Every file the suite keeps (checkpoints, ``run.json``, segment caches, frames, digest memos)
is written to a temporary name beside its target and renamed over it, which POSIX makes
atomic within one file system. The temporary name carries the process id, so two processes
writing one target do not write into each other's temporary file; the last rename wins.

A file can still be damaged after it was written (a copy cut short, a full disk on another
tool's write, a hand edit). Every such file is validated on read: :func:`read_npz` and
:func:`read_json` turn whatever the parser raises (``EOFError`` of a zero-byte file,
``BadZipFile`` of a truncated one, a JSON syntax error) into a :class:`CorruptFileError` that
names the file. The reader then rebuilds it (a cache: segment caches, on-line chunks, digest
memos, with a one-line warning naming it) or stops with one line naming the file and what to
do (state the suite cannot make again: a run record, a synthetic set's ``synth.json``).
"""

from __future__ import annotations

import json
import lzma
import os
import pickle
import tarfile
import zipfile
import zlib
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "UNREADABLE",
    "CorruptFileError",
    "atomic_text",
    "atomic_write",
    "read_json",
    "read_npz",
    "why",
]

UNREADABLE = (
    EOFError,
    OSError,
    ValueError,
    KeyError,
    zipfile.BadZipFile,
    zlib.error,
    lzma.LZMAError,
    pickle.UnpicklingError,
)
"""What the parsers of numpy, zipfile, lzma, pickle and json raise on a zero-byte, truncated or
garbled file (``EOFError``: ``np.load`` of an empty file; ``BadZipFile``: a cut ``.npz``)."""


class CorruptFileError(ValueError):
    """A file the suite wrote (or reads back) is unreadable or not what was written.

    The message starts with the file's path and says what to do; :attr:`path` holds it. A
    ``ValueError``, so the CLI prints it as one line (``error: PATH: ...``, exit 2).
    """

    def __init__(self, path: str | Path, message: str) -> None:
        self.path, self.message = Path(path), message
        super().__init__(f"{self.path}: {message}")

    def __reduce__(self):  # (path, message), not args: it crosses process pools whole
        return type(self), (self.path, self.message)


def why(exc: BaseException) -> str:
    """An exception in a few words for a one-line message: ``EOFError: No data left in file``
    (the type's name alone when it has no text)."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def atomic_write(path: str | Path, write: Callable[[Path], object], suffix: str = "") -> Path:
    """Call ``write(tmp)`` on a temporary path beside ``path``, then rename it to ``path``.

    Args:
        path: the target; its folder is created.
        write: writes the whole file at the path it is given.
        suffix: ending the temporary name needs (``np.savez`` appends ``.npz`` to a name
            without it).

    Returns:
        ``path``. The temporary file is removed if ``write`` raises.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp{suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def atomic_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (:func:`atomic_write`)."""
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def read_npz(
    path: str | Path, names: Iterable[str], what: str, optional: Iterable[str] = ()
) -> dict[str, np.ndarray]:
    """The arrays ``names`` of an ``.npz`` file, read whole into memory (so that a damaged
    member fails here, by its CRC, not later), without pickles.

    Args:
        path: the file (it must exist).
        names: the arrays it must hold.
        what: the file in words for the message (``"segment cache"``).
        optional: arrays read too when the file holds them (a field added later).

    Raises:
        CorruptFileError: the file is empty, truncated or garbled, or lacks one of ``names``.
    """
    path = Path(path)
    names = list(names)
    try:
        with np.load(path, allow_pickle=False) as z:
            if not hasattr(z, "files"):
                raise CorruptFileError(path, f"{what} is a bare array, not an .npz archive")
            missing = [n for n in names if n not in z.files]
            if missing:
                raise CorruptFileError(path, f"{what} lacks fields {missing}")
            return {n: z[n] for n in [*names, *optional] if n in z.files}
    except CorruptFileError:
        raise
    except UNREADABLE as e:
        if isinstance(e, FileNotFoundError):
            raise
        # numpy takes bytes that are neither a zip nor an array for a pickle, and says so
        said = "not an .npz archive" if "allow_pickle" in str(e) else why(e)
        raise CorruptFileError(path, f"{what} is unreadable ({said})") from e


def checked_members(
    archive: str | Path, tar: tarfile.TarFile, into: str | Path, allowed: Callable[[str], bool],
    expected: str,
) -> list[tarfile.TarInfo]:  # fmt: skip
    """The members of ``tar`` (an open ``archive``) that may be unpacked into ``into``, checked
    before anything is written: each name (without a leading ``./``; the folder entry itself
    is skipped) passes ``allowed``, and :func:`tarfile.data_filter` accepts it (no path or
    link outside the folder, no device).

    Raises:
        ValueError: naming the archive and the first member that fails, with ``expected`` (what
            such an archive holds, in words) or the filter's reason; nothing is unpacked.
    """
    members = []
    for m in tar.getmembers():
        name = m.name.removeprefix("./")
        if name in ("", "."):
            continue
        if not allowed(name):
            raise ValueError(f"{archive}: member {m.name!r} is not {expected}; nothing unpacked")
        try:
            tarfile.data_filter(m, str(into))
        except tarfile.FilterError as exc:
            raise ValueError(
                f"{archive}: member {m.name!r} refused ({exc}): such an archive holds only files "
                "inside its own folder, no path or link outside it; nothing unpacked"
            ) from None
        members.append(m)
    return members


def read_json(path: str | Path, what: str, fix: str) -> Any:
    """The JSON document in ``path``.

    Args:
        path: the file (it must exist).
        what: the file in words (``"synthetic set record"``).
        fix: what the user can do, for the message (``"delete the folder and render it again"``).

    Raises:
        CorruptFileError: the file is not UTF-8 JSON (empty, truncated, garbled), naming the
            file, the parser's complaint and ``fix``.
    """
    path = Path(path)
    try:
        return json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CorruptFileError(path, f"{what} is not readable JSON ({why(e)}); {fix}") from e
