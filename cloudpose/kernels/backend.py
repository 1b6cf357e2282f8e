"""The one switch between compiled (numba) kernels and their numpy / pykdtree twins.

numba is optional. Where it is missing, or ``CLOUDPOSE_NO_NUMBA`` is set, :func:`enabled` is
False and every caller takes its twin: the index builders return no compiled index and FPS
uses fpsample. Tests and benchmarks switch the kernels off for a block with :func:`disabled`.

Without numba, ``njit`` leaves the functions as plain Python (slow, but importable), so the
package imports either way.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

try:
    import numba
    from numba import njit, prange
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None

    def njit(*args, **kwargs):  # type: ignore[no-redef]
        if args and callable(args[0]):
            return args[0]
        return lambda f: f

    prange = range  # type: ignore[assignment]

__all__ = ["HAVE_NUMBA", "configure_threads", "disabled", "enabled", "njit", "prange"]

HAVE_NUMBA = numba is not None
"""numba is importable."""

_enabled = HAVE_NUMBA and not os.environ.get("CLOUDPOSE_NO_NUMBA")
_threads_configured = False


def enabled() -> bool:
    """Whether callers should use the compiled kernels."""
    return _enabled


@contextlib.contextmanager
def disabled() -> Iterator[None]:
    """Within the block, :func:`enabled` is False (the numpy / pykdtree paths run)."""
    global _enabled
    before, _enabled = _enabled, False
    try:
        yield
    finally:
        _enabled = before


def configure_threads() -> None:
    """Pick numba's threading layer before the first parallel kernel runs.

    workqueue first: its idle threads sleep (OpenMP's spin), so a parallel kernel does not slow
    down 10x when another process holds a core; and no warning about an old TBB.
    """
    global _threads_configured
    if numba is not None and not _threads_configured:
        numba.config.THREADING_LAYER_PRIORITY = ["workqueue", "omp", "tbb"]
        _threads_configured = True
