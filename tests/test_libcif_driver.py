"""The driver behaviour tests, run against both implementations: host_api.driver and libcif.

Each test takes ``d``, either the Python driver module or libcif through ctypes
(tests/libcif_host.py) with the same call shapes, against a real firmware process: every
success path and every reachable error code must be the same in both.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dpm.errors import Drv
from dpm.layout import offset_of
from dpm.message import Message
from dpm.task2 import ComDiagnostics
from tests.conftest import Card, start_card, wait_until
from tests.libcif_host import PYTHON_DRIVER, CDriver

SHM_READ_RECEIVE = bytes([0, 1, 0, 0, 0, 4, 5, 1])  # COM_Shared_Memory: 4 bytes at 0, read


@pytest.fixture(params=["python", "c"])
def d(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """The implementation under test; the driver is closed again whatever the test did."""
    monkeypatch.setenv("CIF_DPM_DIR", "/nonexistent")
    impl: Any = PYTHON_DRIVER if request.param == "python" else CDriver()
    yield impl
    while impl.DevCloseDriver() == 0:
        pass


@pytest.fixture
def board(card: Card, d: Any) -> int:
    assert d.DevOpenDriver(card.directory) == 0
    assert d.DevInitBoard(0) == 0
    return 0


@pytest.fixture(scope="module")
def shared_card(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Card]:
    """One card for the tests that leave it as they found it: no start, no reset, no
    network, no counter they read (a firmware start per test was most of their time)."""
    running = start_card(tmp_path_factory.mktemp("shared-card"))
    yield running
    running.stop()


@pytest.fixture
def shared_board(shared_card: Card, d: Any) -> Iterator[int]:
    """Board 0 of ``shared_card``; an answer a failed test left unread is taken, so that the
    next test finds an empty mailbox."""
    assert shared_card.proc.poll() is None, "the shared card died in an earlier test"
    assert d.DevOpenDriver(shared_card.directory) == 0
    assert d.DevInitBoard(0) == 0
    yield 0
    while d.DevGetMessage(0, 288, 0)[0] == 0:
        pass


def shm(nr: int, header: bytes, payload: bytes = b"") -> Message:
    return Message(rx=2, tx=16, b=17, nr=nr, data=header + payload)


def transact(d: Any, board: int, msg: Message, timeout: int = 2000) -> Message:
    assert d.DevPutMessage(board, msg, timeout) == 0
    rc, answer = d.DevGetMessage(board, 288, timeout)
    assert rc == 0 and answer is not None
    return answer  # type: ignore[no-any-return]


def start_network(d: Any, board: int) -> None:
    """Download bus parameters (COM_Download area 127): the card starts the network."""
    bus = bytes([0, 127, 0, 0, 2]) + struct.pack("<HH", 0x80, 0) + bytes([0, 0])
    assert transact(d, board, Message(rx=3, tx=16, b=68, nr=1, data=bus)).f == 0
    wait_until(lambda: d.DevGetInfo(board, d.GET_IO_INFO, 6)[1][0] == 1, what="COM")


def warm_start(d: Any, board: int, bmode: int, watchdog_ms: int = 0) -> None:
    assert d.DevPutTaskParameter(board, 2, struct.pack("<BH", bmode, watchdog_ms)) == 0
    assert d.DevReset(board, d.WARMSTART, 5000) == 0


def diagnostics(d: Any, board: int) -> ComDiagnostics:
    rc, raw = d.DevGetTaskState(board, 2, 64)
    assert rc == 0
    return ComDiagnostics.decode(raw)


# --- driver and board -------------------------------------------------------------------


def test_calls_before_open_or_init_are_refused(card: Card, d: Any) -> None:
    assert d.DevInitBoard(0) == Drv.DRV_USR_NOT_INITIALIZED
    assert d.DevGetBoardInfo()[0] == Drv.DRV_USR_NOT_INITIALIZED
    assert d.DevCloseDriver() == Drv.DRV_USR_NOT_INITIALIZED
    assert d.DevGetMessage(0, 288, 0)[0] == Drv.DRV_USR_NOT_INITIALIZED
    assert d.DevOpenDriver(card.directory) == 0
    assert d.DevPutMessage(0, Message(rx=2, tx=16), 0) == Drv.DRV_USR_NOT_INITIALIZED
    assert d.DevGetTaskState(0, 2, 64)[0] == Drv.DRV_USR_NOT_INITIALIZED
    assert d.DevInitBoard(4) == Drv.DRV_USR_DEV_NUMBER_INVALID
    assert d.DevExchangeIO(7, 0, b"", 0, 0, 0)[0] == Drv.DRV_USR_DEV_NUMBER_INVALID
    assert d.DevInitBoard(1) == Drv.DRV_USR_DEV_NUMBER_INVALID  # no image for board 1
    assert d.DevInitBoard(0) == 0
    assert d.DevExitBoard(0) == 0
    assert d.DevGetMBXState(0)[0] == Drv.DRV_USR_NOT_INITIALIZED
    assert d.DevExitBoard(0) == Drv.DRV_USR_NOT_INITIALIZED


def test_open_driver_is_counted(card: Card, d: Any) -> None:
    assert d.DevOpenDriver(card.directory) == 0
    assert d.DevOpenDriver(card.directory) == 0
    assert d.DevInitBoard(0) == 0
    assert d.DevCloseDriver() == 0
    assert d.DevGetInfo(0, d.GET_RCS_INFO, 8)[0] == 0  # still open once
    assert d.DevCloseDriver() == 0
    assert d.DevGetInfo(0, d.GET_RCS_INFO, 8)[0] == Drv.DRV_USR_NOT_INITIALIZED
    assert d.DevCloseDriver() == Drv.DRV_USR_NOT_INITIALIZED


def test_open_driver_needs_the_image_directory(tmp_path: Path, d: Any) -> None:
    assert d.DevOpenDriver(tmp_path / "missing") == Drv.DRV_USR_OPEN_ERROR


def test_board_info_lists_the_running_board(shared_board: int, d: Any) -> None:
    rc, raw = d.DevGetBoardInfo()
    assert rc == 0 and len(raw) == 16 + 4 * 10 + 2
    assert raw[:6] == b"cifemu"
    usboard, available, _, _ = struct.unpack_from("<HHIH", raw, 16)
    assert (usboard, available) == (0, 1)
    assert struct.unpack_from("<HHIH", raw, 26)[:2] == (1, 0)
    assert struct.unpack_from("<H", raw, 56)[0] == 1


def dead_image(directory: Path, *, identifier: bytes = b"CIF", ready: bool = False,
               rcs_error: int = 0, dpm_kib: int = 8, size: int = 8192) -> None:
    """An image file with no firmware behind it, as a crashed card leaves it."""
    image = bytearray(8192)
    start = offset_of("DevInfo.abDevIdentifier")
    image[start : start + 3] = identifier
    image[offset_of("DevInfo.bDpmSize")] = dpm_kib
    image[offset_of("RcsInfo.bRcsError")] = rcs_error
    image[offset_of("HostFlags")] = 0x80 if ready else 0
    (directory / "board0.dpm").write_bytes(bytes(image[:size]))


@pytest.mark.parametrize(
    ("kwargs", "expected"),
    [
        ({}, Drv.DRV_DEV_NOT_READY),
        ({"rcs_error": 42}, 1042),
        ({"rcs_error": 250}, Drv.DRV_DEV_NOT_READY),
        ({"identifier": b"XYZ", "ready": True}, Drv.DRV_DEV_DPM_ACCESS_ERROR),
        ({"ready": True, "dpm_kib": 2}, Drv.DRV_DEV_DPMSIZE_MISMATCH),
        ({"ready": True, "size": 4096}, Drv.DRV_DEV_DPM_ACCESS_ERROR),
    ],
)
def test_init_board_checks_the_card(tmp_path: Path, d: Any, kwargs: dict[str, Any],
                                    expected: int) -> None:
    dead_image(tmp_path, **kwargs)
    assert d.DevOpenDriver(tmp_path) == 0
    assert d.DevInitBoard(0) == expected


def test_init_board_restores_the_identifier_after_its_test_pattern(card: Card, board: int,
                                                                   d: Any) -> None:
    assert card.map()[0x1FFB:0x1FFE] == b"CIF"
    assert d.DevGetInfo(board, d.GET_DEV_INFO, 6) == (0, bytes([8, 0x32, 5]) + b"CIF")


def test_stopped_firmware_leaves_a_board_that_is_not_ready(card: Card, board: int,
                                                           d: Any) -> None:
    assert card.stop() == 0
    assert d.DevPutMessage(board, Message(rx=2, tx=16), 0) == Drv.DRV_DEV_NOT_READY
    assert d.DevGetMessage(board, 288, 0)[0] == Drv.DRV_DEV_NOT_READY
    assert d.DevGetMBXState(board)[0] == Drv.DRV_DEV_NOT_READY
    assert d.DevExchangeIO(board, 0, b"\x01", 0, 1, 0)[0] == Drv.DRV_DEV_NOT_READY
    assert d.DevSetHostState(board, d.HOST_READY, 0) == Drv.DRV_DEV_NOT_READY
    assert d.DevTriggerWatchDog(board, 1)[0] == Drv.DRV_DEV_NOT_READY
    assert d.DevSpecialControl(board, 1)[0] == Drv.DRV_DEV_NOT_READY
    assert d.DevReadSendData(board, 0, 4)[0] == Drv.DRV_DEV_NOT_READY
    assert d.DevReset(board, d.WARMSTART, 50) == Drv.DRV_DEV_NOT_READY  # its lock is free
    d.DevExitBoard(board)
    assert d.DevInitBoard(board) == Drv.DRV_DEV_NOT_READY


# --- mailboxes -----------------------------------------------------------------------------


def test_put_message_rejects_a_malformed_message(shared_board: int, d: Any) -> None:
    """msg.ln 9 with no data bytes behind it: a Python caller's bytes can say so (C passes a
    MSG_STRUC whose bytes are always there)."""
    if d is not PYTHON_DRIVER:
        pytest.skip("a C caller's MSG_STRUC always holds its ln bytes")
    assert (d.DevPutMessage(shared_board, bytes([2, 16, 9, 0, 0, 0, 17, 0]), 0)
            == Drv.DRV_USR_SIZE_INVALID)


def test_put_and_get_message_round_trip(shared_board: int, d: Any) -> None:
    answer = transact(d, shared_board, shm(7, SHM_READ_RECEIVE))
    assert (answer.rx, answer.tx, answer.a, answer.b, answer.nr, answer.f) == (16, 2, 17, 0, 7, 0)
    assert answer.data == SHM_READ_RECEIVE + bytes(4)
    assert d.DevGetMBXState(shared_board) == (0, d.DEVICE_MBX_EMPTY, d.HOST_MBX_EMPTY)


def test_get_message_without_a_message(shared_board: int, d: Any) -> None:
    assert d.DevGetMessage(shared_board, 288, 0) == (Drv.DRV_DEV_GET_NO_MESSAGE, None)
    started = time.monotonic()
    assert d.DevGetMessage(shared_board, 288, 50) == (Drv.DRV_DEV_GET_TIMEOUT, None)
    assert time.monotonic() - started >= 0.045


@pytest.mark.parametrize("size", [0, 289, 65535])
def test_get_message_size_must_fit_a_mailbox(shared_board: int, d: Any, size: int) -> None:
    assert d.DevGetMessage(shared_board, size, 0)[0] == Drv.DRV_USR_SIZE_INVALID


def test_a_message_longer_than_the_buffer_stays_in_the_mailbox(shared_board: int, d: Any) -> None:
    assert d.DevPutMessage(shared_board, shm(1, SHM_READ_RECEIVE), 1000) == 0
    wait_until(lambda: d.DevGetMBXState(shared_board)[2] == d.HOST_MBX_FULL, what="answer")
    assert d.DevGetMessage(shared_board, 12, 0) == (Drv.DRV_USR_MSG_BUF_TOO_SHORT, None)
    rc, answer = d.DevGetMessage(shared_board, 20, 0)
    assert rc == 0 and answer is not None and answer.nr == 1


def test_full_device_mailbox(card: Card, board: int, d: Any) -> None:
    card.freeze()
    try:
        assert d.DevPutMessage(board, shm(1, SHM_READ_RECEIVE), 0) == 0
        assert d.DevGetMBXState(board)[1] == d.DEVICE_MBX_FULL
        assert d.DevPutMessage(board, shm(2, SHM_READ_RECEIVE), 0) == Drv.DRV_DEV_MAILBOX_FULL
        assert d.DevPutMessage(board, shm(2, SHM_READ_RECEIVE), 50) == Drv.DRV_DEV_PUT_TIMEOUT
    finally:
        card.thaw()
    assert d.DevPutMessage(board, shm(2, SHM_READ_RECEIVE), 2000) == 0
    assert [d.DevGetMessage(board, 288, 2000)[1].nr for _ in range(2)] == [1, 2]


def test_a_second_caller_on_a_busy_mailbox_gets_cmd_active(card: Card, board: int,
                                                           d: Any) -> None:
    card.freeze()
    results: list[int] = []
    native: list[int] = []

    def wait_on_the_full_mailbox() -> None:
        native.append(threading.get_native_id())
        results.append(d.DevPutMessage(board, shm(2, SHM_READ_RECEIVE), 400))

    try:
        assert d.DevPutMessage(board, shm(1, SHM_READ_RECEIVE), 0) == 0
        waiter = threading.Thread(target=wait_on_the_full_mailbox)
        waiter.start()

        def held() -> bool:
            # the put channel is a thread lock inside the transaction lock, which this
            # process holds already (the first request's answer is awaited)
            if d is PYTHON_DRIVER:
                return bool(d._driver.boards[board].put_lock.locked())
            # libcif's too: its waiter holds it once it sleeps on the bell (poll or ppoll)
            return bool(native) and sleeps_in_poll(native[0])

        wait_until(held, what="the waiter holds the put channel")
        assert d.DevPutMessage(board, shm(3, SHM_READ_RECEIVE), 0) == Drv.DRV_CMD_ACTIVE
        waiter.join()
    finally:
        card.thaw()
    assert results == [Drv.DRV_DEV_PUT_TIMEOUT]


def sleeps_in_poll(tid: int) -> bool:
    """Whether this process's thread ``tid`` sleeps in poll (7) or ppoll (271)."""
    try:
        call = (Path("/proc/self/task") / str(tid) / "syscall").read_text().split()[0]
    except (OSError, IndexError):
        return False
    return call in ("7", "271")


def test_a_waiting_call_is_woken_by_the_doorbell(card: Card, board: int, d: Any) -> None:
    """The card rings the host when it answers: the wait ends on a ring, not a poll."""
    # The card learns a host's bell from its rings; one round trip makes sure it has
    # (it may handle the first message before the ring that came with it).
    transact(d, board, shm(9, SHM_READ_RECEIVE))
    native: list[int] = []
    got: list[tuple[int, Any]] = []

    def wait_for_the_answer() -> None:
        native.append(threading.get_native_id())
        got.append(d.DevGetMessage(board, 288, 3000))

    card.freeze()
    try:
        assert d.DevPutMessage(board, shm(1, SHM_READ_RECEIVE), 0) == 0
        waiter = threading.Thread(target=wait_for_the_answer)
        waiter.start()
        # the card answers only once the host sleeps on its bell: an answer found before
        # the wait (a host thread late under load) would take no ring
        wait_until(lambda: bool(native) and sleeps_in_poll(native[0]),
                   what="the host waits on its bell")
    finally:
        card.thaw()
    waiter.join()
    rc, answer = got[0]
    assert rc == 0 and answer is not None and answer.nr == 1
    irq_count = struct.unpack_from("<I", d.DevGetInfo(board, d.GET_DRIVER_INFO, 33)[1], 16)[0]
    assert irq_count >= 1


def test_unknown_task_and_unknown_command_are_answered(shared_board: int, d: Any) -> None:
    assert transact(d, shared_board, Message(rx=9, tx=16, b=1, nr=3)).f == 153
    assert transact(d, shared_board, Message(rx=2, tx=16, b=99, nr=4)).f == 152
    assert transact(d, shared_board, Message(rx=0, tx=16, b=99, nr=5)).f == 152


def test_nak_suppresses_only_successful_answers(board: int, d: Any) -> None:
    write = bytes([0, 2, 0, 0, 0, 1, 5, 2])
    assert d.DevPutMessage(board, Message(rx=2, tx=16, b=17, nr=1, e=2, data=write + b"\x5a"),
                           1000) == 0
    assert transact(d, board, Message(rx=2, tx=16, b=17, nr=2, e=2, data=bytes(8))).f == 167
    assert d.DevGetMessage(board, 288, 0)[0] == Drv.DRV_DEV_GET_NO_MESSAGE


def test_unread_answers_push_back_on_the_host(shared_board: int, d: Any) -> None:
    """A host that never reads answers sees a full mailbox, not lost answers."""
    sent = 0
    while d.DevPutMessage(shared_board, shm(sent & 0xFF, SHM_READ_RECEIVE), 200) == 0:
        sent += 1
        assert sent < 200
    received = 0
    while d.DevGetMessage(shared_board, 288, 200)[0] == 0:
        received += 1
    assert received == sent


# --- process data -----------------------------------------------------------------------------


def test_exchange_in_uncontrolled_mode(board: int, d: Any) -> None:
    warm_start(d, board, 2)
    rc, _ = d.DevExchangeIO(board, 10, b"\x11\x22", 0, 0, 0)
    assert rc == Drv.DRV_DEV_NO_COM_FLAG  # data exchanged, but no bus runs yet
    answer = transact(d, board, shm(1, bytes([0, 2, 10, 0, 0, 2, 5, 1])))
    assert answer.data[8:] == b"\x11\x22"
    assert transact(d, board, shm(2, bytes([0, 1, 4, 0, 0, 3, 5, 2]), b"abc")).f == 0
    assert d.DevExchangeIO(board, 0, b"", 4, 3, 0) == (Drv.DRV_DEV_NO_COM_FLAG, b"abc")
    start_network(d, board)
    assert d.DevExchangeIO(board, 0, b"", 4, 3, 0) == (0, b"abc")


@pytest.mark.parametrize("bmode", [3, 1])
def test_buffered_cycles_wait_for_the_device(card: Card, board: int, d: Any, bmode: int) -> None:
    warm_start(d, board, bmode)
    start_network(d, board)
    assert transact(d, board, shm(1, bytes([0, 1, 0, 0, 0, 2, 5, 2]), b"in")).f == 0
    seen = b""
    for cycle in range(50):
        rc, seen = d.DevExchangeIO(board, 0, bytes([cycle]), 0, 2, 1000)
        assert rc == 0
    assert seen == b"in"
    image = card.map()
    device_controlled = bmode == 1
    wait_until(lambda: bool((image[0x1FFE] ^ image[0x1FFF]) & 0x04) == device_controlled,
               what="the host's turn")
    card.freeze()
    try:
        assert d.DevExchangeIO(board, 0, b"x", 0, 0, 0)[0] == 0
        assert d.DevExchangeIO(board, 0, b"y", 0, 0, 0)[0] == Drv.DRV_DEV_EXCHANGE_FAILED
        assert d.DevExchangeIO(board, 0, b"y", 0, 0, 30)[0] == Drv.DRV_DEV_EXCHANGE_TIMEOUT
    finally:
        card.thaw()
    assert transact(d, board, shm(2, bytes([0, 2, 0, 0, 0, 1, 5, 1]))).data[8:] == b"x"


def test_exchange_ex_reaches_modes_1_and_5(board: int, d: Any) -> None:
    start_network(d, board)
    assert d.DevExchangeIOEx(board, 4, 0, b"\x05", 0, 1, 1000)[0] == 0  # driver mode 5
    assert d.DevExchangeIOEx(board, 2, 0, b"\x05", 0, 1, 0)[0] == 0  # driver mode 3
    assert d.DevExchangeIOEx(board, 5, 0, b"", 0, 0, 0)[0] == Drv.DRV_USR_MODE_INVALID
    warm_start(d, board, 1)
    start_network(d, board)
    assert d.DevExchangeIOEx(board, 0, 0, b"\x01", 0, 1, 1000)[0] == 0  # driver mode 1


def test_exchange_size_and_mode_errors(board: int, d: Any) -> None:
    assert d.DevExchangeIO(board, 3580, b"12345", 0, 0, 0)[0] == Drv.DRV_USR_SENDSIZE_TOO_LONG
    assert d.DevExchangeIO(board, 0, b"", 3584, 1, 0)[0] == Drv.DRV_USR_RECVSIZE_TOO_LONG
    assert d.DevExchangeIO(board, 65535, b"", 65535, 0, 0)[0] == Drv.DRV_DEV_NO_COM_FLAG
    warm_start(d, board, 7)
    assert d.DevExchangeIO(board, 0, b"\x01", 0, 1, 0)[0] == Drv.DRV_DEV_COM_MODE_UNKNOWN
    diag = diagnostics(d, board)
    assert (diag.bErr_rem_adr, diag.bErr_event) == (255, 52)
    assert diag.global_bits.name == "CTRL"


def test_exchange_err_reports_state_changes(board: int, d: Any) -> None:
    rc, _, state = d.DevExchangeIOErr(board, 0, b"", 0, 0, 100)
    assert state.usMode == 4
    d.DevPutTaskParameter(board, 2, bytes([9]))
    assert d.DevReset(board, d.WARMSTART, 5000) == 0
    wait_until(lambda: d.DevGetInfo(board, d.GET_DRIVER_INFO, 33)[1][26] & 0x08, what="STATECOM")
    rc, _, state = d.DevExchangeIOErr(board, 0, b"", 0, 0, 0)
    assert rc == Drv.DRV_DEV_COM_MODE_UNKNOWN
    assert state.usStateFlag == 1 and state.abState[3] == 52
    rc, _, state = d.DevExchangeIOErr(board, 0, b"", 0, 0, 0)
    assert state.usStateFlag == 0


def test_read_send_data_needs_com(board: int, d: Any) -> None:
    assert d.DevExchangeIO(board, 0, b"out", 0, 0, 1000)[0] == Drv.DRV_DEV_NO_COM_FLAG
    assert d.DevReadSendData(board, 0, 3)[0] == Drv.DRV_DEV_NO_COM_FLAG
    start_network(d, board)
    assert d.DevReadSendData(board, 0, 3) == (0, b"out")
    assert d.DevReadSendData(board, 3583, 2)[0] == Drv.DRV_USR_SIZE_TOO_LONG


# --- control --------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", [2, 3, 4])
def test_reset_modes(card: Card, board: int, d: Any, mode: int) -> None:
    d.DevPutTaskParameter(board, 2, bytes([2]))
    assert d.DevReset(board, mode, 5000) == 0
    image = card.map()
    assert image[0x1FFF] == 0 and image[0x1FFE] & 0x80
    assert image[0x1FF7] >> 4 == (3 if mode == d.WARMSTART else 4)
    assert image[0x1EF0:0x1F00] == b"\xff" * 16


def test_reset_errors(card: Card, board: int, d: Any) -> None:
    assert d.DevReset(board, 5, 100) == Drv.DRV_USR_MODE_INVALID
    card.freeze()
    try:
        assert d.DevReset(board, d.COLDSTART, 50) == Drv.DRV_DEV_RESET_TIMEOUT
    finally:
        card.thaw()
    assert d.DevReset(board, d.COLDSTART, 5000) == 0


def test_reset_emulates_a_slow_card(tmp_path: Path, d: Any) -> None:
    card = start_card(tmp_path, 0, "--reset-delay", "0.3")
    try:
        assert d.DevOpenDriver(tmp_path) == 0 and d.DevInitBoard(0) == 0
        assert d.DevReset(0, d.WARMSTART, 100) == Drv.DRV_DEV_RESET_TIMEOUT
        wait_until(lambda: card.map()[0x1FFE] & 0x80, what="READY after the slow start")
    finally:
        card.stop()


def test_host_state(board: int, d: Any) -> None:
    assert d.DevSetHostState(board, d.HOST_NOT_READY, 0) == 0
    wait_until(lambda: diagnostics(d, board).bGlobalBits & 0x20, what="NRDY")
    assert d.DevSetHostState(board, d.HOST_READY, 50) == Drv.DRV_DEV_NO_COM_FLAG
    assert diagnostics(d, board).bGlobalBits & 0x20 == 0
    assert d.DevSetHostState(board, 2, 0) == Drv.DRV_USR_MODE_INVALID
    start_network(d, board)
    assert d.DevSetHostState(board, d.HOST_NOT_READY, 1000) == 0
    assert d.DevGetInfo(board, d.GET_IO_INFO, 1)[1] == b"\x00"
    assert d.DevSetHostState(board, d.HOST_READY, 1000) == 0


def test_watchdog_is_answered_and_expires(card: Card, board: int, d: Any) -> None:
    warm_start(d, board, 3, watchdog_ms=100)
    rc, first = d.DevTriggerWatchDog(board, d.WATCHDOG_START)
    assert rc == 0 and first == 1
    wait_until(lambda: d.DevTriggerWatchDog(board, d.WATCHDOG_START)[1] == 2, what="answer")
    for _ in range(5):  # triggering in time keeps the card happy
        value = d.DevTriggerWatchDog(board, d.WATCHDOG_START)[1]

        def answered(v: int = value) -> bool:
            return bool(card.map()[0x1FF3] == v % 255 + 1)

        wait_until(answered, what="watchdog answer")
    assert diagnostics(d, board).bErr_event == 0
    wait_until(lambda: diagnostics(d, board).bErr_event == 220, timeout=2, what="Err_Event 220")
    assert diagnostics(d, board).bErr_rem_adr == 255
    assert d.DevTriggerWatchDog(board, d.WATCHDOG_STOP) == (0, 0)
    assert card.map()[0x1FF4] == 0
    assert d.DevTriggerWatchDog(board, 7)[0] == Drv.DRV_USR_MODE_INVALID


def test_special_control_is_mirrored(shared_board: int, d: Any) -> None:
    assert d.DevSpecialControl(shared_board, 1) == (0, 1)
    assert d.DevSpecialControl(shared_board, 0) == (0, 0)
    assert d.DevSpecialControl(shared_board, 3)[0] == Drv.DRV_USR_MODE_INVALID


# --- information and parameters ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("area", "size"), [(1, 33), (2, 32), (3, 32), (4, 112), (5, 8), (6, 6), (7, 6), (8, 3584)]
)
def test_get_info_areas(shared_board: int, d: Any, area: int, size: int) -> None:
    rc, data = d.DevGetInfo(shared_board, area, size)
    assert rc == 0 and len(data) == size
    assert d.DevGetInfo(shared_board, area, size + 1)[0] == Drv.DRV_USR_SIZE_TOO_LONG
    assert d.DevGetInfo(shared_board, area, 0)[0] == Drv.DRV_USR_SIZE_ZERO


def test_get_info_contents(board: int, d: Any) -> None:
    assert d.DevGetInfo(board, 9, 4)[0] == Drv.DRV_USR_INFO_AREA_INVALID
    assert d.DevGetInfo(board, 0, 4)[0] == Drv.DRV_USR_INFO_AREA_INVALID
    assert d.DevGetInfo(board, 3, 32)[1] == b"CANopen Master  V1.070 cifemu   "
    tasks = d.DevGetInfo(board, 4, 112)[1]
    assert tasks[16:24] == b"PLC     " and tasks[32:40] == b"CAN     "
    assert d.DevGetInfo(board, 5, 8)[1][7] == 0x44
    transact(d, board, shm(1, SHM_READ_RECEIVE))
    info = struct.unpack("<IIIIIBBBBBBBBBI", d.DevGetInfo(board, 1, 33)[1])
    assert info[2:4] == (1, 1)  # ReadCnt, WriteCnt
    assert info[8] == d.FKT_READ and info[11] & 0x80  # bLastFunction, bHostFlags READY
    io = struct.unpack("<BBI", d.DevGetInfo(board, d.GET_IO_INFO, 6)[1])
    assert io == (0, 4, 0)


def test_driver_info_counts_board_opens_and_closes(card: Card, board: int, d: Any) -> None:
    def counts() -> tuple[int, int, int]:
        info = struct.unpack("<IIIIIBBBBBBBBBI", d.DevGetInfo(board, d.GET_DRIVER_INFO, 33)[1])
        return info[0], info[1], info[8]

    assert counts() == (1, 0, d.FKT_OPEN)
    assert d.DevExitBoard(board) == 0
    assert d.DevGetInfo(board, d.GET_DRIVER_INFO, 33)[0] == Drv.DRV_USR_NOT_INITIALIZED
    assert d.DevInitBoard(board) == 0
    assert counts() == (2, 1, d.FKT_OPEN)
    assert d.DevCloseDriver() == 0
    assert d.DevOpenDriver(card.directory) == 0
    assert d.DevInitBoard(board) == 0
    assert counts() == (1, 0, d.FKT_OPEN)


def test_task_state_and_parameters(board: int, d: Any) -> None:
    assert d.DevGetTaskState(board, 3, 64)[0] == Drv.DRV_USR_NUMBER_INVALID
    assert d.DevGetTaskState(board, 2, 0)[0] == Drv.DRV_USR_SIZE_ZERO
    assert d.DevGetTaskState(board, 2, 65)[0] == Drv.DRV_USR_SIZE_TOO_LONG
    assert d.DevGetTaskState(board, 1, 64) == (0, bytes(64))
    assert d.DevGetTaskParameter(board, 0, 3)[0] == Drv.DRV_USR_NUMBER_INVALID
    assert d.DevPutTaskParameter(board, 3, b"\x01") == Drv.DRV_USR_NUMBER_INVALID
    assert d.DevPutTaskParameter(board, 2, bytes(65)) == Drv.DRV_USR_SIZE_TOO_LONG
    assert d.DevPutTaskParameter(board, 2, b"") == Drv.DRV_USR_SIZE_ZERO
    assert d.DevPutTaskParameter(board, 2, struct.pack("<BH", 1, 250)) == 0
    assert d.DevGetTaskParameter(board, 2, 3) == (0, bytes([1, 250, 0]))
    assert d.DevGetInfo(board, 5, 8)[1][7] >> 4 == 4  # not yet: takes effect at a warm start
    assert d.DevReset(board, d.WARMSTART, 5000) == 0
    assert d.DevGetInfo(board, 5, 8)[1][7] >> 4 == 2


def test_raw_access_reaches_the_connection_bits_but_not_the_flags(card: Card, board: int,
                                                                   d: Any) -> None:
    assert d.DevReadWriteDPMRaw(board, d.PARAMETER_WRITE, 0x2F0, 2, b"\x0f\xf0") == (0, b"")
    assert card.map()[0x1EF0:0x1EF2] == b"\x0f\xf0"
    assert d.DevReadWriteDPMRaw(board, d.PARAMETER_READ, 0x2F0, 16)[1][:3] == b"\x0f\xf0\xff"
    assert d.DevReadWriteDPMRaw(board, d.PARAMETER_READ, 1020, 3)[0] == Drv.DRV_USR_SIZE_TOO_LONG
    assert d.DevReadWriteDPMRaw(board, 3, 0, 1)[0] == Drv.DRV_USR_MODE_INVALID
    if d is PYTHON_DRIVER:  # C passes a pointer and a size: they cannot disagree
        assert d.DevReadWriteDPMRaw(board, 2, 0, 2, b"x")[0] == Drv.DRV_USR_SIZE_INVALID


# --- DevDownload ----------------------------------------------------------------------------------

TWO_NODES = ('[bus]\nbitrate = 125000\n[[node]]\nid = 3\nboot = ["start", "pdo"]\n'
             '[[node]]\nid = 4\nboot = ["start", "pdo"]\n')


def make_dbm(directory: Path, name: str = "net.dbm") -> Path:
    from dbm_tools.builder import build_dbm
    from dbm_tools.container import save_dbm
    from dbm_tools.network import parse_network

    path = directory / name
    save_dbm(path, build_dbm(parse_network(TWO_NODES)))
    return path


def test_download_stores_a_database_the_card_starts_from(card: Card, board: int, d: Any,
                                                         tmp_path: Path) -> None:
    path = make_dbm(tmp_path)
    assert d.DevDownload(board, d.CONFIGURATION_DOWNLOAD, path) == 0
    assert d.DevReset(board, d.COLDSTART, 5000) == 0
    wait_until(lambda: card.map()[0x1FFE] & 0x40, what="RUN from the stored database")
    assert node_configured(d, board, 3) and node_configured(d, board, 4)


def node_configured(d: Any, board: int, node: int) -> bool:
    return bool(diagnostics(d, board).abNd_cfg[node // 8] & (1 << (node % 8)))


def test_download_refusals_and_file_errors(board: int, d: Any, tmp_path: Path) -> None:
    from dbm_tools.container import read_data_area, write_dbm

    path = make_dbm(tmp_path)
    broken = bytearray(write_dbm(read_data_area(path.read_bytes()[44:])))
    broken[44] ^= 0xFF  # the checksum word w0: the card refuses with 25
    (tmp_path / "broken.dbm").write_bytes(broken)
    assert d.DevDownload(board, d.CONFIGURATION_DOWNLOAD, tmp_path / "broken.dbm") == 1025
    assert d.DevDownload(board, d.CONFIGURATION_DOWNLOAD, "") == Drv.DRV_USR_FILENAME_INVALID
    assert d.DevDownload(board, d.CONFIGURATION_DOWNLOAD, tmp_path / "none.dbm") == (
        Drv.DRV_USR_FILE_OPEN_FAILED)
    (tmp_path / "empty.dbm").write_bytes(b"")
    assert d.DevDownload(board, d.CONFIGURATION_DOWNLOAD, tmp_path / "empty.dbm") == (
        Drv.DRV_USR_FILE_SIZE_ZERO)
    (tmp_path / "unreadable.dbm").symlink_to("/proc/self/mem")  # opens, then EIO
    assert d.DevDownload(board, d.CONFIGURATION_DOWNLOAD, tmp_path / "unreadable.dbm") == (
        Drv.DRV_USR_FILE_READ_FAILED)
    (tmp_path / "net.txt").write_bytes(path.read_bytes())
    assert d.DevDownload(board, d.CONFIGURATION_DOWNLOAD, tmp_path / "net.txt") == (
        Drv.DRV_USR_INVALID_FILETYPE)
    (tmp_path / "short.dbm").write_bytes(path.read_bytes()[:-2])
    assert d.DevDownload(board, d.CONFIGURATION_DOWNLOAD, tmp_path / "short.dbm") == (
        Drv.DRV_USR_INVALID_FILETYPE)
    assert d.DevDownload(board, d.FIRMWARE_DOWNLOAD, path) == Drv.DRV_DEV_FUNCTION_FAILED
    assert d.DevDownload(board, 7, path) == Drv.DRV_USR_MODE_INVALID
    assert d.DevDownload(3, d.CONFIGURATION_DOWNLOAD, path) == Drv.DRV_USR_NOT_INITIALIZED

