"""Error control of one node: node guarding or heartbeat consumption (CiA 301 7.2.8.3).

Why a module of its own: error control has its own clock (the guard time, the consumer
time), its own frames (the guarding remote request and the node's answers on 700h + ID)
and its own settings, which the host changes at run time (COM_Set_Guarding,
COM_Set_Heartbeat_Consumer). It decides only whether the node still answers in time
and whether a state it reports may predate the card's start command; what a failure
means for the node and the network (Err_Event, Nd_state, auto-clear) stays with the
node handler, which hears it as an Err_Event number.
"""

from __future__ import annotations

import heapq
import itertools
import math
import threading
import time
from collections.abc import Callable

from dbm_tools.parameters import NdFlag, NodeParameterSet
from dpm.cia301 import TOGGLE_BIT
from dpm.errors import NodeEvent

START_GRACE = 0.5
"""[ours] seconds after the NMT start in which a node may still report its old state: an
error-control frame it sent before the start can reach the master after it."""

HEARTBEAT_LOOK_LATE_S = 0.010
"""[ours] How long after a heartbeat consumer's deadline the master looks at it, at most a
tenth of the consumer time: a lost node is found this much later than its deadline. The
receive thread ends its wait for frames then (``HeartbeatWatch``) and wakes the master.

Why: a node produces at a fraction of the consumer time (``cifemu sim``, like many
configurations, at half of it), so a deadline counted from the last heartbeat comes just as
the next heartbeat does. A master looking exactly then found that heartbeat not yet taken,
the node's deadline moved on by one producer period only, and looked again one period later,
racing the next one: about two looks a second for one node at 1 s, 1.5-2.3 measured, each a
thread wake-up of 100-200 us of CPU, most of what a lone configured node cost an idle card
beside its heartbeats' own wake-ups (issue 22). Looking a little later takes that heartbeat
first and moves the deadline on by the whole consumer time: one look per consumer time.
The 1 ms tick the card had before issue 22 found a loss up to 1 ms late as well."""

Send = Callable[..., bool]
"""The network's ``bus_send(can_id, data=b"", remote=False, dlc=None)``."""


class HeartbeatWatch:
    """The heartbeat consumers' deadlines, for the thread that takes the heartbeats [ours].

    Why: a heartbeat only moves its consumer's deadline later, and the controller's receive
    thread, which takes it, waits for the next frame anyway. Bounding that wait by the
    earliest deadline here costs nothing while heartbeats come (each one moves the bound
    before the thread waits again), whereas the master's own timer, which no frame can move,
    woke its thread once per consumer time for each node only to find the deadline moved:
    100-250 us of CPU a look, 40 % of what a lone configured node cost an idle card (issue 22).
    When a deadline here passes, the receive thread wakes the master, which looks at every
    node as at its own deadline (``Master.deadline_came``). While no receive thread runs (a
    bridge's link lost and reopening) the master times the deadlines itself.

    A heap of (deadline, order, consumer); a consumer's entry is live while it is the one its
    consumer last pushed (``ErrorControl.watched``): a heartbeat pushes a new one and leaves
    the old one to be dropped when it comes to the top. Any thread pushes; ``due`` and
    ``take`` are the receive thread's.
    """

    def __init__(self) -> None:
        self._heap: list[tuple[float, int, ErrorControl]] = []
        self._order = itertools.count()
        self._lock = threading.Lock()

    def push(self, due: float, control: ErrorControl) -> None:
        with self._lock:
            heapq.heappush(self._heap, (due, next(self._order), control))

    def due(self) -> float:
        """The earliest live deadline (monotonic seconds; inf: none)."""
        heap = self._heap
        while heap:
            entry = heap[0]
            if entry[2].watched == entry[0]:
                return entry[0]
            with self._lock:
                if heap and heap[0] is entry:  # else another thread pushed an earlier one
                    heapq.heappop(heap)
        return math.inf

    def take(self, now: float) -> bool:
        """Drop every live deadline that came by ``now``; True when there was one."""
        came = False
        while self.due() <= now:
            # The top is still the entry ``due`` saw: another thread only pushes deadlines
            # later than now, which sort below it.
            with self._lock:
                heapq.heappop(self._heap)
            came = True
        return came


class ErrorControl:
    """Guarding or heartbeat for one node, from its node parameters (seed 4.2)."""

    def __init__(self, params: NodeParameterSet, send: Send,
                 watch: HeartbeatWatch | None = None) -> None:
        self._guard_cob_id = params.usCobIDGuard
        self._send = send
        self._watch = watch
        self.watched = math.inf
        """The heartbeat deadline last pushed to ``watch`` (``next_due``; inf: none)."""
        self.heartbeat = bool(params.bNd_Flag & NdFlag.HRTBT)
        self.guard_time = params.usGuardTime
        """Supervision time in ms (guard time or heartbeat consumer time); 0 = none."""
        self.life_time_factor = params.bLifeTimeFactor
        self._last_heartbeat = 0.0
        self._next_guard = 0.0
        self._guard_pending = False
        self._guard_misses = 0
        self._toggle: int | None = None
        self._started_at = 0.0
        self._start_stamp = 0.0
        """[ours] Wall-clock time (as frames are stamped) of the node's last start: an
        error-control frame stamped before it is no answer to it, however late it is read."""
        self._confirmed = False
        """The node reported OPERATIONAL since its start."""

    @property
    def supervised(self) -> bool:
        return self.guard_time > 0

    def configure(self, heartbeat: bool, time_ms: int, life_time_factor: int) -> None:
        """Switch error control at run time (COM_Set_Guarding, COM_Set_Heartbeat_Consumer)."""
        self.heartbeat = heartbeat
        self.guard_time = time_ms
        self.life_time_factor = life_time_factor
        self.restart(time.monotonic())

    def restart(self, now: float) -> None:
        """Supervise from ``now`` on, as if the node had just answered."""
        self._last_heartbeat = now
        self._next_guard = now
        self._guard_pending = False
        self._guard_misses = 0
        self._toggle = None
        self._watch_deadline()

    def unwatch(self) -> None:
        """No deadline of this consumer in the watch any more (the node is gone)."""
        self.watched = math.inf

    def _watch_deadline(self) -> None:
        """Put a heartbeat consumer's deadline into the watch (else none there)."""
        due = self.next_due() if self.heartbeat else math.inf
        self.watched = due
        if self._watch is not None and not math.isinf(due):
            self._watch.push(due, self)

    def started(self, now: float) -> None:
        """A start command went to the node: from now on it must report OPERATIONAL."""
        self._started_at = now
        self._start_stamp = time.time()
        self._confirmed = False

    def next_due(self) -> float:
        """When ``check`` has something to do (monotonic seconds; inf: unsupervised): the
        heartbeat consumer's deadline (``HEARTBEAT_LOOK_LATE_S`` after it), or the next
        guarding request. A heartbeat or an answer only moves it later, so the master need
        not wake for frames."""
        if not self.supervised:
            return math.inf
        if self.heartbeat:
            period = self.guard_time / 1000.0
            return self._last_heartbeat + period + min(HEARTBEAT_LOOK_LATE_S, period / 10)
        return self._next_guard

    def timed_due(self) -> float:
        """``next_due`` less a heartbeat deadline that the watch keeps: what only the master's
        own timer can meet (a guarding request)."""
        return math.inf if self.heartbeat and self._watch is not None else self.next_due()

    def check(self, now: float) -> int:
        """The deadlines, from the master's thread once ``next_due`` has come: GUARDING_FAILED
        or 0.

        Guarding sends the next remote request here when its time has come. Whether the
        node is lost is ``overdue``'s, which the master also asks before it judges.
        """
        if self.overdue(now):
            if not self.heartbeat:
                self._guard_misses += 1
            return NodeEvent.GUARDING_FAILED
        if self.supervised and not self.heartbeat and now >= self._next_guard:
            if self._guard_pending:
                self._guard_misses += 1  # one more unanswered, still within the life time
            self._guard_pending = True
            self._next_guard = now + self.guard_time / 1000.0
            self._send(self._guard_cob_id, remote=True, dlc=1)
        return 0

    def overdue(self, now: float) -> bool:
        """Whether ``check`` at ``now`` finds the node lost (GUARDING_FAILED), without doing
        any of its work: the master asks before it judges (``Master._verdict_waits``)."""
        if not self.supervised:
            return False
        if self.heartbeat:
            return now >= self._last_heartbeat + self.guard_time / 1000.0
        return (now >= self._next_guard and self._guard_pending
                and self._guard_misses + 1 >= max(1, self.life_time_factor))

    def answered(self, value: int, now: float) -> int:
        """An error-control frame of an operating node (its first byte): GUARD_SEQUENCE
        when guarding sees the toggle bit repeated, else 0."""
        if self.heartbeat:
            self._last_heartbeat = now
            self._watch_deadline()
        elif self.supervised:  # guarding; [ours] unsupervised: the node's own heartbeat
            self._guard_pending = False
            self._guard_misses = 0
            toggle = value & TOGGLE_BIT
            if self._toggle is not None and toggle == self._toggle:
                return NodeEvent.GUARD_SEQUENCE
            self._toggle = toggle
        return 0

    def reported(self, operating: bool) -> None:
        """The node reported its NMT state (OPERATIONAL or not) in an error-control frame."""
        self._confirmed |= operating

    def predates_start(self, now: float, stamp: float | None) -> bool:
        """Whether a state other than OPERATIONAL may have left the node before the card's
        start did: until the node first reports OPERATIONAL, a report within
        ``START_GRACE`` of the start; [ours] and one stamped before the start, read late
        by a busy card."""
        if not self._confirmed and now - self._started_at < START_GRACE:
            return True
        return stamp is not None and stamp < self._start_stamp
