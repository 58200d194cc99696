"""``dpm`` is the card's header: no module outside it defines a protocol number or layout.

Every module of the other packages is parsed (never imported) and its module- and
class-level assignments are checked:

- an int literal (or a tuple of them) bound to a name of the card's protocol: a prefix
  the seed uses for a family of numbers (``COM_``, ``NMT_``, ``F_``, ``ERR_``, ``LOAD_``,
  ``MODE_``, ``AREA_``), a name containing ``Err_Event``, a task number's name
  (``CAN_TASK``, ``USER``, ...), or any name ``dpm`` itself exports with an int value;
- a ``struct.Struct`` layout, unless it is listed below as no card message (with why);
- anywhere in the code, a CiA 301 SDO abort code (``dpm.cia301.ABORT_*``) written as a
  number, or as ``0x`` and eight hex digits in a string that is no docstring: the master,
  the simulated nodes, the gateway and the benchmarks name them from ``dpm.cia301``.
- anywhere in the code, a CiA 301 COB-ID base (``dpm.cia301``'s ``*_BASE``/``*_BASES``:
  080h, 180h ... 700h) written as a number where it is one: added to a node-ID
  (``0x580 + node``), taken off an identifier (``can_id - 0x700``), compared with one
  (``0x580 < ident < 0x600``), a table of them (``(0x180, 0x280)``), or 080h bound to a
  SYNC name (``sync_cob_id = 0x80``). 080h alone is also a bit and an SDO command byte:
  compared or in a table it is left alone.

Timeouts, CANopen object indexes and the like stay where they are used: their names
match none of these rules.
"""

from __future__ import annotations

import ast
import importlib
import pkgutil
import re
from pathlib import Path

import dpm
from dpm import cia301

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("firmware", "host_api", "dbm_tools", "bench", "cifemu")

PROTOCOL_NAME = re.compile(
    r"^(COM_|NMT_|F_|ERR_|LOAD_|MODE_|AREA_)|Err_Event|ERR_EVENT"
    r"|^(CAN_TASK|USER|PLC_TASK|RCS_TASK|GET_CONFIGURATION)$"
)

SDO_ABORT_CODES = frozenset(value for name, value in vars(cia301).items()
                            if name.startswith("ABORT_"))
HEX_CODE = re.compile(r"0x([0-9A-Fa-f]{8})\b")
COB_ID_BASES = frozenset({cia301.EMCY_BASE, *cia301.TPDO_BASES, *cia301.RPDO_BASES,
                          cia301.SDO_RESPONSE_BASE, cia301.SDO_REQUEST_BASE,
                          cia301.ERROR_CONTROL_BASE})
SYNC_NAME = re.compile(r"sync", re.IGNORECASE)

NOT_CARD_LAYOUTS: dict[tuple[str, str], str] = {
    ("firmware/shm/station.py", "HEADER"): "the shm bus's file header [ours]",
    ("firmware/shm/station.py", "ENTRY"): "a station record of the shm bus [ours]",
    ("firmware/shm/station.py", "RECORD"): "a frame record of the shm bus's rings [ours]",
    ("firmware/shm/bus.py", "_COUNTERS"): "the shm bus's station counters [ours]",
    ("firmware/shm/bus.py", "_COUNTER"): "one station counter of the shm bus [ours]",
    ("host_api/driver.py", "DRIVERINFO"): "the C driver's DRIVERINFO structure",
    ("host_api/driver.py", "IOINFO"): "the C driver's IOINFO structure",
    ("host_api/driver.py", "BOARD_INFO_ENTRY"): "an entry of the C driver's BOARD_INFO",
    ("host_api/driver.py", "COMSTATE"): "the C driver's COMSTATE structure",
}


def dpm_int_names() -> frozenset[str]:
    """Every public upper-case name ``dpm``'s modules bind to an int (enum members too)."""
    names: set[str] = set()
    for info in pkgutil.iter_modules(dpm.__path__):
        module = importlib.import_module(f"dpm.{info.name}")
        names.update(name for name, value in vars(module).items()
                     if name.isupper() and not name.startswith("_")
                     and isinstance(value, int) and not isinstance(value, bool))
    return frozenset(names)


def _is_int_literal(node: ast.expr) -> bool:
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        node = node.operand
    if isinstance(node, ast.Tuple):
        return bool(node.elts) and all(_is_int_literal(e) for e in node.elts)
    return isinstance(node, ast.Constant) and type(node.value) is int


def _is_struct_layout(node: ast.expr) -> bool:
    return (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
            and node.func.attr == "Struct" and isinstance(node.func.value, ast.Name)
            and node.func.value.id == "struct")


def _bindings(target: ast.expr, value: ast.expr) -> list[tuple[str, ast.expr]]:
    """(name, value) pairs of one assignment; ``A, B = 1, 2`` binds A to 1 and B to 2."""
    if isinstance(target, ast.Name):
        return [(target.id, value)]
    if isinstance(target, ast.Tuple):
        if isinstance(value, ast.Tuple) and len(value.elts) == len(target.elts):
            return [b for t, v in zip(target.elts, value.elts, strict=True)
                    for b in _bindings(t, v)]
        return [b for t in target.elts for b in _bindings(t, value)]
    return []


def _assignments(body: list[ast.stmt], scope: str) -> list[tuple[str, int, str, ast.expr]]:
    """(scope, line, name, value) of every assignment in a module's or class's body."""
    found = []
    for stmt in body:
        if isinstance(stmt, ast.Assign):
            found += [(scope, stmt.lineno, n, v) for t in stmt.targets
                      for n, v in _bindings(t, stmt.value)]
        elif isinstance(stmt, ast.AnnAssign) and stmt.value is not None:
            found += [(scope, stmt.lineno, n, v) for n, v in _bindings(stmt.target, stmt.value)]
        elif isinstance(stmt, ast.ClassDef):
            found += _assignments(stmt.body, f"{stmt.name}.")
    return found


def offences(path: Path, reserved: frozenset[str]) -> list[str]:
    """What ``path`` defines that belongs in ``dpm``, one line each."""
    relative = path.relative_to(ROOT).as_posix() if path.is_relative_to(ROOT) else path.name
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=relative)
    found = []
    for scope, line, name, value in _assignments(tree.body, ""):
        # dpm's own names count at module level; a class's members (an enum's) may reuse them
        if _is_int_literal(value) and (PROTOCOL_NAME.search(name)
                                       or (not scope and name in reserved)):
            found.append(f"{relative}:{line}: {scope}{name} = {ast.unparse(value)}")
        elif _is_struct_layout(value) and (relative, name) not in NOT_CARD_LAYOUTS:
            found.append(f"{relative}:{line}: {scope}{name} = {ast.unparse(value)} (a layout)")
    return found


def abort_literals(path: Path) -> list[str]:
    """Every SDO abort code ``path`` spells as a number or as ``0x`` text, one line each;
    docstrings (any string standing alone as a statement) may quote one."""
    relative = path.relative_to(ROOT).as_posix() if path.is_relative_to(ROOT) else path.name
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=relative)
    docstrings = {id(node.value) for node in ast.walk(tree)
                  if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)}
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Constant) or id(node) in docstrings:
            continue
        if type(node.value) is int and node.value in SDO_ABORT_CODES:
            found.append((node.lineno, f"0x{node.value:08X}"))
        elif isinstance(node.value, str):
            found += [(node.lineno, f"{match.group(0)!r} in a string")
                      for match in HEX_CODE.finditer(node.value)
                      if int(match.group(1), 16) in SDO_ABORT_CODES]
    return [f"{relative}:{line}: {what}" for line, what in sorted(found)]


def _base(node: ast.expr) -> int | None:
    """The COB-ID base ``node`` spells as a literal, else None."""
    if isinstance(node, ast.Constant) and type(node.value) is int and node.value in COB_ID_BASES:
        return node.value
    return None


def _bound_defaults(node: ast.AST) -> list[tuple[str, ast.expr]]:
    """(name, value) of what ``node`` binds: an assignment's targets, a function's defaults."""
    if isinstance(node, ast.Assign):
        return [b for t in node.targets for b in _bindings(t, node.value)]
    if isinstance(node, ast.AnnAssign) and node.value is not None:
        return _bindings(node.target, node.value)
    if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
        positional = node.args.posonlyargs + node.args.args
        pairs = list(zip(positional[len(positional) - len(node.args.defaults):],
                         node.args.defaults, strict=True))
        pairs += [(a, d) for a, d in zip(node.args.kwonlyargs, node.args.kw_defaults,
                                         strict=True) if d is not None]
        return [(a.arg, d) for a, d in pairs]
    return []


def cob_id_literals(path: Path) -> list[str]:
    """Every CiA 301 COB-ID base ``path`` spells as a number where it means one, one line
    each (the module docstring's rules)."""
    relative = path.relative_to(ROOT).as_posix() if path.is_relative_to(ROOT) else path.name
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=relative)
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.expr | ast.stmt):
            continue  # only expressions and statements spell a number (and have a line)
        spelled: list[int | None] = []
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
            spelled = [_base(node.left), _base(node.right)]
        elif isinstance(node, ast.BinOp) and isinstance(node.op, ast.Sub):
            spelled = [_base(node.right)]
        elif isinstance(node, ast.Compare):
            spelled = [_base(n) for n in (node.left, *node.comparators)
                       if _base(n) != cia301.EMCY_BASE]
        elif isinstance(node, ast.Tuple) and len(node.elts) > 1:
            bases = [_base(e) for e in node.elts]
            spelled = bases if None not in bases and cia301.EMCY_BASE not in bases else []
        spelled += [cia301.COB_ID_SYNC for name, value in _bound_defaults(node)
                    if SYNC_NAME.search(name) and isinstance(value, ast.Constant)
                    and type(value.value) is int and value.value == cia301.COB_ID_SYNC]
        found += [(node.lineno, f"0x{base:03X} in {ast.unparse(node).splitlines()[0]}")
                  for base in spelled if base is not None]
    return [f"{relative}:{line}: {what}" for line, what in sorted(set(found))]


def modules() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def test_the_rules_catch_what_they_must(tmp_path: Path) -> None:
    """The checker itself: each kind of definition is caught, ordinary numbers are not."""
    source = (
        "import struct\nCOM_X, COM_Y = 67, 68\nTIMEOUT, AREA_BUS = 0.5, 127\nF_TIMEOUT = 48\n"
        "CAN_TASK, USER = 3, 16\n"
        "class T:\n    NMT_START = 0x01\n    READY = 1\n"
        "REQUEST = struct.Struct('<BBH')\nSEND_TIMEOUT = 0.02\nRETRIES = 3\n"
        "F_NAME = 'text'\nDPM_SIZE = 8192\n"
    )
    path = tmp_path / "sample.py"
    path.write_text(source, encoding="utf-8")
    found = offences(path, frozenset({"DPM_SIZE", "READY"}))
    assert [line.split(": ", 1)[1].split(" =")[0] for line in found] == [
        "COM_X", "COM_Y", "AREA_BUS", "F_TIMEOUT", "CAN_TASK", "USER", "T.NMT_START", "REQUEST",
        "DPM_SIZE"]


def test_the_abort_rule_catches_what_it_must(tmp_path: Path) -> None:
    """Abort codes as numbers or 0x text are caught wherever they stand; docstrings, other
    numbers and the names from dpm.cia301 are not."""
    source = (
        '"""Aborts 0x05040000 on a time-out."""\n'
        "from dpm.cia301 import ABORT_TIMEOUT\n"
        "TEXTS = {0x0503_0000: 'toggle', ABORT_TIMEOUT: 'time-out'}\n"
        "def f(code: int) -> bool:\n"
        "    '''Is it 0x06090011?'''\n"
        "    return code != 0x06090011 and code != 0x05040006\n"
        "LOGGED = 'aborted with code 0x08000000'\n"
        "MASK = 0x0800_0001\n"
    )
    path = tmp_path / "sample.py"
    path.write_text(source, encoding="utf-8")
    assert [line.split(": ", 1)[1] for line in abort_literals(path)] == [
        "0x05030000", "0x06090011", "'0x08000000' in a string"]


def test_no_module_outside_dpm_spells_an_sdo_abort_code() -> None:
    """A copy drifts: the master's time-out abort and the gateway's mapping of it to 309-3
    error 103 must be one number."""
    assert len(SDO_ABORT_CODES) > 25 and 0x0504_0000 in SDO_ABORT_CODES
    found = [line for path in modules() for line in abort_literals(path)]
    assert not found, "SDO abort codes outside dpm.cia301:\n" + "\n".join(found)


def test_the_cob_id_rule_catches_what_it_must(tmp_path: Path) -> None:
    """COB-ID bases with a node-ID, against an identifier, in a table or as a SYNC default
    are caught; the same numbers as sizes, bits, masks or command bytes are not."""
    source = (
        "from dpm.cia301 import SDO_RESPONSE_BASE\n"
        "BASES = (0x180, 0x280)\n"
        "SYNC_COB_ID = 0x080\n"
        "def f(node: int, can_id: int, sync_cob_id: int = 0x80) -> int:\n"
        "    if 0x580 < can_id < 0x600 or can_id - 0x700 == node:\n"
        "        return 0x600 + node\n"
        "    return SDO_RESPONSE_BASE + node\n"
        "SIZE, BIT = 0x200, 0x80\n"
        "def g(byte: int, code: int) -> bool:\n"
        "    return byte & 0x80 == 0x80 or 128 - code > 0 or byte | 0x700 > 0\n"
    )
    path = tmp_path / "sample.py"
    path.write_text(source, encoding="utf-8")
    assert [line.split(": ", 1)[1].split(" in ")[0] for line in cob_id_literals(path)] == [
        "0x180", "0x280", "0x080", "0x080", "0x580", "0x600", "0x700", "0x600"]


def test_no_module_outside_dpm_spells_a_cob_id_base() -> None:
    """A copy drifts: the master's SDO channel, the simulated node's server and the
    benchmarks' clients must meet on one identifier per node."""
    found = [line for path in modules() for line in cob_id_literals(path)]
    assert not found, "CiA 301 COB-ID bases outside dpm.cia301:\n" + "\n".join(found)


def test_every_exempted_layout_exists() -> None:
    """A stale exemption would let a new card layout of the same name pass unseen."""
    for (relative, name), why in NOT_CARD_LAYOUTS.items():
        tree = ast.parse((ROOT / relative).read_text(encoding="utf-8"))
        bound = {n for _, _, n, v in _assignments(tree.body, "") if _is_struct_layout(v)}
        assert name in bound, f"{relative}: {name} ({why}) is gone; drop its exemption"


def test_no_module_outside_dpm_defines_a_protocol_number() -> None:
    reserved = dpm_int_names()
    assert {"COM_DOWNLOAD", "NMT_START", "F_UNKNOWN_TASK", "IO_AREA_SIZE"} <= reserved
    # CiA 301's NMT states have one home too (dpm.cia301), for the card and the simulated nodes
    assert {"INITIALISING", "STOPPED", "OPERATIONAL", "PRE_OPERATIONAL"} <= reserved
    checked = modules()
    assert len(checked) > 50, "the packages were not found"
    found = [line for path in checked for line in offences(path, reserved)]
    assert not found, "protocol numbers or layouts outside dpm:\n" + "\n".join(found)


def test_the_simulated_nodes_take_nothing_from_the_card() -> None:
    """firmware.sim models other vendors' nodes: it imports neither the card's header nor its
    firmware, only the neutral modules both sides share: CiA 301's and CiA 305's numbers,
    the bus's facts, the interpreter's tuning, the ``virtual`` bus's frames handled by their
    sender (``firmware.inline``, which imports nothing of the card)."""
    neutral = {"dpm.cia301", "dpm.cia305", "firmware.frames", "firmware.interpreter",
               "firmware.inline"}
    found = []
    for path in sorted((ROOT / "firmware" / "sim").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                module = node.module
                if (module.startswith(("dpm", "firmware"))
                        and not module.startswith("firmware.sim") and module not in neutral):
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {module}")
    assert not found, "firmware.sim imports the card's modules:\n" + "\n".join(found)
