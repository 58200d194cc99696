"""The test suite's own rules: no test module imports another, and the selection by module
(tests/selection.py) names only modules that exist.

A test module imported by another runs its fixtures and module-level code twice over, and
ties a refactoring of one file's tests to every file that borrowed from it: what tests share
lives in a helper module (tests/buses.py, tests/can_net.py, ...).
"""

from __future__ import annotations

import ast

from tests.selection import (
    HELPER_MODULES,
    PROCESS_MODULES,
    SERIAL_MODULES,
    SERIAL_PASS_MODULES,
    SERIAL_TESTS,
    TESTS,
    VCAN_VM_MODULES,
    module_paths,
)


def _imported(tree: ast.Module) -> set[str]:
    """Every module an ``import`` or ``from ... import`` names, with the names imported from a
    package (``from tests import test_x`` is ``tests.test_x``)."""
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
        elif (isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "pytest_plugins" for t in node.targets)
              and isinstance(node.value, ast.List | ast.Tuple)):
            found.update(e.value for e in node.value.elts
                         if isinstance(e, ast.Constant) and isinstance(e.value, str))
    return found


def test_no_module_of_the_tests_imports_a_test_module() -> None:
    offenders = []
    for path in sorted(TESTS.glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for name in sorted(_imported(tree)):
            if name.startswith("tests.test_"):
                offenders.append(f"tests/{path.name} imports {name}")
    assert not offenders, ("a test module is imported; move what is shared into a helper "
                           "module (tests/can_net.py, ...):\n" + "\n".join(offenders))


def test_the_rule_sees_each_spelling_of_an_import() -> None:
    source = ("import tests.test_a\nfrom tests.test_b import x\nfrom tests import test_c\n"
              "pytest_plugins = ['tests.test_d']\n")
    seen = {n for n in _imported(ast.parse(source)) if n.startswith("tests.test_")}
    assert seen == {"tests.test_a", "tests.test_b", "tests.test_b.x", "tests.test_c",
                    "tests.test_d"}


def test_the_selection_names_test_modules_that_exist() -> None:
    modules = {path.stem for path in TESTS.glob("test_*.py")}
    for listed in (PROCESS_MODULES, VCAN_VM_MODULES, SERIAL_MODULES):
        assert listed <= modules, f"tests/selection.py lists no such module: {listed - modules}"
    assert VCAN_VM_MODULES <= PROCESS_MODULES and SERIAL_MODULES <= PROCESS_MODULES
    assert "tests.buses" in HELPER_MODULES and not any(
        name.startswith("tests.test_") for name in HELPER_MODULES)


def test_the_serial_tests_name_test_functions_that_exist() -> None:
    """A renamed test would silently run in the parallel pass again."""
    for module, name in SERIAL_TESTS:
        tree = ast.parse((TESTS / f"{module}.py").read_text(encoding="utf-8"))
        functions = {node.name for node in tree.body if isinstance(node, ast.FunctionDef)}
        assert name in functions, f"tests/selection.py: no {name} in tests/{module}.py"
        assert module in PROCESS_MODULES


def test_the_serial_pass_collects_the_files_of_the_serial_modules_only() -> None:
    """make test's second pass takes these paths (``python -m tests.selection serial``): each
    is the file of a serial module or of a module with serial tests, from the clone's root,
    and none is left out."""
    paths = module_paths(SERIAL_PASS_MODULES)
    assert paths == sorted({f"tests/{module}.py" for module in SERIAL_MODULES}
                           | {f"tests/{module}.py" for module, _ in SERIAL_TESTS})
    assert all((TESTS.parent / path).is_file() for path in paths)
