"""The package's shape, read from its source (STYLE.md, one concept, one place): no class name is
defined twice, every import at the top of its file but those of the few heavy libraries listed
here, the top level small, no function over 120 lines, the tracking store below inference."""

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

LAZY_LIBRARIES = {
    # The one list of what may be imported inside a function outside cli/: a heavy library
    # (its import alone, measured with `python -X importtime -c "import X"` on a 2-core machine:
    # mlflow ~1.9 s, torch ~1.6 s, open3d ~1.4 s, scipy.stats ~0.7 s, matplotlib.pyplot ~0.5 s,
    # scipy.spatial ~0.4 s, cv2 ~0.4 s, on a busy machine; pyarrow 0.2 s, tqdm, PIL or filelock
    # under 0.1 s are at the top) that a module loads only on the path that needs it, so
    # that a command which never takes that path does not start with it (`cloudpose --help`,
    # `mlflow-ui` before the store opens, the reports' Markdown), or an optional dependency.
    "mlflow": "tracking calls only; the reports and the registry read names without it",
    "torch": "runtime.py and store/runs.py: thread settings and checkpoint reads only",
    "open3d": "the renderer, ICP and FPFH only",
    "scipy": "the paths that read .mat files, build k-d trees or compute statistics only",
    "matplotlib": "the plots only",
    "cv2": "the point-pair features baseline only",
    "ray": "optional (`pip install -e '.[cluster]'`): the Ray executor only",
}


def _imported_module(node: ast.Import | ast.ImportFrom) -> str:
    """The module an import statement names (``cloudpose`` for a relative one)."""
    if isinstance(node, ast.ImportFrom):
        return "cloudpose" if node.level else node.module or ""
    return node.names[0].name


def _imports_inside_functions() -> dict[tuple[str, str], list[int]]:
    """(file, module) -> lines of each import inside a function, outside cli/ (whose commands
    import what each needs when it runs, so that the help starts at once)."""
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
                    found[(path, _imported_module(node))].append(node.lineno)
    return found


def test_the_packages_own_modules_are_imported_at_the_top():
    inside = {k: v for k, v in _imports_inside_functions().items() if k[1].startswith("cloudpose")}
    assert not inside, (
        "imports of cloudpose modules inside functions, (file, module) -> lines: move them to "
        f"the top (a circle is a layering to fix, not a reason): {inside}"
    )


def test_only_the_listed_heavy_libraries_are_imported_inside_functions():
    other = {
        k: v
        for k, v in _imports_inside_functions().items()
        if not k[1].startswith("cloudpose") and k[1].split(".")[0] not in LAZY_LIBRARIES
    }
    assert not other, (
        "imports inside functions, (file, module) -> lines: move them to the top, or (a heavy "
        f"library, its import measured) add it to LAZY_LIBRARIES with the reason: {other}"
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
