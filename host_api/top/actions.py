"""What ``cifemu top``'s keys do to the card: NMT commands and an SDO read, through the mailbox.

Each action is one host command to the CAN task, as any host program sends it
(COM_NMT_Module_Protocol, COM_SDO_Up_Download with a telegram header), and its
outcome is one line for the event log: the card's msg.f with the manual's
text, an SDO abort with CiA 301's, or the value read.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

from dpm.commands import COM_NMT_MODULE_PROTOCOL, COM_SDO_UP_DOWNLOAD, Nmt
from dpm.errors import CanF
from dpm.message import Message, Task, TelegramHeader, Tfc
from host_api.board import Board, CifError
from host_api.monitor.cia301 import NMT_COMMAND_TEXT, sdo_abort_text

ACTION_TIMEOUT_MS = 2000

_ADDRESS = re.compile(
    r"^\s*(?:0x)?([0-9a-fA-F]{1,4})h?\s*(?:[:/ ,]\s*(?:0x)?([0-9a-fA-F]{1,2})h?)?\s*$")


def msg_f_text(f: int) -> str:
    """The manual's text of a CAN-task msg.f number (the one place this module looks it up)."""
    return CanF.text_of(f)


def parse_sdo_address(text: str) -> tuple[int, int]:
    """``1017``, ``1017 0``, ``0x1017:0``, ``1017h/00h`` -> (index, subindex), hex as in CiA 301.

    Raises ValueError with what is wrong."""
    match = _ADDRESS.match(text)
    if match is None:
        raise ValueError(f"{text!r} is no object address: type the index in hex, then the "
                         "subindex, e.g. 1017 0")
    return int(match.group(1), 16), int(match.group(2) or "0", 16)


def nmt(board: int, directory: Path | None, node: int, command: Nmt) -> str:
    what = f"NMT {NMT_COMMAND_TEXT[command]} node {node}"
    try:
        with Board(board, directory, timeout=ACTION_TIMEOUT_MS) as card:
            answer = card.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_NMT_MODULE_PROTOCOL,
                                           data=bytes([command, node])))
    except CifError as exc:
        return f"{what}: {exc}"
    return f"{what}: done" if answer.f == 0 else \
        f"{what}: msg.f {answer.f} {msg_f_text(answer.f)}"


def sdo_read(board: int, directory: Path | None, node: int, index: int, subindex: int) -> str:
    what = f"SDO read node {node} {index:04X}h/{subindex:02X}h"
    head = TelegramHeader(node, 0, index, subindex, 0, 0, Tfc.READ).encode()
    try:
        with Board(board, directory, timeout=ACTION_TIMEOUT_MS) as card:
            answer = card.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_SDO_UP_DOWNLOAD,
                                           data=head))
    except CifError as exc:
        return f"{what}: {exc}"
    payload = answer.data[TelegramHeader.SIZE :]
    if answer.f == CanF.SDO_ABORT and len(payload) >= 4:
        code = struct.unpack_from("<I", payload)[0]
        return f"{what}: abort {code:08X}h {sdo_abort_text(code)}"
    if answer.f:
        return f"{what}: msg.f {answer.f} {msg_f_text(answer.f)}"
    value = int.from_bytes(payload[:8], "little") if payload else 0
    return f"{what} = {payload.hex(' ')}" + (f" ({value})" if len(payload) <= 8 else "")
