"""The project's packages import each other without cycles (issue 15's acceptance).

The graph is read from the source with ``ast``, not by importing: an edge is any
``import`` or ``from ... import`` of a project module, at module level or inside a
function (a lazy import still ties the two modules together), except those under
``if TYPE_CHECKING:``, which never run. ``from package import name`` is an edge to
the submodule ``package.name`` when there is one, else to the package itself, whose
``__init__`` then runs.
"""

from __future__ import annotations

import ast
import importlib
from collections.abc import Iterator
from importlib.metadata import version
from pathlib import Path

from tests.conftest import ROOT

PACKAGES = ("dpm", "firmware", "host_api", "dbm_tools", "cifemu", "bench")

Graph = dict[str, set[str]]


def module_names(root: Path, packages: tuple[str, ...]) -> dict[str, Path]:
    """Every module of ``packages`` under ``root``: dotted name -> file."""
    found = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST) -> Iterator[ast.Import | ast.ImportFrom]:
    """The import statements that can run: everything but ``if TYPE_CHECKING:`` bodies."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.orelse:
                yield from _imports(ast.Module(body=[child], type_ignores=[]))
            continue
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node
        yield from _imports(node)


def _absolute(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".")
    base = base if is_package else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def import_graph(root: Path, packages: tuple[str, ...] = PACKAGES) -> Graph:
    """Module -> the project modules it imports."""
    modules = module_names(root, packages)
    graph: Graph = {name: set() for name in modules}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        for node in _imports(tree):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                source = _absolute(node, name, path.name == "__init__.py")
                targets = [f"{source}.{alias.name}" if f"{source}.{alias.name}" in modules
                           else source for alias in node.names]
            graph[name].update(t for t in targets if t in modules and t != name)
    return graph


def cycles(graph: Graph) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph[node]):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(found)


def describe(component: list[str], graph: Graph) -> str:
    """One component with the edges that close it, e.g. ``a -> b, b -> a``."""
    members = set(component)
    edges = [f"{a} -> {b}" for a in component for b in sorted(graph[a] & members)]
    return "; ".join(edges)


def test_the_packages_import_each_other_without_cycles() -> None:
    graph = import_graph(ROOT)
    assert "host_api.driver" in graph and "bench.can.card" in graph  # the walk found the tree
    found = cycles(graph)
    assert not found, "import cycles:\n" + "\n".join(describe(c, graph) for c in found)


def test_a_cycle_is_found_and_type_checking_imports_are_not_edges(tmp_path: Path) -> None:
    """The checker itself, on a package written for it: a lazy cycle counts, and an import
    under ``if TYPE_CHECKING:`` does not."""
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "__init__.py").write_text("from pkg.a import A\n")
    (package / "a.py").write_text("A = 1\n\ndef f():\n    from . import b\n")
    (package / "b.py").write_text("from pkg import a\n")
    (package / "c.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.d import D\n")
    (package / "d.py").write_text("import pkg.c\nD = 2\n")
    graph = import_graph(tmp_path, ("pkg",))
    assert graph["pkg"] == {"pkg.a"}
    assert graph["pkg.c"] == set() and graph["pkg.d"] == {"pkg.c"}
    assert cycles(graph) == [["pkg.a", "pkg.b"]]


def test_each_package_facade_gives_what_it_lists_and_the_distributions_version() -> None:
    """``from PACKAGE import NAME`` works for every NAME in ``__all__`` (firmware's load on
    first use), and ``__version__`` is the installed distribution's."""
    expected = version("cifemu")
    for name in ("dpm", "firmware", "host_api", "dbm_tools", "cifemu"):
        package = importlib.import_module(name)
        assert package.__all__, name
        missing = [item for item in package.__all__ if getattr(package, item, None) is None]
        assert not missing, f"{name} lists {missing} but has no such names"
        assert package.__version__ == expected, name


def test_the_architecture_page_names_every_modules_job() -> None:
    """docs/architecture.md's module table lists every module of every package with its job."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    rows = {line.split("`", 2)[1].rstrip("/"): line for line in text.splitlines()
            if line.startswith("| `") and "`: " in line}
    missing = []
    for name, path in module_names(ROOT, PACKAGES).items():
        if path.name in ("__init__.py", "__main__.py"):
            continue
        package, module = str(path.parent.relative_to(ROOT)), path.stem
        if f"`{module}`: " not in rows.get(package, ""):
            missing.append(name)
    assert not missing, f"modules without their job in docs/architecture.md: {missing}"
