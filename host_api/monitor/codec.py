"""One CAN frame's CANopen meaning, from its identifier and bytes alone (no I/O).

The identifier is read by CiA 301's predefined connection set (function code
in bits 7..10, node-ID in bits 0..6) and CiA 305's LSS identifiers; a PDO whose
COB-ID the network view knows is named by it instead (node, TPDO/RPDO number,
mapped values). 29-bit frames and error frames are not CANopen: they are only
labelled.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass

from dpm import cia301, cia305
from host_api.monitor.cia301 import NMT_COMMAND_TEXT, emcy_text, nmt_state_text, sdo_abort_text
from host_api.network_view import NetworkView, PdoSlot

KINDS = ("nmt", "sync", "emcy", "time", "pdo", "sdo", "heartbeat", "guarding", "lss", "error",
         "other")
"""What ``--type`` filters on."""


LSS_TEXT: dict[int, str] = {
    cia305.SWITCH_STATE_GLOBAL: "switch state global",
    cia305.CONFIGURE_NODE_ID: "configure node-ID",
    cia305.CONFIGURE_BIT_TIMING: "configure bit timing",
    cia305.ACTIVATE_BIT_TIMING: "activate bit timing",
    cia305.STORE_CONFIGURATION: "store configuration",
    cia305.SWITCH_SELECTIVE_VENDOR: "switch state selective: vendor-ID",
    cia305.SWITCH_SELECTIVE_PRODUCT: "switch state selective: product code",
    cia305.SWITCH_SELECTIVE_REVISION: "switch state selective: revision number",
    cia305.SWITCH_SELECTIVE_SERIAL: "switch state selective: serial number",
    cia305.SWITCH_SELECTIVE_ANSWER: "switch state selective: answer",
    cia305.IDENTIFY_REMOTE_VENDOR: "identify remote slave: vendor-ID",
    cia305.IDENTIFY_REMOTE_PRODUCT: "identify remote slave: product code",
    cia305.IDENTIFY_REMOTE_REVISION_LOW: "identify remote slave: revision low",
    cia305.IDENTIFY_REMOTE_REVISION_HIGH: "identify remote slave: revision high",
    cia305.IDENTIFY_REMOTE_SERIAL_LOW: "identify remote slave: serial low",
    cia305.IDENTIFY_REMOTE_SERIAL_HIGH: "identify remote slave: serial high",
    cia305.IDENTIFY_NON_CONFIGURED_REMOTE: "identify non-configured remote slave",
    cia305.IDENTIFY_SLAVE: "identify slave: answer",
    cia305.IDENTIFY_NON_CONFIGURED_SLAVE: "identify non-configured slave: answer",
    cia305.FASTSCAN: "fastscan",
    cia305.INQUIRE_VENDOR: "inquire vendor-ID",
    cia305.INQUIRE_PRODUCT: "inquire product code",
    cia305.INQUIRE_REVISION: "inquire revision number",
    cia305.INQUIRE_SERIAL: "inquire serial number",
    cia305.INQUIRE_NODE_ID: "inquire node-ID",
}
"""CiA 305 LSS command specifiers."""


@dataclass(frozen=True)
class Meaning:
    """``kind`` (one of ``KINDS``), the node it concerns (None: all or none) and the text."""

    kind: str
    node: int | None
    text: str


def _u32(data: bytes, at: int) -> int:
    return int(struct.unpack_from("<I", data.ljust(at + 4, b"\0"), at)[0])


def _index(data: bytes) -> str:
    index, subindex = struct.unpack_from("<HB", data.ljust(4, b"\0"), 1)
    return f"{index:04X}h/{subindex:02X}h"


def _expedited(data: bytes) -> str:
    """The data of an expedited initiate frame (n unused bytes in bits 2..3 when s is set)."""
    command = data[0]
    size = 4 - ((command >> 2) & 3) if command & 0x01 else 4
    value = data[4 : 4 + size]
    return f"{value.hex(' ')} ({int.from_bytes(value, 'little')})"


def _initiate(data: bytes) -> str:
    """An initiate frame's transfer: the expedited data, or the announced size."""
    if data[0] & 0x02:
        return f"= {_expedited(data)}"
    return f"segmented, {_u32(data, 4)} bytes" if data[0] & 0x01 else "segmented"


def _segment(data: bytes) -> str:
    """A segment's data (n unused bytes in bits 1..3), and whether it is the last."""
    used = data[1 : 8 - ((data[0] >> 1) & 7)]
    return used.hex(" ") + (" (last)" if data[0] & 0x01 else "")


_SdoText = Callable[[int, bytes], str]

_SDO_TEXT: dict[tuple[bool, int], _SdoText] = {
    # (response?, command specifier): the client's ccs, the server's scs (CiA 301 7.2.4.3)
    (False, 1): lambda n, d: f"SDO download request node {n} {_index(d)} {_initiate(d)}",
    (False, 2): lambda n, d: f"SDO upload request node {n} {_index(d)}",
    (False, 0): lambda n, d: f"SDO download segment node {n} {_segment(d)}",
    (False, 3): lambda n, d: f"SDO upload segment request node {n}",
    (False, 4): lambda n, d: _abort("SDO abort by client", n, d),
    (False, 5): lambda n, d: f"SDO block upload request node {n}",
    (False, 6): lambda n, d: f"SDO block download request node {n}",
    (True, 2): lambda n, d: f"SDO upload response node {n} {_index(d)} {_initiate(d)}",
    (True, 3): lambda n, d: f"SDO download response node {n} {_index(d)} ok",
    (True, 0): lambda n, d: f"SDO upload segment node {n} {_segment(d)}",
    (True, 1): lambda n, d: f"SDO download segment response node {n}",
    (True, 4): lambda n, d: _abort("SDO abort by server", n, d),
    (True, 5): lambda n, d: f"SDO block download response node {n}",
    (True, 6): lambda n, d: f"SDO block upload response node {n}",
}


def _abort(what: str, node: int, data: bytes) -> str:
    code = _u32(data, 4)
    return f"{what} node {node} {_index(data)}: {code:08X}h {sdo_abort_text(code)}"


def _pdo(slot: PdoSlot, data: bytes) -> str:
    values = slot.values(data)
    place = "in" if slot.direction == "input" else "out"
    where = f"{place}[{slot.offset}..{slot.offset + slot.length - 1}]"
    shown = ", ".join(f"{name}={value:#x} ({value})" for name, value in values)
    return f"{slot.label} node {slot.node} {where}" + (f": {shown}" if shown else "")


def _sdo_text(node: int, data: bytes, response: bool) -> str:
    if len(data) != 8:
        return f"SDO {'response' if response else 'request'} node {node} of {len(data)} bytes " \
            "(CiA 301 wants 8)"
    specifier = data[0] >> 5
    text = _SDO_TEXT.get((response, specifier))
    if text is None:
        return (f"SDO {'response' if response else 'request'} node {node} with unknown "
                f"command specifier {specifier}")
    return text(node, data)


def decode(can_id: int, data: bytes, *, extended: bool = False, remote: bool = False,
           error: bool = False, view: NetworkView | None = None) -> Meaning:
    """The CANopen meaning of one frame."""
    if error:
        return Meaning("error", None, f"error frame, class {can_id:#x}")
    if extended:
        return Meaning("other", None, "29-bit frame (not CANopen)")
    slot = view.slot_for(can_id) if view is not None and not remote else None
    if slot is not None:
        return Meaning("pdo", slot.node, _pdo(slot, data))
    function, node = can_id & cia301.FUNCTION_CODE_MASK, can_id & cia301.NODE_ID_MASK
    if can_id == cia301.COB_ID_NMT:
        if len(data) < 2:
            return Meaning("nmt", None, f"NMT of {len(data)} bytes (CiA 301 wants 2)")
        target = data[1]
        command = NMT_COMMAND_TEXT.get(data[0], f"unknown command {data[0]:#04x}")
        return Meaning("nmt", target or None,
                       f"NMT {command}: {'all nodes' if target == 0 else f'node {target}'}")
    if can_id == cia301.COB_ID_SYNC:
        return Meaning("sync", None, "SYNC" + (f" counter {data[0]}" if data else ""))
    if can_id == cia301.COB_ID_TIME:
        return Meaning("time", None, "TIME")
    if can_id in (cia305.LSS_REQUEST_COB_ID, cia305.LSS_ANSWER_COB_ID):
        what = LSS_TEXT.get(data[0], f"command {data[0]:#04x}") if data else "empty"
        side = "request" if can_id == cia305.LSS_REQUEST_COB_ID else "response"
        return Meaning("lss", None, f"LSS {side}: {what}")
    if node == 0:
        return Meaning("other", None, "")
    if function == cia301.COB_ID_SYNC:  # 081h..0FFh
        code = int.from_bytes(data[:2].ljust(2, b"\0"), "little")
        register = data[2] if len(data) > 2 else 0
        return Meaning("emcy", node, f"EMCY node {node} {code:04X}h {emcy_text(code)}, "
                                     f"error register {register:02X}h")
    if function in cia301.TPDO_BASES or function in cia301.RPDO_BASES:
        kind = "TPDO" if function in cia301.TPDO_BASES else "RPDO"
        number = (cia301.TPDO_BASES if kind == "TPDO" else cia301.RPDO_BASES).index(function) + 1
        return Meaning("pdo", node, f"{kind}{number} node {node}" + (" (RTR)" if remote else ""))
    if function in (cia301.SDO_RESPONSE_BASE, cia301.SDO_REQUEST_BASE) and not remote:
        return Meaning("sdo", node, _sdo_text(node, data, function == cia301.SDO_RESPONSE_BASE))
    if function == cia301.ERROR_CONTROL_BASE:
        if remote:
            return Meaning("guarding", node, f"guarding request node {node}")
        if not data:
            return Meaning("heartbeat", node, f"error control node {node} without data")
        state = nmt_state_text(data[0])
        if data[0] & cia301.STATE_MASK == cia301.BOOT_UP:
            return Meaning("heartbeat", node, f"boot-up node {node}")
        toggle = " toggle 1" if data[0] & cia301.TOGGLE_BIT else ""
        return Meaning("heartbeat", node, f"heartbeat node {node} {state}{toggle}")
    return Meaning("other", node, "")
