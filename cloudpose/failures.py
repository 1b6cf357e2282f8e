"""How a command stops other than on bad input: a file-system error, a full disk, and SIGTERM.

- A file-system error the operating system raises about a path (no permission, a file where
  a folder is expected, an immutable file, a read-only file system, ...) is one line
  (:func:`file_system_message`): the path, what the system said, what it means and, where the
  user gave that path, the option (or argument) to give another. The CLI's one handler prints
  it as ``error: ...``, exit 2, in every command.
- A full disk is one line naming the file that could not be written, the space it needed
  (where known) and the space left there (:class:`DiskFullError`, made from the ``OSError``
  with ``errno.ENOSPC`` of a write, or SQLite's "database or disk is full", by
  :func:`disk_full`). The CLI prints it as ``error: ...``, exit 2.
- SIGTERM (``kill PID``, a scheduler's time limit, ``docker stop``) stops a command as Ctrl-C
  does (:func:`sigterm_as_interrupt`): ``KeyboardInterrupt`` is raised in the main thread, so
  every ``finally`` runs: temporary files and folders are removed, a training run is marked
  KILLED in MLflow and resumes from its last checkpoint. (``kill -9`` runs nothing; a
  training run resumes after it too, from its last checkpoint.)
"""

from __future__ import annotations

import contextlib
import errno
import shutil
import signal
import threading
from collections.abc import Iterator
from pathlib import Path

__all__ = [
    "DiskFullError",
    "disk_full",
    "file_system_message",
    "free_bytes",
    "is_disk_full",
    "is_file_system_error",
    "sigterm_as_interrupt",
]


class DiskFullError(OSError):
    """A write that found no space left: the message names the file, the space it needed and
    the space free there, and what to do."""

    def __init__(self, path: str | Path, needed: int | None = None, then: str = "") -> None:
        path = Path(path)
        free = free_bytes(path)
        details = [f"it needs {_mb(needed)}"] if needed is not None else []
        if free is not None:
            details.append(f"{_mb(free)} free there")
        message = f"no space left on the device writing {path}"
        message += f" ({', '.join(details)})" if details else ""
        message += f"; free some space{' and ' + then if then else ''}"
        super().__init__(errno.ENOSPC, message)
        self.path, self.needed, self.free = path, needed, free

    def __str__(self) -> str:
        return self.strerror


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def free_bytes(path: str | Path) -> int | None:
    """Bytes free to this user on the file system of ``path`` (or of its nearest existing
    folder); None when it cannot be told."""
    p = Path(path)
    for folder in (p, *p.parents):
        if folder.exists():
            try:
                return shutil.disk_usage(folder).free
            except OSError:
                return None
    return None


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or an exception it was raised from) is a full disk: ``ENOSPC`` (or
    ``EDQUOT``, a full quota), or SQLite's "database or disk is full"."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if "database or disk is full" in str(exc):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def disk_full(
    exc: BaseException, path: str | Path, needed: int | None = None, then: str = ""
) -> DiskFullError | None:
    """A :class:`DiskFullError` for ``exc`` if it is a full disk (:func:`is_disk_full`), else
    None. ``path``: the file being written (an ``OSError``'s own file name wins); ``needed``:
    its size in bytes, where known; ``then``: what to do once space is free."""
    if isinstance(exc, DiskFullError):
        return exc
    if not is_disk_full(exc):
        return None
    filename = getattr(exc, "filename", None)
    return DiskFullError(filename or path, needed, then)


_MEANS = {
    errno.EACCES: "no permission: check the folder's owner and mode",
    errno.EPERM: "not permitted: an immutable or read-only file or folder",
    errno.EROFS: "a read-only file system",
    errno.ENOTDIR: "a part of the path is a file, not a folder",
    errno.EISDIR: "a folder where a file was expected",
    errno.ENOSPC: "no space left on the device: free some",
    errno.EDQUOT: "the disk quota is full: free some",
    errno.ENOENT: "no such file or folder",
    errno.EEXIST: "it exists already",
}
"""What each class of file-system error means, in the words of a one-line message."""


def is_file_system_error(exc: BaseException) -> bool:
    """Whether ``exc`` is an error the operating system raised about a file (an ``OSError``
    with an errno), not a message of the suite's own (``FileNotFoundError("...")``, a
    :class:`DiskFullError`) nor a connection's."""
    return (
        isinstance(exc, OSError)
        and not isinstance(exc, (DiskFullError, ConnectionError))
        and exc.errno is not None
    )


def file_system_message(exc: OSError, option: str | None = None) -> str:
    """One line for a file-system error: ``PATH: what the system said (what it means; choose
    another OPTION)``. ``option``: the option or argument the user gave the path by (``--out``,
    ``OUT``), None when the path is none the user gave. ``EEXIST`` on a file is a file where
    a folder is expected (``mkdir`` of a path through a file)."""
    paths = [str(p) for p in (exc.filename, exc.filename2) if p is not None]
    where = " -> ".join(paths) or "a file this command writes"
    said = exc.strerror or type(exc).__name__
    means = _MEANS.get(exc.errno or 0)
    if exc.errno == errno.EEXIST and paths and Path(paths[0]).is_file():
        means = "a file, not a folder, where a folder is expected"
    parts = [m for m in (means, f"choose another {option}" if option else None) if m]
    return f"{where}: {said}" + (f" ({'; '.join(parts)})" if parts else "")


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt(f"stopped by signal {signal.Signals(signum).name}")


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises ``KeyboardInterrupt`` as Ctrl-C does, so that the
    command's ``finally`` clauses and interrupt handling run; the previous handler comes back
    after it. Outside the main thread (where Python cannot take signals) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
