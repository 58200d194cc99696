"""The foundation issue's acceptance program: a host that knows only docs/dpm.md's numbers.

Everything here goes through ``mmap`` and ``struct`` with the offsets and flag bits of
docs/dpm.md, like a legacy C program poking the card's memory: no ``dpm``, ``host_api`` or
``firmware`` import, and no doorbell (the device's fallback poll serves it, docs/dpm.md 2).
"""

from __future__ import annotations

import mmap
import struct
import time
from collections.abc import Iterator

import pytest

from tests.conftest import Card, wait_until
from tests.raw_mailbox import (
    AREA_BY_FUNCTION,
    AREA_RECEIVE,
    AREA_SEND,
    BIT,
    COM_SHARED_MEMORY,
    CONN_STATUS,
    DEV_FLAGS,
    DRIVER_TYPE,
    ERR_EVENT,
    ERR_NODE_ADR,
    HOST_FLAGS,
    INIT,
    IO_SIZE,
    PD,
    PLC,
    PLC_PARAMETER,
    RCV_PD,
    READ,
    READY,
    RESET,
    RUN,
    SND_PD,
    SPC,
    STRING,
    TASK2_PARAMETER,
    TELEGRAM,
    TIMEOUT,
    UINT8,
    UINT16,
    USER,
    WRITE,
    Answer,
    exchange_mode,
    pending,
    start,
    toggle,
    transact,
)


@pytest.fixture
def dpm(card: Card) -> Iterator[mmap.mmap]:
    mm = card.map()
    yield mm
    mm.close()


def shared_memory(
    mm: mmap.mmap,
    nr: int,
    area: int,
    adr: int,
    cnt: int,
    data_type: int,
    function: int,
    payload: bytes = b"",
    idx: int = 0,
) -> tuple[bytes, Answer]:
    """Send one COM_Shared_Memory command; return its telegram header and the answer."""
    header = TELEGRAM.pack(0, area, adr, idx, cnt, data_type, function)
    answer = transact(mm, PLC, COM_SHARED_MEMORY, header + payload, nr)
    assert (answer.rx, answer.tx, answer.a, answer.b, answer.nr) == (USER, PLC, 17, 0, nr)
    assert answer.ln == len(answer.data)
    return header, answer


def shm_ok(mm: mmap.mmap, nr: int, area: int, adr: int, cnt: int, data_type: int, function: int,
           payload: bytes = b"", idx: int = 0) -> bytes:
    """A COM_Shared_Memory command that must succeed; returns the data read (if any)."""
    header, answer = shared_memory(mm, nr, area, adr, cnt, data_type, function, payload, idx)
    assert answer.f == 0, f"f = {answer.f}"
    assert answer.data[:8] == header, "the answer must echo the telegram header"
    return answer.data[8:]


def shm_error(mm: mmap.mmap, nr: int, area: int, adr: int, cnt: int, data_type: int,
              function: int, payload: bytes = b"", idx: int = 0) -> int:
    _, answer = shared_memory(mm, nr, area, adr, cnt, data_type, function, payload, idx)
    assert answer.ln == 0, "an error answer carries no data (seed 5.1.1: msg.ln 0)"
    return answer.f


# --- a. protocol parameters, warm and cold start ----------------------------------------------


def assert_started(mm: mmap.mmap, mode: int, b_mode: int, watchdog: int) -> None:
    assert exchange_mode(mm) == mode
    assert mm[DRIVER_TYPE] & 0x0F == 4  # [ours] event-driven state field
    assert PLC_PARAMETER.unpack_from(mm, TASK2_PARAMETER) == (b_mode, watchdog)
    assert mm[CONN_STATUS : CONN_STATUS + 16] == b"\xff" * 16
    assert mm[HOST_FLAGS] & READY
    assert not mm[HOST_FLAGS] & RUN  # no configuration: the card is not running
    assert mm[DEV_FLAGS] == 0


def test_cold_start_defaults(dpm: mmap.mmap) -> None:
    assert_started(dpm, 4, 3, 0)
    assert dpm[ERR_EVENT] == 0


@pytest.mark.parametrize(("b_mode", "mode"), [(1, 2), (2, 3), (3, 4)])
def test_warm_start_takes_new_protocol_parameters(dpm: mmap.mmap, b_mode: int, mode: int) -> None:
    dpm[CONN_STATUS : CONN_STATUS + 16] = bytes(16)  # a start enables every node again
    start(dpm, INIT, (b_mode, 500 + b_mode))
    assert_started(dpm, mode, b_mode, 500 + b_mode)
    assert dpm[ERR_EVENT] == 0

    start(dpm, RESET)
    assert_started(dpm, 4, 3, 0)  # the cold start restores the defaults


def test_warm_start_with_unknown_mode(dpm: mmap.mmap) -> None:
    start(dpm, INIT, (7, 100))
    assert exchange_mode(dpm) == 0
    assert dpm[ERR_EVENT] == 52  # unknown handshake mode
    assert dpm[ERR_NODE_ADR] == 255  # the device itself
    assert dpm[CONN_STATUS : CONN_STATUS + 16] == b"\xff" * 16

    start(dpm, RESET)
    assert exchange_mode(dpm) == 4
    assert dpm[ERR_EVENT] == 0


# --- b. COM_Shared_Memory through the raw mailbox handshake -----------------------------------


def test_shared_memory_bytes(dpm: mmap.mmap) -> None:
    data = b"\x11\x22\x33\x44\x55"
    assert shm_ok(dpm, 1, AREA_SEND, 0x123, len(data), UINT8, WRITE, payload=data) == b""
    assert dpm[SND_PD + 0x123 : SND_PD + 0x128] == data
    assert dpm[SND_PD + 0x122] == 0 and dpm[SND_PD + 0x128] == 0
    assert shm_ok(dpm, 2, AREA_SEND, 0x123, 5, UINT8, READ) == data
    assert shm_ok(dpm, 3, AREA_SEND, 0x124, 3, STRING, READ) == data[1:4]

    # data_area 0: the function decides (write -> send area); the last byte of the area
    assert shm_ok(dpm, 4, AREA_BY_FUNCTION, IO_SIZE - 1, 1, STRING, WRITE, payload=b"Z") == b""
    assert dpm[SND_PD + IO_SIZE - 1] == ord("Z")
    assert dpm[RCV_PD] == 0  # the receive area right behind it is untouched


def test_shared_memory_words(dpm: mmap.mmap) -> None:
    words = struct.pack("<HH", 0x1234, 0xBEEF)  # Intel order: LSB first
    assert shm_ok(dpm, 10, AREA_SEND, 0x40, 2, UINT16, WRITE, payload=words) == b""
    assert dpm[SND_PD + 0x80 : SND_PD + 0x84] == b"\x34\x12\xef\xbe"  # word 0x40 = byte 0x80
    assert shm_ok(dpm, 11, AREA_SEND, 0x40, 2, UINT16, READ) == words
    assert shm_ok(dpm, 12, AREA_SEND, 0x41, 1, UINT16, READ) == b"\xef\xbe"
    assert shm_ok(dpm, 13, AREA_SEND, 1791, 1, UINT16, WRITE, payload=b"\x01\x02") == b""
    assert dpm[SND_PD + 3582 : SND_PD + 3584] == b"\x01\x02"


def test_shared_memory_bits(dpm: mmap.mmap) -> None:
    shm_ok(dpm, 20, AREA_SEND, 20, 2, UINT8, WRITE, payload=b"\xff\x00")  # word 10
    # six bits from word 10, bit 5: bits 165..170 of the area, packed from bit 0 of d[0]
    assert shm_ok(dpm, 21, AREA_SEND, 10, 6, BIT, WRITE, payload=b"\x2a", idx=5) == b""
    assert dpm[SND_PD + 20 : SND_PD + 22] == b"\x5f\x05"  # the bits around keep their value
    assert shm_ok(dpm, 22, AREA_SEND, 10, 6, BIT, READ, idx=5) == b"\x2a"
    assert shm_ok(dpm, 23, AREA_SEND, 10, 16, BIT, READ) == b"\x5f\x05"
    assert shm_ok(dpm, 24, AREA_SEND, 10, 9, BIT, READ, idx=4) == b"\x55\x00"


def test_shared_memory_errors(dpm: mmap.mmap) -> None:
    tail = bytes(dpm[SND_PD + IO_SIZE - 16 : SND_PD + IO_SIZE])
    assert shm_error(dpm, 30, 3, 0, 1, UINT8, READ) == 162  # illegal address area
    assert shm_error(dpm, 31, AREA_SEND, IO_SIZE - 5, 10, UINT8, WRITE, payload=b"x" * 10) == 163
    assert shm_error(dpm, 32, AREA_SEND, 1791, 2, UINT16, READ) == 163
    assert shm_error(dpm, 33, AREA_SEND, 1791, 20, BIT, READ, idx=0) == 163
    assert shm_error(dpm, 34, AREA_SEND, 0, 0, UINT8, READ) == 165  # illegal data count
    assert shm_error(dpm, 35, AREA_SEND, 0, 240, UINT8, READ) == 165  # max 239 bytes
    assert shm_error(dpm, 36, AREA_SEND, 0, 120, UINT16, READ) == 165  # max 119 words
    assert shm_error(dpm, 37, AREA_SEND, 0, 1, 7, READ) == 166  # unknown data type
    assert shm_error(dpm, 38, AREA_SEND, 0, 1, UINT8, 9) == 167  # unknown function
    assert dpm[SND_PD + IO_SIZE - 16 : SND_PD + IO_SIZE] == tail  # no failed write landed


def test_unknown_command_and_task(dpm: mmap.mmap) -> None:
    answer = transact(dpm, PLC, 99, b"", 40)
    assert (answer.rx, answer.tx, answer.a, answer.f, answer.nr) == (USER, PLC, 99, 152, 40)
    answer = transact(dpm, 9, 17, b"\x00" * 8, 41)
    assert (answer.rx, answer.tx, answer.a, answer.f, answer.nr) == (USER, 9, 17, 153, 41)


# --- c. process-data cycles -------------------------------------------------------------------


def run_cycles(mm: mmap.mmap, count: int, host_turn_when_pending: bool) -> int:
    """``count`` buffered cycles: wait for the host's turn, write outputs, toggle PDCOM."""
    done = 0
    for i in range(count):
        wait_until(
            lambda: pending(mm, PD) == host_turn_when_pending, TIMEOUT, f"PD turn {i}"
        )
        struct.pack_into("<I", mm, SND_PD, i)
        toggle(mm, PD)
        done += 1
    wait_until(lambda: pending(mm, PD) == host_turn_when_pending, TIMEOUT, "the last PDACK")
    return done


def test_buffered_host_controlled_cycles(dpm: mmap.mmap) -> None:
    assert exchange_mode(dpm) == 4  # default after the cold start
    assert not pending(dpm, PD)  # bits equal: the host's turn
    shm_ok(dpm, 50, AREA_RECEIVE, 100, 4, UINT8, WRITE, payload=b"INPT")
    assert dpm[RCV_PD + 100 : RCV_PD + 104] == bytes(4)  # buffered: not before a cycle
    assert shm_ok(dpm, 51, AREA_RECEIVE, 100, 4, UINT8, READ) == b"INPT"

    toggle(dpm, PD)
    wait_until(lambda: not pending(dpm, PD), TIMEOUT, "PDACK")
    assert dpm[RCV_PD + 100 : RCV_PD + 104] == b"INPT"

    begin = time.monotonic()
    assert run_cycles(dpm, 1000, host_turn_when_pending=False) == 1000
    print(f"mode 4: 1000 cycles in {time.monotonic() - begin:.3f} s")
    assert dpm[RCV_PD + 100 : RCV_PD + 104] == b"INPT"


def test_buffered_device_controlled_cycles(dpm: mmap.mmap) -> None:
    start(dpm, INIT, (1, 0))
    assert exchange_mode(dpm) == 2
    # device-controlled: the device produces a cycle on its own and hands it over
    wait_until(lambda: pending(dpm, PD), TIMEOUT, "the device's first cycle")
    shm_ok(dpm, 60, AREA_RECEIVE, 300, 4, UINT8, WRITE, payload=b"DEV2")
    assert dpm[RCV_PD + 300 : RCV_PD + 304] == bytes(4)  # still the host's turn
    toggle(dpm, PD)
    wait_until(lambda: pending(dpm, PD), TIMEOUT, "the next cycle")
    assert dpm[RCV_PD + 300 : RCV_PD + 304] == b"DEV2"

    begin = time.monotonic()
    assert run_cycles(dpm, 1000, host_turn_when_pending=True) == 1000
    print(f"mode 2: 1000 cycles in {time.monotonic() - begin:.3f} s")


def test_uncontrolled_mode(dpm: mmap.mmap) -> None:
    start(dpm, INIT, (2, 0))
    assert exchange_mode(dpm) == 3
    pd_before = dpm[HOST_FLAGS] & PD
    shm_ok(dpm, 70, AREA_RECEIVE, 200, 4, UINT8, WRITE, payload=b"UNCT")
    wait_until(
        lambda: dpm[RCV_PD + 200 : RCV_PD + 204] == b"UNCT", TIMEOUT, "inputs without handshake"
    )
    dpm[SND_PD + 7] = 0x77  # the host writes outputs at any time
    assert shm_ok(dpm, 71, AREA_SEND, 7, 1, UINT8, READ) == b"\x77"
    assert dpm[HOST_FLAGS] & PD == pd_before  # no PD handshake in this mode


# --- d. special control -----------------------------------------------------------------------


def test_special_control_is_mirrored(dpm: mmap.mmap) -> None:
    assert not dpm[HOST_FLAGS] & SPC
    dpm[DEV_FLAGS] |= SPC
    wait_until(lambda: dpm[HOST_FLAGS] & SPC, TIMEOUT, "SPCACK set")
    dpm[DEV_FLAGS] &= ~SPC & 0xFF
    wait_until(lambda: not dpm[HOST_FLAGS] & SPC, TIMEOUT, "SPCACK cleared")
