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
import shutil
import subprocess
import sys
import sysconfig
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dpm.commands import COM_SDO_UP_DOWNLOAD, COM_SHARED_MEMORY
from dpm.layout import HOST_FLAGS, IO_AREA_SIZE, SND_PD
from dpm.message import Message, Task, TelegramHeader, Tfc
from firmware import native_mailbox
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

SOURCE = Path(__file__).parent.parent / "firmware" / "_mailbox.c"
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


FUZZ_REQUESTS = 3000


def fuzz(directory: str, module: str) -> None:
    """The sanitizers' run (in its own process, the sanitized build of the turn in C loaded
    as ``firmware._mailbox``): random and edge-case COM_Shared_Memory requests, each answer
    compared with what the PLC task's Python handler gives for the same request, and host
    SDO requests of such bytes, compared with the CAN task's."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("firmware._mailbox", module)
    assert spec is not None and spec.loader is not None
    sanitized = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sanitized)
    native_mailbox.serve = native_mailbox.configure(sanitized)
    device = Device(0, directory, flash_dir=Path(directory) / "flash")
    rng = random.Random(309)
    device.plc.image.write_inputs(0, rng.randbytes(IO_AREA_SIZE))
    thread = threading.Thread(target=device.run, daemon=True)
    thread.start()
    assert DevOpenDriver(directory) == 0
    wait_until(lambda: DevInitBoard(0) == 0, what="READY")
    edges = [0, 1, 7, 8, 15, 16, 119, 120, 239, 240, 255, 1791, 1792, 3583, 3584, 0xFFFF]
    for nr in range(FUZZ_REQUESTS):
        if nr % 3:
            header = TelegramHeader(
                rng.randrange(256), rng.choice([0, 1, 2, 3]), rng.choice(edges),
                rng.choice([0, 7, 15, 16, 255]), rng.choice(edges) & 0xFF,
                rng.choice([5, 6, 10, 14, 0x85, 0]), rng.choice([1, 1, 0, 2, 3]))
            data = header.encode()
        else:
            data = rng.randbytes(rng.randrange(0, 24))
        if nr % 4 == 3:  # a host SDO request: the CAN task's, by sdo_turn in C (msg.e 0)
            request = Message(rx=Task.CAN, tx=Task.USER, b=COM_SDO_UP_DOWNLOAD, nr=nr & 0xFF,
                              e=rng.choice([0, 0, 4]), data=data)
            answer = _ask(0, request)
            expected = device.can.handle(request)
            assert answer == expected, (request, answer, expected)
            continue
        request = Message(rx=Task.PLC, tx=Task.USER, b=COM_SHARED_MEMORY, nr=nr & 0xFF,
                          data=data)
        answer = _ask(0, request)
        expected = device.plc.com_shared_memory(request)
        assert answer == expected, (request, answer, expected)
    device.bell.ring_self()
    wait_until(lambda: device.native_turns > FUZZ_REQUESTS // 2, what="the turns in C")
    DevExitBoard(0)
    DevCloseDriver()
    device.stop()
    thread.join(10)


def test_the_turn_in_c_under_the_sanitizers(tmp_path: Path) -> None:
    """Built with AddressSanitizer and UBSan, the turn in C answers random and edge-case
    requests (lengths 0-23, every area, counts and addresses at and past each limit) as
    the Python handler does, without a read or write out of bounds or undefined
    behaviour; host SDO requests of the same bytes (the card unconfigured: every answer
    comes from the call ``sdo_turn`` makes) too."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    runtimes = [subprocess.run([cc, f"-print-file-name={name}"], capture_output=True,
                               text=True, check=True).stdout.strip()
                for name in ("libasan.so", "libubsan.so")]
    if not all(Path(runtime).is_absolute() for runtime in runtimes):
        pytest.skip("no ASan/UBSan run-time libraries for this compiler")
    module = tmp_path / f"_mailbox{sysconfig.get_config_var('EXT_SUFFIX')}"
    subprocess.run([cc, "-shared", "-fPIC", "-std=gnu11", "-Wall", "-Wextra", "-Werror", "-g",
                    "-fsanitize=address,undefined", "-fno-sanitize-recover=all",
                    f"-I{sysconfig.get_paths()['include']}", str(SOURCE), "-o", str(module)],
                   check=True)
    env = {**os.environ, "LD_PRELOAD": " ".join(runtimes),
           "ASAN_OPTIONS": "detect_leaks=0"}
    directory = tmp_path / "dpm"
    directory.mkdir()
    done = subprocess.run(
        [sys.executable, "-c", "import sys, tests.test_native_mailbox as t; "
         "t.fuzz(sys.argv[1], sys.argv[2])", str(directory), str(module)],
        env=env, capture_output=True, text=True, timeout=300, check=False,
        cwd=Path(__file__).parent.parent)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "runtime error" not in done.stderr and "AddressSanitizer" not in done.stderr
