"""Atomic file writes: a reader (or a crash) never sees half a file.

Every file the suite keeps (checkpoints, ``run.json``, segment caches, frames, digest memos)
is written to a temporary name beside its target and renamed over it, which POSIX makes
atomic within one file system. The temporary name carries the process id, so two processes
writing one target do not write into each other's temporary file; the last rename wins.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

__all__ = ["atomic_text", "atomic_write"]


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
    return atomic_write(path, lambda tmp: tmp.write_text(text))
