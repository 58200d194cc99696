"""The emulated card: one image, one device loop, the tasks behind it.

The device loop is the only writer of HostFlags, as the card's firmware is the
only writer of its flag byte: it wakes on a host's ring, on a wake-up from
another thread of the card, when a timer is due (the host watchdog) or at the
next fallback poll, looks at DevFlags, and serves the mailboxes, the
process-data and state handshakes, special control, NOTREADY and the watchdog.
Tasks that work in threads of their own (the CAN task) hand answers over with
``post``; their Task2State writes wake the loop, which shows them (STATECOM).

The fallback poll (``AdaptivePoll``) serves a host that writes the flags without
ringing: every millisecond while such a host is busy, backing off to 50 ms when it pauses
and to 250 ms a second after its last change. A host that rings starts no poll: its ring
is what wakes the loop, once per request (issue 22). After each turn the
loop tells the CAN master's thread, which sleeps too, when the host changed what it
follows: the outputs, the connection bits, its readiness (``Master.notice_host``);
a change no ring announced marks a ring-less host, as a flag change does. The CAN
master's thread wakes the loop when it halts or clears the network
(``can_state_changed``), which the loop shows as bCAN_State, RUN and COM.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from dpm import flags as fl
from dpm._quicklock import Lock as QuickLock
from dpm.doorbell import POLL_INTERVAL, AdaptivePoll, DeviceBell
from dpm.errors import F_UNKNOWN_TASK
from dpm.image import (
    CardDirectory,
    ExclusiveLock,
    create_image,
    dpm_dir,
    image_path,
    lock_path,
)
from dpm.layout import (
    DEV_FLAGS,
    DEV_MBX,
    DEV_WATCHDOG,
    DRIVER_TYPE,
    HOST_FLAGS,
    IO_AREA_SIZE,
    PC_MBX,
    SND_PD,
    TASK2_STATE,
    TASK_STATE_SIZE,
    pack_field,
)
from dpm.message import MSG_MAX_SIZE, Ext, Message
from dpm.task2 import CanState
from firmware import info, native_mailbox
from firmware.can.bus import BusConfig
from firmware.can_task import CanTask
from firmware.card import Answer
from firmware.faults import CardFaults
from firmware.flash import FlashStore, StoredDatabase, default_flash_dir
from firmware.plc import HOST_CONTROLLED, PlcTask
from firmware.process_image import UNCONTROLLED
from firmware.rcs import RcsTask, Start
from firmware.record_socket import RecordSocket
from firmware.task import Task

if TYPE_CHECKING:
    from firmware.recorder import Recorder

log = logging.getLogger(__name__)

OUTBOX_LIMIT = 64
"""Answers waiting for the host; past this the device stops taking commands,
so a host that never reads its answers sees a full mailbox (-16/-17) instead
of the card silently dropping answers."""

WATCHDOG_WAKE_LATE = 0.0002
"""Seconds the loop wakes after a watchdog deadline: the expiry is ``now > deadline``, and a
wake-up exactly on it would find the watchdog still alive and sleep once more."""

_NAK = int(Ext.NAK)
"""msg.e's no-answer bit as a plain int, for the test on every message."""

STATE_MODE_EVENT = 4
"""[ours] low nibble of bDriverType: the state field is event driven."""

HOP_TRACE_ENV = "CIFEMU_HOP_TRACE"
"""[ours] A file name: the device loop stamps (CLOCK_MONOTONIC, ns) each wake-up by a ring,
each message it takes and each answer it hands over, and writes the stamps there at power-off,
for ``python -m bench hops``. Unset (always, but in that benchmark), nothing is wrapped: the
loop runs the same code as without the hook."""
HOP_TRACE_LIMIT = 1_000_000
"""Stamps kept at most: a forgotten trace does not grow without bound."""


class _HopTrace:
    """The stamps of ``HOP_TRACE_ENV``: installed by wrapping three of the device's methods."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.events: list[tuple[str, int]] = []

    def _stamp(self, name: str) -> None:
        if len(self.events) < HOP_TRACE_LIMIT:
            self.events.append((name, time.monotonic_ns()))

    def install(self, device: Device) -> None:
        wait, receive, deliver = device.bell.wait, device._receive, device._deliver

        def woke(timeout: float) -> bool:
            rung = wait(timeout)
            if rung:
                self._stamp("woke")
            return rung

        def took() -> None:
            self._stamp("took")
            receive()

        def delivered() -> None:
            deliver()
            self._stamp("delivered")

        setattr(device.bell, "wait", woke)  # noqa: B010 (a method replaced on one instance)
        setattr(device, "_receive", took)  # noqa: B010
        setattr(device, "_deliver", delivered)  # noqa: B010

    def write(self) -> None:
        with open(self.path, "w", encoding="ascii") as out:
            out.writelines(f"{name} {ns}\n" for name, ns in self.events)


class Device:
    """Board N of one emulated card, served from the calling thread by ``run``."""

    def __init__(
        self, board: int = 0, directory: str | Path | None = None, *, reset_delay: float = 0.0,
        bus: BusConfig | None = None, flash_dir: str | Path | None = None,
    ) -> None:
        self.board = board
        self.directory = dpm_dir(directory)
        self.files = CardDirectory(self.directory, create=True)
        """The checked image directory: every file the firmware writes is opened in it."""
        self.path = image_path(self.directory, board)
        # Mapped before the lock (harmless beside a running card: same file, same size), so
        # that a killed predecessor's READY goes the moment this firmware holds the lock,
        # which is when hosts start to take it for a running one.
        try:
            self.mm = create_image(self.files, self.path.name)
        except BaseException:
            self.files.close()
            raise
        try:
            self._instance_lock = ExclusiveLock(self.files, lock_path(self.directory, board).name,
                                                on_acquired=self._clear_host_flags)
        except BaseException:
            self.mm.close()
            self.files.close()
            raise
        self.bell = DeviceBell(self.files, self.path)
        self.faults = CardFaults(self)
        """[ours] Card-side faults on demand (firmware/faults.py, docs/faults.md)."""
        self.outbox: deque[Answer] = deque()
        self._calls: deque[Callable[[], None]] = deque()
        self._turn = QuickLock()
        """Held by the device loop for each turn; ``post`` takes it to answer at once. Tried
        by the turn in C on every ring and by the receive thread for each SDO answer it hands
        over: a lock that reads no clock when free (``dpm._quicklock``, issue 22)."""
        self._receiving = False
        """The loop's thread hands the host's message to its task (``_receive``), after
        which the turn delivers the outbox (set by that thread, for ``hand_over``)."""
        self._stopping = False
        self._stop_r, self._stop_w = os.pipe2(os.O_CLOEXEC | os.O_NONBLOCK)
        """``stop`` writes a byte here for ``sleep``. Not a ``threading.Event``: ``stop``
        runs in signal handlers, and one that interrupted the loop inside that Event's own
        wait, holding its lock, deadlocked the card (a firmware that ignored SIGTERM).
        Closed with the object, not at power-off: a late signal must not write to a
        descriptor number that something else opened since."""
        weakref.finalize(self, _close_all, self._stop_r, self._stop_w)
        self._ring = False
        self._loop_thread: int | None = None
        self._wake_pending = False
        """A wake-up from another thread is on its way (one ring per turn is enough)."""
        self._state_sent = b""
        self._shown_can_state = -1
        self.state_lock = threading.RLock()
        """Task2State is written by the device loop and the CAN task's threads."""
        self._errors: dict[int, int] = {}
        self.flash = FlashStore(Path(flash_dir) if flash_dir else default_flash_dir(board))
        self.database: StoredDatabase | None = None
        """What the last start found in flash (``RcsTask.start``)."""
        self.rcs = RcsTask(self, reset_delay)
        self.plc = PlcTask(self)
        self.can = CanTask(self, bus)
        self.tasks: dict[int, Task] = {t.number: t for t in (self.rcs, self.plc, self.can)}
        self.recorder: Recorder | None = None
        """The recording that runs (firmware/recorder.py): ``--record``'s, set before
        ``run``, or one a ``cifemu record`` attached (``record``)."""
        self._record_socket: RecordSocket | None = None
        trace = os.environ.get(HOP_TRACE_ENV)
        self._hop_trace = _HopTrace(trace) if trace else None
        self.native = True
        """[ours] Plain COM_Shared_Memory reads served by the loop's turn in C
        (``firmware.native_mailbox``); False: every turn in Python (the tests compare)."""
        self.native_turns = 0
        """Turns the C turn served (the tests count them)."""
        if self._hop_trace is not None:
            self._hop_trace.install(self)

    # --- life cycle -----------------------------------------------------------------

    def run(self, started: Callable[[], None] | None = None) -> None:
        """Power on (a cold start), then serve the image until ``stop``.

        ``started`` is called once the card serves (READY), before the first turn: what must
        only begin once the controller is on the bus (``--simulate``'s nodes, whose power-on
        frames the controller must hear), and no sooner.
        """
        self._loop_thread = threading.get_ident()
        try:
            self.faults.start()
            self.can.open()
            self._record_frames()
            self._record_socket = RecordSocket(self)  # before READY: a host may attach then
            self.rcs.start(Start.COLD)
            self._flush()
            if started is not None:
                started()
            poll = AdaptivePoll()
            self.can.master.notice_host()  # what the start set up is no host's change
            host_seen = self._host_bytes()
            card_seen = self.mm[HOST_FLAGS]
            timeout = POLL_INTERVAL
            now = time.monotonic()
            while not self._stopping:
                served = self._native_turns(poll, now) if self.native else None
                if served is None:
                    self.bell.wait(timeout)
                elif served:
                    host_seen, card_seen = served
                with self._turn:
                    self._wake_pending = False  # before service reads what woke it
                    host_rang, self.bell.host_rang = self.bell.host_rang, False
                    now = time.monotonic()
                    self.service(now)
                    recorder = self.recorder
                    if recorder is not None:
                        recorder.settle()  # after the ring: off the way of the host's answer
                    waiting = self._answers_waiting()
                # The CAN master sleeps until told: of new outputs, connection bits, NOTREADY.
                host_wrote = self.can.master.notice_host()
                host_now, card_now = self._host_bytes(), self.mm[HOST_FLAGS]
                interval = poll.next_interval(
                    now, host_rang=host_rang, host_wrote=host_wrote or host_now != host_seen,
                    card_wrote=card_now != card_seen, waiting=waiting)
                host_seen, card_seen = host_now, card_now
                timeout = self._until_due(now, interval)
        finally:
            self._power_off()

    def _native_turns(
            self, poll: AdaptivePoll, now: float,
    ) -> tuple[tuple[int, int], int] | tuple[()] | None:
        """Serve the turns of plain COM_Shared_Memory reads in C until one needs this loop
        (``firmware.native_mailbox``) [ours]: only while such a turn would change nothing
        here but the mailbox (no fault, queued call, answer or indication, no PD exchange
        due, the poll settled, no hop trace). A recording card's turns too: C appends the
        events the recorder's hooks would have to its queue (``Recorder.native_record``;
        until 2026-12-03 a recording card took this Python turn for every message, and
        recording cost a mailbox round trip +64..104 %). In the host-controlled modes also
        the exchanges a host rings for while C waits, as long as they bring no new output
        (the CAN master's ``notice_host`` follows those, after this loop's Python turn) and
        flip no input bit (until 2026-12-04 each exchange took this Python turn, and on a
        recording card its recorder's three hooks: docs/benchmarks.md, note 8). None: not
        now, wait in Python; () when C served no turn; else what the last turn C served left
        for the fallback poll's comparison (``_host_bytes`` and HostFlags). The rings C took
        and left are this loop's, as if ``bell.wait`` had taken them; it returns without
        waiting."""
        mm = self.mm
        if (self._calls or self.outbox or self._ring or self._hop_trace is not None
                or not self.faults.idle or self.bell.mailbox_wanted or self.bell.host_rang
                or self.can.indication_waiting() or not poll.settled(now)
                or self.plc.handshake_due(mm[HOST_FLAGS], mm[DEV_FLAGS])):
            return None
        hosts = self.bell.native_hosts()  # a list: made only for a turn C may serve
        if hosts is None:
            return None
        recorder = self.recorder
        record = recorder.native_record() if recorder is not None else None
        if recorder is not None and record is None:
            return None
        due = self.rcs.watchdog_due()
        master = self.can.master
        seen = master.host_seen()
        if seen is None:
            return None
        image = self.plc.image
        outputs, conn = seen
        if image.mode != UNCONTROLLED:  # the master follows the outputs of the last exchange
            outputs = mm[SND_PD : SND_PD + IO_AREA_SIZE]
        rings, dead, turns, dev, watchdog, host, recorded = native_mailbox.serve(
            mm, self.bell.fileno(), hosts, poll.interval, -1.0 if due is None else due, self,
            self._calls, self.outbox, master.layer2.indications, self._turn, image.lock,
            image.inputs, outputs, conn, record,
            self.can.host_sdo.native_request if self.can.fatal is None else None,
            (image, image.outputs) if image.mode in HOST_CONTROLLED else None)
        if recorder is not None:
            recorder.native_recorded(recorded)
        self.native_turns += turns
        self.bell.take_native(rings, dead)
        return ((dev & ~fl.HOSTACK, watchdog), host) if turns else ()

    def _host_bytes(self) -> tuple[int, int]:
        """What a host that never rings changes: its flags and its watchdog trigger. Not
        HOSTACK: the drivers take an answer without ringing unless the card asked for one
        (``waiting`` in ``AdaptivePoll`` covers that)."""
        mm = self.mm
        return mm[DEV_FLAGS] & ~fl.HOSTACK, mm[DEV_WATCHDOG]

    def _answers_waiting(self) -> bool:
        """Answers or indications wait behind one the host has not acknowledged yet: a host
        acknowledges without ringing unless the card's last ring asked it to."""
        mm = self.mm
        return (bool((mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.HOST_MBX)
                and (bool(self.outbox) or self.can.indication_waiting()))

    def _until_due(self, now: float, interval: float) -> float:
        """Seconds to sleep: the poll ``interval``, or less when the host watchdog is due."""
        due = self.rcs.watchdog_due()
        if due is None:
            return interval
        return max(0.0, min(interval, due + WATCHDOG_WAKE_LATE - now))

    def _wake(self) -> None:
        """Wake the loop after another thread changed what it shows (Task2State).

        The loop's own writes need no ring: it looks at the state field at the end of the
        turn it is in. One ring per turn: further changes before that turn are seen by it.
        """
        if threading.get_ident() != self._loop_thread and not self._wake_pending:
            self._wake_pending = True
            self.bell.ring_self()

    def can_state_changed(self) -> None:
        """The CAN master's thread changed its state (halted, cleared): the loop derives
        bCAN_State, RUN and COM from it, and shows them now, not at its next fallback poll."""
        self._wake()

    def stop(self) -> None:
        """Ask the loop to end; safe from signal handlers and other threads: a flag, a
        byte into a pipe and a ring, none of which takes a lock."""
        self._stopping = True
        with contextlib.suppress(BlockingIOError):  # full: told to stop often enough
            os.write(self._stop_w, b"s")
        self.bell.ring_self()

    def sleep(self, seconds: float) -> bool:
        """Wait inside the loop (an emulated slow reset); True when told to stop."""
        deadline = time.monotonic() + seconds
        while not self._stopping:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            select.select([self._stop_r], [], [], remaining)
        return True

    @contextmanager
    def between_turns(self) -> Iterator[None]:
        """Hold the device loop between two turns while another thread changes what the card
        serves (a fault begins or ends, firmware/faults.py); the loop looks again at once."""
        with self._turn:
            yield
            self._flush()
        self.bell.ring_self()

    def _power_off(self) -> None:
        self.faults.close()
        self.can.close()
        self.write_host_flags(0)
        self._flush()
        if self._record_socket is not None:
            self._record_socket.close()  # an attached recording ends, complete
        recorder = self.record(None)
        if recorder is not None:
            recorder.close()
        self.bell.close()
        self.mm.flush()
        self.mm.close()
        self._instance_lock.release()
        self.files.close()
        self.flash.close()
        if self._hop_trace is not None:
            self._hop_trace.write()

    def record(self, recorder: Recorder | None) -> Recorder | None:
        """Start (``recorder``, started) or end (None) a recording: swapped between two
        turns of the loop, so that no turn sees half of it. Returns the one that ran, for
        its owner to close."""
        with self._turn:
            previous, self.recorder = self.recorder, recorder
            self._record_frames()
        return previous

    def _record_frames(self) -> None:
        bus = self.can.master.bus
        if bus is not None:
            bus.record = self.recorder.frame if self.recorder is not None else None

    # --- cross-thread entry points ---------------------------------------------------

    def post(self, msg: Answer) -> None:
        """Give the host an answer or indication (any thread); a slow card (a fault) holds
        it back first."""
        if not self.faults.hold(msg):
            self.hand_over(msg)

    def hand_over(self, msg: Answer) -> None:
        """Put ``msg`` into the host's mailbox now or at the loop's next turn (any thread).

        When the loop is between turns, nothing is queued before it and the
        host's mailbox is free, the calling thread hands ``msg`` over itself:
        waking the loop for it costs a thread switch, a third of an expedited
        SDO transfer here. Otherwise the loop's next turn delivers it. The loop's
        own thread, while its task handles the host's message (a host SDO answered
        where its request went out, ``firmware.inline.answered_here``), leaves it to
        the turn under way, which delivers the outbox right after, rather than ringing
        itself for one more turn [ours].
        """
        if (threading.get_ident() == self._loop_thread and self._receiving
                and not self._calls):
            self.outbox.append(msg)
            return
        if self._turn.acquire(blocking=False):
            try:
                mm = self.mm
                if (not self._stopping and not self._calls and not self.outbox
                        and not (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.HOST_MBX):
                    self.outbox.append(msg)
                    self._deliver()
                    self._flush()
                    return
            finally:
                self._turn.release()
        self._calls.append(lambda: self.outbox.append(msg))
        self.bell.ring_self()

    # --- flags -------------------------------------------------------------------------

    def _clear_host_flags(self) -> None:
        self.mm[HOST_FLAGS] = 0  # a killed predecessor's READY is not this firmware's

    def write_host_flags(self, value: int) -> None:
        recorder = self.recorder  # once: ``record`` may swap it from another thread
        if recorder is not None:
            recorder.host_flags(self.mm[HOST_FLAGS], value)
        self.mm[HOST_FLAGS] = value
        self._ring = True

    def _ring_for_mailbox(self) -> None:
        """Ring the hosts once the device mailbox is free, if one asked (``DeviceBell``'s
        ``mailbox_wanted``): it may have asked after the card took the message."""
        mm = self.mm
        if self.bell.mailbox_wanted and not (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.DEV_MBX:
            self.bell.mailbox_wanted = False
            self._ring = True

    def toggle_host_flags(self, bits: int) -> None:
        self.write_host_flags(self.mm[HOST_FLAGS] ^ bits)

    def _set_level(self, bit: int, on: bool) -> None:
        host = self.mm[HOST_FLAGS]
        if bool(host & bit) != on:
            self.write_host_flags(host ^ bit)

    def _flush(self) -> None:
        if self._ring:
            self._ring = False
            self.bell.ring_hosts(want_ack=bool(self.outbox) or self.can.indication_waiting())

    # --- Task2State ----------------------------------------------------------------------

    def clear_state(self) -> None:
        with self.state_lock:
            self.mm[TASK2_STATE : TASK2_STATE + TASK_STATE_SIZE] = bytes(TASK_STATE_SIZE)
            self._errors.clear()
        self._state_sent = bytes(TASK_STATE_SIZE)
        self._shown_can_state = CanState.OFFLINE

    def _state(self, name: str) -> int:
        """A number of Task2State (``dpm.layout.pack_field``: no numpy at start-up)."""
        offset, packing = pack_field(f"Task2State.{name}")
        value: int = packing.unpack_from(self.mm, offset)[0]
        return value

    def _set_state(self, name: str, value: int) -> None:
        offset, packing = pack_field(f"Task2State.{name}")
        packing.pack_into(self.mm, offset, value)

    def set_global_bit(self, bit: int, on: bool) -> None:
        with self.state_lock:
            value = self._state("bGlobalBits")
            new = value | bit if on else value & ~bit
            if new != value:
                self._set_state("bGlobalBits", new)
                self._wake()

    def set_node_bit(self, field: str, address: int, on: bool) -> None:
        """One node's bit in Nd_cfg, Nd_state or Nd_diag (bit n = node n)."""
        offset = TASK2_STATE + {"abNd_cfg": 16, "abNd_state": 32, "abNd_diag": 48}[field]
        offset += address >> 3
        bit = 1 << (address & 7)
        with self.state_lock:
            value = self.mm[offset]
            new = value | bit if on else value & ~bit
            if new != value:
                self.mm[offset] = new
                self._wake()

    def report_error(self, node: int, event: int, bits: int = 0) -> None:
        """Report an error; Err_Node_adr shows the lowest faulty address (seed 4.3)."""
        with self.state_lock:
            self._errors[node] = event
            self._show_error()
            self._wake()
            if bits:
                self.set_global_bit(bits, True)

    def clear_error(self, node: int) -> None:
        with self.state_lock:
            if self._errors.pop(node, None) is not None:
                self._show_error()
                self._wake()

    def _show_error(self) -> None:
        if self._errors:
            node = min(self._errors)
            self._set_state("bErr_rem_adr", node)
            self._set_state("bErr_event", self._errors[node])
        else:
            self._set_state("bErr_rem_adr", 0)
            self._set_state("bErr_event", 0)

    def count(self, counter: str, by: int = 1, bit: int = 0) -> None:
        """Increment a Task2State counter (usBus_Error_Cnt ...), saturating at 65535, and
        raise the global ``bit`` that goes with it in the same step: a COM_Reset_Err_Event
        between the two left TOUT set beside a cleared usMsg_Time_Out."""
        with self.state_lock:
            self._set_state(counter, min(0xFFFF, self._state(counter) + by))
            if bit:
                self.set_global_bit(bit, True)
        self._wake()

    def reset_counters(self, bits: int) -> None:
        """The four error counters to 0 and the global ``bits`` down, in one step."""
        with self.state_lock:
            for counter in ("usBus_Error_Cnt", "usBus_Off_Cnt", "usMsg_Time_Out",
                            "usRx_Overflow"):
                self._set_state(counter, 0)
            self.set_global_bit(bits, False)
        self._wake()

    def descript_records(self) -> dict[int, bytes] | None:
        """DESCRIPT records of the stored database by station address; None: no table."""
        return self.database.descript_records() if self.database is not None else None

    def set_exchange_mode(self, mode: int) -> None:
        self.mm[DRIVER_TYPE] = (mode << 4) | STATE_MODE_EVENT

    def update_driving(self) -> None:
        """Outputs reach the bus only while the host is ready and its watchdog alive."""
        self.plc.image.driving = not (self.rcs.host_not_ready or self.rcs.watchdog_expired)
        if not self.plc.image.driving:
            # Seed 5.3.2.1: stopping removes the layer-2 filters, at once, so that a
            # stop and restart quicker than the CAN master looks still removes them.
            self.can.master.layer2.stop()

    def fill_info(self) -> None:
        """The identification areas, at every start (``RcsTask.start``)."""
        info.fill(self.mm, self.board)
        self.faults.started()

    # --- the loop's work ---------------------------------------------------------------

    def service(self, now: float) -> None:
        """One turn of the device loop."""
        while self._calls:
            self._calls.popleft()()
        if self.faults.before_turn():  # [ours] a card that hangs, or its start afterwards
            self._flush()
            return
        mm = self.mm
        dev = mm[DEV_FLAGS]
        recorder = self.recorder
        if recorder is not None:
            recorder.dev_flags(dev, now)
        if dev & (fl.RESET | fl.INIT):
            self.rcs.start(Start.from_flags(dev))
            self._flush()
            return
        self.rcs.service(dev, now)
        if ((mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.DEV_MBX and len(self.outbox) < OUTBOX_LIMIT
                and not self.faults.stalled):
            self._receiving = True
            try:
                self._receive()
            finally:
                self._receiving = False
        self._levels()  # after the message: RUN as it left it (delete database), before its answer
        if not (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.HOST_MBX:
            if not self.outbox:
                indication = self.can.next_indication()
                if indication is not None:
                    self.outbox.append(indication)
            if self.outbox:
                self._deliver()
        self.plc.service(mm[HOST_FLAGS], mm[DEV_FLAGS])
        self._state_field()
        spcack = bool(mm[DEV_FLAGS] & fl.SPCCOM)
        if bool(mm[HOST_FLAGS] & fl.SPCACK) != spcack:  # seldom: a look, not a call, per turn
            self._set_level(fl.SPCACK, spcack)
        self._ring_for_mailbox()
        self._flush()

    def _current_can_state(self) -> CanState:
        configured = self.can.configured and self.plc.image.mode != 0
        state = self.can.can_state() if configured else CanState.OFFLINE
        if state == CanState.OPERATE and not self.plc.image.driving:
            state = CanState.STOP  # the CAN master follows once this turn wakes it
        return state

    def level_flags(self) -> int:
        """RUN while configured (and no database deleted since), COM while the bus
        communication runs; shows CAN_state too."""
        state = self._current_can_state()
        if state != self._shown_can_state:
            self._shown_can_state = state
            self._set_state("bCAN_State", state)
        run = state != CanState.OFFLINE and not self.can.run_withdrawn
        return (fl.RUN if run else 0) | (
            fl.COM if state == CanState.OPERATE else 0)

    def _levels(self) -> None:
        levels = self.level_flags()
        if (self.mm[HOST_FLAGS] ^ levels) & (fl.RUN | fl.COM):  # seldom: a look per turn
            self._set_level(fl.RUN, bool(levels & fl.RUN))
            self._set_level(fl.COM, bool(levels & fl.COM))

    def _receive(self) -> None:
        # One copy of the whole message slot, decoded from the copy: a host that
        # rewrites msg.ln while the card reads cannot make the length and the data
        # disagree (every ln of 0..255 fits the slot). The tasks answer a message
        # that is malformed for its command with their own msg.f.
        mm = self.mm
        raw = mm[DEV_MBX : DEV_MBX + MSG_MAX_SIZE]
        # No ring for DEVACK alone: a host waiting for the free mailbox asks for one
        # (``_ring_for_mailbox``); its answer, now or later, rings the one that waits for it.
        # The toggle is recorded with the message (one event instead of two:
        # docs/recording.md, what it costs).
        before = mm[HOST_FLAGS]
        mm[HOST_FLAGS] = before ^ fl.DEVACK
        recorder = self.recorder
        if recorder is not None:
            recorder.put(raw, before, before ^ fl.DEVACK)
        msg = Message.decode(raw)
        task = self.tasks.get(msg.rx)
        answer = task.handle(msg) if task else msg.answer(f=F_UNKNOWN_TASK)
        if (answer is not None and not (msg.e & _NAK and answer.f == 0)
                and not self.faults.hold(answer)):
            self.outbox.append(answer)

    def _deliver(self) -> None:
        item = self.outbox.popleft()
        raw = item if isinstance(item, bytes) else item.encode()
        mm = self.mm
        host = mm[HOST_FLAGS]
        recorder = self.recorder
        if recorder is not None:
            recorder.answer(raw, host, host ^ fl.HOSTCOM)
        mm[PC_MBX : PC_MBX + len(raw)] = raw
        mm[HOST_FLAGS] = host ^ fl.HOSTCOM  # recorded with the answer, rung at the turn's end
        self._ring = True

    def _state_field(self) -> None:
        """Event-driven state field: toggle STATECOM when Task2State changed."""
        mm = self.mm
        if (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.STATE:
            return
        current = mm[TASK2_STATE : TASK2_STATE + TASK_STATE_SIZE]
        if current != self._state_sent:
            self._state_sent = current
            self.toggle_host_flags(fl.STATECOM)


def _close_all(*fds: int) -> None:
    for fd in fds:
        os.close(fd)
