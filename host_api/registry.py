"""The boards this process has initialised: the driver's one piece of state.

The C driver keeps a table of the boards it has opened; so does this module, and every
part of host_api that needs an open board asks it: the ``Dev*`` functions
(``host_api.driver``), ``Board.transact``, the load-function services
(``host_api.download``) and the CiA 309 gateway. Its public face is small:

- ``registry``: the table (``boards``, ``counters``, the image directory, the open count
  and the lock that guards them), written by DevOpenDriver, DevInitBoard,
  DevExitBoard and DevCloseDriver only;
- ``lookup(number)`` / ``ready_board(number)``: the ``MappedBoard`` of an initialised
  board, or the driver's return code that says why there is none;
- ``transaction_lock(number)``: the lock that makes a request and its answer one
  transaction across threads and processes.

A child forked after DevInitBoard gets lock files, thread locks and a doorbell of its own
[ours]: inherited descriptors would share their flocks with the parent, so both would be
inside a channel at once and read each other's answers.
"""

from __future__ import annotations

import mmap
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from dpm import flags as fl
from dpm._quicklock import Lock as QuickLock
from dpm.doorbell import POLL_INTERVAL, RING, WANT_ACK, HostBell
from dpm.errors import Drv
from dpm.image import MAX_DEV_BOARDS
from dpm.layout import DEV_FLAGS, HOST_FLAGS
from host_api._devflags import change as _change_flags
from host_api._devflags import change_ring as _change_ring
from host_api._devflags import wait_ring as _wait_ring
from host_api.liveness import firmware_liveness
from host_api.locks import ChannelLock, Transaction

SPIN_SECONDS = 100e-6
"""How long a waiting call watches the flags before it sleeps on the bell."""
SPIN_BACKOFF_MAX = 6
"""[ours] After a watch that the answer outlasted, so many waits (1, 3, 7 ... up to
2**6 - 1 = 63) sleep at once (``MappedBoard.wait_for``)."""
_PLAIN_RING = RING[0]
"""The byte of the ring ``change_dev_flags`` sends (``HostBell.ring_device``'s plain one)."""

POLLS_BEFORE_YIELD = 8
"""[ours] Uncontrolled exchanges in a row that read the same inputs, after which a host
polling the card gives up its CPU once (``MappedBoard.poll_inputs``): every 10-30 µs of a
Python host's spinning (a call takes 1.4-4 µs here), one system call per eight calls."""
POLL_WINDOW_NS = 1_000_000
"""[ours] ... when those calls came within this many ns: a host polling, not a periodic
control loop (a 1 kHz one takes eight milliseconds for eight calls)."""


@dataclass
class Counters:
    """DRIVERINFO's counters of one board number (DevGetInfo GET_DRIVER_INFO)."""

    open: int = 0
    close: int = 0
    read: int = 0
    write: int = 0
    irq: int = 0
    last_function: int = 0
    io: int = 0


@dataclass
class MappedBoard:
    """One initialised board: its map, its bell, its channel locks."""

    number: int
    path: Path
    mm: mmap.mmap
    bell: HostBell
    put_lock: QuickLock
    get_lock: QuickLock
    """The put and get channels exclude this process's threads only: every put and get, of
    a Python host and of libcif's, is made inside the board's transaction lock, which one
    process at a time holds (``host_api.locks.Transaction``). An flock of their own would
    exclude nobody more and cost four system calls per round trip (issue 22)."""
    io_lock: ChannelLock
    transaction: Transaction
    counters: Counters
    """The registry's for this board number (``Registry.counters``), kept past DevExitBoard."""
    polled: bytes = b""
    """The inputs the last uncontrolled exchange read (``poll_inputs``)."""
    polls: int = 0
    """Uncontrolled exchanges since, that read ``polled`` again."""
    polls_since: int = 0
    """When the first of them returned (perf_counter_ns)."""
    spin_misses: int = 0
    """Watches of the flags in a row (the skipped waits between them aside) that the
    answer outlasted (``wait_for``)."""
    spin_skip: int = 0
    """Waits left that sleep on the bell without watching the flags first."""

    def host(self) -> int:
        return self.mm[HOST_FLAGS]

    def dev(self) -> int:
        return self.mm[DEV_FLAGS]

    def ready(self) -> bool:
        return bool(self.host() & fl.READY)

    def timed_out(self, code: int) -> int:
        """A wait's time-out code, or DRV_DEV_NOT_READY when the firmware has died
        meanwhile [ours]: a killed firmware leaves READY set, so only its lock tells."""
        alive = firmware_liveness(self.path.parent, self.number).alive
        return code if alive else Drv.DRV_DEV_NOT_READY

    def poll_inputs(self, inputs: bytes) -> None:
        """[ours] A host that spins on the uncontrolled exchange lets the card run.

        Called after each uncontrolled DevExchangeIO that only read, ``inputs``. Every
        ``POLLS_BEFORE_YIELD``-th such call in a row that reads the same inputs, within
        ``POLL_WINDOW_NS`` of the first, comes from a host polling for a change that only
        the card can make: it gives up its CPU (``sched_yield``) to whatever waits for one.
        A real card has a CPU of its own; this one's threads run on the host's. A host
        spinning on one of two cores left each of the card's wake-ups in a PDO round trip
        (device loop, node, receive thread) that the scheduler put behind it waiting for
        the next scheduler tick, up to 4 ms: the loop's p99 was 10-22 times canopen's,
        whose host blocks on a condition. A host alone on its CPU loses a system call
        (about a microsecond) every eight polls. Never yields: a periodic control loop,
        whose calls are further apart, and a call that also writes outputs (a host that
        exchanges as fast as it can, ``bench.exchange_io``, keeps its CPU as before).
        """
        if inputs != self.polled:
            self.polled, self.polls = inputs, 0
            return
        self.polls += 1
        if self.polls == 1:
            self.polls_since = time.perf_counter_ns()
        elif self.polls >= POLLS_BEFORE_YIELD:
            self.polls = 0
            if time.perf_counter_ns() - self.polls_since < POLL_WINDOW_NS:
                os.sched_yield()

    def change_dev_flags(
        self, set_bits: int = 0, clear_bits: int = 0, toggle: int = 0, ring: bool = True
    ) -> None:
        """Change DevFlags by one atomic read-modify-write, then ring the device.

        [ours] Every host process writes DevFlags, C hosts too: the byte is changed by a
        compare-and-swap (``host_api._devflags``, as libcif's change_dev_flags), so no
        host's toggle is lost, without the flock round (four system calls per mailbox round
        trip) that guarded it before (issue 22; docs/dpm.md section 2). The change and the
        ring are one call (``_devflags.change_ring``, ``HostBell.ring_device``'s plain ring):
        four Python calls fewer on each put of a message."""
        if ring:
            bell = self.bell
            _change_ring(self.mm, DEV_FLAGS, set_bits, clear_bits, toggle, bell.sock.fileno(),
                         bell.device_path, _PLAIN_RING)
        else:
            _change_flags(self.mm, DEV_FLAGS, set_bits, clear_bits, toggle)

    def take_rings(self, timeout: float, wake: int = -1) -> int:
        """The host's wait on its doorbell (``HostBell.wait`` in one call: ppoll, then every
        queued ring in one recvmmsg, where select, recvfrom and select were; issue 22):
        ``_devflags.wait_ring``'s answer, ``wake`` a thread's own wake-up pipe watched
        beside the bell (the CiA 309 gateway's reader). A ring taken counts as the driver's
        interrupt (DevGetInfo), and the last one's byte says whether the device wants a ring
        on HOSTACK (``HostBell.device_wants_ack``)."""
        bell = self.bell
        ring = _wait_ring(bell.sock.fileno(), timeout, wake)
        if ring >= 0:
            self.counters.irq += 1
            if ring:
                bell.device_wants_ack = ring == WANT_ACK
        return ring

    def wait_for(self, condition: Callable[[], bool], timeout_ms: int,
                 before_sleep: Callable[[], None] | None = None) -> bool:
        """Wait on the bell (polling as a fallback) until ``condition`` or the timeout;
        ``before_sleep`` runs once, before the first sleep on the bell."""
        if condition():
            return True
        if timeout_ms <= 0:
            return False
        start = time.monotonic()
        deadline = start + timeout_ms / 1000.0
        # A card answers most requests within tens of microseconds: checking the
        # flags for that long first saves the sleep and wake-up of the bell. Only a
        # single-threaded host spins: in a host with more threads the spinning one
        # would hold the interpreter lock the others need (the CiA 309 gateway's
        # mailbox reader and its callers).
        skipped = False
        if threading.active_count() == 1:
            if self.spin_skip:
                self.spin_skip -= 1
                skipped = True
            elif self._spin(condition):
                return True
        if before_sleep is not None:
            before_sleep()
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return condition()
            self.take_rings(min(remaining, POLL_INTERVAL))
            if condition():
                if skipped and time.monotonic() - start < SPIN_SECONDS:
                    self.spin_misses = self.spin_skip = 0  # a watch would have seen it
                return True

    def _spin(self, condition: Callable[[], bool]) -> bool:
        """Watch the flags for ``SPIN_SECONDS``: True when ``condition`` came true.

        [ours] A watch the answer outlasts cost its whole CPU time for nothing, and on a
        busy machine it takes that time from the card, whose threads wait for a CPU to
        answer: the next 1, 3, 7 ... (``SPIN_BACKOFF_MAX``) waits sleep at once, until a
        watch sees its answer or a wait that slept at once ends within ``SPIN_SECONDS``
        (a watch would have seen it: the machine is quiet again). Beside two busy
        processes on two cores (load average 12-16) a mailbox round trip cost the host
        87-123 µs of CPU and took 107-200 µs at p50 with a watch every time, 43-65 µs and
        55-98 µs with the back-off (three alternating pairs, issue 22; docs/dpm.md
        section 2)."""
        spin_end = time.perf_counter() + SPIN_SECONDS
        while time.perf_counter() < spin_end:
            if condition():
                self.spin_misses = 0
                return True
        misses = self.spin_misses = min(self.spin_misses + 1, SPIN_BACKOFF_MAX)
        self.spin_skip = (1 << misses) - 1
        return False

    def after_fork(self) -> None:
        """In a forked child: its own lock files, thread locks and doorbell."""
        self.io_lock.reopen_after_fork()
        # a parent's thread that held one is not here
        self.put_lock, self.get_lock = QuickLock(), QuickLock()
        self.transaction.reopen_after_fork()
        self.bell.close()
        self.bell = HostBell(self.path)
        self.bell.ring_device()  # introduces the child to the device

    def close(self) -> None:
        self.bell.close()
        self.io_lock.close()
        self.transaction.close()
        self.mm.close()


class Registry:
    """The driver's state in this process; ``lock`` guards every change to it."""

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.open_count = 0
        self.directory: Path | None = None
        self.boards: dict[int, MappedBoard] = {}
        self.counters: dict[int, Counters] = {}
        """DRIVERINFO per board number: kept from DevExitBoard to the next DevInitBoard, as
        the real driver keeps them while it is loaded (here: while this process has it open)."""


registry = Registry()


def _after_fork_in_child() -> None:
    registry.lock = threading.RLock()  # a parent's thread may have held it
    for number, board in list(registry.boards.items()):
        try:
            board.after_fork()
        except OSError:  # the lock files are gone: the board is closed here (-32)
            del registry.boards[number]
            board.close()


os.register_at_fork(after_in_child=_after_fork_in_child)


def lookup(number: int) -> MappedBoard | int:
    """The initialised board, or the return code that says why not (-1 ... -34)."""
    if not 0 <= number < MAX_DEV_BOARDS:
        return Drv.DRV_USR_DEV_NUMBER_INVALID
    if registry.open_count == 0:
        return Drv.DRV_USR_NOT_INITIALIZED
    board = registry.boards.get(number)
    if board is None:
        return Drv.DRV_USR_NOT_INITIALIZED
    return board


def ready_board(number: int) -> MappedBoard | int:
    """``lookup``, and DRV_DEV_NOT_READY (-11) while the card has not set READY."""
    board = registry.boards.get(number)  # on every mailbox call: one look-up, no calls
    if board is None:
        return lookup(number)
    return board if board.mm[HOST_FLAGS] & fl.READY else Drv.DRV_DEV_NOT_READY


def transaction_lock(number: int) -> Transaction | None:
    """The board's transaction lock (request + answer as one), None when not initialised."""
    board = registry.boards.get(number)
    return None if board is None else board.transaction
