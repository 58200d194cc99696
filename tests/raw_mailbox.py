"""A host that knows only docs/dpm.md's numbers: the image's offsets and flag bits, raw
mailbox handshakes through ``mmap`` and ``struct``, like a legacy C program poking the card's
memory: no ``dpm``, ``host_api`` or ``firmware`` import, and no doorbell (the device polls the
flags at least every ms). tests/test_raw_dpm.py is its acceptance program; other tests borrow
its mailbox when they must show what a program without our libraries sees.
"""

from __future__ import annotations

import mmap
import struct
from dataclasses import dataclass

from tests.conftest import wait_until

# --- docs/dpm.md section 1: the 8 KiB image ----------------------------------------------
SND_PD = 0x0000  # send process data (host outputs)
RCV_PD = 0x0E00  # receive process data (host inputs)
IO_SIZE = 3584
DEV_MBX = 0x1C00  # host -> device
PC_MBX = 0x1D40  # device -> host
TASK2_PARAMETER = 0x1EC0  # bMode u8, usWatchDogTime u16, ...
CONN_STATUS = 0x1EF0  # 16 bytes, bit n = node n
TASK2_STATE = 0x1F40  # COM_DIAGNOSTICS
ERR_NODE_ADR = TASK2_STATE + 2
ERR_EVENT = TASK2_STATE + 3
DRIVER_TYPE = 0x1FF7  # RCSINFO.bDriverType: high nibble = exchange mode
HOST_FLAGS = 0x1FFE  # written by the device
DEV_FLAGS = 0x1FFF  # written by the host

# --- docs/dpm.md section 2: flag bits ---------------------------------------------------
HOST_MBX = 0x01  # HOSTCOM / HOSTACK
DEV_MBX_BIT = 0x02  # DEVACK / DEVCOM
PD = 0x04  # PDACK / PDCOM
SPC = 0x10  # SPCACK / SPCCOM
RUN = 0x40  # HostFlags
READY = 0x80  # HostFlags
INIT = 0x40  # DevFlags: warm start
RESET = 0x80  # DevFlags: cold start

# --- messages -----------------------------------------------------------------------------
MSG_HEADER = struct.Struct("<8B")  # rx tx ln nr a f b e
TELEGRAM = struct.Struct("<BBHBBBB")  # device_adr data_area data_adr data_idx cnt type function
PLC_PARAMETER = struct.Struct("<BH")  # bMode, usWatchDogTime

USER, PLC = 16, 2
COM_SHARED_MEMORY = 17
AREA_BY_FUNCTION, AREA_RECEIVE, AREA_SEND = 0, 1, 2
UINT8, UINT16, STRING, BIT = 5, 6, 10, 14
READ, WRITE = 1, 2

TIMEOUT = 5.0


@dataclass
class Answer:
    rx: int
    tx: int
    ln: int
    nr: int
    a: int
    f: int
    b: int
    e: int
    data: bytes


# --- the raw handshakes -----------------------------------------------------------------------


def pending(mm: mmap.mmap, bit: int) -> bool:
    """True when HostFlags and DevFlags differ at ``bit``."""
    return bool((mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & bit)


def toggle(mm: mmap.mmap, bit: int) -> None:
    mm[DEV_FLAGS] ^= bit


def start(mm: mmap.mmap, request: int, parameters: tuple[int, int] | None = None) -> None:
    """A cold (RESET) or warm (INIT) start, optionally with new protocol parameters."""
    if parameters is not None:
        PLC_PARAMETER.pack_into(mm, TASK2_PARAMETER, *parameters)
    mm[DEV_FLAGS] |= request
    wait_until(
        lambda: not mm[DEV_FLAGS] & request and mm[HOST_FLAGS] & READY,
        TIMEOUT,
        f"the device to clear DevFlags 0x{request:02X} and raise READY",
    )


def exchange_mode(mm: mmap.mmap) -> int:
    return mm[DRIVER_TYPE] >> 4


def put(mm: mmap.mmap, raw: bytes) -> None:
    wait_until(lambda: not pending(mm, DEV_MBX_BIT), TIMEOUT, "the device mailbox to be free")
    mm[DEV_MBX : DEV_MBX + len(raw)] = raw
    toggle(mm, DEV_MBX_BIT)


def get(mm: mmap.mmap) -> Answer:
    wait_until(lambda: pending(mm, HOST_MBX), TIMEOUT, "an answer in the host mailbox")
    ln = mm[PC_MBX + 2]
    raw = bytes(mm[PC_MBX : PC_MBX + 8 + ln])  # only ln + 8 bytes, never the whole slot
    toggle(mm, HOST_MBX)
    rx, tx, ln, nr, a, f, b, e = MSG_HEADER.unpack_from(raw)
    return Answer(rx, tx, ln, nr, a, f, b, e, raw[8:])


def transact(mm: mmap.mmap, rx: int, b: int, data: bytes, nr: int, e: int = 0) -> Answer:
    put(mm, MSG_HEADER.pack(rx, USER, len(data), nr, 0, 0, b, e) + data)
    return get(mm)
