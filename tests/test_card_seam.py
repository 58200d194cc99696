"""The card's tasks see it through ``firmware.card.Card``, never the device (issue 21).

``tests/test_imports.py`` finds cycles among the imports that run; this one also counts
the imports under ``if TYPE_CHECKING:``, since a type the tasks take from the device ties
them to it as much as a call does: nine modules once stood in one circle that way. Read
from the source with ``ast``, not by importing.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

TASKS = ("task", "rcs", "plc", "can_task", "can_download", "can_diagnosis", "can_host_sdo",
         "can_bus_access", "can_gateway", "card_info", "flash", "card", "whole_card")
"""The tasks and what a start reaches: none of them may name the device."""


def imported(module: str) -> set[str]:
    """Every module ``firmware.<module>`` imports, under TYPE_CHECKING or lazily too."""
    path = ROOT / "firmware" / (module.replace(".", "/") + ".py")
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def test_no_task_imports_the_device() -> None:
    offenders = [m for m in TASKS if "firmware.device" in imported(m)]
    assert not offenders, f"these import firmware.device (take firmware.card.Card): {offenders}"


def test_the_can_services_import_downwards_only() -> None:
    """The master composes the services; a node handler and its services never import it."""
    for module in ("can.node", "can.nmt", "can.boot", "can.supervision", "can.emcy",
                   "can.pdo", "can.sync", "can.layer2", "can.sdo"):
        assert "firmware.can.master" not in imported(module), module
