"""Events of the CiA 309 gateway: their dispatcher, the ways a program takes them, and the
Task2State monitor that makes most of them.

* Subscribers are called from one dispatcher thread (:class:`EventDispatcher`), never from
  the mailbox reader, so a callback may itself call gateway services.
* A :class:`Monitor` per board reads Task2State when the card's flags say it changed and,
  as a fallback, every ``MONITOR_PERIOD`` while it changes, backing off to
  ``MONITOR_PERIOD_QUIET``: Nd_state and Nd_diag changes, CAN_state and the error counters
  become error control and emergency events (COM_Node_Diag is read when a node's Nd_diag
  bit sets).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import replace
from types import TracebackType

from dpm.com import NodeDiagnosis, node_diag_request
from dpm.commands import (
    COM_NODE_DIAG,
    ERR_EVENT_GUARD_SEQUENCE,
    ERR_EVENT_GUARDING_FAILED,
    ERR_EVENT_LEFT_OPERATIONAL,
    ERR_EVENT_NODE_STOPPED,
    NODE_DIAG_SIZE,
)
from dpm.errors import Drv
from dpm.message import MessageError, TelegramHeader
from dpm.task2 import CanState, ComDiagnostics
from host_api import driver as d
from host_api.cia309.link import DEFAULT_ANSWER_TIMEOUT, Link
from host_api.cia309.model import (
    Cia309Error,
    EmergencyEvent,
    ErrorCode,
    ErrorControlEvent,
    Event,
    NmtState,
)

log = logging.getLogger(__name__)

MONITOR_PERIOD = 0.01
"""Seconds between two looks at Task2State while it changes."""
MONITOR_PERIOD_QUIET = 0.25
"""[ours] The longest time between two looks once Task2State stopped changing (each quiet
look doubles the period): how late the gateway may see a change the card makes without
toggling STATECOM (the state channel stays pending while no host acknowledges it, and the
gateway leaves that to a host exchanging I/O). It looked every 10 ms before, 100 wake-ups
a second of a gateway with nothing to do (issue 22)."""
EMCY_HISTORY = 64
"""EMCYs the gateway keeps per node for ``read_device_error``."""



class Subscription:
    """A callback registered with ``Gateway.subscribe``; ``cancel`` removes it."""

    def __init__(self, events: EventDispatcher, callback: Callable[[Event], None]) -> None:
        self._events = events
        self.callback = callback

    def cancel(self) -> None:
        self._events.remove(self)


class EventStream:
    """Events as a queue (``Gateway.events``): for code that waits for them in turn."""

    def __init__(self, dispatcher: EventDispatcher) -> None:
        self._queue: queue.SimpleQueue[Event] = queue.SimpleQueue()
        self._subscription = dispatcher.add(self._queue.put)

    def get(self, timeout: float | None = None) -> Event:
        """The next event; ``queue.Empty`` when none came within ``timeout`` seconds."""
        return self._queue.get(timeout=timeout)

    def wait_for(self, predicate: Callable[[Event], bool], timeout: float) -> Event:
        """The first event (from now on, in order) ``predicate`` accepts; TimeoutError
        when none does within ``timeout`` seconds. Events it skips are dropped."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"no matching event within {timeout} s")
            try:
                event = self._queue.get(timeout=remaining)
            except queue.Empty:
                continue
            if predicate(event):
                return event

    def __iter__(self) -> Iterator[Event]:
        while True:
            yield self._queue.get()

    def close(self) -> None:
        self._subscription.cancel()

    def __enter__(self) -> EventStream:
        return self

    def __exit__(
        self, t: type[BaseException] | None, v: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


_STOP = object()


class EventDispatcher:
    """One dispatcher thread calls the subscribers, so none runs on the mailbox reader."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[Event | object] = queue.SimpleQueue()
        self._subscriptions: list[Subscription] = []
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="cia309-events", daemon=True)
        self._thread.start()

    def emit(self, event: Event) -> None:
        self._queue.put(event)

    def add(self, callback: Callable[[Event], None]) -> Subscription:
        subscription = Subscription(self, callback)
        with self._lock:
            self._subscriptions.append(subscription)
        return subscription

    def remove(self, subscription: Subscription) -> None:
        with self._lock:
            if subscription in self._subscriptions:
                self._subscriptions.remove(subscription)

    def close(self) -> None:
        self._queue.put(_STOP)
        self._thread.join(timeout=2)

    def _run(self) -> None:
        while True:
            event = self._queue.get()
            if event is _STOP:
                return
            with self._lock:
                subscriptions = list(self._subscriptions)
            for subscription in subscriptions:
                try:
                    subscription.callback(event)  # type: ignore[arg-type]
                except Exception:
                    log.exception("an event subscriber failed on %r", event)


class Monitor:
    """Task2State of one board, read when the card's flags changed and every
    ``MONITOR_PERIOD`` to ``MONITOR_PERIOD_QUIET``, as events.

    It also keeps what the events need beyond one look: the NMT state the gateway's own
    command put a node in, the nodes it reset, the EMCY history ``read_device_error``
    returns.
    """

    def __init__(self, link: Link, emit: Callable[[Event], None]) -> None:
        self.link = link
        self.network = link.network
        self.number = link.number
        self._emit = emit
        self.emcy_history: dict[int, deque[EmergencyEvent]] = {}
        self.expected: dict[int, NmtState] = {}
        """The state the gateway's own NMT command put a node in, until it operates again."""
        self.rebooting: dict[int, float] = {}
        """Nodes the gateway reset, with the time the card took the command: a node the card
        boots again within one monitor turn never shows a gap in Nd_state."""
        self._reported: dict[int, int] = {}
        self._last_state: ComDiagnostics | None = None
        self._last_raw = b""
        self._can_state: int | None = None
        self._state_lock = threading.Lock()
        self._closing = threading.Event()
        self._look = threading.Event()
        """Set by the link's reader when the card's STATECOM, COM, RUN or READY changed."""
        link.on_state_flags = self._look.set
        self._thread = threading.Thread(target=self._monitor_loop, daemon=True,
                                        name=f"cia309-monitor-{link.number}")
        self._thread.start()

    def close(self) -> None:
        self._closing.set()
        self._look.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2)

    def operating(self, node: int) -> bool:
        """Whether the last look saw the node in data exchange."""
        state = self._last_state
        return state is not None and node in state.operating()

    def starting(self) -> None:
        """The gateway starts the card: CAN init now, CAN active when the monitor sees the
        bus run again (a start with a stored database is quicker than a monitor turn)."""
        with self._state_lock:
            self._can_state = CanState.OFFLINE
            self.link.forget_node_sets()
        self._emit(ErrorControlEvent(self.network, self.link.own_node_id(),
                                     error=ErrorCode.CAN_INIT))

    def _monitor_loop(self) -> None:
        period = MONITOR_PERIOD
        while True:
            told = self._look.wait(period)
            if self._closing.is_set():
                return
            self._look.clear()
            changed = True
            try:
                changed = self._monitor_once()
            except Cia309Error as exc:
                log.debug("board %d: monitor: %s", self.number, exc)
            except Exception:
                log.exception("board %d: monitor failed", self.number)
            quiet = not changed and not told
            period = min(period * 2, MONITOR_PERIOD_QUIET) if quiet else MONITOR_PERIOD

    def _monitor_once(self) -> bool:
        """One look; whether Task2State changed since the last (or could not be read)."""
        read_at = time.monotonic()
        code, raw = d.DevGetTaskState(self.number, 2, 64)
        if code != Drv.DRV_NO_ERROR:
            return True
        changed = raw != self._last_raw
        self._last_raw = raw
        state = ComDiagnostics.decode(raw)
        # At the first look every pending diagnosis counts as new, so the EMCYs
        # collected before the gateway opened reach the history too.
        previous = self._last_state or replace(state, abNd_diag=bytes(16))
        self._last_state = state
        with self._state_lock:
            if self._can_state is None:
                self._can_state = state.bCAN_State
            elif state.bCAN_State != self._can_state:
                self._can_state = state.bCAN_State
                if state.bCAN_State == CanState.OPERATE:
                    self._emit(ErrorControlEvent(self.network, self.link.own_node_id(),
                                                 error=ErrorCode.CAN_ACTIVE))
                elif state.bCAN_State == CanState.OFFLINE:
                    self.link.forget_node_sets()
                    self._emit(ErrorControlEvent(self.network, self.link.own_node_id(),
                                                 error=ErrorCode.CAN_INIT))
        own = self.link.own_node_id()
        for counter, error in (
            ("usBus_Error_Cnt", ErrorCode.ERROR_PASSIVE),
            ("usBus_Off_Cnt", ErrorCode.BUS_OFF),
            ("usRx_Overflow", ErrorCode.CAN_BUFFER_OVERFLOW),
        ):
            if getattr(state, counter) > getattr(previous, counter):
                self._emit(ErrorControlEvent(self.network, own, error=error))
        operating = set(state.operating())
        before = set(previous.operating())
        timeout = DEFAULT_ANSWER_TIMEOUT
        rebooted = {node for node in operating
                    if self.rebooting.get(node, read_at) < read_at}
        for node in sorted((operating - before) | rebooted):
            self.rebooting.pop(node, None)
            self.expected.pop(node, None)
            self._reported.pop(node, None)
            started = self.link.supervised_by(node, timeout) == "heartbeat"
            self._emit(ErrorControlEvent(self.network, node, NmtState.OPERATIONAL,
                                         ErrorCode.HEARTBEAT_STARTED if started else None))
        for node in sorted(before - operating):
            if node in self.expected:
                self._emit(ErrorControlEvent(self.network, node, self.expected[node]))
        for node in state.diagnostic():
            self.read_diagnosis(node, timeout, operating=node in operating)
        return changed

    def read_diagnosis(self, node: int, timeout: float, *, operating: bool) -> int:
        """COM_Node_Diag: EMCYs into the history and out as events, a failure out as an
        error control event; returns the node's Actual_Error."""
        answer = self.link.command(COM_NODE_DIAG, node_diag_request(node), timeout,
                                   "COM_Node_Diag")
        try:
            diagnosis = NodeDiagnosis.decode(
                TelegramHeader.decode(answer.data).payload.ljust(NODE_DIAG_SIZE, b"\0"))
        except MessageError as exc:
            raise Cia309Error(ErrorCode.INTERNAL_STATE,
                              f"COM_Node_Diag of node {node}: {exc}") from exc
        node_state, actual_error = diagnosis.node_state, diagnosis.actual_error
        history = self.emcy_history.setdefault(node, deque(maxlen=EMCY_HISTORY))
        for entry in diagnosis.emcy:
            event = EmergencyEvent(self.network, node, int.from_bytes(entry[:2], "little"),
                                   entry[2], bytes(entry[3:8]))
            history.append(event)
            self._emit(event)
        if not operating and actual_error and self._reported.get(node) != actual_error:
            self._reported[node] = actual_error
            try:
                nmt_state: NmtState | None = NmtState(node_state)
            except ValueError:
                nmt_state = None
            error = _error_control(actual_error, self.link.supervised_by(node, timeout))
            self._emit(ErrorControlEvent(self.network, node, nmt_state, error))
        return actual_error


def _error_control(event: int, supervision: str | None) -> ErrorCode:
    """The 309-3 error of a node's Err_Event [ours, after Lely's gateway]: guarding and
    heartbeat time-outs by the supervision in force, a state the node should not be in
    as 204, a node that cannot be reached (no answer, wrong device) as lost connection."""
    if event == ERR_EVENT_GUARDING_FAILED:
        if supervision == "heartbeat":
            return ErrorCode.HEARTBEAT_LOST
        return ErrorCode.LOST_GUARDING_MESSAGE
    if event == ERR_EVENT_GUARD_SEQUENCE:
        return ErrorCode.LOST_GUARDING_MESSAGE
    if event in (ERR_EVENT_LEFT_OPERATIONAL, ERR_EVENT_NODE_STOPPED):
        return ErrorCode.WRONG_NMT_STATE
    return ErrorCode.LOST_CONNECTION


# --------------------------------------------------------------------------- the gateway

