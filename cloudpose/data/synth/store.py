"""On-line chunks kept on disk: synthesized once per seed, trained on by every variant.

Chunk ``j`` of an on-line run (:class:`~cloudpose.data.synth.online.OnlineChunks`) is a pure
function of the synthesis settings, the seed, the chunk size and ``j``. The variants of a
preset share all of these (they differ in the network and the loss), so at one seed they train
on the same segments, and synthesis, not the training step, sets a run's pace on a small
machine (on a 2-core Xeon: ~180 ms a chunk of 8 segments against ~120 ms a training step of
batch 32, one core each). A
:class:`ChunkStore` keeps each chunk as it is made; a later run of the same seed reads it
instead of synthesizing it again. What a run trains on is unchanged to the bit: a stored chunk
holds the synthesized float32 tensors themselves, and the training process keeps the threads
it has without the store (tested).

The key of a store folder covers everything a chunk depends on: the :class:`OnlineSynth`
arguments, the chunk size, the code of the modules that could make it (``cloudpose/data``,
``cloudpose/kernels``, ``cloudpose/geometry``, ``conventions.py``, this module aside; as syntax
trees, so an edit of a docstring or comment keeps the key), the packaged model points and
surfaces, and the versions of the numeric libraries. Edit the sensor model and the next run
synthesizes afresh into a new folder; nothing stale is read. What the key does not cover: the
CPU. Compiled kernels can round differently on another instruction set, as synthesis without a
store would; a store carried to another machine gives that machine's runs the chunks of the
machine that made them.

Layout: ``ROOT/KEY/settings.json`` (the key's parts, readable) and
``ROOT/KEY/seed-S/chunk-JJJJJJ.npz`` (points, cls_id, R, t, and where = (S, J): a file copied
to another chunk's name is found; ~26 kB at 8 segments of 256 points:
~110 MB for the 4,192 chunks of the default's 4,096 steps). Writes are atomic (a temporary file renamed),
so processes that make the same chunk at once, or a run killed mid-write, leave whole files; a
file that is unreadable (empty, truncated, garbled) or not the chunk the store expects (another
chunk size or point count, NaN) is synthesized again and replaced, with a one-line warning
naming it. Delete a folder to reclaim its space.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.metadata
import json
import warnings
from pathlib import Path

import numpy as np
import torch

from cloudpose.conventions import resource_path
from cloudpose.files import CorruptFileError, atomic_text, atomic_write, read_npz

DEFAULT_N_POINTS = 256
"""Points per on-line segment when the synthesis arguments do not say (``OnlineSynth``'s
default, which is this constant)."""

STORE_DIR = ("data", "cache", "online")
"""Where a project keeps its store, under the project folder."""

_SOURCE_PARTS = ("data", "kernels", "geometry", "conventions.py")
"""The package's modules that make a chunk (folders are read recursively): all of them, not only
the ones a chunk is known to use, so that no edit that changes chunks keeps a key."""

_RESOURCE_PARTS = ("models", "meshes", "classes.txt")
"""The packaged data a chunk is made from: model points, surfaces, class list."""

_LIBRARIES = ("numpy", "scipy", "open3d", "numba", "torch")

_FIELDS = ("points", "cls_id", "R", "t")

Chunk = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def _code_of(path: Path) -> bytes:
    """A module's code without its docstrings and comments (its syntax tree, dumped): edits
    of the prose keep a store's key, edits of the code change it."""
    tree = ast.parse(path.read_bytes(), filename=str(path))
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (
            isinstance(body, list)
            and body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree).encode()


def _digest_files(paths: list[Path], base: Path, code: bool = False) -> str:
    h = hashlib.blake2b(digest_size=16)
    for p in sorted(paths):
        h.update(str(p.relative_to(base)).encode())
        h.update(_code_of(p) if code else p.read_bytes())
    return h.hexdigest()


def _files_under(base: Path, parts: tuple[str, ...], suffix: str | None) -> list[Path]:
    out: list[Path] = []
    for part in parts:
        p = base / part
        if p.is_dir():
            out += [
                f for f in p.rglob("*") if f.is_file() and (suffix is None or f.suffix == suffix)
            ]
        elif p.is_file():
            out.append(p)
    return out


def _synthesis_sources(package: Path) -> list[Path]:
    """The modules that make a chunk: :data:`_SOURCE_PARTS`, less this one (it keeps chunks;
    it does not make them)."""
    this = Path(__file__).resolve()
    return [p for p in _files_under(package, _SOURCE_PARTS, ".py") if p.resolve() != this]


@functools.cache
def code_digest() -> str:
    """Digest of what makes a chunk besides its arguments: the package's synthesis source, its
    packaged models and surfaces, and the numeric libraries' versions (32 hex digits)."""
    package = Path(__file__).resolve().parents[2]
    resources = resource_path()
    h = hashlib.blake2b(digest_size=16)
    h.update(_digest_files(_synthesis_sources(package), package, code=True).encode())
    h.update(_digest_files(_files_under(resources, _RESOURCE_PARTS, None), resources).encode())
    for lib in _LIBRARIES:
        try:
            h.update(f"{lib}={importlib.metadata.version(lib)};".encode())
        except importlib.metadata.PackageNotFoundError:
            h.update(f"{lib}=-;".encode())
    return h.hexdigest()


def store_settings(synth_kwargs: dict, chunk_size: int) -> dict:
    """The parts of a store's key, as written to its ``settings.json``."""
    kwargs = {
        k: (sorted(int(c) for c in v) if k == "class_ids" and v is not None else v)
        for k, v in synth_kwargs.items()
        if k != "nthreads"  # speed only
    }
    return {"synth": kwargs, "chunk_size": int(chunk_size), "code": code_digest()}


class ChunkStore:
    """The stored chunks of one synthesis setting and chunk size, for any seed.

    Args:
        root: the store's root folder (a project's is ``data/cache/online``).
        synth_kwargs: :class:`~cloudpose.data.synth.online.OnlineSynth` arguments.
        chunk_size: segments per chunk.
    """

    def __init__(self, root: str | Path, synth_kwargs: dict, chunk_size: int) -> None:
        self.settings = store_settings(synth_kwargs, chunk_size)
        text = json.dumps(self.settings, sort_keys=True)
        self.key = hashlib.sha256(text.encode()).hexdigest()[:20]
        self.folder = Path(root) / self.key

    def path(self, seed: int, j: int) -> Path:
        """File of chunk ``j`` of seed ``seed``."""
        return self.folder / f"seed-{int(seed)}" / f"chunk-{int(j):06d}.npz"

    def load(self, seed: int, j: int) -> Chunk | None:
        """Chunk ``j`` of ``seed`` as ``(points, cls_id, R, t)``, None if not stored (or not
        readable: it is then made again)."""
        path = self.path(seed, j)
        if not path.is_file():
            return None
        try:
            arrays = read_npz(path, _FIELDS, "stored chunk", optional=("where",))
            self._check(path, arrays)
            where = arrays.get("where")  # absent in files stored before it was written
            if where is not None and where.tolist() != [int(seed), int(j)]:
                raise CorruptFileError(
                    path, f"stored chunk is chunk {where.tolist()} (seed, j), not {[seed, j]}"
                )
        except CorruptFileError as e:
            warnings.warn(f"{e}; synthesizing it again", stacklevel=2)
            return None
        return tuple(torch.from_numpy(arrays[k]) for k in _FIELDS)  # type: ignore[return-value]

    def _check(self, path: Path, arrays: dict[str, np.ndarray]) -> None:
        """A stored chunk is what this store makes: ``chunk_size`` segments of ``n_points``
        finite float32 points, int64 classes, float32 rotations and translations."""
        n, k = self.settings["chunk_size"], self._n_points()
        expected = {
            "points": ((n, k, 3), np.float32),
            "cls_id": ((n,), np.int64),
            "R": ((n, 3, 3), np.float32),
            "t": ((n, 3), np.float32),
        }
        for name, (shape, dtype) in expected.items():
            a = arrays[name]
            if a.shape != shape or a.dtype != dtype:
                raise CorruptFileError(
                    path,
                    f"stored chunk field {name} is {a.dtype} {a.shape}, expected "
                    f"{np.dtype(dtype)} {shape}",
                )
            if a.dtype.kind == "f" and not np.isfinite(a).all():
                raise CorruptFileError(path, f"stored chunk field {name} holds NaN or inf")

    def _n_points(self) -> int:
        """Points per segment: the synthesis argument, or its default."""
        return int(self.settings["synth"].get("n_points", DEFAULT_N_POINTS))

    def save(self, seed: int, j: int, chunk: Chunk) -> None:
        """Keep chunk ``j`` of ``seed`` (atomic: written to a temporary file, then renamed)."""
        path = self.path(seed, j)
        arrays = {k: v.numpy() for k, v in zip(_FIELDS, chunk, strict=True)}
        arrays["where"] = np.array([int(seed), int(j)], dtype=np.int64)
        try:
            settings = self.folder / "settings.json"
            if not settings.is_file():
                atomic_text(settings, json.dumps(self.settings, indent=1, sort_keys=True))
            atomic_write(path, lambda tmp: np.savez(tmp, **arrays), suffix=".npz")
        except OSError as e:  # a full disk slows later runs; it must not stop this one
            warnings.warn(f"{path}: chunk not stored ({e})", stacklevel=2)

    def stored(self, seed: int, n_chunks: int) -> int:
        """How many of chunks ``0 .. n_chunks - 1`` of ``seed`` are stored."""
        folder = self.folder / f"seed-{int(seed)}"
        if not folder.is_dir():
            return 0
        names = {p.name for p in folder.glob("chunk-*.npz")}
        return sum(f"chunk-{j:06d}.npz" in names for j in range(n_chunks))
