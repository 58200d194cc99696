"""The link to the card: one board's host mailbox, its layer-2 access and the
configuration the card holds, for the CiA 309 service layer.

* One :class:`Link` per board owns the host mailbox: a single reader (a thread, or the
  309-3 server's event loop: ``Link.read_on``) sleeps on the card's doorbell, takes every
  message with ``DevGetMessage`` and routes answers by (``msg.a``, ``msg.nr``) to the
  waiting call and indications (layer-2 frames, boot-up) to the gateway's own listeners.
  Two readers would steal each other's answers, so the link also holds the board's
  transaction lock for its lifetime: another host's ``Board.transact`` gets
  DRV_CMD_ACTIVE instead of silently losing its answer to us.
* The card's answers become 309 reasons here (:func:`card_error`, :func:`driver_error`):
  the services above never look at a ``msg.f`` or a driver code.
* The gateway's own on-line download and read-back of data sets (COM_Start_Seq /
  COM_Download / COM_End_Seq, COM_Upload) are here and nowhere else in the package.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import queue
import struct
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType

from dbm_tools.errors import DbmError
from dbm_tools.parameters import NdFlag, NodeParameterSet
from dpm import flags as fl
from dpm._quicklock import Lock as QuickLock
from dpm.com import CanFrame, UploadRequest, decode_layer2_frames, encode_layer2_frame
from dpm.commands import (
    AREA_BUS,
    COM_BOOTUP_FORWARDING,
    COM_BOOTUP_INDICATION,
    COM_CFGRX_LAYER2,
    COM_RX_CAN_LAYER2,
    COM_SET_NODE_ID,
    COM_TX_CAN_LAYER2,
    COM_UPLOAD,
    F_BUFFER_LENGTH_OVERSTEPPED,
    F_DOUBLE_NODE_ADDRESS,
    F_FAULTY_PARAMETER,
    F_HANDLER_FAILED,
    F_LOCAL_RESOURCE,
    F_NO_RESPONSE,
    F_NOT_CONFIGURED,
    F_NOT_OPERATIONAL,
    F_PARAMETER_FAULT,
    F_RECEIVE_BUFFER_OVERSTEPPED,
    F_REMOTE_ADDRESS_RANGE,
    F_SDO_ABORT,
    F_SEQUENCE_ERROR,
    F_SERVICE_ACTIVE,
    F_TIMEOUT,
    MAX_LEN_DATA_UNIT,
    Com,
)
from dpm.doorbell import HostBell
from dpm.errors import F_UNKNOWN_COMMAND, F_UNKNOWN_TASK, Drv
from dpm.layout import DEV_FLAGS, HOST_FLAGS
from dpm.message import Ext, Message, MessageError, Task
from host_api import driver as d
from host_api.board import Board, CifError
from host_api.cia309.model import (
    BootUpEvent,
    Cia309Error,
    ErrorCode,
    Event,
    RpdoEvent,
    syntax_error,
)
from host_api.cia309.pdo import Pdo
from host_api.online import download_data_set
from host_api.registry import MappedBoard, lookup, registry, transaction_lock

log = logging.getLogger(__name__)

DEFAULT_ANSWER_TIMEOUT = 120.0
"""[ours] seconds a call waits for the card when no command time-out is set. The card
answers every request itself (its SDO time-out runs out first); this only bounds the wait
on a card that stopped."""
READER_POLL_FIRST = 0.005
"""[ours] Seconds the mailbox reader sleeps without a ring, after it found a message the card
did not ring for (or the card restarted), before it looks at the flags itself; each look
that finds nothing unannounced doubles it, up to ``READER_POLL_QUIET``."""
READER_POLL_QUIET = 0.25
"""[ours] The reader's longest sleep without a ring: what an indication waits when the card
does not ring this host (started again after the gateway, or its ring taken by another
thread of this process waiting on the same board). Four looks a second when idle."""
LOOP_CALL_WAIT_S = 1.0
"""How long a pause waits for the reading event loop to stop reading."""
STATE_FLAGS = fl.STATECOM | fl.COM | fl.RUN | fl.READY
"""HostFlags whose change tells the Task2State monitor to look now (the card toggles
STATECOM when Task2State changed, while the state channel is free)."""
ABANDONED_NR_S = 60.0
"""A message number whose caller gave up stays reserved this long for its late answer."""
TRANSACTION_LOCK_WAIT_S = 5.0
RESET_TIMEOUT_MS = 10000

_F_ERRORS: dict[int, ErrorCode] = {
    F_NO_RESPONSE: ErrorCode.TIME_OUT,
    F_TIMEOUT: ErrorCode.TIME_OUT,  # download sequence timed out
    F_NOT_OPERATIONAL: ErrorCode.INTERNAL_STATE,  # the node boots: the card's SDO channel
    F_SERVICE_ACTIVE: ErrorCode.INTERNAL_STATE,  # another transfer to the node still runs
    F_SEQUENCE_ERROR: ErrorCode.INTERNAL_STATE,  # of a split transfer
    F_DOUBLE_NODE_ADDRESS: ErrorCode.INTERNAL_STATE,  # the node-ID is a configured node's
    F_NOT_CONFIGURED: ErrorCode.INTERNAL_STATE,  # the network is not configured / running
    F_HANDLER_FAILED: ErrorCode.INTERNAL_STATE,
    F_LOCAL_RESOURCE: ErrorCode.UNSUPPORTED_NODE,  # the node is not configured
    F_REMOTE_ADDRESS_RANGE: ErrorCode.UNSUPPORTED_NODE,
    F_RECEIVE_BUFFER_OVERSTEPPED: ErrorCode.OUT_OF_MEMORY,  # upload over the card's buffer
    F_BUFFER_LENGTH_OVERSTEPPED: ErrorCode.OUT_OF_MEMORY,  # download over the card's buffer
    F_PARAMETER_FAULT: ErrorCode.SYNTAX_ERROR,
    F_FAULTY_PARAMETER: ErrorCode.SYNTAX_ERROR,
    F_UNKNOWN_COMMAND: ErrorCode.REQUEST_NOT_SUPPORTED,  # firmware without the command
    F_UNKNOWN_TASK: ErrorCode.REQUEST_NOT_SUPPORTED,
}
"""[ours] the card's msg.f -> the 309-3 error number a client sees."""



def card_error(f: int, what: str) -> Cia309Error:
    """The card answered msg.f != 0: the 309-3 error a client sees for it."""
    error = _F_ERRORS.get(f, ErrorCode.INTERNAL_STATE)
    return Cia309Error(error, f"{what}: the card answered msg.f = {f}", f=f)


def driver_error(code: int, what: str) -> Cia309Error:
    """A driver call failed: its time-outs are 103, anything else 102."""
    timeouts = (Drv.DRV_DEV_PUT_TIMEOUT, Drv.DRV_DEV_GET_TIMEOUT, Drv.DRV_DEV_RESET_TIMEOUT)
    error = ErrorCode.TIME_OUT if code in timeouts else ErrorCode.INTERNAL_STATE
    return Cia309Error(error, f"{what}: {CifError(code)}")


# --------------------------------------------------------------------------- layer 2


# --------------------------------------------------------------------------- events


class FrameListener:
    """Frames of chosen identifiers received by layer-2 access (``Gateway.listen``)."""

    def __init__(self, link: Link, cob_ids: frozenset[int]) -> None:
        self._link = link
        self.cob_ids = cob_ids
        self._queue: queue.SimpleQueue[CanFrame] = queue.SimpleQueue()

    def put(self, frame: CanFrame) -> None:
        self._queue.put(frame)

    def get(self, timeout: float | None = None) -> CanFrame:
        """The next frame; ``queue.Empty`` when none came within ``timeout`` seconds."""
        return self._queue.get(timeout=timeout)

    def close(self) -> None:
        self._link.remove_listener(self)

    def __enter__(self) -> FrameListener:
        return self

    def __exit__(
        self, t: type[BaseException] | None, v: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


class IndicationQueue:
    """Every COM_Rx_CAN_Layer2 indication (msg.b 83) as the card sent it, for code that
    reads the layer-2 messages itself (the LSS master): call it with a time-out."""

    def __init__(self, link: Link) -> None:
        self._link = link
        self._queue: queue.SimpleQueue[Message] = queue.SimpleQueue()

    def put(self, msg: Message) -> None:
        self._queue.put(msg)

    def __call__(self, timeout: float) -> Message | None:
        """The next indication within ``timeout`` seconds (0: only one already here)."""
        try:
            if timeout <= 0:
                return self._queue.get_nowait()
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def close(self) -> None:
        self._link.remove_indication_queue(self)


# --------------------------------------------------------------------------- PDOs





class _Backoff:
    """How long a mailbox reader sleeps without a ring before it looks at the flags itself:
    ``READER_POLL_FIRST`` after activity the card did not ring for, doubled by each other
    look up to ``READER_POLL_QUIET``. One for the reader thread and the event loop that reads
    instead.

    A ring is not such activity: a card that rings this host needs no look. While a 309-3
    client read, the card's rings held the look at 5 ms, an extra wake-up and mailbox turn
    every 5 ms (one or two per read under User-Mode Linux, issue 22)."""

    def __init__(self) -> None:
        self.interval = READER_POLL_FIRST

    def after(self, active: bool) -> float:
        """The next sleep, after a look that found activity (a ring, a restart) or none."""
        self.interval = (READER_POLL_FIRST if active
                         else min(self.interval * 2, READER_POLL_QUIET))
        return self.interval


@dataclass
class _Pending:
    """A request waiting for its answer; a long upload collects several messages."""

    b: int
    multipart: bool
    on_part: Callable[[Message], None] | None
    messages: list[Message] = field(default_factory=list)
    done: threading.Event | None = field(default_factory=threading.Event)
    """What a blocking ``Link.request`` waits on; None for ``Link.try_request``, whose
    owner is called back (``on_done``) instead."""
    abandoned_at: float | None = None
    on_done: Callable[[], None] | None = None
    """Called in the reader thread once the answer is complete (``Link.try_request``)."""

    def deliver(self, msg: Message) -> None:
        self.messages.append(msg)
        sequence = msg.e & Ext.SEQ_MASK
        if self.multipart and not msg.f and sequence in (Ext.FIRST, Ext.CONT):
            if self.on_part is not None:
                self.on_part(msg)
            return
        if self.on_part is not None and self.multipart and sequence == Ext.LAST:
            self.on_part(msg)
        if self.done is not None:
            self.done.set()
        if self.on_done is not None:
            self.on_done()


class _Gate:
    """Requests share a link; a reset or a flash transfer takes it alone.

    The thread holding it alone may still send requests (re-configuring after a reset).
    ``try_shared`` and ``leave_shared``, on the 309-3 server's path of every read, take no
    lock (under User-Mode Linux each lock taken reads the clock, a system call): a sharer
    adds its token, then looks for an owner; ``exclusive`` sets the owner, then looks for
    tokens (each step one under the interpreter lock), so at least one sees the other.
    """

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._active: list[None] = []
        """One token per request inside."""
        self._owner: int | None = None

    @contextmanager
    def shared(self) -> Iterator[None]:
        me = threading.get_ident()
        with self._condition:
            if self._owner != me:
                while self._owner is not None:
                    self._condition.wait()
            self._active.append(None)
        try:
            yield
        finally:
            with self._condition:
                self._active.pop()
                self._condition.notify_all()

    def try_shared(self) -> bool:
        """Enter shared, without waiting: False while a thread holds the gate alone (or
        waits to)."""
        self._active.append(None)
        if self._owner is not None:
            self.leave_shared()
            return False
        return True

    def leave_shared(self) -> None:
        """End a ``try_shared``; an owner waiting for the sharers to leave is told."""
        self._active.pop()
        if self._owner is not None:
            with self._condition:
                self._condition.notify_all()

    @contextmanager
    def exclusive(self) -> Iterator[None]:
        me = threading.get_ident()
        with self._condition:
            while self._owner is not None:
                self._condition.wait()
            self._owner = me
            while self._active:
                self._condition.wait()
        try:
            yield
        finally:
            with self._condition:
                self._owner = None
                self._condition.notify_all()


PUT_RETRY_S = 0.0002
_NEITHER = -1
"""``MappedBoard.take_rings``' answer when neither a ring came nor the wake-up pipe."""
_boards = registry.boards
"""The driver's table of mapped boards (changed in place, never replaced)."""


def _put(put_now: Callable[[Message], int], msg: Message, timeout: float) -> int:
    """``put_now`` (a DevPutMessage without waiting on the doorbell) retried until ``timeout``
    seconds.

    [ours] The reader thread waits on the board's doorbell in DevGetMessage; a second
    thread waiting there too (DevPutMessage with a time-out, on a full mailbox) makes the
    driver's poll object fail ("concurrent poll() invocation"). A full mailbox empties
    within a device loop turn, so a short retry costs nothing.
    """
    code = put_now(msg)
    if code not in (Drv.DRV_DEV_MAILBOX_FULL, Drv.DRV_CMD_ACTIVE):
        return code  # the usual case: no clock read
    deadline = time.monotonic() + timeout
    while True:
        time.sleep(PUT_RETRY_S)
        code = put_now(msg)
        if code not in (Drv.DRV_DEV_MAILBOX_FULL, Drv.DRV_CMD_ACTIVE):
            return code
        if time.monotonic() > deadline:
            return Drv.DRV_DEV_PUT_TIMEOUT


class _LinkBoard(Board):
    """The board as the gateway holds it: sending never waits on the doorbell (see
    ``_put``), and reading the mailbox is the reader thread's alone."""

    def put_message(self, msg: Message, timeout: int | None = None) -> None:
        code = _put(lambda m: int(d.DevPutMessage(self.number, m, 0)), msg,
                    self._timeout(timeout) / 1000.0)
        if code != Drv.DRV_NO_ERROR:
            raise CifError(code, "DevPutMessage")

    def get_message(self, timeout: int | None = None) -> Message:
        raise CifError(Drv.DRV_CMD_ACTIVE, "DevGetMessage: the 309 gateway reads this mailbox")


class InFlight:
    """A request sent without waiting for its answer (``Link.try_request``): its owner
    waits for ``on_done`` in its own way, then reads ``messages``, or ``abandon``s it when
    it gives up. It holds the link's gate (shared) and the node's SDO channel until its
    answer is complete or it is given up, whichever comes first: the reader thread lets them
    go itself, so an owner that never comes back (an event loop that stopped) holds nothing
    once the card has answered."""

    def __init__(self, link: Link, nr: int, pending: _Pending, channel: QuickLock | None,
                 timeout: float, on_done: Callable[[], None]) -> None:
        self.link = link
        self.nr = nr
        self.pending = pending
        self.timeout = timeout
        """Seconds its owner waits for the answer, as ``Link.request`` would."""
        self._channel = channel
        self._on_done = on_done
        self._open = [True]
        """The reader thread (answer complete) and the owner (``abandon``) may both end it:
        the first to take the token (``list.pop``, one step under the interpreter lock) does.
        Not a lock: under User-Mode Linux each lock taken reads the clock, a system call."""

    @property
    def messages(self) -> list[Message]:
        """The answer (several messages for a long upload), once ``on_done`` was called."""
        return self.pending.messages

    def release(self, forget: bool = True) -> None:
        """Let the gate and the SDO channel go, and the request's number unless ``forget``
        is False (a given-up request's stays taken for its late answer); once, whichever of
        the reader thread (the answer complete) and the owner calls first."""
        try:
            self._open.pop()
        except IndexError:
            return
        if forget:
            self.link.forget(self.nr)
        if self._channel is not None:
            self._channel.release()
        self.link.gate.leave_shared()

    def delivered(self) -> None:
        """From the reader thread: the answer is complete."""
        self.release()
        self._on_done()

    def abandon(self) -> Cia309Error:
        """Give up waiting (a late answer is discarded); the error ``Link.request`` raises."""
        self.link.abandoned(self.pending)
        self.release(forget=False)  # the number stays taken for the late answer
        return self.link.no_answer(self.pending.b, self.timeout)


class Link:
    """One board: its mailbox reader, its layer-2 access, the gateway state kept for it."""

    def __init__(self, number: int, directory: str | Path | None, emit: Callable[[Event], None]):
        self.number = number
        self.network = number + 1
        self._emit = emit
        try:
            self.board = _LinkBoard(number, directory).open()
        except CifError as exc:
            raise driver_error(exc.code, f"board {number}") from exc
        lock = transaction_lock(number)
        assert lock is not None  # the board was opened just now
        self._transaction = lock
        self._holding = self._transaction.acquire(TRANSACTION_LOCK_WAIT_S)
        if not self._holding:
            self.board.close()
            holder = self._transaction.holder
            raise Cia309Error(ErrorCode.INTERNAL_STATE, f"board {number}: " + (
                holder.advice() if holder is not None else "another host holds its mailbox"))
        self._closing = threading.Event()
        self._pending: dict[int, _Pending] = {}
        self._pending_lock = threading.Lock()
        self._abandoned = 0
        """Requests given up on whose numbers may still be taken (``abandoned``): only then
        does ``_register`` look through the entries (no list and no search per request)."""
        self._numbers = itertools.cycle(range(1, 256))
        self.gate = _Gate()
        self._reader_condition = threading.Condition()
        self._reader_paused = False
        self._reader_busy = False
        self._wake_r, self._wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self.taken = 0
        """Messages taken from the mailbox so far (a look that took any found activity)."""
        self.on_state_flags: Callable[[], None] | None = None
        """Called from the reader thread when the card's STATECOM, COM, RUN or READY
        changed (the Task2State monitor looks at once)."""
        self._sdo_channels: dict[int, QuickLock] = {}
        self._sdo_channels_lock = threading.Lock()
        self._listeners: list[FrameListener] = []
        self._indication_queues: list[IndicationQueue] = []
        self._filters: set[int] = set()
        self.rpdos: dict[int, Pdo] = {}
        self.tpdos: dict[int, Pdo] = {}
        self.pdo_lock = threading.Lock()
        self.rtr_waiters: dict[int, queue.SimpleQueue[bytes]] = {}
        self.settings: dict[tuple[int, int], bytes] = {}
        """Card settings the gateway made (COM_Set_*), by (msg.b, node): replayed after
        ``initialize_gateway`` re-configures the card."""
        self.bootup_forwarding = False
        self.supervision: dict[int, str | None] = {}
        """Error control the gateway switched at run time, by node: "heartbeat",
        "guarding" or None; other nodes supervise as their data set says."""
        self._node_sets: dict[int, NodeParameterSet | None] = {}
        self._reader: threading.Thread | None = None
        self._reader_stop = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        """The event loop that reads the mailbox instead of the reader thread (``read_on``)."""
        self._loop_thread = 0
        self._loop_reading = False
        self._loop_active = False
        self._loop_backoff = _Backoff()
        self._loop_flags = -1
        self._fallback: asyncio.TimerHandle | None = None
        self._bell: HostBell | None = None
        self._loop_board: MappedBoard | None = None
        """The board as the driver mapped it when the loop began to read (``read_on``): the
        one whose doorbell the loop watches (``_bell``), looked up once, not per ring."""
        self._start_reader()

    def close(self) -> None:
        self._closing.set()
        self._on_loop(self._pause_on_loop)
        self._loop = None
        self._stop_reader()
        os.close(self._wake_r)
        os.close(self._wake_w)
        if self._holding:
            self._transaction.release()
        self.board.close()

    def own_node_id(self) -> int:
        """The card's node-ID as the gateway set it (0: as its configuration says)."""
        data = self.settings.get((COM_SET_NODE_ID, 0))
        return data[0] if data else 0

    # --- the mailbox -------------------------------------------------------------------------

    def _read_loop(self) -> None:
        """The reader thread: take each message as the card's ring announces it; sleep
        while none comes.

        It waits on the board's doorbell itself (``_wait_for_ring``) and reads the mailbox
        without waiting (DevGetMessage with time-out 0): a DevGetMessage that waits
        re-checks the flags every millisecond (the driver's fallback poll for a ring another
        thread took), so a gateway with nothing to do woke 1,000 times a second (issue 22).
        A ring is a hint (dpm.doorbell): a card started again does not know this host until
        it rings it, so the reader still looks now and then, at ``READER_POLL_FIRST`` after
        activity it did not ring for, backing off to ``READER_POLL_QUIET`` (``_Backoff``)."""
        backoff = _Backoff()
        flags = -1
        stop = self._reader_stop
        rung = True  # the first look: nothing to judge by
        restarted = False
        while not stop.is_set():
            with self._reader_condition:
                while self._reader_paused and not stop.is_set():
                    self._reader_condition.wait()
                self._reader_busy = True
            taken = self.taken
            code = self._take_messages()
            if code != Drv.DRV_DEV_GET_NO_MESSAGE:
                restarted = True
                stop.wait(0.01)  # the card restarts (-11) or is gone
                continue
            flags = self._state_flags(flags)
            backoff.after(restarted or (not rung and self.taken != taken))
            restarted = False
            rung = self._wait_for_ring(backoff.interval)

    def _take_messages(self, board: MappedBoard | None = None) -> int:
        """Route every message waiting in the mailbox, by a reader its caller marked busy
        (``_reader_busy``), which is not busy again when this returns (a pause for a card
        reset waits until no reader takes messages); the driver's code that ended it
        (DRV_DEV_GET_NO_MESSAGE: the mailbox is empty).

        After a message, the next DevGetMessage is made only when the flags show another:
        one that finds the mailbox empty still takes and gives back the board's ledger
        lock, a fifth of the mailbox's cost of a 309-3 read. The first call of a turn is
        always made, so a card that restarts still reports DRV_DEV_NOT_READY. ``board``: the
        caller's look-up for this turn (None: looked up after the first message)."""
        try:
            while True:
                held = self._held()
                if held is None:
                    code, msg = d.DevGetMessage(self.number, d.MSG_BUFFER_SIZE, 0)
                else:
                    code, msg = d.get_inside(held, d.MSG_BUFFER_SIZE, 0, 0.0)
                if code != Drv.DRV_NO_ERROR or msg is None:
                    return int(code)
                self.taken += 1
                try:
                    self._route(msg)
                except Exception:
                    log.exception("board %d: routing %r failed", self.number, msg)
                if board is None:
                    board = self._mapped()
                # the flags read from the map here: ``fl.pending`` with the board's ``host``
                # and ``dev`` were three Python calls per 309-3 read (issue 22)
                if board is not None and not (
                        (board.mm[HOST_FLAGS] ^ board.mm[DEV_FLAGS]) & fl.HOST_MBX):
                    return Drv.DRV_DEV_GET_NO_MESSAGE
        finally:
            self._not_busy()

    def _held(self) -> MappedBoard | None:
        """The board when this link may call the driver's insides (``put_inside``,
        ``get_inside``, as ``Board.transact``): mapped, READY, and its transaction lock held
        by this link (not while ``mailbox_released``, whose callers hold the gate alone and
        pause the reader). None: the public call, which gives the code that says why not.
        The insides save the lock's ``enter`` and ``leave`` and the argument checks: four
        Python calls and two thread locks taken per mailbox call (issue 22)."""
        board = _boards.get(self.number)
        if board is None or not self._holding or not board.mm[HOST_FLAGS] & fl.READY:
            return None
        return board

    def _put_now(self, msg: Message) -> int:
        """DevPutMessage(number, msg, 0), by the driver's insides when ``_held``."""
        board = self._held()
        if board is None:
            return int(d.DevPutMessage(self.number, msg, 0))
        try:
            raw = msg.encode()
        except MessageError:
            return Drv.DRV_USR_SIZE_INVALID
        return d.put_inside(board, msg, raw, 0, 0.0)

    def _mapped(self) -> MappedBoard | None:
        """The board as the driver maps it now (None while it is not initialised)."""
        board = lookup(self.number)
        return board if isinstance(board, MappedBoard) else None

    def _wait_for_ring(self, timeout: float) -> bool:
        """Sleep until the card rings, ``wake`` is called or ``timeout`` seconds pass;
        True unless the time ran out."""
        board = self._mapped()
        if board is None:
            self._reader_stop.wait(timeout)
            return False
        # the ring and the wake-up pipe in one call in C (``HostBell.wait`` was select,
        # recvfrom, select, then os.read of the pipe; issue 22)
        return board.take_rings(timeout, self._wake_r) != _NEITHER

    def wake(self) -> None:
        """Make the reader thread look up from its wait (a pause, the end)."""
        with contextlib.suppress(BlockingIOError):  # full: it is woken already
            os.write(self._wake_w, b"w")

    def _state_flags(self, seen: int, board: MappedBoard | None = None) -> int:
        """Tell ``on_state_flags`` when the card's STATECOM, COM, RUN or READY changed
        since ``seen`` (a ring came with them); returns them. ``board``: the caller's
        look-up for this turn (None: looked up here)."""
        if board is None:
            board = self._mapped()
        if board is None:
            return seen
        flags = board.mm[HOST_FLAGS] & STATE_FLAGS
        if flags != seen and seen >= 0 and self.on_state_flags is not None:
            self.on_state_flags()
        return flags

    def _start_reader(self) -> None:
        self._reader_stop = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, daemon=True,
                                        name=f"cia309-reader-{self.number}")
        self._reader.start()

    def _stop_reader(self) -> None:
        reader = self._reader
        if reader is None:
            return
        self._reader = None
        self._reader_stop.set()
        self.wake()
        with self._reader_condition:
            self._reader_condition.notify_all()
        if reader is not threading.current_thread():
            reader.join(timeout=2)

    # --- the mailbox read on an event loop ---------------------------------------------------

    def read_on(self, loop: asyncio.AbstractEventLoop) -> bool:
        """Read the mailbox on ``loop`` (call from its thread) instead of the reader thread,
        until ``read_on_thread``; False when another loop reads it already.

        Why: the 309-3 server sends its SDO reads from its event loop; with the reader in a
        thread of its own, each answer costs one more thread wake-up (the reader, then the
        event loop it hands the answer to), each a wait for a CPU and the interpreter lock.
        On the loop the card's ring wakes the loop itself (``add_reader`` on the doorbell).
        Blocking calls from other threads still get their answers: the loop routes them."""
        if self._loop is not None or self._closing.is_set():
            return False
        board = self._mapped()
        if board is None:
            return False
        self._stop_reader()
        self._loop = loop
        self._loop_thread = threading.get_ident()
        self._loop_board = board
        self._bell = board.bell
        self._loop_flags = -1
        self._loop_backoff = _Backoff()
        self._loop_active = False
        self._resume_on_loop()
        return True

    def read_on_thread(self) -> None:
        """Back to the reader thread (from the loop's thread, before the loop ends)."""
        if self._loop is None:
            return
        self._pause_on_loop()
        self._loop = None
        if not self._closing.is_set():
            self._start_reader()

    def _resume_on_loop(self) -> None:
        loop = self._loop
        if loop is None or self._loop_reading or self._reader_paused:
            return
        assert self._bell is not None
        loop.add_reader(self._bell.fileno(), self._loop_turn, True)
        self._loop_reading = True
        self._loop_turn()
        self._fallback = loop.call_later(self._loop_backoff.interval, self._on_fallback)

    def _pause_on_loop(self) -> None:
        if not self._loop_reading or self._loop is None:
            return
        self._loop_reading = False
        assert self._bell is not None
        self._loop.remove_reader(self._bell.fileno())
        if self._fallback is not None:
            self._fallback.cancel()
            self._fallback = None

    def _not_busy(self) -> None:
        """The reader is done with the mailbox; a pause waiting for that is told.

        The lock is taken only when a pause waits: set busy, then look at paused, while a
        pause sets paused, then looks at busy (each step one under the interpreter lock),
        so at least one of them sees the other. Under User-Mode Linux each lock taken reads
        the clock, a system call (issue 22)."""
        self._reader_busy = False
        if self._reader_paused:
            with self._reader_condition:
                self._reader_condition.notify_all()

    def _loop_turn(self, rung: bool = False) -> None:
        """One look at the mailbox and the flags on the loop: when the card rang (``rung``:
        the doorbell is readable, and its ring is taken and counted first), at the
        fallback's time, or when the loop begins to read."""
        board = self._loop_board
        if rung:
            assert board is not None  # set with ``_bell``, whose readability called this
            board.take_rings(0)  # every ring queued, in C without waiting
        self._reader_busy = True  # before paused is looked at: see ``_not_busy``
        if self._reader_paused or not self._loop_reading:
            self._not_busy()
            return
        code = self._take_messages(board)
        if code != Drv.DRV_DEV_GET_NO_MESSAGE:
            self._loop_active = True  # the card restarts: look again soon
        self._loop_flags = self._state_flags(self._loop_flags, board)

    def _on_fallback(self) -> None:
        """The loop's fallback look, as the reader thread's (``_read_loop``)."""
        self._fallback = None
        if not self._loop_reading or self._loop is None:
            return
        taken = self.taken
        self._loop_turn()
        interval = self._loop_backoff.after(self._loop_active or self.taken != taken)
        self._loop_active = False
        self._fallback = self._loop.call_later(interval, self._on_fallback)

    def _on_loop(self, call: Callable[[], None]) -> None:
        """Run ``call`` on the reading loop and wait for it (at once on the loop's thread);
        a loop that no longer runs reads nothing, and is not waited for."""
        loop = self._loop
        if loop is None:
            return
        if threading.get_ident() == self._loop_thread:
            call()
            return
        done = threading.Event()

        def run() -> None:
            try:
                call()
            finally:
                done.set()

        try:
            loop.call_soon_threadsafe(run)
        except RuntimeError:  # the loop is closed
            return
        done.wait(LOOP_CALL_WAIT_S)

    @contextmanager
    def reader_paused(self) -> Iterator[None]:
        """The reader stands still: a driver call that waits on the doorbell (DevReset)
        may, as only one thread of a process may wait there at a time."""
        with self._reader_condition:
            self._reader_paused = True
        self.wake()
        self._on_loop(self._pause_on_loop)
        with self._reader_condition:
            while self._reader_busy:
                self._reader_condition.wait()
        try:
            yield
        finally:
            with self._reader_condition:
                self._reader_paused = False
                self._reader_condition.notify_all()
            loop = self._loop
            if loop is not None:
                with contextlib.suppress(RuntimeError):  # the loop is closed
                    loop.call_soon_threadsafe(self._resume_on_loop)

    @contextmanager
    def mailbox_released(self) -> Iterator[None]:
        """The reader stands still and the transaction lock is free, so a driver routine
        with its own request/answer loop (DevDownload, the flash directory) can run."""
        with self.reader_paused():
            self._transaction.release()
            self._holding = False
            try:
                yield
            finally:
                self._holding = self._transaction.acquire(TRANSACTION_LOCK_WAIT_S)
                if not self._holding:
                    log.warning("board %d: another host took the mailbox", self.number)

    def _route(self, msg: Message) -> None:
        if msg.a == 0:
            self._indication(msg)
            return
        pending = self._pending.get(msg.nr)
        if pending is None or pending.b != msg.a:
            log.debug("board %d: no caller for %r", self.number, msg)
            return
        if pending.abandoned_at is not None:
            with self._pending_lock:  # not one registered meanwhile under the same number
                if self._pending.get(msg.nr) is pending:
                    del self._pending[msg.nr]
            return
        pending.deliver(msg)

    def request(
        self,
        b: int,
        data: bytes,
        timeout: float,
        *,
        e: int = 0,
        multipart: bool = False,
        on_part: Callable[[Message], None] | None = None,
    ) -> list[Message]:
        """Send one CAN-task command and wait for its answer (several for a long upload)."""
        with self.gate.shared():
            nr, pending = self._register(b, multipart, on_part)
            try:
                msg = Message(rx=Task.CAN, tx=Task.USER, b=b, data=data, nr=nr, e=e)
                code = _put(self._put_now, msg, timeout)
                if code != Drv.DRV_NO_ERROR:
                    raise driver_error(code, "DevPutMessage")
                assert pending.done is not None  # a blocking request's
                if not pending.done.wait(timeout):
                    self.abandoned(pending)
                    raise self.no_answer(b, timeout)
            finally:
                if pending.abandoned_at is None:
                    self.forget(nr)
            return pending.messages

    def abandoned(self, pending: _Pending) -> None:
        """A request's owner gave up waiting: its number stays taken for a late answer,
        ``ABANDONED_NR_S`` at most (``_register``)."""
        with self._pending_lock:  # rare (a time-out); the sweep recounts under it
            pending.abandoned_at = time.monotonic()
            self._abandoned += 1

    def forget(self, nr: int) -> None:
        """A request's number is free again (its answer came): only its owner calls this,
        so the entry is its own (one step under the interpreter lock, no lock taken)."""
        self._pending.pop(nr, None)

    def no_answer(self, b: int, timeout: float) -> Cia309Error:
        return Cia309Error(ErrorCode.TIME_OUT,
                           f"board {self.number}: no answer to msg.b {b} within {timeout:g} s")

    def try_request(
        self,
        b: int,
        data: bytes,
        timeout: float,
        on_done: Callable[[], None],
        *,
        e: int = 0,
        multipart: bool = False,
        on_part: Callable[[Message], None] | None = None,
        sdo_node: int | None = None,
    ) -> InFlight | None:
        """``request`` for a caller that cannot block (the 309-3 server's event loop): the
        command is sent and ``on_done`` called from the reader thread once its answer is
        complete. None, with nothing sent, when it would have to wait: the gate held alone,
        ``sdo_node``'s SDO channel busy (``sdo_channel``), the card's mailbox full; the
        caller then makes the blocking call from a thread.

        Why: a thread that waits for the answer costs the server two more thread wake-ups
        per request (to the worker and back to the event loop), each a wait for the
        interpreter lock and a CPU; the reader can wake the event loop directly. Context
        switches per 309-3 read went from about 20 to 7 (docs/benchmarks.md)."""
        if not self.gate.try_shared():
            return None
        channel = None
        if sdo_node is not None:
            channel = self._sdo_channels.get(sdo_node) or self._sdo_channel_lock(sdo_node)
            if not channel.acquire(blocking=False):
                self.gate.leave_shared()
                return None
        try:
            nr, pending = self._register(b, multipart, on_part, wait=False)
        except BaseException:
            if channel is not None:
                channel.release()
            self.gate.leave_shared()
            raise
        flight = InFlight(self, nr, pending, channel, timeout, on_done)
        pending.on_done = flight.delivered
        msg = Message(rx=Task.CAN, tx=Task.USER, b=b, data=data, nr=nr, e=e)
        # ``_put_now`` and its ``_held`` written out: two Python calls fewer per read on the
        # 309-3 server's loop (test_a_read_costs_the_loop_few_calls_of_the_gateways_own_python)
        board = _boards.get(self.number)
        if board is None or not self._holding or not board.mm[HOST_FLAGS] & fl.READY:
            code = d.DevPutMessage(self.number, msg, 0)
        else:
            try:
                code = d.put_inside(board, msg, msg.encode(), 0, 0.0)
            except MessageError:
                code = Drv.DRV_USR_SIZE_INVALID
        if code != Drv.DRV_NO_ERROR:
            flight.release()
            if code in (Drv.DRV_DEV_MAILBOX_FULL, Drv.DRV_CMD_ACTIVE):
                return None
            raise driver_error(code, "DevPutMessage")
        return flight

    def _sdo_channel_lock(self, node: int) -> QuickLock:
        channel = self._sdo_channels.get(node)  # a dict read is atomic: no lock to find it
        if channel is not None:
            return channel
        with self._sdo_channels_lock:
            return self._sdo_channels.setdefault(node, QuickLock())

    @contextmanager
    def sdo_channel(self, node: int, timeout: float) -> Iterator[None]:
        """The node's SDO channel for one transfer: the card runs one transfer per node
        and refuses a second (f 54), so the gateway's sessions take turns; 103 when the
        turn does not come within the time-out."""
        channel = self._sdo_channel_lock(node)
        if not channel.acquire(timeout=timeout):
            raise Cia309Error(ErrorCode.TIME_OUT, f"node {node}: its SDO channel stays busy")
        try:
            yield
        finally:
            channel.release()

    def command(self, b: int, data: bytes, timeout: float, what: str) -> Message:
        """A request whose answer must say f 0; f 3 with four data bytes carries the SDO
        abort of a node the card wrote to (COM_Set_Guarding writes 100Ch/100Dh/1017h)."""
        answer = self.request(b, data, timeout)[-1]
        if answer.f == F_SDO_ABORT and len(answer.data) == 4:
            raise Cia309Error.abort(int.from_bytes(answer.data, "little"), what)
        if answer.f:
            raise card_error(answer.f, what)
        return answer

    def send(self, b: int, data: bytes) -> None:
        """A command without an answer (COM_Tx_CAN_Layer2).

        [ours] Sent with msg.e NAK (no answer wanted unless it fails), which is what the
        card does with it: the driver's ledger then awaits no answer. Without it each send
        stayed in the ledger as a request awaited for ever (the link holds the transaction
        lock for its lifetime, so nothing gives it up), and every later mailbox answer was
        compared with each such entry and rewrote all of them into the ledger file: 41 more
        Python calls and a pwrite per 309-3 read after 13 LSS or layer-2 sends, up to 128
        entries (issue 22). Since branch ledger the drivers await no answer to b 84 whatever
        msg.e (``dpm.commands.UNANSWERED``); the NAK stays, as what the card does."""
        with self.gate.shared():
            msg = Message(rx=Task.CAN, tx=Task.USER, b=b, data=data, e=Ext.NAK)
            code = _put(self._put_now, msg, 1.0)
            if code != Drv.DRV_NO_ERROR:
                raise driver_error(code, "DevPutMessage")

    def _register(
        self, b: int, multipart: bool, on_part: Callable[[Message], None] | None,
        *, wait: bool = True,
    ) -> tuple[int, _Pending]:
        """A number for a request and its entry. Without a
        lock or a clock read on the usual path (under User-Mode Linux each is a system
        call): a number is claimed with one ``setdefault`` (one step under the interpreter
        lock); only numbers given up on are looked at under the lock, for the time they stay
        reserved."""
        if self._abandoned:
            now = time.monotonic()
            with self._pending_lock:
                left = 0
                for nr, old in list(self._pending.items()):
                    if old.abandoned_at is None:
                        continue
                    if now - old.abandoned_at > ABANDONED_NR_S:
                        del self._pending[nr]
                    else:
                        left += 1
                self._abandoned = left
        pending = _Pending(b, multipart, on_part, done=threading.Event() if wait else None)
        for _ in range(255):
            nr = next(self._numbers)
            if self._pending.setdefault(nr, pending) is pending:
                return nr, pending
        raise Cia309Error(ErrorCode.OUT_OF_MEMORY,
                          f"board {self.number}: 255 requests wait for answers")

    # --- layer 2 -------------------------------------------------------------------------------

    def add_filters(self, cob_ids: Iterable[int], timeout: float) -> None:
        """COM_CfgRx_Layer2 for identifiers not filtered yet (a filter stays until a start)."""
        new = sorted(set(cob_ids) - self._filters)
        if not new:
            return
        data = b"".join(bytes([cob_id & 0xFF, cob_id >> 8]) for cob_id in new)
        answer = self.request(COM_CFGRX_LAYER2, data, timeout)[-1]
        if answer.f == F_FAULTY_PARAMETER:
            raise Cia309Error(ErrorCode.PDO_ALREADY_USED,
                              f"identifier(s) {', '.join(f'0x{i:X}' for i in new)} in use by "
                              "the card's CANopen side", f=answer.f)
        if answer.f:
            raise card_error(answer.f, "COM_CfgRx_Layer2")
        self._filters.update(new)

    def add_listener(self, listener: FrameListener, timeout: float) -> None:
        self.add_filters(listener.cob_ids, timeout)
        with self.pdo_lock:
            self._listeners.append(listener)

    def remove_listener(self, listener: FrameListener) -> None:
        with self.pdo_lock:
            if listener in self._listeners:
                self._listeners.remove(listener)

    def add_indication_queue(self, indications: IndicationQueue) -> None:
        with self.pdo_lock:
            self._indication_queues.append(indications)

    def remove_indication_queue(self, indications: IndicationQueue) -> None:
        with self.pdo_lock:
            if indications in self._indication_queues:
                self._indication_queues.remove(indications)

    def send_frames(self, frames: Sequence[CanFrame]) -> None:
        data = b"".join(encode_layer2_frame(frame) for frame in frames)
        if not frames or len(data) > 255:
            raise syntax_error(f"{len(frames)} frames do not fit one COM_Tx_CAN_Layer2")
        self.send(COM_TX_CAN_LAYER2, data)

    def forget_node_sets(self) -> None:
        """The card starts or went off line: its data sets are read again when needed."""
        self._node_sets.clear()

    def restore_after_start(self, timeout: float) -> None:
        """A card start dropped the layer-2 filters and boot-up forwarding: set them again."""
        filters, self._filters = self._filters, set()
        self._node_sets.clear()
        self.add_filters(filters, timeout)
        if self.bootup_forwarding:
            self.command(COM_BOOTUP_FORWARDING, b"\x01", timeout, "COM_Bootup_Forwarding")

    def _indication(self, msg: Message) -> None:
        if msg.b == COM_BOOTUP_INDICATION and msg.data:
            if self.bootup_forwarding:
                self._emit(BootUpEvent(self.network, msg.data[0]))
            return
        if msg.b != COM_RX_CAN_LAYER2:
            return
        with self.pdo_lock:
            queues = list(self._indication_queues)
        for indications in queues:
            indications.put(msg)
        try:
            frames = decode_layer2_frames(msg.data)
        except MessageError as exc:  # the card's own indication: never expected
            log.warning("network %d: a malformed COM_Rx_CAN_Layer2 indication: %s",
                        self.network, exc)
            return
        for frame in frames:
            self._frame(frame)

    def _frame(self, frame: CanFrame) -> None:
        with self.pdo_lock:
            listeners = [item for item in self._listeners if frame.ident in item.cob_ids]
            rpdos = [pdo for pdo in self.rpdos.values() if pdo.cob_id == frame.ident]
            for pdo in rpdos:
                if not frame.rtr and len(frame.data) >= pdo.length:
                    pdo.last = frame.data[: pdo.length]
        for listener in listeners:
            listener.put(frame)
        for pdo in rpdos:
            if frame.rtr or len(frame.data) < pdo.length:
                continue  # a PDO length error: nothing to unmap
            waiter = self.rtr_waiters.get(pdo.number)
            if waiter is not None:
                waiter.put(frame.data)
            self._emit(RpdoEvent(self.network, pdo.number, pdo.unpack(frame.data)))

    # --- card configuration read back ------------------------------------------------------

    def upload_area(self, area: int, timeout: float) -> bytes | None:
        """A data set as the card holds it (COM_Upload); None when it has none (f 20)."""
        def chunk(offset: int) -> bytes | None:
            request = UploadRequest(area, MAX_LEN_DATA_UNIT, offset).encode()
            answer = self.request(COM_UPLOAD, request, timeout)[-1]
            if answer.f == F_LOCAL_RESOURCE:
                return None
            if answer.f:
                raise card_error(answer.f, f"COM_Upload of area {area}")
            return answer.data

        first = chunk(0)
        if first is None or area == AREA_BUS:
            return first
        (total,) = struct.unpack_from("<H", first, 0)
        data = first
        while len(data) < total:
            more = chunk(len(data))
            if not more:
                break
            data += more
        return data[:total]

    def download_area(self, area: int, data: bytes, timeout: float) -> None:
        """COM_Download of a data set, split by COM_Start_Seq when it is long (seed 5.2.3),
        by the host's one on-line download routine; a refusal raises ``Cia309Error``."""
        download_data_set(lambda b, payload: self.command(b, payload, timeout, Com(b).name),
                          area, data, f"area {area}")

    def node_set(self, node: int, timeout: float) -> NodeParameterSet | None:
        """The node's parameter data set in the card (cached until the next start)."""
        if node not in self._node_sets:
            raw = self.upload_area(node, timeout) if node < AREA_BUS else None
            try:
                self._node_sets[node] = NodeParameterSet.decode(raw) if raw else None
            except DbmError:
                self._node_sets[node] = None
        return self._node_sets[node]

    def supervised_by(self, node: int, timeout: float) -> str | None:
        """How the card supervises the node: "heartbeat", "guarding" or None."""
        if node in self.supervision:
            return self.supervision[node]
        params = self.node_set(node, timeout)
        if params is None or not params.usGuardTime:
            return None
        return "heartbeat" if params.bNd_Flag & NdFlag.HRTBT else "guarding"

