"""The device loop's mailbox turn in C (firmware/_mailbox.c) against its Python turn.

Why in process: the counts are of one device loop's turns, which only that process sees.
The parts are the real ones: two cards (``Device``) serving their images from their own
threads in one directory, one with the turn in C (the default) and one without, asked
through the driver API by a host in the test's thread, so every request reaches both
through the same image, flags and doorbell a host process uses.
"""

from __future__ import annotations

import os
import random
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dpm.commands import COM_SHARED_MEMORY
from dpm.layout import HOST_FLAGS, IO_AREA_SIZE, SND_PD
from dpm.message import Message, Task, TelegramHeader, Tfc
from firmware.device import Device
from host_api.driver import (
    MSG_BUFFER_SIZE,
    DevCloseDriver,
    DevExitBoard,
    DevGetMessage,
    DevInitBoard,
    DevOpenDriver,
    DevPutMessage,
)
from tests.conftest import wait_until

READS = 500
"""COM_Shared_Memory reads a host makes in the turn count's test."""
PYTHON_TURNS_MAX = 60
"""The Python turns the device loop may take for them: the start of the fallback poll's back
off (eight turns) and the odd turn a wake-up of another thread costs; it took one Python turn
per read (500) before the turn in C."""


@dataclass
class Cards:
    native: Device
    python: Device
    turns: dict[int, int]
    """Python turns (``Device.service``) per board."""


def _serve(device: Device, turns: dict[int, int]) -> None:
    service = device.service

    def counted(now: float) -> None:
        turns[device.board] += 1
        service(now)

    device.service = counted  # type: ignore[method-assign]  # counts this card's turns
    device.run()


@pytest.fixture
def cards(tmp_path: Path) -> Iterator[Cards]:
    """Board 0 with the turn in C, board 1 without, the same process data in both; a host
    (this thread) has both open."""
    rng = random.Random(22)
    inputs = bytes(rng.getrandbits(8) for _ in range(IO_AREA_SIZE))
    outputs = bytes(rng.getrandbits(8) for _ in range(IO_AREA_SIZE))
    devices = [Device(board, tmp_path, flash_dir=tmp_path / f"flash{board}") for board in (0, 1)]
    devices[1].native = False
    turns = {0: 0, 1: 0}
    for device in devices:
        device.plc.image.write_inputs(0, inputs)
        device.plc.image.write_send_area(0, outputs)
    threads = [threading.Thread(target=_serve, args=(device, turns), daemon=True)
               for device in devices]
    for thread in threads:
        thread.start()
    try:
        assert DevOpenDriver(os.fspath(tmp_path)) == 0
        for board in (0, 1):
            wait_until(lambda b=board: DevInitBoard(b) == 0,  # type: ignore[misc]
                       what=f"board {board} READY")
        yield Cards(devices[0], devices[1], turns)
        for board in (0, 1):
            DevExitBoard(board)
        DevCloseDriver()
    finally:
        for device, thread in zip(devices, threads, strict=True):
            device.stop()
            thread.join(10)


def _ask(board: int, request: Message) -> Message:
    assert DevPutMessage(board, request, 1000) == 0
    rc, answer = DevGetMessage(board, MSG_BUFFER_SIZE, 1000)
    assert rc == 0 and answer is not None
    return answer


def _read(nr: int, area: int, adr: int, cnt: int, data_type: int, idx: int = 0) -> Message:
    return Message(rx=Task.PLC, tx=Task.USER, b=COM_SHARED_MEMORY, nr=nr & 0xFF,
                   data=TelegramHeader(data_area=area, data_adr=adr, data_idx=idx,
                                       data_cnt=cnt, data_type=data_type,
                                       function=Tfc.READ).encode())


def test_a_host_polling_the_image_costs_the_card_no_python_turn_per_read(cards: Cards) -> None:
    """COM_Shared_Memory reads in a row are answered by the turn in C: the device loop's
    Python turns stay far below one per read, and every answer is the image's bytes. On
    the old code every read took a Python turn (500 of 500)."""
    device = cards.native
    before = cards.turns[0]
    for nr in range(READS):
        answer = _ask(0, _read(nr, 1, nr % 64, 8, 5))
        offset = nr % 64
        assert answer.f == 0 and answer.nr == nr & 0xFF
        assert answer.data[8:] == bytes(device.plc.image.inputs[offset : offset + 8])
    python_turns = cards.turns[0] - before
    assert python_turns <= PYTHON_TURNS_MAX, f"{python_turns} Python turns for {READS} reads"
    device.bell.ring_self()  # the turn in C returns and counts what it served
    wait_until(lambda: device.native_turns >= READS - python_turns, what="the turns in C")


TELEGRAMS = st.builds(
    lambda adr, area, data_adr, idx, cnt, data_type, function, tail: TelegramHeader(
        adr, area, data_adr, idx, cnt, data_type, function, tail).encode(),
    st.integers(0, 255), st.sampled_from([0, 1, 2, 3, 127, 255]),
    st.one_of(st.integers(0, 40), st.integers(0, 0xFFFF)), st.integers(0, 17),
    st.one_of(st.integers(0, 12), st.integers(0, 255)),
    st.sampled_from([5, 6, 10, 14, 0, 7, 0x85, 0x8E, 255]),
    st.sampled_from([1, 1, 1, 0, 2, 3, 255]), st.binary(max_size=4))
REQUEST_DATA = st.one_of(TELEGRAMS, st.binary(max_size=12))


@settings(max_examples=300, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=REQUEST_DATA, nr=st.integers(0, 255), tx=st.integers(0, 255),
       e=st.sampled_from([0, 0, 2, 4]))
def test_the_turn_in_c_answers_as_the_python_turn(cards: Cards, data: bytes, nr: int, tx: int,
                                                  e: int) -> None:
    """Valid and malformed COM_Shared_Memory requests get the same answer bytes (msg.f,
    data, header) and leave the same flags from both cards; reads of the send area and
    of bits included. A request without an answer (msg.e NAK, no error) gets none."""
    request = Message(rx=Task.PLC, tx=tx, b=COM_SHARED_MEMORY, nr=nr, e=e, data=data)
    answers = []
    for board in (0, 1):
        assert DevPutMessage(board, request, 1000) == 0
        rc, answer = DevGetMessage(board, MSG_BUFFER_SIZE, 100 if e & 2 else 1000)
        answers.append((rc, answer.encode() if answer is not None else None))
    assert answers[0] == answers[1]
    assert cards.native.mm[HOST_FLAGS] == cards.python.mm[HOST_FLAGS]
    assert (cards.native.mm[SND_PD : SND_PD + IO_AREA_SIZE]
            == cards.python.mm[SND_PD : SND_PD + IO_AREA_SIZE])
