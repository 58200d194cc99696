"""The built-in generic node: a CiA 401-style 8-byte digital I/O module.

A network description that names no EDS for a node gets this one
(docs/network-toml.md). Its object dictionary is built
here in code, so no data file has to travel with the package, and its
defaults follow the description so the node works even when the master skips
boot steps: 1017h is half the master's heartbeat consumer time, 100Ch/100Dh
are the description's guarding times, 1005h and 1014h its COB-IDs.

The module's inputs echo its outputs (see ``SimulatedNode``), so a host can
check the whole loop output -> bus -> node -> bus -> input.
"""

from __future__ import annotations

from canopen import objectdictionary as od
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable

from dbm_tools.network import (
    GENERIC_DEVICE_TYPE,
    GENERIC_PRODUCT,
    GENERIC_PRODUCT_CODE,
    GENERIC_VENDOR_ID,
    NodeDescription,
)
from dpm.cia301 import COB_ID_SYNC, ERROR_CONTROL_BASE, RPDO_BASES, TPDO_BASES
from dpm.cia305 import LssAddress

GENERIC_REVISION = 0x00010000
IO_BYTES = 8
INPUTS = 0x6000
"""Read input 8-bit (CiA 401): mapped into TPDO1, echoes 6200h."""
OUTPUTS = 0x6200
"""Write output 8-bit (CiA 401): mapped from RPDO1."""
ERROR_HISTORY = 8
"""Entries of the pre-defined error field 1003h."""


def _var(name: str, index: int, subindex: int, data_type: int, access: str,
         default: int, mappable: bool = False) -> ODVariable:
    var = ODVariable(name, index, subindex)
    var.data_type = data_type
    var.access_type = access
    var.default = default
    var.pdo_mappable = mappable
    return var


def _string(name: str, index: int, text: str) -> ODVariable:
    var = ODVariable(name, index)
    var.data_type = od.VISIBLE_STRING
    var.access_type = "const"
    var.default = text  # type: ignore[assignment]  # canopen annotates int, stores any value
    return var


def _record(name: str, index: int, members: list[ODVariable]) -> ODRecord:
    record = ODRecord(name, index)
    highest = max(m.subindex for m in members)
    record.add_member(_var("Highest sub-index supported", index, 0, od.UNSIGNED8, "ro", highest))
    for member in members:
        record.add_member(member)
    return record


def _io_array(name: str, index: int, access: str) -> ODArray:
    array = ODArray(name, index)
    array.add_member(_var("Number of entries", index, 0, od.UNSIGNED8, "ro", IO_BYTES))
    for sub in range(1, IO_BYTES + 1):
        array.add_member(_var(f"{name} {sub}", index, sub, od.UNSIGNED8, access, 0, True))
    return array


def _pdo_mapping(name: str, index: int, mapped: int) -> ODRecord:
    entries = [_var(f"Mapped object {sub}", index, sub, od.UNSIGNED32, "rw",
                    mapped << 16 | sub << 8 | 8) for sub in range(1, IO_BYTES + 1)]
    record = _record(name, index, entries)
    record[0].access_type = "rw"
    return record


def _error_field() -> ODArray:
    array = ODArray("Pre-defined error field", 0x1003)
    array.add_member(_var("Number of errors", 0x1003, 0, od.UNSIGNED8, "rw", 0))
    for sub in range(1, ERROR_HISTORY + 1):
        array.add_member(_var(f"Standard error field {sub}", 0x1003, sub, od.UNSIGNED32, "ro",
                              0))
    return array


def generic_object_dictionary(node: NodeDescription, sync_cob_id: int = COB_ID_SYNC
                              ) -> ObjectDictionary:
    """The object dictionary of the generic I/O module described by ``node``."""
    ident = node.lss or LssAddress(GENERIC_VENDOR_ID, GENERIC_PRODUCT_CODE, GENERIC_REVISION,
                                   node.id)
    heartbeat = node.heartbeat_ms // 2 if node.error_control == "heartbeat" else 0
    guarding = node.error_control == "guarding"
    dictionary = ObjectDictionary()  # type: ignore[no-untyped-call]
    dictionary.node_id = node.id
    for obj in (
        _var("Device type", 0x1000, 0, od.UNSIGNED32, "ro", GENERIC_DEVICE_TYPE),
        _var("Error register", 0x1001, 0, od.UNSIGNED8, "ro", 0),
        _error_field(),
        _var("COB-ID SYNC", 0x1005, 0, od.UNSIGNED32, "rw", sync_cob_id),
        _string("Manufacturer device name", 0x1008, GENERIC_PRODUCT),
        _var("Guard time", 0x100C, 0, od.UNSIGNED16, "rw", node.guard_time_ms if guarding else 0),
        _var("Life time factor", 0x100D, 0, od.UNSIGNED8, "rw",
             node.life_time_factor if guarding else 0),
        # 100Eh starts at the default: a card that configures another guarding COB-ID
        # must write it here, as the seed's card does at start-up.
        _var("COB-ID guarding", 0x100E, 0, od.UNSIGNED32, "rw", ERROR_CONTROL_BASE + node.id),
        _var("COB-ID EMCY", 0x1014, 0, od.UNSIGNED32, "rw", node.cob_id_emcy),
        _var("Producer heartbeat time", 0x1017, 0, od.UNSIGNED16, "rw", heartbeat),
        _record("Identity object", 0x1018, [
            _var("Vendor-ID", 0x1018, 1, od.UNSIGNED32, "ro", ident.vendor),
            _var("Product code", 0x1018, 2, od.UNSIGNED32, "ro", ident.product),
            _var("Revision number", 0x1018, 3, od.UNSIGNED32, "ro", ident.revision),
            _var("Serial number", 0x1018, 4, od.UNSIGNED32, "ro", ident.serial),
        ]),
        _record("RPDO1 communication parameter", 0x1400, [
            _var("COB-ID used by RPDO", 0x1400, 1, od.UNSIGNED32, "rw", RPDO_BASES[0] + node.id),
            _var("Transmission type", 0x1400, 2, od.UNSIGNED8, "rw", 255),
        ]),
        _pdo_mapping("RPDO1 mapping parameter", 0x1600, OUTPUTS),
        _record("TPDO1 communication parameter", 0x1800, [
            _var("COB-ID used by TPDO", 0x1800, 1, od.UNSIGNED32, "rw", TPDO_BASES[0] + node.id),
            _var("Transmission type", 0x1800, 2, od.UNSIGNED8, "rw", 255),
            _var("Inhibit time", 0x1800, 3, od.UNSIGNED16, "rw", 0),
            _var("Event timer", 0x1800, 5, od.UNSIGNED16, "rw", 0),
        ]),
        _pdo_mapping("TPDO1 mapping parameter", 0x1A00, INPUTS),
        _io_array("Read input 8-bit", INPUTS, "ro"),
        _io_array("Write output 8-bit", OUTPUTS, "rw"),
    ):
        dictionary.add_object(obj)
    return dictionary

