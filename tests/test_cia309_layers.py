"""The CiA 309 package keeps Lely's split of ``gw`` and ``gw_txt``: no module of the typed
service layer imports the 309-3 text layer, directly or through another module; and its
exceptions have one root."""

from __future__ import annotations

import ast
import importlib
import inspect
from pathlib import Path

PACKAGE = Path(__file__).parent.parent / "host_api" / "cia309"
TYPED = {"model", "link", "events", "pdo", "gateway"}
TEXT = {"framing", "parser", "requests", "formatters", "datatypes", "server"}
"""The command line over them is ``cifemu.commands.cia309``, a layer above both."""


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
        reached: set[str] = set()
        todo = [module]
        while todo:
            for imported in _imports(todo.pop()) - reached:
                reached.add(imported)
                todo.append(imported)
        assert not reached & TEXT, f"{module} reaches {sorted(reached & TEXT)}"


def test_one_exception_root() -> None:
    """Every exception class the package defines derives from Cia309Error, so a program
    catches the package's failures with one clause."""
    root = importlib.import_module("host_api.cia309.model").Cia309Error
    found = []
    for path in sorted(PACKAGE.glob("*.py")):
        module = importlib.import_module(f"host_api.cia309.{path.stem}")
        for _, item in inspect.getmembers(module, inspect.isclass):
            if issubclass(item, BaseException) and item.__module__ == module.__name__:
                found.append(item)
                assert issubclass(item, root), f"{item.__qualname__} is no Cia309Error"
    assert len(found) >= 4  # the root, ParseError, DataTypeError, LssError
