"""On-line chunks kept on disk: synthesized once per seed, trained on by every variant.

Chunk ``j`` of an on-line run (:class:`~cloudpose.data.synth.online.OnlineChunks`) is a pure
function of the synthesis settings (:class:`OnlineSettings`, here: they are the store's key),
the seed, the chunk size and ``j``. The variants of a
preset share all of these (they differ in the network and the loss), so at one seed they train
on the same segments, and synthesis, not the training step, sets a run's pace on a small
machine (on a 2-core Xeon: ~180 ms a chunk of 8 segments against ~120 ms a training step of
batch 32, one core each). A
:class:`ChunkStore` keeps each chunk as it is made; a later run of the same seed reads it
instead of synthesizing it again. What a run trains on is unchanged to the bit: a stored chunk
holds the synthesized float32 tensors themselves, and the training process keeps the threads
it has without the store (tested).

The key of a store folder covers everything a chunk depends on: the synthesis settings, the
chunk size, the code of the modules that could make it (``cloudpose/data``,
``cloudpose/kernels``, ``cloudpose/geometry``, ``conventions.py``, this module aside; as syntax
trees without their prose and layout, so an edit of a docstring or comment, an import moved into
or out of a function and a definition moved to another module keep the key), the packaged model
points and surfaces, and the versions of the numeric libraries. Edit the sensor model and the
next run synthesizes afresh into a new folder; nothing stale is read. What the key does not
cover: the CPU. Compiled kernels can round differently on another instruction set, as synthesis
without a store would; a store carried to another machine gives that machine's runs the chunks
of the machine that made them.

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
import dataclasses
import functools
import hashlib
import importlib.metadata
import json
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from cloudpose.config import (
    BLEED_BRANCHES,
    GENERATOR_VERSION,
    ONLINE_SCENE_MIN_CLASSES,
    ONLINE_SCENES,
    VERSION_3_SETTINGS,
    check_online_version,
    check_synth_version,
)
from cloudpose.conventions import resource_path
from cloudpose.files import CorruptFileError, atomic_text, atomic_write, read_npz

if TYPE_CHECKING:
    from cloudpose.config import Config

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


@dataclasses.dataclass(frozen=True)
class OnlineSettings:
    """What on-line segments are made with (:class:`~cloudpose.data.synth.online.OnlineSynth`):
    every setting a chunk depends on besides the seed, the chunk size and its index, so the
    key of a :class:`ChunkStore`.

    Attributes:
        synth_version: generator version (``data.synth_version``,
            :data:`~cloudpose.config.GENERATOR_VERSIONS`): its surfaces, stacking share and
            sensor model.
        noise: apply the version's sensor model (``data.noise``).
        n_points: points per segment (``train.n_points``: the FPS prefix the network sees).
        outlier_radius: the segment path's outlier filter, metres (``data.outlier_radius``).
        class_ids: keep segments of these 1-based classes only (``data.classes`` as ids,
            sorted); None: all.
        online_scenes: with ``class_ids``, what the scenes hold (``data.online_scenes``,
            :data:`~cloudpose.config.ONLINE_SCENES`): "all", objects of every class, the others
            staying in the scene as occluders (the scenes of the test frames); "classes",
            objects of the kept classes only (at least 3 of them), so no scene is drawn for
            segments it then drops: with 3 of the 21 classes ~5x the segments per second, at
            the price of occluders of those classes only.
        online_version: how the segments are made (``data.online_version``,
            :data:`~cloudpose.config.ONLINE_VERSIONS`): 1, the ray cast path; 2,
            the same scenes, sensor and segment path computed by compiled kernels (a z-buffer
            of the meshes instead of the ray cast, the sensor's edge distance and correlated
            field compiled, segments cut in one pass): the same random draws and the same
            numbers to float rounding (:mod:`cloudpose.data.synth.online`, "Version 2"); 3,
            the same scenes and sensor model, a scene's objects in a few compiled passes
            with draws of their own: the same distribution, other segments ("Version 3").
        online_bleed: version 3's masks grown into the pixels next to them
            (``data.online_bleed``: the largest share of them an object takes).
        online_bleed_branch: which branch's segments bleed (``data.online_bleed_branch``):
            "both", or "translation": each segment is cut from the rendered masks and from the
            bleeding ones, its ``n_points`` rows of the first form then those of the second
            (:attr:`forms`); "translation-paired" likewise, the first form drawn as without
            bleeding (:data:`~cloudpose.config.PAIRED_BRANCH`).
        online_smooth: version 3's depth readings averaged over each object's own
            (``data.online_smooth``: the Gaussian's sigma, pixels).
        online_noise_corr: version 3's axial noise off depth edges correlated over pixels
            (``data.online_noise_corr``: the Gaussian's sigma, pixels).
    """

    synth_version: int = GENERATOR_VERSION
    noise: bool = True
    n_points: int = 256
    outlier_radius: float = 0.2
    class_ids: tuple[int, ...] | None = None
    online_scenes: str = "all"
    online_version: int = 1
    online_bleed: float = 0.0
    online_bleed_branch: str = "both"
    online_smooth: float = 0.0
    online_noise_corr: float = 0.0

    @property
    def forms(self) -> int:
        """Forms of each segment side by side along its points: 2 with the translation branch
        alone on bleeding masks (rendered, then bleeding), else 1."""
        return 1 if self.online_bleed_branch == "both" else 2

    @property
    def cuts_from_scene(self) -> bool:
        """Whether segments are cut from the whole rendered scene (version 3's path: masks,
        ring, bleeding, smoothing and correlated noise), not from a window around each object
        (version 1's noisy sensor takes the window path, which has none of them)."""
        return self.online_version >= 3 and (self.synth_version >= 2 or not self.noise)

    def __post_init__(self) -> None:
        check_synth_version(self.synth_version)
        check_online_version(self.online_version)
        if self.n_points < 1:
            raise ValueError(f"on-line n_points must be >= 1, got {self.n_points}")
        if self.online_bleed_branch not in BLEED_BRANCHES:
            raise ValueError(
                f"on-line bleed branch {self.online_bleed_branch!r}: expected one of "
                f"{BLEED_BRANCHES}"
            )
        if self.forms == 2 and not (self.online_bleed and self.cuts_from_scene):
            raise ValueError(
                f"on-line segments in two forms (bleed branch {self.online_bleed_branch!r}) need "
                "bleeding masks of version 3's path (online_bleed > 0, online_version 3, "
                f"synth_version >= 2 or no noise); got online_bleed={self.online_bleed}, "
                f"online_version={self.online_version}, synth_version={self.synth_version}, "
                f"noise={self.noise}"
            )
        if self.online_scenes not in ONLINE_SCENES:
            raise ValueError(
                f"on-line scenes {self.online_scenes!r}: expected one of {ONLINE_SCENES}"
            )
        if self.class_ids is not None:
            ids = tuple(sorted({int(c) for c in self.class_ids}))
            if not ids:
                raise ValueError("on-line classes: expected a non-empty set of model ids")
            few = len(ids) < ONLINE_SCENE_MIN_CLASSES
            if self.online_scenes == "classes" and few:
                raise ValueError(
                    f"on-line scenes 'classes' need at least {ONLINE_SCENE_MIN_CLASSES} "
                    f"classes (a table scene holds {ONLINE_SCENE_MIN_CLASSES} or more distinct "
                    f"objects); got {list(ids)}"
                )
            object.__setattr__(self, "class_ids", ids)

    @classmethod
    def from_config(cls, cfg: Config, class_names: list[str]) -> OnlineSettings:
        """The settings of an on-line run of ``cfg``: the generator version, noise and segment
        settings of ``cfg.data``, ``train.n_points``, and the ids of ``data.classes`` in
        ``class_names`` (the dataset's ``classes.txt``), every class when empty."""
        d = cfg.data
        if d.root:
            raise ValueError(
                f"data.train_source='online' synthesizes YCB-Video scenes from the packaged "
                f"models; it cannot be combined with data.root={d.root!r} (train on its frames "
                "instead)"
            )
        classes = None
        if d.classes:
            classes = tuple(sorted(class_names.index(c) + 1 for c in d.classes))
        return cls(
            synth_version=d.synth_version,
            noise=d.noise,
            n_points=cfg.train.n_points,
            outlier_radius=d.outlier_radius,
            class_ids=classes,
            online_scenes=d.online_scenes,
            online_version=d.online_version,
            online_bleed=d.online_bleed,
            online_bleed_branch=d.online_bleed_branch,
            online_smooth=d.online_smooth,
            online_noise_corr=d.online_noise_corr,
        )


class _Imports(ast.NodeTransformer):
    """Takes every import statement out of a syntax tree, at any depth, into :attr:`names`:
    one line per name bound from another library (``from M import N as A``). Imports of the
    package's own modules are left out: their code is in the digest wherever it lives, so a
    definition moved to another module, and the import that follows it, keep the key."""

    def __init__(self) -> None:
        self.names: set[str] = set()

    def visit_Import(self, node: ast.Import) -> None:
        for a in node.names:
            if a.name.split(".")[0] != "cloudpose":
                self.names.add(f"import {a.name} as {a.asname or a.name}")

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        module = node.module or ""
        if node.level == 0 and module.split(".")[0] != "cloudpose":
            for a in node.names:
                self.names.add(f"from {module} import {a.name} as {a.asname or a.name}")


def _code_of(path: Path) -> tuple[set[str], set[str]]:
    """A module's code without its prose and its layout: ``(imports, statements)``, the names
    it imports (:class:`_Imports`) and each top-level statement's syntax tree dumped, with
    docstrings, comments, import statements and ``__all__`` left out. Edits of the prose, an
    import moved into or out of a function and a definition moved to another module keep
    what this gives for the modules together; edits of the code change it."""
    tree = ast.parse(path.read_bytes(), filename=str(path))
    imports = _Imports()
    tree = imports.visit(tree)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (
            isinstance(body, list)
            and body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            node.body = body = body[1:]
        if isinstance(body, list) and not body and not isinstance(node, ast.Module):
            node.body = [ast.Pass()]  # a block that held only imports or a docstring
    statements = {
        ast.dump(stmt)
        for stmt in tree.body
        if not (
            isinstance(stmt, ast.Assign)
            and any(isinstance(t, ast.Name) and t.id == "__all__" for t in stmt.targets)
        )
    }
    return imports.names, statements


def _digest_code(paths: list[Path]) -> str:
    """Digest of modules' code together (:func:`_code_of`): not of their names or order."""
    names: set[str] = set()
    statements: set[str] = set()
    for p in paths:
        i, s = _code_of(p)
        names |= i
        statements |= s
    h = hashlib.blake2b(digest_size=16)
    for line in sorted(names) + sorted(statements):
        h.update(line.encode())
        h.update(b"\0")
    return h.hexdigest()


def _digest_files(paths: list[Path], base: Path) -> str:
    h = hashlib.blake2b(digest_size=16)
    for p in sorted(paths):
        h.update(str(p.relative_to(base)).encode())
        h.update(p.read_bytes())
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
    h.update(_digest_code(_synthesis_sources(package)).encode())
    h.update(_digest_files(_files_under(resources, _RESOURCE_PARTS, None), resources).encode())
    for lib in _LIBRARIES:
        try:
            h.update(f"{lib}={importlib.metadata.version(lib)};".encode())
        except importlib.metadata.PackageNotFoundError:
            h.update(f"{lib}=-;".encode())
    return h.hexdigest()


def store_settings(settings: OnlineSettings, chunk_size: int) -> dict[str, Any]:
    """The parts of a store's key, as written to its ``settings.json``: the synthesis settings
    field by field, the chunk size and the synthesis code (:func:`code_digest`)."""
    synth = dataclasses.asdict(settings)
    for name in VERSION_3_SETTINGS:  # at its default, a field is left out: older keys stay
        if not synth[name]:
            del synth[name]
    if synth["online_bleed_branch"] == "both":
        del synth["online_bleed_branch"]
    if synth["class_ids"] is not None:
        synth["class_ids"] = list(synth["class_ids"])
    return {"synth": synth, "chunk_size": int(chunk_size), "code": code_digest()}


class ChunkStore:
    """The stored chunks of one synthesis setting and chunk size, for any seed.

    Args:
        root: the store's root folder (a project's is ``data/cache/online``).
        settings: what the chunks are made with.
        chunk_size: segments per chunk.
    """

    def __init__(self, root: str | Path, settings: OnlineSettings, chunk_size: int) -> None:
        self.settings = store_settings(settings, chunk_size)
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
        finite float32 points (twice that in two forms), int64 classes, float32 rotations and
        translations."""
        n, k = self.settings["chunk_size"], self.settings["synth"]["n_points"]
        if self.settings["synth"].get("online_bleed_branch", "both") != "both":
            k *= 2  # the rendered form's points, then the bleeding form's
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
