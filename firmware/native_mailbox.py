"""The device loop's mailbox turn in C for a plain COM_Shared_Memory read and a host SDO
request, and its process-data exchange in the host-controlled modes [ours] (issues 22, 25).

``firmware/_mailbox.c`` answers, with the interpreter lock released while it waits, the
COM_Shared_Memory reads (and malformed COM_Shared_Memory requests) a host rings for while
nothing else needs the device loop's Python turn, and hands a host's COM_SDO_Up_Download
(msg.e 0, or 4: a long upload's request) to the CAN task's one callable for it
(``HostSdo.native_request``) when the card does not record, and serves a host's
DevExchangeIO in the buffered host-controlled modes while it changes no output the CAN
master follows; it returns to that turn for everything else. This module hands it the
numbers it works with, from ``dpm/`` and the PLC task's limits, so the C file holds no
number of the protocol; and, for a recording card, the spool's heads (``dpm.session``) and
the recorder's ledger reads, so that a turn served in C appends to the recorder's queue the
events its hooks would have (``firmware.recorder``) [ours].
"""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType
from typing import Any

import firmware._mailbox as _mailbox
from dpm import flags as fl
from dpm import session as s
from dpm.commands import (
    AREA_BY_FUNCTION,
    AREA_RECEIVE,
    AREA_SEND,
    COM_SDO_UP_DOWNLOAD,
    COM_SHARED_MEMORY,
)
from dpm.doorbell import RING
from dpm.errors import PlcF
from dpm.layout import (
    CONN_STATUS,
    DEV_FLAGS,
    DEV_MBX,
    DEV_WATCHDOG,
    HOST_FLAGS,
    IO_AREA_SIZE,
    MSG_HEADER_SIZE,
    PC_MBX,
    RCV_PD,
    SND_PD,
    TASK2_STATE,
    TASK_STATE_SIZE,
    size_of,
)
from dpm.ledger import END
from dpm.message import LN_OFFSET, MSG_MAX_SIZE, TELEGRAM_HEADER, Ext, Task, Tdt, Tfc
from firmware.plc import data_type_limits
from firmware.recorder import LEDGER_BYTES, LEDGER_FIRST_READ

LAYOUT = {
    "DEV_MBX": DEV_MBX, "PC_MBX": PC_MBX, "HOST_FLAGS": HOST_FLAGS, "DEV_FLAGS": DEV_FLAGS,
    "DEV_WATCHDOG": DEV_WATCHDOG, "SND_PD": SND_PD, "CONN_STATUS": CONN_STATUS,
    "CONN_SIZE": size_of("Task2Parameter.abConnStatus"), "IO_AREA_SIZE": IO_AREA_SIZE,
    "MSG_MAX_SIZE": MSG_MAX_SIZE, "TELEGRAM_HEADER_SIZE": TELEGRAM_HEADER.size,
    "HOSTCOM": fl.HOSTCOM, "DEVACK": fl.DEVACK, "HOSTACK": fl.HOSTACK, "DEVCOM": fl.DEVCOM,
    "HOST_MBX": fl.HOST_MBX, "DEV_MBX_BIT": fl.DEV_MBX, "NAK": int(Ext.NAK),
    "RING": RING[0], "PLC_TASK": int(Task.PLC), "COM_SHARED_MEMORY": COM_SHARED_MEMORY,
    "READ": int(Tfc.READ), "WRITE": int(Tfc.WRITE), "AREA_BY_FUNCTION": AREA_BY_FUNCTION,
    "AREA_RECEIVE": AREA_RECEIVE, "AREA_SEND": AREA_SEND, "BIT": int(Tdt.BIT),
    "UINT16": int(Tdt.UINT16), "UNKNOWN_FUNCTION": int(PlcF.UNKNOWN_FUNCTION),
    "UNKNOWN_DATA_TYPE": int(PlcF.UNKNOWN_DATA_TYPE), "ILLEGAL_AREA": int(PlcF.ILLEGAL_AREA),
    "ILLEGAL_COUNT": int(PlcF.ILLEGAL_COUNT), "BUFFER_OVERFLOW": int(PlcF.BUFFER_OVERFLOW),
    "CAN_TASK": int(Task.CAN), "COM_SDO_UP_DOWNLOAD": int(COM_SDO_UP_DOWNLOAD),
    "SDO_LONG_FIRST": int(Ext.FIRST), "TASK2_STATE": TASK2_STATE,
    "TASK2_STATE_SIZE": TASK_STATE_SIZE,
}
"""What ``configure`` hands the C file, by name."""

SPOOL = {
    **{name: (s.SPOOL_CODES[kind], head.format, head.size) for name, kind, head in (
        ("PUT", s.PUT, s.SPOOL_PUT), ("ANSWER", s.ANSWER, s.SPOOL_ANSWER),
        ("DEV_FLAGS", s.DEV_FLAGS, s.SPOOL_DEV_FLAGS))},
    "LN_OFFSET": LN_OFFSET, "MSG_HEADER_SIZE": MSG_HEADER_SIZE,
    "LEDGER_FIRST_READ": LEDGER_FIRST_READ, "LEDGER_BYTES": LEDGER_BYTES, "END": END[0],
    "STARTS": fl.RESET | fl.INIT,
}
"""What ``configure_record`` hands the C file, by name: per event kind the turn in C records
(the DevFlags it read, the message it took, the answer it gave) its spool code and head
(``dpm.session``'s struct format, which the C file packs field by field, and its size, which
it checks), and what ``Recorder.put`` reads beside it; Task2State, the mailbox's size and the
DEVACK and HOSTCOM bits it takes from ``LAYOUT``."""


EXCHANGE = {
    "PD": fl.PD, "PDACK": fl.PDACK, "READY": fl.READY, "SPC": fl.SPC, "RCV_PD": RCV_PD,
    "EXCHANGE": (s.SPOOL_CODES[s.EXCHANGE], s.SPOOL_EXCHANGE.format, s.SPOOL_EXCHANGE.size),
}
"""What ``configure_exchange`` hands the C file, by name: the host-controlled exchange's
flag bits, RcvPd's offset and the spool head of a recorded exchange."""


def configure(module: ModuleType) -> Callable[..., Any]:
    """Hand ``module`` (``firmware._mailbox``, or a build of it with the sanitizers) its
    numbers; its ``serve``."""
    module.configure(LAYOUT, data_type_limits())
    module.configure_record(SPOOL)
    module.configure_exchange(EXCHANGE)
    serve: Callable[..., Any] = module.serve
    return serve


serve = configure(_mailbox)
