"""The network description: one TOML file for the DBM builder and the simulator.

A file describes the bus and its nodes (docs/network-toml.md). ``cifemu dbm build``
turns it into a DBM; ``--simulate`` turns the same file into live simulated nodes. Keys
under ``[node.sim]`` are for the simulator only; the builder ignores them. The smallest
useful file is a list of node-IDs, which gives generic CiA 401-style I/O modules::

    [[node]]
    id = 1
    [[node]]
    id = 2

The whole schema, with defaults, is docs/network-toml.md.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dbm_tools.container import FILE_MAGIC
from dbm_tools.errors import DbmError
from dpm.cia301 import COB_ID_SYNC, EMCY_BASE, ERROR_CONTROL_BASE
from dpm.cia305 import UNCONFIGURED, LssAddress

BITRATES: dict[int, int] = {
    1_000_000: 0, 800_000: 1, 500_000: 2, 250_000: 3, 125_000: 4,
    100_000: 5, 50_000: 6, 20_000: 7, 10_000: 8,
}
"""Bit/s -> the card's Baud_rate code (seed 5.2.5.4.1)."""

BOOT_STEPS = ("reset", "device", "guard", "sync", "emcy", "sdo", "start", "pdo")
"""Boot steps in bitConfigNdState bit order (bit n set = step n skipped)."""

GENERIC_DEVICE_TYPE = 0x000F0191
"""Device type of the built-in generic I/O module (CiA 401, digital in and out)."""
GENERIC_VENDOR_ID = 0x00434946
"""Vendor-ID of the generic module ("CIF" in ASCII; not a CiA-assigned number)."""
GENERIC_PRODUCT_CODE = 0x00000191
GENERIC_PRODUCT = "cifemu generic I/O"
"""The generic module's identity: the simulator reports it, the builder describes it."""

HANDSHAKES: dict[str, int] = {
    "buffered-device-controlled": 1, "uncontrolled": 2, "buffered-host-controlled": 3,
}
"""[bus] handshake -> PLC_PARAM bMode (seed 2.1, CANM_SET_MODE_*)."""


class NetworkError(DbmError, ValueError):
    """A network description that cannot be used; the message names the key."""


@dataclass
class BusDescription:
    bitrate: int = 500_000
    sync_cob_id: int = COB_ID_SYNC
    sync_period_ms: int = 0
    auto_clear: bool = False
    byte_order: str = "intel"
    master_node_id: int = 0
    heartbeat_ms: int = 0
    global_start: bool = False
    accept_code: int = 0
    accept_mask: int = 0
    extended_ids: bool = False
    wait_for_host: bool = False
    host_watchdog_ms: int = 1000
    handshake: str = "buffered-host-controlled"
    interface: str | None = None
    """The python-can interface that reaches this network, for ``cifemu sim`` and ``cifemu
    firmware --simulate`` when their command line names none [ours]; not in the DBM."""
    channel: str | None = None
    options: dict[str, Any] = field(default_factory=dict)
    """Keyword arguments for python-can's ``can.Bus`` (a socketcand host and port ...),
    typed by TOML; see ``dbm_tools.bus_options``."""

    @property
    def baud_rate_code(self) -> int:
        return BITRATES[self.bitrate]

    @property
    def plc_mode(self) -> int:
        """bMode of PLC_PARAM, the protocol parameter a cold start takes from the DBM."""
        return HANDSHAKES[self.handshake]


@dataclass
class SdoEntry:
    index: int
    subindex: int
    value: int
    size: int = 4


@dataclass
class PdoDescription:
    direction: str
    """"output": master -> node (the node's RPDO); "input": node -> master (TPDO)."""
    cob_id: int
    length: int = 8
    transmission: int = 255
    inhibit: int = 0
    word: bool = False
    offset: int | None = None


@dataclass
class EmcyBurst:
    after_s: float = 1.0
    count: int = 1
    code: int = 0x1000
    interval_s: float = 0.01


SDO_RESPONSE_FAULTS = ("unknown", "short")
"""Broken SDO responses a simulated node can send instead of every correct one: an
undefined command specifier (7, command byte 0xE0), or a frame of 4 bytes instead of 8."""

BUS_ERROR_KINDS = ("warning", "bus_off", "ack", "rx_overflow", "protocol")
"""Error frames a simulated node can put on the bus: the controller's error-warning
limit, bus-off, a missing acknowledge, and a receive FIFO overflow (SocketCAN error
classes, as the card's CAN controller driver would report them)."""


@dataclass
class BusErrors:
    after_s: float = 1.0
    count: int = 1
    kind: str = "warning"


@dataclass
class SimFaults:
    """Fault injection for a simulated node; all off by default."""

    silent: bool = False
    device_type: int | None = None
    sdo_abort: dict[tuple[int, int], int] = field(default_factory=dict)
    heartbeat_stop_after_s: float | None = None
    guarding_fail_after_s: float | None = None
    guard_toggle_stuck: bool = False
    """Guarding answers keep the toggle bit of the first one (the card's Err_Event 32)."""
    sdo_response: str | None = None
    """One of ``SDO_RESPONSE_FAULTS``: how every SDO response is broken (Err_Event 37, 38)."""
    emcy_burst: EmcyBurst | None = None
    boot_delay_s: float = 0.0
    no_bootup: bool = False
    """The node sends no boot-up message after a reset, as nodes before CiA 301 4.0 did."""
    leave_operational_after_s: float | None = None
    bus_errors: BusErrors | None = None


@dataclass
class NodeDescription:
    id: int
    eds: Path | None = None
    name: str = ""
    active: bool = True
    error_control: str = "heartbeat"
    heartbeat_ms: int = 1000
    guard_time_ms: int = 0
    life_time_factor: int = 3
    emcy_cob_id: int | None = None
    guard_cob_id: int | None = None
    device_type: int | None = None
    boot: tuple[str, ...] = BOOT_STEPS
    lss: LssAddress | None = None
    sdo: list[SdoEntry] = field(default_factory=list)
    pdo: list[PdoDescription] | None = None
    sim: SimFaults = field(default_factory=SimFaults)

    @property
    def cob_id_emcy(self) -> int:
        return self.emcy_cob_id if self.emcy_cob_id is not None else EMCY_BASE + self.id

    @property
    def cob_id_guard(self) -> int:
        return self.guard_cob_id if self.guard_cob_id is not None else ERROR_CONTROL_BASE + self.id

    @property
    def config_nd_state(self) -> int:
        """bitConfigNdState: a set bit skips that boot step."""
        return sum(1 << bit for bit, step in enumerate(BOOT_STEPS) if step not in self.boot)


@dataclass
class Network:
    bus: BusDescription
    nodes: list[NodeDescription]
    path: Path | None = None

    def node(self, node_id: int) -> NodeDescription:
        for node in self.nodes:
            if node.id == node_id:
                return node
        raise KeyError(node_id)


# --- reading -------------------------------------------------------------------------


Spec = dict[str, type | tuple[type, ...]]


def _take(table: dict[str, Any], where: str, spec: Spec) -> dict[str, Any]:
    """Check a TOML table's keys and value types against ``spec``."""
    unknown = set(table) - set(spec)
    if unknown:
        raise NetworkError(f"{where}: unknown key(s) {', '.join(sorted(unknown))}")
    for key, value in table.items():
        kinds = spec[key] if isinstance(spec[key], tuple) else (spec[key],)
        # TOML booleans are Python ints too; an int field must not take true/false.
        if isinstance(value, bool) and bool not in kinds:  # type: ignore[operator]
            raise NetworkError(f"{where}.{key}: expected a number, got a boolean")
        if not isinstance(value, kinds):
            names = " or ".join(k.__name__ for k in kinds)  # type: ignore[union-attr]
            raise NetworkError(f"{where}.{key}: expected {names}, got {type(value).__name__}")
    return table


def _range(where: str, value: int, low: int, high: int) -> int:
    if not low <= value <= high:
        raise NetworkError(f"{where} = {value} is outside {low}..{high}")
    return value


LINK_KEYS = {"interface": "bus.interface", "bustype": "bus.interface",
             "channel": "bus.channel", "bitrate": "bus.bitrate"}
"""python-can keys that ``[bus]`` names itself: ``[bus.options]`` refuses them."""
OPTION_TYPES = (str, int, float, bool, list, dict)
"""TOML values an option may have: all but dates and times, which no ``can.Bus`` takes."""


def _bus(table: dict[str, Any]) -> BusDescription:
    _take(table, "bus", {
        "bitrate": int, "sync_cob_id": int, "sync_period_ms": int, "auto_clear": bool,
        "byte_order": str, "master_node_id": int, "heartbeat_ms": int, "global_start": bool,
        "accept_code": int, "accept_mask": int, "extended_ids": bool, "wait_for_host": bool,
        "host_watchdog_ms": int, "handshake": str, "interface": str, "channel": str,
        "options": dict,
    })
    if "interface" in table:
        _interface(table["interface"])
    _options(table.get("options", {}))
    bus = BusDescription(**table)
    if bus.bitrate not in BITRATES:
        rates = ", ".join(str(r) for r in BITRATES)
        raise NetworkError(f"bus.bitrate = {bus.bitrate} is not one of {rates}")
    if bus.byte_order not in ("intel", "motorola"):
        raise NetworkError(f"bus.byte_order = {bus.byte_order!r}: use \"intel\" or \"motorola\"")
    _range("bus.sync_cob_id", bus.sync_cob_id, 1, 0x7FF)
    _range("bus.sync_period_ms", bus.sync_period_ms, 0, 0xFFFF)
    _range("bus.master_node_id", bus.master_node_id, 0, 126)  # seed 5.2.5.3.1: 0-126
    _range("bus.heartbeat_ms", bus.heartbeat_ms, 0, 0xFFFF)
    _range("bus.accept_code", bus.accept_code, 0, 0x1FFFFFFF)
    _range("bus.accept_mask", bus.accept_mask, 0, 0x1FFFFFFF)
    _range("bus.host_watchdog_ms", bus.host_watchdog_ms, 0, 0xFFFF)
    if bus.handshake not in HANDSHAKES:
        raise NetworkError(f"bus.handshake = {bus.handshake!r}: use one of "
                           + ", ".join(f'"{name}"' for name in HANDSHAKES))
    return bus


def _interface(name: str) -> None:
    """An interface python-can does not know is refused when the file is read, naming the
    key, not when a bus opens. python-can is imported only here: the builder and the
    other readers of a description never need it."""
    from can.interfaces import VALID_INTERFACES

    if name not in VALID_INTERFACES:
        raise NetworkError(f"bus.interface = {name!r} is not a python-can interface (one of "
                           f"{', '.join(sorted(VALID_INTERFACES))})")


def _options(options: dict[str, Any]) -> None:
    """``[bus.options]``: keyword arguments, so identifiers, none that ``[bus]`` names."""
    for key, value in options.items():
        if not key.isidentifier():
            raise NetworkError(f"bus.options: key {key!r} is not a python identifier")
        if key in LINK_KEYS:
            raise NetworkError(f"bus.options.{key}: use {LINK_KEYS[key]}")
        if not isinstance(value, OPTION_TYPES):
            raise NetworkError(f"bus.options.{key}: a {type(value).__name__} is no python-can "
                               "option value")


def _sdo_key(text: str, where: str) -> tuple[int, int]:
    try:
        index, _, sub = text.partition(":")
        return int(index, 16), int(sub or "0", 0)
    except ValueError:
        raise NetworkError(f"{where}: key {text!r} is not \"INDEX:SUB\" (hex index)") from None


def _sim(table: dict[str, Any], where: str) -> SimFaults:
    _take(table, where, {
        "silent": bool, "device_type": int, "sdo_abort": dict,
        "heartbeat_stop_after_s": (int, float), "guarding_fail_after_s": (int, float),
        "guard_toggle_stuck": bool, "sdo_response": str, "emcy_burst": dict,
        "boot_delay_s": (int, float), "no_bootup": bool,
        "leave_operational_after_s": (int, float), "bus_errors": dict,
    })
    faults = SimFaults(**{k: v for k, v in table.items()
                          if k not in ("sdo_abort", "emcy_burst", "bus_errors")})
    for key, code in table.get("sdo_abort", {}).items():
        if not isinstance(code, int):
            raise NetworkError(f"{where}.sdo_abort.{key}: the abort code must be an integer")
        faults.sdo_abort[_sdo_key(key, f"{where}.sdo_abort")] = code
    if "emcy_burst" in table:
        burst = _take(table["emcy_burst"], f"{where}.emcy_burst", {
            "after_s": (int, float), "count": int, "code": int, "interval_s": (int, float)})
        faults.emcy_burst = EmcyBurst(**burst)
    if "bus_errors" in table:
        errors = _take(table["bus_errors"], f"{where}.bus_errors",
                       {"after_s": (int, float), "count": int, "kind": str})
        faults.bus_errors = BusErrors(**errors)
        if faults.bus_errors.kind not in BUS_ERROR_KINDS:
            raise NetworkError(f"{where}.bus_errors.kind = {faults.bus_errors.kind!r}: use one "
                               f"of {', '.join(BUS_ERROR_KINDS)}")
    if faults.sdo_response is not None and faults.sdo_response not in SDO_RESPONSE_FAULTS:
        raise NetworkError(f"{where}.sdo_response = {faults.sdo_response!r}: use "
                           + " or ".join(f'"{name}"' for name in SDO_RESPONSE_FAULTS))
    return faults


def _node(table: dict[str, Any], where: str, base: Path) -> NodeDescription:
    _take(table, where, {
        "id": int, "eds": str, "name": str, "active": bool, "error_control": str,
        "heartbeat_ms": int, "guard_time_ms": int, "life_time_factor": int, "emcy_cob_id": int,
        "guard_cob_id": int, "device_type": int, "boot": list, "lss": dict, "sdo": list,
        "pdo": list, "sim": dict,
    })
    if "id" not in table:
        raise NetworkError(f"{where}: every node needs an id")
    values = {k: v for k, v in table.items() if k not in ("eds", "boot", "lss", "sdo", "pdo",
                                                          "sim")}
    node = NodeDescription(**values)
    where = f"node {node.id}"
    if node.id != UNCONFIGURED:
        _range(f"{where}: id", node.id, 1, 127)
    if "eds" in table:
        node.eds = (base / table["eds"]).resolve()
        if not node.eds.is_file():
            raise NetworkError(f"{where}: EDS file {node.eds} not found")
    if node.error_control not in ("heartbeat", "guarding", "none"):
        raise NetworkError(f"{where}: error_control = {node.error_control!r}: use "
                           "\"heartbeat\", \"guarding\" or \"none\"")
    _range(f"{where}: heartbeat_ms", node.heartbeat_ms, 0, 0xFFFF)
    _range(f"{where}: guard_time_ms", node.guard_time_ms, 0, 0xFFFF)
    _range(f"{where}: life_time_factor", node.life_time_factor, 0, 255)
    if "boot" in table:
        steps = table["boot"]
        bad = [s for s in steps if s not in BOOT_STEPS]
        if bad:
            raise NetworkError(f"{where}: unknown boot step(s) {bad}; known: {BOOT_STEPS}")
        node.boot = tuple(steps)
    if "lss" in table:
        lss = _take(table["lss"], f"{where}.lss",
                    {"vendor": int, "product": int, "revision": int, "serial": int})
        missing = {"vendor", "product", "revision", "serial"} - set(lss)
        if missing:
            raise NetworkError(f"{where}.lss: missing {', '.join(sorted(missing))}")
        node.lss = LssAddress(**lss)
    elif node.id == UNCONFIGURED:
        raise NetworkError(f"{where}: an unconfigured node (id 255) needs an lss address")
    for n, entry in enumerate(table.get("sdo", [])):
        sdo_where = f"{where}.sdo[{n}]"
        if not isinstance(entry, dict):
            raise NetworkError(f"{sdo_where}: expected a table")
        _take(entry, sdo_where, {"index": int, "subindex": int, "value": int, "size": int})
        missing = {"index", "subindex", "value"} - set(entry)
        if missing:
            raise NetworkError(f"{sdo_where}: missing {', '.join(sorted(missing))}")
        sdo = SdoEntry(**entry)
        _range(f"{sdo_where}.index", sdo.index, 0, 0xFFFF)
        _range(f"{sdo_where}.subindex", sdo.subindex, 0, 0xFF)
        _range(f"{sdo_where}.size", sdo.size, 1, 4)
        _range(f"{sdo_where}.value", sdo.value, 0, (1 << (8 * sdo.size)) - 1)
        node.sdo.append(sdo)
    if "pdo" in table:
        node.pdo = []
        for n, entry in enumerate(table["pdo"]):
            pdo_where = f"{where}.pdo[{n}]"
            if not isinstance(entry, dict):
                raise NetworkError(f"{pdo_where}: expected a table")
            _take(entry, pdo_where, {"direction": str, "cob_id": int, "length": int,
                                     "transmission": int, "inhibit": int, "word": bool,
                                     "offset": int})
            if "direction" not in entry or "cob_id" not in entry:
                raise NetworkError(f"{pdo_where}: direction and cob_id are required")
            pdo = PdoDescription(**entry)
            if pdo.direction not in ("input", "output"):
                raise NetworkError(f"{pdo_where}.direction = {pdo.direction!r}: use \"input\" "
                                   "or \"output\"")
            _range(f"{pdo_where}.cob_id", pdo.cob_id, 1, 0x7FF)
            _range(f"{pdo_where}.length", pdo.length, 1, 8)
            _range(f"{pdo_where}.transmission", pdo.transmission, 0, 255)
            _range(f"{pdo_where}.inhibit", pdo.inhibit, 0, 0xFFFF)
            if pdo.offset is not None:
                _range(f"{pdo_where}.offset", pdo.offset, 0, 3583)
            node.pdo.append(pdo)
    if "sim" in table:
        node.sim = _sim(table["sim"], f"{where}.sim")
    return node


def parse_network(text: str, base: Path = Path(".")) -> Network:
    """Parse a network description; EDS paths are relative to ``base``.

    Raises NetworkError naming the key of anything the description gets wrong.
    """
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise NetworkError(f"not valid TOML: {exc}") from None
    _take(doc, "file", {"bus": dict, "node": list})
    bus = _bus(dict(doc.get("bus", {})))
    nodes: list[NodeDescription] = []
    seen: set[int] = set()
    for n, table in enumerate(doc.get("node", [])):
        if not isinstance(table, dict):
            raise NetworkError(f"node[{n}]: expected a table")
        node = _node(dict(table), f"node[{n}]", base)
        if node.id in seen and node.id != UNCONFIGURED:
            raise NetworkError(f"node {node.id} is described twice")
        if node.id == bus.master_node_id and node.id:
            raise NetworkError(f"node {node.id} has the master's own node-ID")
        seen.add(node.id)
        nodes.append(node)
    return Network(bus, nodes)


UTF16_BOMS = (b"\xff\xfe", b"\xfe\xff")
"""A UTF-16 (or UTF-32) file starts with one of these: what Windows editors save as "Unicode"."""
UTF8_BOM = b"\xef\xbb\xbf"
EDS_SECTION = re.compile(rb"^\[(FileInfo|DeviceInfo|DeviceComissioning)\]", re.M | re.I)
"""Sections only an EDS or DCF file (CiA 306) has; one near the start names the file's kind."""


def decode_description(data: bytes, path: Path) -> str:
    """The text of a network description: TOML is UTF-8. A file of another kind -- the
    SyCon DBM or EDS a SyCon user mixes up with it most easily, or UTF-16 text -- is
    named as such, with the command that takes it, instead of a decoding traceback or a
    TOML error about its first odd byte [ours]."""
    name = path.name
    if data.startswith(FILE_MAGIC):
        raise NetworkError(
            f"{name} is a SyCon DBM database, not a network description: use "
            f"`cifemu dbm download {path}` for the card's flash, or `cifemu dbm show {path}`")
    if EDS_SECTION.search(data[:4096]):
        raise NetworkError(
            f"{name} is an EDS/DCF device description, not a network description: name it "
            f"in a node's eds key (eds = \"{name}\")")
    if data.startswith(UTF16_BOMS):
        raise NetworkError(
            f"{name} is UTF-16 text; a network description is TOML, which is UTF-8: save it "
            "as UTF-8")
    try:
        return data.removeprefix(UTF8_BOM).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise NetworkError(
            f"{name} is not a network description: byte {exc.start} (0x{data[exc.start]:02x}) "
            "is not UTF-8 text; a network description is a TOML text file") from None


def load_network(path: str | Path) -> Network:
    """Read and parse a network description file; NetworkError when it cannot be read or
    used."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise NetworkError(f"cannot read {path}: {exc.strerror}") from None
    network = parse_network(decode_description(data, path), path.parent)
    network.path = path
    return network
