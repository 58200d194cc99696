"""The CiA 309 package keeps Lely's split of ``gw`` and ``gw_txt``: no module of the typed
service layer imports the 309-3 text layer, directly or through another module."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).parent.parent / "host_api" / "cia309"
TYPED = {"model", "link", "events", "pdo", "gateway"}
TEXT = {"framing", "parser", "requests", "formatters", "datatypes", "server", "cli"}


def _imports(module: str) -> set[str]:
    """The modules of this package that ``module`` imports."""
    tree = ast.parse((PACKAGE / f"{module}.py").read_text())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            parts = node.module.split(".")
            if parts[:2] == ["host_api", "cia309"] and len(parts) == 3:
                found.add(parts[2])
    return found


def test_the_typed_layer_never_reaches_the_text_layer() -> None:
    assert {path.stem for path in PACKAGE.glob("*.py")} >= TYPED | TEXT
    for module in TYPED:
        reached, todo = set(), [module]
        while todo:
            for imported in _imports(todo.pop()) - reached:
                reached.add(imported)
                todo.append(imported)
        assert not reached & TEXT, f"{module} reaches {sorted(reached & TEXT)}"
