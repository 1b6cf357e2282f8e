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

Open3D runs its parallel loops on oneTBB; :func:`open3d_threads` (1) confines them to the
calling thread for code whose result would otherwise depend on thread scheduling (RANSAC draws
its samples from one shared generator in whatever order its threads ask).

Environment:
    CLOUDPOSE_NO_TCMALLOC: set (to anything) to keep the allocator the process started with.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import platform
import subprocess
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path

__all__ = [
    "ALLOCATOR_LIBS",
    "CPU_FLAGS_OF_INTEREST",
    "active_allocator",
    "configure_threads",
    "cpu_features",
    "describe_cpu",
    "open3d_parallelism",
    "open3d_threads",
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


CPU_FLAGS_OF_INTEREST = (
    "avx",
    "avx2",
    "fma",
    "avx512f",
    "avx512bw",
    "avx512_vnni",
    "avx512_bf16",
    "amx_bf16",
    "amx_tile",
)
"""CPU flags that decide which matrix-product kernels (fp32 / bf16) run fast."""


def cpu_features(cpuinfo: str | None = None) -> dict:
    """What this CPU offers the matrix products: model, vendor, flags, cores, torch's view.

    Args:
        cpuinfo: the text of ``/proc/cpuinfo`` (read when None; empty where unreadable).

    Returns:
        ``model``, ``vendor``, ``flags`` (those of :data:`CPU_FLAGS_OF_INTEREST` present),
        ``cores`` (logical CPUs), ``usable_cores`` (this process's affinity mask),
        ``torch_capability`` (``torch.backends.cpu.get_cpu_capability()``: the vector ISA
        torch's own kernels dispatch to), ``bf16_hardware`` (avx512_bf16 or AMX: bfloat16
        products run natively rather than emulated) and ``amx`` (AMX tiles with bf16).
    """
    import torch

    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    model = vendor = ""
    flags: set[str] = set()
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "model name" and not model:
            model = value.strip()
        elif key == "vendor_id" and not vendor:
            vendor = value.strip()
        elif key == "flags" and not flags:
            flags = set(value.split())
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count()
    amx = {"amx_bf16", "amx_tile"} <= flags
    return {
        "model": model or platform.processor() or platform.machine(),
        "vendor": vendor or "unknown",
        "flags": [f for f in CPU_FLAGS_OF_INTEREST if f in flags],
        "cores": os.cpu_count(),
        "usable_cores": usable,
        "torch_capability": torch.backends.cpu.get_cpu_capability(),
        "bf16_hardware": bool("avx512_bf16" in flags or amx),
        "amx": amx,
    }


def describe_cpu(features: dict | None = None) -> str:
    """One line naming the CPU and what it has, e.g. for a benchmark report's header."""
    f = features if features is not None else cpu_features()
    bf16 = "AMX bf16" if f["amx"] else ("avx512_bf16" if f["bf16_hardware"] else "no bf16 GEMM")
    return (
        f"{f['model']} ({f['vendor']}), {f['usable_cores']}/{f['cores']} cores, flags "
        f"{' '.join(f['flags']) or '-'}; torch dispatches {f['torch_capability']}; {bf16}"
    )


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


class _TBBGlobalControl(ctypes.Structure):
    """oneTBB's ``tbb::global_control`` (libtbb.so.12 ABI: value, reserved, parameter)."""

    _fields_ = [("value", ctypes.c_size_t), ("reserved", ctypes.c_ssize_t), ("param", ctypes.c_int)]


_TBB_MAX_ALLOWED_PARALLELISM = 0  # tbb::global_control::max_allowed_parallelism
_tbb_api: tuple | bool | None = False  # False: not looked up yet; None: unavailable


def _open3d_tbb():
    """(create, destroy, active_value) of the oneTBB library Open3D uses, or None."""
    global _tbb_api
    if _tbb_api is not False:
        return _tbb_api
    _tbb_api = None
    try:
        import open3d

        here = Path(open3d.__file__).parent
        names = [p for p in sorted(here.glob("libtbb*")) if ".so" in p.name or ".dylib" in p.name]
        lib = ctypes.CDLL(str(names[0])) if names else ctypes.CDLL("libtbb.so.12")
        create = lib._ZN3tbb6detail2r16createERNS0_2d114global_controlE
        destroy = lib._ZN3tbb6detail2r17destroyERNS0_2d114global_controlE
        active = lib._ZN3tbb6detail2r127global_control_active_valueEi
    except (ImportError, OSError, AttributeError):
        return None
    create.argtypes = destroy.argtypes = [ctypes.POINTER(_TBBGlobalControl)]
    create.restype = destroy.restype = None
    active.argtypes, active.restype = [ctypes.c_int], ctypes.c_size_t
    _tbb_api = (create, destroy, active)
    return _tbb_api


def open3d_parallelism() -> int | None:
    """How many threads Open3D's parallel loops may use now (oneTBB's limit), None if unknown."""
    api = _open3d_tbb()
    return None if api is None else int(api[2](_TBB_MAX_ALLOWED_PARALLELISM))


@contextlib.contextmanager
def open3d_threads(n: int = 1) -> Iterator[None]:
    """Let Open3D's parallel loops use at most ``n`` threads inside the ``with`` block.

    oneTBB's ``global_control(max_allowed_parallelism, n)``: process-wide while it lives, and
    the smallest of the limits alive wins. Where Open3D's oneTBB cannot be found (another build
    of Open3D), warns and runs as is.
    """
    if n < 1:
        raise ValueError(f"open3d_threads: n must be >= 1, got {n}")
    api = _open3d_tbb()
    if api is None:
        warnings.warn(
            "open3d: its oneTBB library was not found, so its thread count cannot be set; "
            "Open3D's RANSAC then runs multi-threaded and its result can change from run to run",
            RuntimeWarning,
            stacklevel=3,
        )
        yield
        return
    create, destroy, _ = api
    control = _TBBGlobalControl(int(n), 0, _TBB_MAX_ALLOWED_PARALLELISM)
    create(ctypes.byref(control))
    try:
        yield
    finally:
        destroy(ctypes.byref(control))
