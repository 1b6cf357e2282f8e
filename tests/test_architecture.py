"""The package's shape, read from its source (docs/STYLE: one concept, one place): no class name
is defined twice, and the package's own modules are imported at the top of each file."""

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
