"""The SYNC producer (CiA 301 7.2.5): a thread, or a timer outside the interpreter.

Why a module of its own: SYNC is the one service of the master with a clock of its own,
and the one with a process of its own on ``shm`` (``firmware.shm.cyclic``). All it asks
of the network is whether SYNC is due and at which period (``period``), and all it tells
is that a SYNC went out (``on_sync``, which drives the synchronous PDOs). The master
rings ``wake`` when either answer may have changed (a start, a halt, a reset).

SYNC_Timer 0 with synchronous PDOs configured means another station produces SYNC (seed
revision 16: 0 "disables the timer"): the producer then sends nothing and the synchronous
PDOs follow that station's SYNC frames as they arrive (``foreign``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import can
from can.broadcastmanager import CyclicSendTaskABC

from firmware.can.bus import PERIODIC_OUTSIDE_INTERFACES, CanBus

log = logging.getLogger("firmware.can.master")
"""The master's log, as before SYNC had a module of its own."""

TIMER_CHECK_S = 0.05
"""[ours] How often the thread looks whether the outside SYNC timer still runs (its process
may be killed) or a failed one is due to be tried again."""
SYNC_RETRY_MAX_S = 5.0
"""[ours] the longest pause between tries to start an outside SYNC timer that fails."""


class SyncProducer:
    """Sends SYNC every ``period()`` seconds while ``active()``; see the module docstring.

    ``cob_id`` gives COB_ID_SYNC, ``period`` SYNC_Timer in seconds (0: no SYNC),
    ``active`` whether the network exchanges data now (running, not halted, not
    cleared), ``foreign`` whether another station's SYNC drives the synchronous PDOs
    (SYNC_Timer 0 while they exist), ``on_sync`` is called with the time of each SYNC.
    """

    def __init__(self, stop: threading.Event, cob_id: Callable[[], int],
                 period: Callable[[], float], active: Callable[[], bool],
                 foreign: Callable[[], bool], on_sync: Callable[[float], None]) -> None:
        self._stop = stop
        self._cob_id = cob_id
        self._period = period
        self._active = active
        self._foreign = foreign
        self._on_sync = on_sync
        self._followed: int | None = None
        """The COB-ID of another station's SYNC that the synchronous PDOs follow now."""
        self._bus: CanBus | None = None
        self._thread: threading.Thread | None = None
        self._wakeup = threading.Event()
        self._timer: tuple[tuple[int, float], CyclicSendTaskABC] | None = None
        """The outside SYNC timer, with the (COB-ID, period) it runs for."""
        self._on = False
        """Whether SYNC frames coming back drive the synchronous PDOs (outside timer)."""
        self._retry_at = 0.0
        self._retry_s = 0.0

    def start(self, bus: CanBus) -> None:
        self._bus = bus
        self._thread = threading.Thread(target=self._loop, name="can-sync", daemon=True)
        self._thread.start()

    def join(self, timeout: float) -> None:
        """After ``stop`` is set: the thread ends and stops an outside timer."""
        self._wakeup.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout)

    def wake(self) -> None:
        """Whether or how SYNC runs may have changed: the thread looks again at once."""
        self._wakeup.set()

    def retry_now(self) -> None:
        """A new configuration tries a failing outside timer at once."""
        self._retry_at = 0.0

    def _loop(self) -> None:
        """A timer outside the interpreter where the bus has one, else this thread.

        The thread sleeps most of the period, then watches the clock for the
        rest; under PDO load it still waits for the interpreter lock behind the
        receive and tick threads (milliseconds, see docs/benchmarks.md). With an
        outside timer, the synchronous PDOs follow the SYNC frame as it comes back
        from the bus, as on a real bus they follow it on the wire.
        """
        bus = self._bus
        assert bus is not None
        outside = bus.interface in PERIODIC_OUTSIDE_INTERFACES
        next_sync = time.perf_counter()
        while not self._stop.is_set():
            period = self._period()
            if not (self._active() and period):
                self._stop_timer()
                self._follow(self._active() and self._foreign())
                self._await_change(None)
                next_sync = time.perf_counter()
                continue
            self._follow(False)
            if outside:
                self._run_timer(self._cob_id(), period)
                self._await_change(TIMER_CHECK_S)
                continue
            next_sync += period
            remaining = next_sync - time.perf_counter()
            if remaining < -period:  # fell behind (the machine stalled): resynchronise
                next_sync = time.perf_counter()
            elif remaining > 0.0008:
                self._stop.wait(remaining - 0.0005)
            while time.perf_counter() < next_sync:
                time.sleep(0)  # let the other threads have the GIL meanwhile
            bus.send(self._cob_id())
            self._on_sync(time.monotonic())
        self._stop_timer()
        self._follow(False)

    def _await_change(self, timeout: float | None) -> None:
        """Until a start, halt or reset rings, or ``timeout`` passes (None: no SYNC runs, so
        only a ring can change that: an idle card's thread sleeps)."""
        self._wakeup.wait(timeout)
        self._wakeup.clear()

    def _run_timer(self, cob_id: int, period: float) -> None:
        """(Re)start the outside SYNC timer when it is not running as configured.

        A timer that ended (its process was killed) starts again; one that
        will not start is tried again after a pause that doubles up to
        ``SYNC_RETRY_MAX_S``, since each try may cost an interpreter start.
        """
        timer = self._timer
        if timer is not None:
            if timer[0] == (cob_id, period):
                if getattr(timer[1], "alive", True):
                    return
                log.warning("the SYNC timer ended unasked; starting it again")
            self._stop_timer()
        now = time.monotonic()
        if now < self._retry_at:
            return
        bus = self._bus
        assert bus is not None
        self._on = True  # before the first frame can come back
        bus.subscribe(cob_id, self._on_frame)
        try:
            task = bus.send_periodic(cob_id, period)
        except (can.CanError, OSError) as exc:
            self._on = False
            bus.unsubscribe(cob_id, self._on_frame)
            if self._retry_s:
                log.warning("SYNC timer did not start again: %s", exc)
            else:
                log.exception("SYNC timer did not start; trying again")
            self._retry_s = min(SYNC_RETRY_MAX_S, max(0.1, 2 * self._retry_s))
            self._retry_at = now + self._retry_s
            return
        self._retry_s = 0.0
        self._timer = ((cob_id, period), task)
        if getattr(task, "realtime", True) is False:
            log.warning("the SYNC timer process runs without SCHED_FIFO (no CAP_SYS_NICE): "
                        "its jitter is the machine's")

    def _stop_timer(self) -> None:
        if self._timer is None:
            return
        (cob_id, _), task = self._timer
        self._timer = None
        self._on = False
        task.stop()
        if self._bus is not None:
            self._bus.unsubscribe(cob_id, self._on_frame)

    def _follow(self, on: bool) -> None:
        """Follow another station's SYNC on the configured COB-ID, or stop following."""
        cob_id = self._cob_id() if on else None
        if cob_id == self._followed or self._bus is None:
            return
        if self._followed is not None:
            self._bus.unsubscribe(self._followed, self._on_foreign)
        self._followed = cob_id
        if cob_id is not None:
            self._bus.subscribe(cob_id, self._on_foreign)

    def _on_foreign(self, msg: can.Message) -> None:
        """Another station's SYNC, while SYNC_Timer is 0 (not after a halt the thread has
        yet to hear of)."""
        if self._followed is not None and not msg.data and self._active():
            self._on_sync(time.monotonic())

    def _on_frame(self, msg: can.Message) -> None:
        """The outside timer's SYNC as it comes back; not after a halt the timer has yet
        to hear of (the sync thread stops it within its next look)."""
        if self._on and not msg.data and self._active():
            self._on_sync(time.monotonic())
