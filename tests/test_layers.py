"""Every import follows the layer table (issue 21): one direction for every arrow.

``dpm`` holds the card's contracts (the image, the doorbell, the facts beside the
image, the frame tap's wire format); ``dbm_tools`` the database files; ``firmware``
and ``host_api`` are the two sides of the card and meet only in ``dpm`` and
``dbm_tools``; ``cifemu`` composes them into commands and ``bench`` measures them.
The imports are read from the source with ``ast``, not by importing: a lazy import
inside a function and an import under ``if TYPE_CHECKING:`` tie the packages together
all the same (a type names the other side's concept), so both count. There is no
exception list: a new arrow the wrong way is a design change, made here on purpose.
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from pathlib import Path

from tests import commands
from tests.conftest import ROOT

ALLOWED = {
    "dpm": {"dpm"},
    "dbm_tools": {"dbm_tools", "dpm"},
    "firmware": {"firmware", "dpm", "dbm_tools"},
    "host_api": {"host_api", "dpm", "dbm_tools"},
    "cifemu": {"cifemu", "firmware", "host_api", "dpm", "dbm_tools"},
    "bench": {"bench", "cifemu", "firmware", "host_api", "dpm", "dbm_tools"},
}
"""Per package, the project packages its modules may import."""

PROJECT = frozenset(ALLOWED) | {"tests"}


def imported_packages(path: Path, own: str) -> Iterator[tuple[int, str]]:
    """(line, top-level package) of every import in ``path``, a module of ``own``."""
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                yield node.lineno, own  # a relative import stays in its package
            elif node.module is not None:
                yield node.lineno, node.module.split(".")[0]


def layer_breaks(root: Path) -> list[str]:
    found = []
    for package, allowed in ALLOWED.items():
        for path in sorted((root / package).rglob("*.py")):
            for line, target in imported_packages(path, package):
                if target in PROJECT and target not in allowed:
                    found.append(f"{path.relative_to(root)}:{line} imports {target}")
    return found


def test_every_import_follows_the_layer_table() -> None:
    assert layer_breaks(ROOT) == []


def test_the_reader_sees_type_checking_and_lazy_imports(tmp_path: Path) -> None:
    """The checker itself: an arrow hidden in a function or under TYPE_CHECKING is found."""
    (tmp_path / "dpm").mkdir()
    (tmp_path / "dpm" / "a.py").write_text(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from firmware.device import Device\n"
        "def f():\n    import host_api.board\n")
    assert layer_breaks(tmp_path) == ["dpm/a.py:3 imports firmware", "dpm/a.py:5 imports host_api"]


def test_cifemu_help_imports_no_command_module() -> None:
    """``cifemu --help`` builds the parser from the table alone: no command's module (and
    none of its heavy dependencies) is imported until that command runs."""
    code = (
        "import sys\n"
        "from cifemu.cli import COMMANDS, build_parser\n"
        "build_parser('').format_help()\n"
        "print(sorted(c.module for c in COMMANDS if c.module in sys.modules))\n"
        "print(sorted(m for m in ('canopen', 'textual', 'rich', 'can', 'firmware', 'host_api',"
        " 'dbm_tools') if m in sys.modules))\n")
    out = commands.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                       check=True, timeout=60).stdout
    assert out.splitlines() == ["[]", "[]"]
