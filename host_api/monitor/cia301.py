"""CiA 301's words for the numbers a monitor sees on the bus.

EMCY error-code classes, SDO abort codes and NMT states are CiA 301's, not the
card's; python ``canopen`` already carries CiA 301's tables for them, so they
are taken from there, in this one place. The NMT command specifiers are the
card's too (COM_NMT_Module_Protocol) and come from ``dpm.commands``.
"""

from __future__ import annotations

from canopen.emcy import EmcyError
from canopen.nmt import NMT_STATES
from canopen.sdo.exceptions import SdoAbortedError

from dpm.cia301 import BOOT_UP, STATE_MASK
from dpm.commands import Nmt

NMT_COMMAND_TEXT: dict[int, str] = {
    Nmt.START: "start",
    Nmt.STOP: "stop",
    Nmt.PREOPERATIONAL: "enter pre-operational",
    Nmt.RESET_NODE: "reset node",
    Nmt.RESET_COMMUNICATION: "reset communication",
}


EMCY_DETAIL_TEXT: dict[int, str] = {
    0x2100: "current, device input side",
    0x2200: "current inside the device",
    0x2300: "current, device output side",
    0x3100: "mains voltage",
    0x3200: "voltage inside the device",
    0x3300: "output voltage",
    0x4100: "ambient temperature",
    0x4200: "device temperature",
    0x6100: "internal software",
    0x6200: "user software",
    0x6300: "data set",
    0x8100: "communication",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
    0x8150: "CAN-ID collision",
    0x8200: "protocol error",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8230: "MPDO destination object not available",
    0x8240: "unexpected SYNC data length",
    0x8250: "RPDO time-out",
}
"""CiA 301's finer EMCY codes (exact, then by their upper byte); canopen has the classes."""


def emcy_text(code: int) -> str:
    """The most specific CiA 301 meaning of an EMCY error code (0000h: error reset)."""
    detail = EMCY_DETAIL_TEXT.get(code) or EMCY_DETAIL_TEXT.get(code & 0xFF00)
    matches = [(mask, text) for value, mask, text in EmcyError.DESCRIPTIONS
               if code & mask == value]
    group = str(max(matches)[1]) if matches else "unknown error code"
    return f"{group}: {detail}" if detail else group


def sdo_abort_text(code: int) -> str:
    return str(SdoAbortedError.CODES.get(code, "unknown abort code"))


def nmt_state_text(state: int) -> str:
    """The NMT state of a heartbeat or guarding answer (toggle bit removed)."""
    state &= STATE_MASK
    if state == BOOT_UP:
        return "BOOT-UP"
    return str(NMT_STATES.get(state, f"state {state}"))
