"""``shm``: a python-can interface whose bus is shared memory between processes [ours].

Why it exists: python-can's ``virtual`` bus lives inside one process, and this
machine (like many CI runners) has no SocketCAN, so a card and a simulated
network in *another* process could only meet over ``udp_multicast``, which
loses frames under load. This interface is a vcan for any Linux machine:
every bus object ("station") opened on the same channel, in any process, sees
every frame the others send, or learns that it lost some.

The medium is a file (``/dev/shm/cifemu-can-<channel>``, mode 0660): a header,
a table of stations, and one ring of fixed 32-byte frame records per station.
A station writes only its own ring and publishes the record by advancing its
ring's counter; readers copy what is new from every other ring. Neither side
makes a system call on that path, and that is the point: a system call lets
go of CPython's interpreter lock, and in a busy multi-threaded process such
as the firmware, getting it back costs up to a switch interval (measured
here: 1.5 µs for an flock pair alone, 100 µs with one busy thread beside it).
The ring protocol needs the stores of a record to become visible before its
counter's, which x86-64 guarantees (TSO); on other CPUs a reader may find
late a frame it was woken for, never a torn one (see ``_read``).

Order: the frames of one station keep their order; frames of different
stations that a reader picks up together are delivered by time stamp. (On a
real bus, arbitration orders them; this bus does not model arbitration.)

A reader falling more than a ring behind a station has lost frames: it gets
one SocketCAN-style controller error frame (``CAN_ERR_CRTL`` with
``CAN_ERR_CRTL_RX_OVERFLOW``) and ``rx_overflows`` grows by the number lost,
as when a CAN controller's receive FIFO overflows. Writers never wait.

A reader with nothing to read marks itself waiting and sleeps on a datagram
socket in Linux's abstract namespace; a writer rings only the waiting ones.
Mark and publish are each followed by a memory fence, so one of the two
always sees the other (Dekker). A writer does not ring its own station's reader, which
does not take the station's own frames (unless ``receive_own_messages``): that woke the
card's receive thread for nothing after every frame the card sent, a thread switch per
SDO request (issue 22). The sleep is bounded anyway (``MAX_SLEEP_S``),
as a net for a ring that never came (a writer killed between its record and its
ring), but long enough that an idle reader hardly wakes; ``loop_back``
ends a reader's wait from another thread of its process.

Use it as any python-can interface (the package's entry point registers it)::

    bus = can.Bus(interface="shm", channel="bench")

Opening and closing a station take an ``flock`` on the file. The file stays
while a station is open on it; the last one to shut down removes it. A
station killed without shutting down is reclaimed by the next one that opens
the channel once its process is gone. The file's layout, the table and a station's writing
side are ``firmware.shm.station``'s, which the timer process uses without python-can.
"""

from __future__ import annotations

import contextlib
import heapq
import os
import select
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import can

from firmware.frames import CAN_ERR_CRTL, CAN_ERR_CRTL_RX_OVERFLOW
from firmware.shm.station import (
    BITRATE_AT,
    BITRATE_SIZE,
    CAPACITY,
    ERROR,
    EXTENDED,
    MAX_STATIONS,
    RECORD,
    RECORD_SIZE,
    REMOTE,
    RING_BYTES,
    RINGS_AT,
    SEQS_AT,
    SEQS_BYTES,
    WAITING_AT,
    ChannelError,
    Station,
    channel_path,
    copy_records,
)

if TYPE_CHECKING:
    from firmware.shm.tasks import SpareTimer

MAX_SLEEP_S = 1.0
"""The longest a reader sleeps before it looks again, whatever its time-out: a net for a
missed ring, which the protocol does not lose. It was 50 ms: 20 wake-ups a second of a reader
with nothing to read, 0.35-0.45 % of a core of an idle card's receive thread (issue 22)."""

_COUNTERS = struct.Struct(f"<{MAX_STATIONS}Q")
_COUNTER = struct.Struct("<Q")
_STATION_BITS = (1 << 64) - 1
"""One station's counter among the counters read as one integer (``ShmBus._read``)."""


class ShmBus(can.BusABC):
    """One station on a shared-memory CAN channel."""

    def __init__(self, channel: Any = "cifemu", receive_own_messages: bool = False,
                 preserve_timestamps: bool = False, timer_process: bool = False,
                 **kwargs: Any) -> None:
        """``timer_process``: ``send_periodic`` hands its frames to a timer process.

        See ``firmware.shm.cyclic``; the bus keeps one started ahead from here on. Off by
        default, because libraries call ``send_periodic`` freely (canopen for
        every heartbeat producer) and a process each is too dear; the card's
        controller turns it on for its SYNC producer.
        """
        self.channel = "cifemu" if channel is None else str(channel)
        self.channel_info = f"shared-memory channel {self.channel!r}"
        self.receive_own_messages = receive_own_messages
        self.preserve_timestamps = preserve_timestamps
        self.rx_overflows = 0
        """Frames this station lost because it fell a whole ring behind a sender."""
        self._path = channel_path(self.channel)
        self._read_lock = threading.Lock()
        self._fence = threading.Lock()
        """Taking an uncontended lock is an atomic instruction: a full memory fence."""
        self._pending: deque[can.Message] = deque()
        try:
            self._station = Station(self._path, int(kwargs.get("bitrate") or 0))
        except ChannelError as exc:
            raise can.CanInitializationError(str(exc)) from exc
        self._closed = False
        self._map, self._index = self._station.map, self._station.index
        self._bell, self._ringer = self._station.bell, self._station.ringer
        self._written_seen = self._map[SEQS_AT:SEQS_AT + SEQS_BYTES]
        """The stations' counters as ``_read`` last copied them, before it took what they
        announced: while they read the same, there is nothing new; each station's is the
        records this station has taken of it."""
        self._own_bits = _STATION_BITS << (64 * self._index)
        """This station's counter among ``_written_seen``'s bits (``_read``)."""
        self._timers: SpareTimer | None = None
        if timer_process:  # only once the station is open: a failed open leaves no spare
            from firmware.shm.tasks import SpareTimer  # only a bus that asks pays for it

            self._timers = SpareTimer()
        super().__init__(channel=channel, **kwargs)

    # --- the channel ------------------------------------------------------------------------

    @property
    def bitrate(self) -> int | None:
        """The channel's bit rate, or None [ours].

        The first station opened with a ``bitrate`` (``cifemu sim`` always gives its
        network's) fixes it for as long as the channel exists; later stations join at
        it whatever they ask, as a SocketCAN link's rate is the kernel's and not a
        socket's. The bus does not model bit timing: the rate is there for a card to
        compare its Baud_rate with (``firmware.can.bus``).
        """
        rate = int.from_bytes(self._map[BITRATE_AT:BITRATE_AT + BITRATE_SIZE], "little")
        return rate or None

    # --- sending -----------------------------------------------------------------------------

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Append ``msg`` to this station's ring; never waits for readers."""
        del timeout
        if msg.is_fd or len(msg.data) > 8:
            raise can.CanOperationError("the shared-memory bus carries classic CAN frames only")
        flags = ((EXTENDED if msg.is_extended_id else 0) | (REMOTE if msg.is_remote_frame else 0)
                 | (ERROR if msg.is_error_frame else 0))
        stamp = msg.timestamp if self.preserve_timestamps else time.time()
        record = RECORD.pack(stamp, msg.arbitration_id, flags, msg.dlc, 0, bytes(msg.data))
        if not self._station.write(record, self.receive_own_messages):
            raise can.CanOperationError("the bus is shut down")

    def _send_periodic_internal(
        self, msgs: Sequence[can.Message] | can.Message, period: float,
        duration: float | None = None, autostart: bool = True,
        modifier_callback: Callable[[can.Message], None] | None = None,
    ) -> can.broadcastmanager.CyclicSendTaskABC:
        """Cyclic frames from a timer process (``firmware.shm.cyclic``), as SocketCAN's BCM would.

        Without ``timer_process``, or with a ``modifier_callback`` (it must run
        in this process), python-can's thread sends them.
        """
        if self._timers is None or modifier_callback is not None:
            return super()._send_periodic_internal(msgs, period, duration, autostart,
                                                   modifier_callback)
        from firmware.shm.tasks import ShmCyclicSendTask

        return ShmCyclicSendTask(self._timers, self._path, msgs, period, duration, autostart)

    # --- receiving ---------------------------------------------------------------------------

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._pending:
            return self._pending.popleft(), False
        if timeout == 0:  # a look, no wait: unmarked, so that no sender rings it for nothing
            return (self._pending.popleft() if self._read() else None), False
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._closed:
            if self._read():
                return self._pending.popleft(), False
            self._mark_waiting(True)
            if self._read():  # published between the first look and the mark
                self._mark_waiting(False)
                return self._pending.popleft(), False
            remaining = MAX_SLEEP_S if deadline is None else min(
                MAX_SLEEP_S, deadline - time.monotonic())
            if remaining <= 0:
                self._mark_waiting(False)
                return None, False
            try:
                rung = select.select((self._bell,), (), (), remaining)[0]
            except (OSError, ValueError):  # shut down by another thread meanwhile
                return None, False
            if rung:  # one ring taken: a second one (rare) only ends the next wait at once
                try:  # noqa: SIM105 (contextlib.suppress: three calls more per woken frame)
                    self._bell.recv(16)
                except OSError:  # shut down by another thread meanwhile
                    pass
        return None, False

    def loop_back(self, msg: can.Message) -> None:
        """Hand ``msg`` to this station's own next ``recv``, at once to one that waits in
        another thread [ours]. The card's controller ends its receive thread's wait so
        (``firmware.can.bus``), which can then wait long without a time-out's wake-ups."""
        self._pending.append(msg)
        with contextlib.suppress(OSError):  # shut down, or the bell's queue is full: awake
            self._ringer.sendto(b"\x01", self._bell.getsockname())

    def _mark_waiting(self, waiting: bool) -> None:
        with self._read_lock:
            if not self._closed:
                self._map[WAITING_AT + self._index] = waiting
                with self._fence:
                    pass

    def _read(self) -> bool:
        """Take every new record of the other stations into ``_pending``; True when any.

        A ring's records are copied up to its counter as ``written`` holds it, and its
        counter is read again after copying them: records a writer may have overwritten
        meanwhile (the reader was a whole ring behind) are dropped and counted as lost,
        never delivered torn.

        Plain Python on this path, no numpy: the receive thread runs it once per wake-up,
        with cold caches, where numpy's compare and ``flatnonzero`` of the 64 counters took
        55-60 us and ``heapq.merge`` of one station's batch 15 us, most of the 190-230 us of
        CPU a frame's wake-up cost the thread, against 20-40 us for a thread woken by a
        datagram (issue 22: the idle card's cost per node is its heartbeats' wake-ups).
        """
        with self._read_lock:
            if self._closed:
                return False
            # Nothing written since the last look: one 512-byte compare, twice per frame a
            # reader takes (before and after it marks itself waiting; issue 22). Each
            # counter copied here is no lower than any read before, and every record it
            # counts was published before it (x86-64 keeps loads in order, see the top).
            written = self._map[SEQS_AT:SEQS_AT + SEQS_BYTES]
            if written == self._written_seen:
                return bool(self._pending)
            seen, self._written_seen = self._written_seen, written
            mapped = self._map
            batches: list[bytes] = []
            lost = 0
            # The stations whose counter moved, lowest first, from the bits in which the two
            # copies differ: a Python loop over the 64 counters took 10-16 us per wake-up, a
            # boot of 127 nodes wakes the card's receive thread about 1,000 times (issue 22).
            moved = int.from_bytes(written, "little") ^ int.from_bytes(seen, "little")
            if not self.receive_own_messages:
                moved &= ~self._own_bits
            while moved:
                station = ((moved & -moved).bit_length() - 1) >> 6
                moved &= ~(_STATION_BITS << (64 * station))
                cursor = _COUNTER.unpack_from(seen, 8 * station)[0]
                seq = _COUNTER.unpack_from(written, 8 * station)[0]
                first = max(cursor, seq - CAPACITY)
                raw = copy_records(mapped, RINGS_AT + station * RING_BYTES, first, seq)
                now_at = _COUNTER.unpack_from(mapped, SEQS_AT + 8 * station)[0]
                overwritten = now_at - CAPACITY - first  # meanwhile, by the writer
                if overwritten > 0:
                    raw = raw[overwritten * RECORD_SIZE:]
                    first += overwritten
                lost += first - cursor
                batches.append(raw)
        if lost:
            self.rx_overflows += lost
            self._pending.append(can.Message(
                timestamp=time.time(), arbitration_id=CAN_ERR_CRTL, is_error_frame=True,
                is_extended_id=False, dlc=8, channel=self.channel,
                data=bytes([0, CAN_ERR_CRTL_RX_OVERFLOW, 0, 0, 0, 0, 0, 0])))
        # Each station's records stay in their order whatever their time stamps say.
        records = (RECORD.iter_unpack(batches[0]) if len(batches) == 1 else
                   heapq.merge(*(RECORD.iter_unpack(raw) for raw in batches), key=_stamp))
        channel, message, pending = self.channel, can.Message, self._pending
        for stamp, ident, flags, dlc, _, data in records:
            remote = bool(flags & REMOTE)
            # positional: binding ten keywords cost 2 us of the 6 a frame's Message took
            pending.append(message(stamp, ident, bool(flags & EXTENDED), remote,
                                   bool(flags & ERROR), channel, dlc,
                                   None if remote else data[:dlc]))
        return bool(self._pending)

    # --- closing -----------------------------------------------------------------------------

    def shutdown(self) -> None:
        if self._closed:
            return
        with self._read_lock:
            self._closed = True
            self._station.leave()
        with contextlib.suppress(OSError):  # wake a receive thread of this station
            self._ringer.sendto(b"\x01", self._bell.getsockname())
        self._station.release()
        super().shutdown()  # stops the cyclic tasks
        if self._timers is not None:
            self._timers.close()


def _stamp(record: tuple[Any, ...]) -> float:
    return float(record[0])


def frames_written(channel: str) -> int:
    """Frames written on ``channel`` since its file was created, by every station [ours].

    Read from the counters without opening a station: a benchmark that counts a card's
    traffic this way costs the card nothing, whereas a station of its own would sleep on
    its bell and every writer would ring it, a system call per frame in the very
    processes being measured. A station's entry keeps its counter when reused, so the
    figure only grows.
    """
    fd = os.open(channel_path(channel), os.O_RDONLY)
    try:
        raw = os.pread(fd, 8 * MAX_STATIONS, SEQS_AT)
    finally:
        os.close(fd)
    return sum(_COUNTERS.unpack(raw))
