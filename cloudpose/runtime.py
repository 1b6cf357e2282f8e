"""Runtime settings of a process: the device, the memory allocator and threads.

glibc's malloc gives large blocks (the (B*n, 1024) activations of a training step, 128 MiB each)
back to the kernel on ``free`` and takes them again on the next step, so half of a plain
training step is page faults. tcmalloc (Debian ``libtcmalloc-minimal4``) or jemalloc
(``libjemalloc2``) keep them. An allocator can only be chosen before the process starts, so
:func:`reexec_with_allocator` restarts the command once with ``LD_PRELOAD`` set; the CLI calls
it first thing. Where no replacement is installed (or it is refused), glibc is tuned instead
(:func:`tune_glibc_malloc`): that removes the page faults of blocks up to 32 MiB (all of a fused
network's), not those of the plain network's 128 MiB activations. Everything here falls back
silently where unavailable.

Environment:
    CLOUDPOSE_NO_TCMALLOC: set (to anything) to keep the allocator the process started with.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

__all__ = [
    "ALLOCATOR_LIBS",
    "active_allocator",
    "configure_threads",
    "pick_device",
    "preferred_allocator",
    "reexec_with_allocator",
    "tune_glibc_malloc",
]

ALLOCATOR_LIBS = ("libtcmalloc_minimal.so.4", "libtcmalloc.so.4", "libjemalloc.so.2")
"""Shared libraries tried in order of preference."""

_LIB_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
    "/lib/x86_64-linux-gnu",
    "/lib64",
)
_REEXEC_GUARD = "CLOUDPOSE_ALLOCATOR_REEXEC"


def _ldconfig_paths() -> dict[str, Path]:
    try:
        text = subprocess.run(
            ["ldconfig", "-p"], capture_output=True, text=True, timeout=5, check=False
        ).stdout
    except (OSError, subprocess.SubprocessError):
        return {}
    found: dict[str, Path] = {}
    for line in text.splitlines():
        name, sep, path = line.strip().partition(" => ")
        if sep:
            found.setdefault(name.split(" ", 1)[0], Path(path))
    return found


def preferred_allocator() -> Path | None:
    """The best malloc replacement installed on this machine, if any.

    Returns:
        Path of tcmalloc (minimal, then full) or jemalloc, or None (non-Linux, or none found).
    """
    if not sys.platform.startswith("linux"):
        return None
    listed: dict[str, Path] | None = None
    for lib in ALLOCATOR_LIBS:
        for d in _LIB_DIRS:
            p = Path(d) / lib
            if p.is_file():
                return p
        if listed is None:
            listed = _ldconfig_paths()
        if lib in listed and listed[lib].is_file():
            return listed[lib]
    return None


def active_allocator() -> str:
    """Which malloc this process uses: "tcmalloc", "jemalloc" or "glibc" (from its memory map).

    Returns "unknown" where /proc is unavailable.
    """
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return "unknown"
    for name in ("tcmalloc", "jemalloc"):
        if name in maps:
            return name
    return "glibc"


_M_TRIM_THRESHOLD = -1  # glibc malloc.h
_M_MMAP_THRESHOLD = -3
_GLIBC_MMAP_MAX = 32 << 20  # the largest mmap threshold glibc accepts on 64-bit


def tune_glibc_malloc() -> bool:
    """Make glibc keep freed blocks up to 32 MiB instead of unmapping them (``mallopt``).

    Returns:
        True if glibc is the allocator and accepted both settings.
    """
    if active_allocator() != "glibc":
        return False
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(_M_MMAP_THRESHOLD, _GLIBC_MMAP_MAX) == 1
        return libc.mallopt(_M_TRIM_THRESHOLD, 1 << 30) == 1 and ok
    except (OSError, AttributeError):
        return False


def reexec_with_allocator() -> None:
    """Restart this very command with tcmalloc/jemalloc preloaded, once; else tune glibc.

    Does not restart when ``CLOUDPOSE_NO_TCMALLOC`` is set, when a replacement allocator is
    already loaded or preloaded, when none is installed, when this process is already the
    restarted one, inside pytest or an interactive session, or when ``exec`` fails; it then
    returns, after :func:`tune_glibc_malloc` if the process runs on glibc. Call it before doing
    any work: a restart never returns (``os.execve``).
    """
    lib = _allocator_to_preload()
    if lib is None:
        tune_glibc_malloc()
        return
    preload = os.environ.get("LD_PRELOAD", "")
    env = dict(os.environ)
    env["LD_PRELOAD"] = f"{lib}:{preload}" if preload else str(lib)
    env[_REEXEC_GUARD] = "1"
    # tcmalloc reports every allocation above 1 GiB on stderr by default; that is noise here.
    env.setdefault("TCMALLOC_LARGE_ALLOC_REPORT_THRESHOLD", str(1 << 40))
    argv = [sys.executable, *sys.orig_argv[1:]]
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        os.execve(sys.executable, argv, env)
    except OSError:
        tune_glibc_malloc()


def _allocator_to_preload() -> Path | None:
    if os.environ.get("CLOUDPOSE_NO_TCMALLOC") or os.environ.get(_REEXEC_GUARD):
        return None
    if "pytest" in sys.modules or sys.flags.interactive or not getattr(sys, "orig_argv", None):
        return None
    if any(name in os.environ.get("LD_PRELOAD", "") for name in ("tcmalloc", "jemalloc")):
        return None
    if active_allocator() != "glibc":
        return None
    return preferred_allocator()


def configure_threads(num_threads: int | None = None) -> int:
    """Use every core this process may run on for intra-op work, one inter-op thread.

    Args:
        num_threads: intra-op threads; None = the CPUs in this process's affinity mask, shared
            out among the processes torchrun starts on this node (``LOCAL_WORLD_SIZE``).

    Returns:
        The intra-op thread count now in effect.
    """
    import torch

    if num_threads is None:
        try:
            num_threads = len(os.sched_getaffinity(0))
        except (AttributeError, OSError):
            num_threads = os.cpu_count() or 1
        num_threads //= max(1, int(os.environ.get("LOCAL_WORLD_SIZE", "1")))
    torch.set_num_threads(max(1, num_threads))
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # already set, or parallel work already ran
        pass
    return torch.get_num_threads()


def pick_device(name: str = "auto"):
    """``auto``: CUDA when available, else CPU; anything else is passed to ``torch.device``."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"device {name!r}: expected auto, cpu, cuda or cuda:N") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {name!r}: CUDA is not available here; use auto or cpu")
    return device
