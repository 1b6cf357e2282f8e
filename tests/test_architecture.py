"""The package's shape, read from its source (STYLE.md, one concept, one place): no class name is
defined twice, and the package's own modules are imported at the top of each file."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "cloudpose"


def _modules() -> dict[str, ast.Module]:
    """Path relative to the repository (``cloudpose/store/runs.py``) -> its parsed source."""
    return {
        p.relative_to(PACKAGE.parent).as_posix(): ast.parse(p.read_text(), str(p))
        for p in sorted(PACKAGE.rglob("*.py"))
    }


def test_no_class_name_is_defined_twice():
    where = defaultdict(list)
    for path, tree in _modules().items():
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                where[node.name].append(f"{path}:{node.lineno}")
    twice = {name: places for name, places in where.items() if len(places) > 1}
    assert not twice, f"class names defined more than once (rename each for what it holds): {twice}"


# ------------------------------------------------------------------------ imports at the top

KEPT_LAZY = {
    # (file, module imported inside a function): how many, and why not at the top. None breaks
    # a circle (the package's top-level imports have none); each keeps a heavy library out of
    # a light command's start-up, measured with that import at the top:
    # - `cloudpose mlflow-server` imports suite.cluster (its port check), which imports
    #   store.runs: the pipeline or store.pretrained at their tops load torch, numba and scipy
    #   (0.4 s -> 7.7 s to start on a busy 2-core machine).
    # - `store-pack` and `store-unpack` import archive.pack -> archive.compact ->
    #   archive.checkpoints, store.instances: infer and data/ at the top add numba and
    #   scipy, geometry adds roma and sympy (1.6-1.7x the CPU time to start).
    ("cloudpose/store/runs.py", "cloudpose.store.pretrained"): 2,
    ("cloudpose/suite/cluster.py", "cloudpose.suite"): 1,  # the pipeline
    ("cloudpose/archive/checkpoints.py", "cloudpose.infer"): 1,
    ("cloudpose/archive/checkpoints.py", "cloudpose.geometry.rigid"): 1,
    ("cloudpose/archive/checkpoints.py", "cloudpose.data.dataset"): 1,
    ("cloudpose/archive/checkpoints.py", "cloudpose.data.layout"): 1,
    ("cloudpose/archive/checkpoints.py", "cloudpose.data.segments"): 1,
    ("cloudpose/store/instances.py", "cloudpose.geometry.rotations"): 2,
    # the reports read the evaluation's metric names at their tops without loading torch
    # (tests/test_evaluate.py), which cloudpose.metrics loads
    ("cloudpose/store/metric_names.py", "cloudpose.metrics"): 2,
}


def _own_module(node: ast.Import | ast.ImportFrom) -> str | None:
    """The package module an import statement names (None: a third-party or stdlib one)."""
    if isinstance(node, ast.ImportFrom):
        ours = node.level == 0 and (node.module or "").split(".")[0] == "cloudpose"
        return node.module if ours else None
    names = [a.name for a in node.names if a.name.split(".")[0] == "cloudpose"]
    return names[0] if names else None


def _imports_inside_functions() -> dict[tuple[str, str], list[int]]:
    """(file, module) -> lines of each import of the package inside a function, outside cli/."""
    found = defaultdict(list)
    for path, tree in _modules().items():
        if path.startswith("cloudpose/cli/"):
            continue
        seen = set()
        for fn in ast.walk(tree):
            if not isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            for node in ast.walk(fn):
                if isinstance(node, ast.Import | ast.ImportFrom) and id(node) not in seen:
                    seen.add(id(node))
                    module = _own_module(node)
                    if module is not None:
                        found[(path, module)].append(node.lineno)
    return found


def test_the_packages_own_modules_are_imported_at_the_top():
    found = _imports_inside_functions()
    kept = {k: len(v) for k, v in found.items()}
    moved = {
        k: found.get(k, [])
        for k in kept.keys() | KEPT_LAZY.keys()
        if kept.get(k) != KEPT_LAZY.get(k)
    }
    assert not moved, (
        "imports of cloudpose modules inside functions, (file, module) -> lines: move them to "
        "the top, or (a circle, a measured start-up cost) list them in KEPT_LAZY with the "
        f"reason; one listed there and now at the top leaves the list: {moved}"
    )


# ------------------------------------------------------------------------ rooms and sizes

MAX_TOP_LEVEL_MODULES = 12
"""``cloudpose/*.py``: the core's modules; a new concept makes a package of its own (issue 63)."""
MAX_FUNCTION_LINES = 120
"""The longest a function may be, numba kernels (``@njit``: one compiled loop) aside."""


def test_the_top_level_holds_at_most_twelve_modules():
    top = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(top) <= MAX_TOP_LEVEL_MODULES, f"{len(top)} modules in cloudpose/: {top}"


def _decorated_njit(node: ast.FunctionDef) -> bool:
    names = []
    for d in node.decorator_list:
        d = d.func if isinstance(d, ast.Call) else d
        names.append(d.attr if isinstance(d, ast.Attribute) else getattr(d, "id", ""))
    return any(n in ("njit", "jit") for n in names)


def test_no_function_is_over_120_lines_outside_numba_kernels():
    long = [
        f"{path}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for path, tree in _modules().items()
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES
        and not _decorated_njit(node)
    ]
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines (split into named steps): {long}"


def _imported(tree: ast.Module) -> set[str]:
    """Every module a file imports, at the top or inside a function."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
    return out


def test_the_tracking_store_sits_below_inference_and_the_archive():
    """store/ is MLflow tracking: it imports neither the network's inference nor the packing of
    stores for git (archive/ builds on it, not the other way)."""
    wrong = {
        path: sorted(
            m
            for m in _imported(tree)
            if m.split(".")[:2] in (["cloudpose", "infer"], ["cloudpose", "archive"])
        )
        for path, tree in _modules().items()
        if path.startswith("cloudpose/store/")
    }
    wrong = {k: v for k, v in wrong.items() if v}
    assert not wrong, f"store/ importing infer or archive: {wrong}"


def test_the_readmes_layout_names_every_module_and_package_of_the_top_level():
    """Every ``cloudpose/*.py`` and package is named in the README's Layout, and every
    path it names (a word ending in ``.py`` or ``/``) is in the tree."""
    readme = (PACKAGE.parent / "README.md").read_text()
    block = readme.split("## Layout", 1)[1].split("```")[1]
    paths = {
        w.removeprefix("cloudpose/")
        for w in block.split()
        if w.endswith((".py", "/")) and w.removeprefix("cloudpose/")
    }
    tree = {p.name for p in PACKAGE.glob("*.py") if p.name != "__init__.py"}
    tree |= {f"{p.name}/" for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    assert not tree - paths, f"README's Layout does not name: {sorted(tree - paths)}"
    assert not paths - tree, f"README's Layout names what cloudpose/ lacks: {sorted(paths - tree)}"
