"""A network description as an operator reads the card: names, PDOs, process-image places.

``cifemu monitor`` and ``cifemu top`` need the same facts: which node a PDO's
COB-ID belongs to, where its bytes sit in the card's process image, and what
the node maps into it. The offsets and COB-IDs are taken from the database the
builder makes of the file (the NODES records the card itself is given, so the
view and the card cannot disagree); node names from the file, else from the
EDS's product name; mapped objects from the EDS's default PDO mapping
(1600h/1A00h, with the object dictionary's names). A node without an EDS maps
nothing by name: its PDO shows as bytes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dbm_tools.builder import build_dbm
from dbm_tools.eds import import_od
from dbm_tools.network import Network, NodeDescription, load_network
from dbm_tools.parameters import NodeParameterSet
from dbm_tools.tables import NODES
from dpm.cia301 import RPDO_BASES, TPDO_BASES
from dpm.image import CardDirectory, UnsafePathError

RPDO_MAPPING = 0x1600
TPDO_MAPPING = 0x1A00
"""CiA 301: the mapping parameter objects of the first RPDO and TPDO."""
PREDEFINED_BASES = {"input": TPDO_BASES, "output": RPDO_BASES}
"""CiA 301's predefined connection set: TPDO1..4 and RPDO1..4 at these COB-IDs + node-ID."""

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MappedEntry:
    """One object mapped into a PDO: where it sits (in bits) and what it is called."""

    name: str
    index: int
    subindex: int
    bit_offset: int
    bits: int


@dataclass(frozen=True)
class PdoSlot:
    """One PDO of one node as the card handles it.

    ``direction`` is the master's: "input" is the node's TPDO (RcvPd area),
    "output" its RPDO (SndPd area); ``number`` is the node's own PDO number (TPDO3 is
    1802h/1A02h): from the EDS's communication object with this COB-ID, else from the
    predefined connection set, else the place among the node's PDOs of that direction in
    the card's list, counted from 1.
    """

    node: int
    direction: str
    number: int
    cob_id: int
    length: int
    offset: int
    entries: tuple[MappedEntry, ...] = ()

    @property
    def label(self) -> str:
        return f"{'TPDO' if self.direction == 'input' else 'RPDO'}{self.number}"

    def values(self, data: bytes) -> list[tuple[str, int]]:
        """The mapped objects' values (little-endian, CiA 301) in ``data``."""
        whole = int.from_bytes(data, "little")
        return [(entry.name, (whole >> entry.bit_offset) & ((1 << entry.bits) - 1))
                for entry in self.entries if entry.bit_offset + entry.bits <= 8 * len(data)]


@dataclass
class NetworkView:
    names: dict[int, str] = field(default_factory=dict)
    slots: list[PdoSlot] = field(default_factory=list)

    def slot_for(self, cob_id: int) -> PdoSlot | None:
        return next((slot for slot in self.slots if slot.cob_id == cob_id), None)

    def name(self, node: int) -> str:
        return self.names.get(node, "")


def _object_dictionary(node: NodeDescription) -> Any:
    if node.eds is None:
        return None
    try:
        return import_od(node.eds, node.id)  # only a network with EDS files imports canopen
    except Exception:  # the builder has read this EDS already; a view does without names
        return None


def _value(od: Any, index: int, subindex: int) -> Any:
    try:
        entry = od[index][subindex]
    except (KeyError, TypeError):
        return None
    return entry.value if getattr(entry, "value", None) is not None else entry.default


def _entries(od: Any, mapping: int) -> tuple[MappedEntry, ...]:
    """The default mapping of one PDO mapping object, named from the dictionary."""
    count = _value(od, mapping, 0) or 0
    entries, bit = [], 0
    for sub in range(1, int(count) + 1):
        raw = _value(od, mapping, sub)
        if not isinstance(raw, int):
            break
        index, subindex, bits = raw >> 16, (raw >> 8) & 0xFF, raw & 0xFF
        try:
            obj = od[index]
            name = obj[subindex].name if hasattr(obj, "subindices") else obj.name
        except (KeyError, TypeError):
            name = f"{index:04X}h/{subindex}"
        entries.append(MappedEntry(str(name), index, subindex, bit, bits))
        bit += bits
    return tuple(entries)


def _eds_mappings(od: Any) -> dict[tuple[str, int], tuple[int, tuple[MappedEntry, ...]]]:
    """(direction, COB-ID) -> number and mapped entries of every PDO the EDS defines."""
    found: dict[tuple[str, int], tuple[int, tuple[MappedEntry, ...]]] = {}
    for direction, communication, mapping in (("input", 0x1800, TPDO_MAPPING),
                                              ("output", 0x1400, RPDO_MAPPING)):
        for number in range(512):
            cob_id = _value(od, communication + number, 1)
            if not isinstance(cob_id, int):
                if number >= 4:
                    break
                continue
            found[(direction, cob_id & 0x7FF)] = (number + 1, _entries(od, mapping + number))
    return found


def _predefined_number(direction: str, node_id: int, cob_id: int) -> int | None:
    bases = PREDEFINED_BASES[direction]
    return bases.index(cob_id - node_id) + 1 if cob_id - node_id in bases else None


def network_view(network: Network) -> NetworkView:
    """Names and PDO slots of ``network`` (``BuildError`` when the builder refuses it)."""
    dbm = build_dbm(network)
    view = NetworkView()
    descriptions = {node.id: node for node in network.nodes}
    nodes = dbm.table(NODES)
    for record in nodes.records if nodes else []:
        node_id = record[0]
        description = descriptions.get(node_id)
        od = _object_dictionary(description) if description is not None else None
        name = description.name if description is not None else ""
        if not name and od is not None:
            name = od.device_information.product_name or ""
        view.names[node_id] = name
        mappings = _eds_mappings(od) if od is not None else {}
        parameters = NodeParameterSet.decode(record[1:])
        counters = {"input": 0, "output": 0}
        offsets = {"input": list(parameters.ausInputOffsets),
                   "output": list(parameters.ausOutputOffsets)}
        for pdo in parameters.atPdoCfgData:
            direction = "input" if pdo.is_input else "output"
            position = counters[direction]
            counters[direction] += 1
            offset = offsets[direction][position] if position < len(offsets[direction]) else 0
            number, entries = mappings.get((direction, pdo.usPdoCOBId), (None, ()))
            if number is None:
                number = _predefined_number(direction, node_id, pdo.usPdoCOBId) or position + 1
            view.slots.append(PdoSlot(node_id, direction, number, pdo.usPdoCOBId,
                                      pdo.data_length, offset, entries))
    return view


def load_view(path: Path | None) -> NetworkView:
    """The view of a network file, or an empty one (no names, no PDO map)."""
    if path is None:
        return NetworkView()
    return network_view(load_network(path))


def _remembered_path(directory: Path, board: int) -> Path:
    return directory / f"board{board}.network"


def remember_network(directory: Path, board: int, network: Path) -> None:
    """Note beside the image which file the card was configured from [ours], so that
    ``cifemu top`` and ``cifemu monitor`` name its nodes without being told.

    Written through a new file of an unpredictable name (``CardDirectory.replace``): a
    host tool run as root follows no symlink another user planted (docs/security.md).
    A directory a host may not trust gets no note, and a one-line warning: the
    configuration itself stands."""
    try:
        files = CardDirectory(directory, host=True)
    except UnsafePathError as exc:
        log.warning("no note of the network file beside the image: %s", exc)
        return
    try:
        files.replace(_remembered_path(directory, board).name, f"{network.resolve()}\n".encode())
    finally:
        files.close()


def remembered_network(directory: Path, board: int) -> Path | None:
    try:
        text = _remembered_path(directory, board).read_text().strip()
    except OSError:
        return None
    return Path(text) if text and Path(text).exists() else None
