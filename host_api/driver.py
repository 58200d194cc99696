"""The classic CIF device driver API over an emulated card's image.

Each ``Dev*`` function keeps the C driver's name, argument order and return
codes (docs/dpm.md section 4), so a legacy host program ports line by line. Output
parameters come back in a tuple after the return code::

    rc, msg = DevGetMessage(0, 288, 500)

Timeouts are milliseconds; 0 means try once and never wait. No function raises for a
failure the driver reports: every one is a return code (``host_api.board.Board`` turns
them into ``CifError``).

Concurrency [ours]: DevPutMessage, DevGetMessage and the process-data
exchange are each atomic across threads and processes. A call waits for its
channel up to its own timeout and returns DRV_CMD_ACTIVE (-4) when another
caller holds it longer (the put and get channels are thread locks inside the
transaction lock, which excludes other processes). A DevPutMessage takes the
board's transaction lock for this process until its answer is read
(``host_api.locks.Transaction``, the lock libcif takes), so processes that pair
raw DevPutMessage/DevGetMessage calls, Python or C, never read each other's
answers, and the answers of a host that died or gave up waiting are discarded,
never returned. A request the card does not answer (COM_Tx_CAN_Layer2:
``dpm.commands.UNANSWERED``; or one with msg.e NAK) takes the lock for its call
only. Threads of one process that pair raw calls can still read each other's
answers; ``Board.transact`` pairs them atomically.
"""

from __future__ import annotations

import math
import mmap
import struct
import time
from contextlib import ExitStack
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path

from dpm import flags as fl
from dpm._quicklock import Lock as QuickLock
from dpm.commands import UNANSWERED
from dpm.doorbell import RING, HostBell
from dpm.errors import Drv
from dpm.image import MAX_DEV_BOARDS, dpm_dir, image_path, lock_path, open_image
from dpm.layout import (
    DEV_FLAGS,
    DEV_IDENTIFIER,
    DEV_INFO,
    DEV_MBX,
    DEV_WATCHDOG,
    DPM_SIZE,
    DRIVER_TYPE,
    FIRMWARE_INFO,
    HOST_FLAGS,
    HOST_WATCHDOG,
    IO_AREA_SIZE,
    LAST_KB,
    PC_MBX,
    RCS_ERROR,
    RCS_INFO,
    RCV_PD,
    SND_PD,
    TASK1_PARAMETER,
    TASK1_STATE,
    TASK2_PARAMETER,
    TASK2_STATE,
    TASK_INFO,
    TASK_STATE_SIZE,
    VERSION_INFO,
    offset_of,
)
from dpm.message import Ext, Message, MessageError
from host_api._devflags import put_request as _put_request
from host_api._devflags import setup as _setup_transaction
from host_api._devflags import take_answer as _take_answer
from host_api.liveness import firmware_serving
from host_api.locks import LEDGER_MAX, Answer, ChannelLock, Request, Transaction
from host_api.registry import Counters as _Counters
from host_api.registry import MappedBoard as _Board
from host_api.registry import lookup as _board
from host_api.registry import ready_board as _ready_board
from host_api.registry import registry

DRIVER_VERSION = f"cifemu V{version('cifemu')}".encode()[:16]
"""BOARD_INFO.abDriverVersion (16 bytes): the installed distribution's version."""

# Mode and function constants of CIFUSER.H
COLDSTART, WARMSTART, BOOTSTART = 2, 3, 4
HOST_READY, HOST_NOT_READY = 1, 0
WATCHDOG_STOP, WATCHDOG_START = 0, 1
PARAMETER_READ, PARAMETER_WRITE = 1, 2
SPECIAL_CONTROL_CLEAR, SPECIAL_CONTROL_SET = 0, 1
DEVICE_MBX_EMPTY, DEVICE_MBX_FULL = 0, 1
HOST_MBX_EMPTY, HOST_MBX_FULL = 0, 1
STATE_MODE_3, STATE_MODE_4 = 3, 4
STATE_FLAG_UNKNOWN = 0xFF
"""usStateFlag when the card's state-field mode is neither 3 nor 4."""

MSG_BUFFER_SIZE = 288
RAW_AREA_LIMIT = 1022
"""DevReadWriteDPMRaw reaches the last kilobyte up to, not including, the flags."""

# DevGetInfo areas
GET_DRIVER_INFO = 1
GET_VERSION_INFO = 2
GET_FIRMWARE_INFO = 3
GET_TASK_INFO = 4
GET_RCS_INFO = 5
GET_DEV_INFO = 6
GET_IO_INFO = 7
GET_IO_SEND_DATA = 8

_INFO_AREAS: dict[int, tuple[int, int]] = {
    GET_VERSION_INFO: (VERSION_INFO, 32),
    GET_FIRMWARE_INFO: (FIRMWARE_INFO, 32),
    GET_TASK_INFO: (TASK_INFO, 112),
    GET_RCS_INFO: (RCS_INFO, 8),
    GET_DEV_INFO: (DEV_INFO, 6),
    GET_IO_SEND_DATA: (SND_PD, IO_AREA_SIZE),
}
_INFO_SIZES = {**{k: v[1] for k, v in _INFO_AREAS.items()}, GET_DRIVER_INFO: 33, GET_IO_INFO: 6}

DRIVERINFO = struct.Struct("<IIIIIBBBBBBBBBI")
IOINFO = struct.Struct("<BBI")
BOARD_INFO_ENTRY = struct.Struct("<HHIH")
COMSTATE = struct.Struct("<HH64s")

# DRIVERINFO.LastFunction values
FKT_OPEN, FKT_CLOSE, FKT_READ, FKT_WRITE, FKT_IO = 1, 2, 3, 4, 5


@dataclass(slots=True)
class ComState:
    """COMSTATE of DevExchangeIOErr."""

    usMode: int = 0
    usStateFlag: int = 0
    abState: bytes = bytes(TASK_STATE_SIZE)

    def encode(self) -> bytes:
        return COMSTATE.pack(self.usMode, self.usStateFlag, self.abState)


_driver = registry
"""This module's name for the registry (the public API is ``host_api.registry``)."""


# --- driver and board ------------------------------------------------------------------


def DevOpenDriver(directory: str | Path | None = None) -> int:
    """Open the "driver": the image directory (``CIF_DPM_DIR``, /dev/shm/cif)."""
    with _driver.lock:
        path = dpm_dir(directory)
        if not path.is_dir():
            return Drv.DRV_USR_OPEN_ERROR
        if _driver.open_count and _driver.directory != path:
            return Drv.DRV_USR_OPEN_ERROR
        _driver.directory = path
        _driver.open_count += 1
        return Drv.DRV_NO_ERROR


def DevCloseDriver() -> int:
    with _driver.lock:
        if _driver.open_count == 0:
            return Drv.DRV_USR_NOT_INITIALIZED
        _driver.open_count -= 1
        if _driver.open_count == 0:
            for number in list(_driver.boards):
                _driver.boards.pop(number).close()
            _driver.counters.clear()
        return Drv.DRV_NO_ERROR


def DevGetBoardInfo() -> tuple[int, bytes]:
    """BOARD_INFO: the driver version, then {usBoard, usAvailable, ulPhysicalAddress, usIrq}."""
    with _driver.lock:
        if _driver.open_count == 0 or _driver.directory is None:
            return Drv.DRV_USR_NOT_INITIALIZED, b""
        entries = b""
        detected = 0
        for number in range(MAX_DEV_BOARDS):
            available = image_path(_driver.directory, number).exists()
            detected += available
            entries += BOARD_INFO_ENTRY.pack(number, int(available), 0, 0)
        return Drv.DRV_NO_ERROR, DRIVER_VERSION.ljust(16, b"\0") + entries + struct.pack(
            "<H", detected
        )


def DevInitBoard(number: int) -> int:
    """Map board ``number``: -34 when no image exists, -11 when its firmware is not up."""
    with _driver.lock:
        if not 0 <= number < MAX_DEV_BOARDS:
            return Drv.DRV_USR_DEV_NUMBER_INVALID
        if _driver.open_count == 0 or _driver.directory is None:
            return Drv.DRV_USR_NOT_INITIALIZED
        if number in _driver.boards:
            return Drv.DRV_NO_ERROR
        path = image_path(_driver.directory, number)
        if not path.exists():
            return Drv.DRV_USR_DEV_NUMBER_INVALID
        try:
            mm = open_image(path)
        except OSError:
            return Drv.DRV_DEV_DPM_ACCESS_ERROR
        # [ours] READY left behind by a killed firmware: who serves is asked first, READY
        # after (host_api.liveness.firmware_serving).
        serving = firmware_serving(_driver.directory, number)
        rc = _check_card(mm)
        if rc == Drv.DRV_NO_ERROR and not serving:
            rc = Drv.DRV_DEV_NOT_READY
        if rc != Drv.DRV_NO_ERROR:
            mm.close()
            return rc
        board = _open_board(number, path, mm)
        if board is None:
            mm.close()
            return Drv.DRV_USR_INIT_DRV_ERROR
        board.counters.open += 1
        board.counters.last_function = FKT_OPEN
        board.bell.ring_device()  # introduces this host to the device
        _driver.boards[number] = board
        return Drv.DRV_NO_ERROR


def _open_board(number: int, path: Path, mm: mmap.mmap) -> _Board | None:
    """The board with its doorbell and lock files; None when one cannot be had [ours]
    (a directory or a link planted in a lock file's place): the board cannot be shared
    safely, and what was opened is closed again."""
    assert _driver.directory is not None
    directory = _driver.directory
    try:
        with ExitStack() as opened:
            bell = HostBell(path)
            opened.callback(bell.close)
            io = ChannelLock(lock_path(directory, number, "io"))
            opened.callback(io.close)
            transaction = Transaction(lock_path(directory, number, "transaction"))
            opened.pop_all()
    except OSError:
        return None
    return _Board(number, path, mm, bell, QuickLock(), QuickLock(), io, transaction,
                  _driver.counters.setdefault(number, _Counters()))


def _check_card(mm: mmap.mmap) -> int:
    """The driver's checks: DPM access (test pattern), READY, the DPM size."""
    identifier = bytes(mm[DEV_IDENTIFIER : DEV_IDENTIFIER + 3])
    if identifier != b"CIF":
        return Drv.DRV_DEV_DPM_ACCESS_ERROR
    mm[DEV_IDENTIFIER : DEV_IDENTIFIER + 3] = b"\x55\xaa\x00"
    readback = bytes(mm[DEV_IDENTIFIER : DEV_IDENTIFIER + 3])
    mm[DEV_IDENTIFIER : DEV_IDENTIFIER + 3] = identifier
    if readback != b"\x55\xaa\x00":
        return Drv.DRV_DEV_DPM_ACCESS_ERROR
    if not mm[HOST_FLAGS] & fl.READY:
        error = mm[RCS_ERROR]
        return Drv.DRV_RCS_ERROR_OFFSET + error if 0 < error < 250 else Drv.DRV_DEV_NOT_READY
    if mm[offset_of("DevInfo.bDpmSize")] * 1024 != DPM_SIZE:
        return Drv.DRV_DEV_DPMSIZE_MISMATCH
    return Drv.DRV_NO_ERROR


def DevExitBoard(number: int) -> int:
    with _driver.lock:
        board = _board(number)
        if not isinstance(board, _Board):
            return board
        board.counters.close += 1
        board.counters.last_function = FKT_CLOSE
        _driver.boards.pop(number).close()
        return Drv.DRV_NO_ERROR


# --- mailboxes ---------------------------------------------------------------------------


_NO_ERROR = Drv.DRV_NO_ERROR
_STALE = Answer.STALE
"""Read from the module, not from their enum classes, on every mailbox call: an enum
member's look-up through its class is ten times a global's (issue 22)."""

_setup_transaction(HOST_FLAGS, DEV_FLAGS, DEV_MBX, PC_MBX, fl.DEVCOM, fl.HOSTACK, fl.DEV_MBX,
                   fl.HOST_MBX, Ext.NAK, Ext.SEQ_MASK, Ext.FIRST, Ext.CONT, Ext.LAST, RING[0],
                   LEDGER_MAX, UNANSWERED, Request, Message)
native_transaction = True
"""[ours] ``put_inside`` and ``get_inside`` make a put or get that need not wait in one C
call each (``host_api._devflags.put_request``, ``take_answer``: the message, the ledger, the
flags and the ring, as the Python steps below do them, in their order): about 30 us of the
309-3 server's CPU per read were those steps (issue 22). False: the Python steps alone, which
also do every case the C calls hand back (a wait, a stale answer, a sequence continued); the
tests run both."""
_boards = _driver.boards
"""The registry's table, which is never replaced (only changed in place): a mailbox call
looks its board up and tests READY inline, and asks ``ready_board`` only for the code of a
board that is not open or not READY (two Python calls fewer per round trip)."""


def DevPutMessage(number: int, msg: Message | bytes, timeout: int) -> int:
    """Write one message into the device mailbox (-16 full, -17 timeout)."""
    board = _boards.get(number)
    if board is None or not board.mm[HOST_FLAGS] & fl.READY:
        found = _ready_board(number)  # the code that says why, or READY by now
        if not isinstance(found, _Board):
            return found
        board = found
    try:
        message = msg if isinstance(msg, Message) else Message.decode(msg)
        raw = message.encode()
    except MessageError:
        return Drv.DRV_USR_SIZE_INVALID
    deadline = call_deadline(timeout)
    transaction = board.transaction
    if not transaction.enter(timeout / 1000.0):
        return Drv.DRV_CMD_ACTIVE
    try:
        return put_inside(board, message, raw, timeout, deadline)
    finally:
        transaction.leave()


def put_inside(board: _Board, message: Message, raw: bytes, timeout: int,
               deadline: float) -> int:
    """DevPutMessage of ``message`` (encoded: ``raw``) inside the board's transaction lock,
    which the caller holds: by ``Transaction.enter`` (DevPutMessage) or a session
    (``Board.transact``, which so saves an ``enter`` and a ``leave`` per call; issue 22)."""
    put_lock = board.put_lock
    if not (put_lock.acquire(False) or _take(put_lock, deadline)):
        return Drv.DRV_CMD_ACTIVE
    try:
        mm = board.mm
        # The card rings for a message it took only when asked (dpm/doorbell.py).
        if (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.DEV_MBX and not board.wait_for(
                lambda: not (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.DEV_MBX,
                _left_ms(deadline), lambda: board.bell.ring_device(want_mailbox=True)):
            return (Drv.DRV_DEV_MAILBOX_FULL if timeout <= 0
                    else board.timed_out(Drv.DRV_DEV_PUT_TIMEOUT))
        bell = board.bell
        if not (native_transaction and _put_request(board.transaction, mm, message, raw,
                                                    bell.sock.fileno(), bell.device_path)):
            _put_steps(board, message, raw)
        counters = board.counters
        counters.write += 1
        counters.last_function = FKT_WRITE
        return _NO_ERROR
    finally:
        put_lock.release()


def _put_steps(board: _Board, message: Message, raw: bytes) -> None:
    """``put_inside``'s work once the device mailbox is free, step by step in Python: what
    ``_devflags.put_request`` does in one call, and the cases it leaves to these steps."""
    mm = board.mm
    mm[DEV_MBX : DEV_MBX + len(raw)] = raw
    # recorded before the card can see it: a host killed now leaves it in the ledger
    board.transaction.sent(message)
    board.change_dev_flags(toggle=fl.DEVCOM)


def call_deadline(timeout: int) -> float:
    """A mailbox call's deadline on the monotonic clock; 0.0 for a call that does not wait
    (``timeout`` <= 0, the 309-3 server's), which then reads no clock: under User-Mode Linux
    each reading is a system call of about 30 us (issue 22)."""
    return time.monotonic() + timeout / 1000.0 if timeout > 0 else 0.0


def _take(channel: QuickLock, deadline: float) -> bool:
    """The put or get channel of this process, waited for until the call's deadline; the
    transaction lock the call holds already keeps every other host out (``MappedBoard``).
    The callers try the lock without waiting first (the usual case: free, and neither a
    clock read nor this call, on every mailbox round trip)."""
    if not deadline:
        return False
    left = deadline - time.monotonic()
    return left > 0 and channel.acquire(timeout=left)


def _left_ms(deadline: float) -> int:
    """Whole milliseconds left, rounded up: a wait never ends before its time."""
    if not deadline:
        return 0
    return max(0, math.ceil((deadline - time.monotonic()) * 1000))


def DevGetMessage(number: int, size: int, timeout: int) -> tuple[int, Message | None]:
    """Take the waiting message from the host mailbox (-19 none, -18 timeout).

    A message longer than ``size`` stays in the mailbox (-39), so it is not lost.
    [ours] Answers to requests of a host that died, or whose DevGetMessage timed out, are
    read and discarded (with the handshake) within the time-out, never returned.
    """
    if not 0 < size <= MSG_BUFFER_SIZE:
        return Drv.DRV_USR_SIZE_INVALID, None
    board = _boards.get(number)
    if board is None or not board.mm[HOST_FLAGS] & fl.READY:
        found = _ready_board(number)
        if not isinstance(found, _Board):
            return found, None
        board = found
    deadline = call_deadline(timeout)
    transaction = board.transaction
    # a host expecting nothing still waits for other hosts' transactions to finish
    if not transaction.enter(timeout / 1000.0):
        return Drv.DRV_CMD_ACTIVE, None
    try:
        return get_inside(board, size, timeout, deadline)
    finally:
        transaction.leave()


def get_inside(board: _Board, size: int, timeout: int,
               deadline: float) -> tuple[int, Message | None]:
    """DevGetMessage inside the board's transaction lock, which the caller holds (as
    ``put_inside``'s). The flags are read from the map in the waiting condition itself:
    ``fl.pending`` and the board's ``host``/``dev`` were three Python calls more per look,
    and a wait looks a few times (issue 22)."""
    get_lock = board.get_lock
    if not (get_lock.acquire(False) or _take(get_lock, deadline)):
        return Drv.DRV_CMD_ACTIVE, None
    try:
        mm = board.mm
        transaction = board.transaction
        while True:
            if not (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.HOST_MBX and not board.wait_for(
                    lambda: bool((mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.HOST_MBX),
                    _left_ms(deadline)):
                if timeout <= 0:
                    return Drv.DRV_DEV_GET_NO_MESSAGE, None
                # [ours] an answer that did not come in time frees the board for other
                # hosts, and is discarded by whichever host reads it later
                transaction.give_up()
                return board.timed_out(Drv.DRV_DEV_GET_TIMEOUT), None
            if native_transaction:  # the usual case in one call: none to discard, it fits
                bell = board.bell
                msg = _take_answer(transaction, mm, size, bell.sock.fileno(),
                                   bell.device_path, bell.device_wants_ack)
                if msg is not None:
                    break
            msg = Message.decode_at(mm, PC_MBX)
            stale = transaction.is_stale(msg)
            if not stale and 8 + len(msg.data) > size:
                return Drv.DRV_USR_MSG_BUF_TOO_SHORT, None
            # The device polls anyway; a ring only speeds up answers it has queued.
            board.change_dev_flags(toggle=fl.HOSTACK,
                                   ring=stale or board.bell.device_wants_ack)
            # after the handshake: a host killed in between leaves a discarded answer's
            # request in the ledger, never an answer nobody discards
            if transaction.answered(msg) is not _STALE:
                break
        counters = board.counters
        counters.read += 1
        counters.last_function = FKT_READ
        return _NO_ERROR, msg
    finally:
        get_lock.release()


def DevGetMBXState(number: int) -> tuple[int, int, int]:
    """(rc, device mailbox state, host mailbox state): 1 = full."""
    board = _ready_board(number)
    if not isinstance(board, _Board):
        return board, 0, 0
    host, dev = board.host(), board.dev()
    return (
        Drv.DRV_NO_ERROR,
        DEVICE_MBX_FULL if fl.pending(host, dev, fl.DEV_MBX) else DEVICE_MBX_EMPTY,
        HOST_MBX_FULL if fl.pending(host, dev, fl.HOST_MBX) else HOST_MBX_EMPTY,
    )


# --- process data --------------------------------------------------------------------------


def _exchange(
    board: _Board, mode: int, send_offset: int, send_data: bytes, recv_offset: int,
    recv_size: int, timeout: int,
) -> tuple[int, bytes]:
    if send_data and send_offset + len(send_data) > IO_AREA_SIZE:
        return Drv.DRV_USR_SENDSIZE_TOO_LONG, b""
    if recv_size and recv_offset + recv_size > IO_AREA_SIZE:
        return Drv.DRV_USR_RECVSIZE_TOO_LONG, b""
    if not board.ready():
        return Drv.DRV_DEV_NOT_READY, b""
    if not 1 <= mode <= 5:
        return Drv.DRV_DEV_COM_MODE_UNKNOWN, b""
    mm = board.mm
    received = b""
    if mode == 3:  # uncontrolled: no handshake, just the copy
        span = slice(SND_PD + send_offset, SND_PD + send_offset + len(send_data))
        if send_data and mm[span] != send_data:
            mm[span] = send_data
            board.bell.ring_device()  # [ours] the card sends changed outputs when rung
        if recv_size:
            received = mm[RCV_PD + recv_offset : RCV_PD + recv_offset + recv_size]
            if not send_data:
                board.poll_inputs(received)  # [ours] a host polling lets the card run
        rc: int = Drv.DRV_NO_ERROR
    else:
        if not board.io_lock.acquire(timeout / 1000.0):
            return Drv.DRV_CMD_ACTIVE, b""
        try:
            device_controlled = mode in (1, 2)
            # Device-controlled: the host's turn is while the bits differ;
            # host-controlled: while they are equal (the device answered).
            if board.wait_for(
                lambda: fl.pending(board.host(), board.dev(), fl.PD) == device_controlled,
                timeout,
            ):
                if send_data:
                    mm[SND_PD + send_offset : SND_PD + send_offset + len(send_data)] = send_data
                if recv_size:
                    received = mm[RCV_PD + recv_offset : RCV_PD + recv_offset + recv_size]
                board.change_dev_flags(toggle=fl.PDCOM)
                rc = Drv.DRV_NO_ERROR
            else:
                rc = (Drv.DRV_DEV_EXCHANGE_FAILED if timeout <= 0
                      else board.timed_out(Drv.DRV_DEV_EXCHANGE_TIMEOUT))
        finally:
            board.io_lock.release()
    board.counters.io += 1
    board.counters.last_function = FKT_IO
    if not board.host() & fl.COM:
        rc = Drv.DRV_DEV_NO_COM_FLAG
    return rc, bytes(received)


def _driver_mode(board: _Board) -> int:
    return board.mm[DRIVER_TYPE] >> 4


def DevExchangeIO(
    number: int, send_offset: int, send_data: bytes, recv_offset: int, recv_size: int,
    timeout: int,
) -> tuple[int, bytes]:
    """Write outputs and read inputs in the card's handshake mode (bDriverType)."""
    board = _board(number)
    if not isinstance(board, _Board):
        return board, b""
    return _exchange(board, _driver_mode(board), send_offset, send_data, recv_offset,
                     recv_size, timeout)


def DevExchangeIOEx(
    number: int, mode: int, send_offset: int, send_data: bytes, recv_offset: int,
    recv_size: int, timeout: int,
) -> tuple[int, bytes]:
    """DevExchangeIO with the caller's mode: 0..4 select driver modes 1..5."""
    board = _board(number)
    if not isinstance(board, _Board):
        return board, b""
    if not 0 <= mode <= 4:
        return Drv.DRV_USR_MODE_INVALID, b""
    return _exchange(board, mode + 1, send_offset, send_data, recv_offset, recv_size, timeout)


def DevExchangeIOErr(
    number: int, send_offset: int, send_data: bytes, recv_offset: int, recv_size: int,
    timeout: int,
) -> tuple[int, bytes, ComState]:
    """DevExchangeIO, then the state field (COMSTATE) by the card's state mode."""
    rc, received = DevExchangeIO(number, send_offset, send_data, recv_offset, recv_size, timeout)
    board = _driver.boards.get(number)
    if board is None or rc in (Drv.DRV_USR_DEV_NUMBER_INVALID, Drv.DRV_USR_NOT_INITIALIZED):
        return rc, received, ComState()
    state_mode = board.mm[DRIVER_TYPE] & 0x0F
    state = ComState(usMode=state_mode)

    def raw_state() -> bytes:
        return bytes(board.mm[TASK2_STATE : TASK2_STATE + TASK_STATE_SIZE])

    if state_mode == STATE_MODE_4:
        if fl.pending(board.host(), board.dev(), fl.STATE):
            state.abState = raw_state()
            state.usStateFlag = 1
            board.change_dev_flags(toggle=fl.STATEACK)
    elif state_mode == STATE_MODE_3:
        state.usStateFlag = 1 if board.host() & fl.STATECOM else 0
        state.abState = raw_state()
    else:
        state.usStateFlag = STATE_FLAG_UNKNOWN
    return rc, received, state


def DevReadSendData(number: int, offset: int, size: int) -> tuple[int, bytes]:
    """Read back the send area (the outputs the host wrote); needs READY and COM."""
    board = _ready_board(number)
    if not isinstance(board, _Board):
        return board, b""
    if offset + size > IO_AREA_SIZE:
        return Drv.DRV_USR_SIZE_TOO_LONG, b""
    if not board.host() & fl.COM:
        return Drv.DRV_DEV_NO_COM_FLAG, b""
    return Drv.DRV_NO_ERROR, bytes(board.mm[SND_PD + offset : SND_PD + offset + size])


# --- control -----------------------------------------------------------------------------------


def DevReset(number: int, mode: int, timeout: int) -> int:
    """Cold (2), warm (3) or boot (4) start; waits for the card to come back READY."""
    board = _board(number)
    if not isinstance(board, _Board):
        return board
    request = {COLDSTART: fl.RESET, WARMSTART: fl.INIT,
               BOOTSTART: fl.RESET | fl.INIT}.get(mode)
    if request is None:
        return Drv.DRV_USR_MODE_INVALID
    board.change_dev_flags(set_bits=request)
    deadline = time.monotonic() + timeout / 1000.0
    if not board.wait_for(lambda: not board.dev() & (fl.RESET | fl.INIT), timeout):
        return board.timed_out(Drv.DRV_DEV_RESET_TIMEOUT)
    remaining = max(0, int((deadline - time.monotonic()) * 1000))
    if not board.wait_for(board.ready, remaining):
        return board.timed_out(Drv.DRV_DEV_RESET_TIMEOUT)
    return Drv.DRV_NO_ERROR


def DevSetHostState(number: int, mode: int, timeout: int) -> int:
    """HOST_READY (1) clears NOTREADY, HOST_NOT_READY (0) sets it; waits for COM to follow."""
    board = _ready_board(number)
    if not isinstance(board, _Board):
        return board
    if mode == HOST_READY:
        board.change_dev_flags(clear_bits=fl.NOTREADY)
    elif mode == HOST_NOT_READY:
        board.change_dev_flags(set_bits=fl.NOTREADY)
    else:
        return Drv.DRV_USR_MODE_INVALID
    if timeout > 0:
        want = mode == HOST_READY
        if not board.wait_for(lambda: bool(board.host() & fl.COM) == want, timeout):
            return Drv.DRV_DEV_NO_COM_FLAG
    return Drv.DRV_NO_ERROR


def DevTriggerWatchDog(number: int, function: int) -> tuple[int, int]:
    """Start/trigger (1): copy bHostWatchDog into bDevWatchDog; stop (0): write 0."""
    board = _ready_board(number)
    if not isinstance(board, _Board):
        return board, 0
    mm = board.mm
    if function == WATCHDOG_START:
        value = mm[HOST_WATCHDOG]
        mm[DEV_WATCHDOG] = value
        board.bell.ring_device()
        return Drv.DRV_NO_ERROR, value
    if function == WATCHDOG_STOP:
        mm[DEV_WATCHDOG] = 0
        board.bell.ring_device()
        return Drv.DRV_NO_ERROR, 0
    return Drv.DRV_USR_MODE_INVALID, 0


def DevSpecialControl(number: int, mode: int) -> tuple[int, int]:
    """Set (1) or clear (0) SPCCOM; returns the SPCACK level once the card mirrored it.

    [ours] the call waits up to 100 ms for the mirror, then reports the level as it is.
    """
    board = _ready_board(number)
    if not isinstance(board, _Board):
        return board, 0
    if mode == SPECIAL_CONTROL_SET:
        board.change_dev_flags(set_bits=fl.SPCCOM)
    elif mode == SPECIAL_CONTROL_CLEAR:
        board.change_dev_flags(clear_bits=fl.SPCCOM)
    else:
        return Drv.DRV_USR_MODE_INVALID, 0
    board.wait_for(lambda: bool(board.host() & fl.SPCACK) == (mode == 1), 100)
    return Drv.DRV_NO_ERROR, int(bool(board.host() & fl.SPCACK))


# --- information and parameters ---------------------------------------------------------------


def DevGetInfo(number: int, area: int, size: int) -> tuple[int, bytes]:
    """Copy ``size`` bytes of an information area (DRIVERINFO ... send-area readback)."""
    board = _board(number)
    if not isinstance(board, _Board):
        return board, b""
    if size == 0:
        return Drv.DRV_USR_SIZE_ZERO, b""
    if area not in _INFO_SIZES:
        return Drv.DRV_USR_INFO_AREA_INVALID, b""
    if size > _INFO_SIZES[area]:
        return Drv.DRV_USR_SIZE_TOO_LONG, b""
    if area == GET_DRIVER_INFO:
        data = _driver_info(board)
    elif area == GET_IO_INFO:
        data = IOINFO.pack(int(bool(board.host() & fl.COM)), _driver_mode(board),
                           board.counters.io & 0xFFFFFFFF)
    else:
        offset, _ = _INFO_AREAS[area]
        data = bytes(board.mm[offset : offset + size])
    return Drv.DRV_NO_ERROR, data[:size]


def _driver_info(board: _Board) -> bytes:
    c = board.counters
    host, dev = board.host(), board.dev()
    return DRIVERINFO.pack(
        c.open, c.close, c.read, c.write, c.irq,
        int(bool(host & fl.READY)),
        int(fl.pending(host, dev, fl.HOST_MBX)),
        int(fl.pending(host, dev, fl.DEV_MBX)),
        c.last_function, 0, 0, host, dev, int(bool(host & fl.COM)), c.io & 0xFFFFFFFF,
    )


def _task_area(kind: str, task: int) -> int:
    if kind == "state":
        return TASK1_STATE if task == 1 else TASK2_STATE
    return TASK1_PARAMETER if task == 1 else TASK2_PARAMETER


def _check_task_size(size: int) -> int:
    if size == 0:
        return Drv.DRV_USR_SIZE_ZERO
    if not 0 < size <= TASK_STATE_SIZE:
        return Drv.DRV_USR_SIZE_TOO_LONG
    return Drv.DRV_NO_ERROR


def DevGetTaskState(number: int, task: int, size: int) -> tuple[int, bytes]:
    """Read task 1's or task 2's state area (task 2: COM_DIAGNOSTICS)."""
    return _read_task_area(number, "state", task, size)


def DevGetTaskParameter(number: int, task: int, size: int) -> tuple[int, bytes]:
    return _read_task_area(number, "parameter", task, size)


def _read_task_area(number: int, kind: str, task: int, size: int) -> tuple[int, bytes]:
    board = _board(number)
    if not isinstance(board, _Board):
        return board, b""
    if task not in (1, 2):
        return Drv.DRV_USR_NUMBER_INVALID, b""
    rc = _check_task_size(size)
    if rc:
        return rc, b""
    offset = _task_area(kind, task)
    return Drv.DRV_NO_ERROR, bytes(board.mm[offset : offset + size])


def DevPutTaskParameter(number: int, task: int, data: bytes) -> int:
    """Write a task's parameters; they take effect at the next warm start.

    [ours] the driver accepts tasks 1..7, but a CANopen card has parameter
    areas for tasks 1 and 2 only: 3..7 get -36 rather than a silent no-op.
    """
    board = _board(number)
    if not isinstance(board, _Board):
        return board
    if task not in (1, 2):
        return Drv.DRV_USR_NUMBER_INVALID
    rc = _check_task_size(len(data))
    if rc:
        return rc
    offset = _task_area("parameter", task)
    board.mm[offset : offset + len(data)] = data
    board.bell.ring_device()  # [ours] the connection bits take effect when rung (docs/dpm.md 2)
    return Drv.DRV_NO_ERROR


def DevReadWriteDPMRaw(
    number: int, mode: int, offset: int, size: int, data: bytes = b""
) -> tuple[int, bytes]:
    """Read (1) or write (2) the last kilobyte; offset+size may not reach the flags."""
    board = _board(number)
    if not isinstance(board, _Board):
        return board, b""
    if mode not in (PARAMETER_READ, PARAMETER_WRITE):
        return Drv.DRV_USR_MODE_INVALID, b""
    if offset < 0 or size < 0 or offset + size > RAW_AREA_LIMIT:
        return Drv.DRV_USR_SIZE_TOO_LONG, b""
    start = LAST_KB + offset
    if mode == PARAMETER_READ:
        return Drv.DRV_NO_ERROR, bytes(board.mm[start : start + size])
    if len(data) != size:
        return Drv.DRV_USR_SIZE_INVALID, b""
    board.mm[start : start + size] = data
    board.bell.ring_device()
    return Drv.DRV_NO_ERROR, b""


__all__ = [name for name in dir() if name.startswith("Dev")] + [
    "BOOTSTART", "COLDSTART", "HOST_NOT_READY", "HOST_READY", "WARMSTART", "ComState",
]
