"""One node handler per configured node: its state machine over boot-up, error control, EMCY, PDOs.

The seed calls them node handlers: "for every node station one state machine
is implemented" (seed 5.2). The handler holds that state machine and the node's
diagnosis; the services it composes each own their frames and their state: the
boot-up (``boot``, driven by the node's answers in the bus thread), error control
(``supervision``, from the master's thread; the heartbeat deadlines kept by the bus thread's
wait), EMCY (``emcy``) and the PDOs (``pdo``).
They report back an Err_Event; only the handler changes the node's state and tells
the network (``Network``, ``NodeEvents``), which the master implements. The master's
thread sleeps until something is due: the handler says when (``next_due``) and asks it
to look again after each change of state (``Network.reschedule``).
"""

from __future__ import annotations

import enum
import logging
import math
import time
from contextlib import AbstractContextManager
from typing import Protocol

import can

from dbm_tools.parameters import ConfigNdState, NodeParameterSet
from dpm.cia301 import BOOT_UP, ERROR_CONTROL_BASE, OPERATIONAL, STATE_MASK
from dpm.com import NodeDiagnosis as Diagnosis
from dpm.com import NodeStatus
from dpm.commands import NMT_STOP
from dpm.errors import NodeEvent, err_event_text
from firmware.can.boot import BootLink, BootSequence, BootSlots
from firmware.can.bus import CanBus
from firmware.can.emcy import EmcyConsumer
from firmware.can.pdo import NodePdos, PdoLink
from firmware.can.sdo import SdoChannel, SdoChannels
from firmware.can.supervision import ErrorControl, HeartbeatWatch
from firmware.can.workers import Workers

log = logging.getLogger(__name__)

RETRY_DELAY = 1.0
"""[ours] seconds before a lost node is booted again when auto-clear is off."""
HOST_SDO_RETRY_S = 0.001
"""[ours] How often the master tries again to send a node's RX-PDOs that the host changed
while its SDO transfer to the node runs (seed 5.2.8: they wait for its end). A transfer
takes about a millisecond; only a node with changed outputs and a transfer under way is
looked at this often."""
FOREIGN_CLOCK_S = 60.0
"""[ours] A frame stamped further than this from the wall clock is stamped by the adapter's
own clock: its stamp says nothing about when it was on the bus relative to the card's
resets and starts (``wall_stamp``)."""


class State(enum.Enum):
    INACTIVE = "inactive"
    """bNd_Flag ACTIVE clear: I/O reserved, never booted."""
    WAITING = "waiting"
    """Configured; the network is not running (or the host stopped it)."""
    BOOTING = "booting"
    OPERATING = "operating"
    FAILED = "failed"
    DISCONNECTED = "disconnected"
    """The host cleared its connection-status bit."""


class Network(BootLink, PdoLink, Protocol):
    """What a node handler uses of the network (the master): the bus and its services."""

    @property
    def bus(self) -> CanBus | None: ...

    @property
    def workers(self) -> Workers: ...

    @property
    def boot_slots(self) -> BootSlots: ...

    @property
    def auto_clear(self) -> bool: ...

    @property
    def sdo(self) -> SdoChannels: ...

    @property
    def heartbeats(self) -> HeartbeatWatch:
        """Where the heartbeat consumers' deadlines go for the receive thread to keep."""

    @property
    def outputs_lock(self) -> AbstractContextManager[object]:
        """Held while the host's outputs are followed (``OutputWatch``): a node's forced
        RX-PDOs taken under it never interleave with a change going out."""

    def reschedule(self, handler: NodeHandler | None = None) -> None:
        """``handler``'s state changed (None: the network's): the master supervises it
        again at once."""

    def operating(self, handler: NodeHandler) -> None:
        """``handler``'s boot-up ended in data exchange: the master supervises it from its
        next look on, which comes before the node's first deadline."""


class NodeEvents(Protocol):
    """Whom a node handler tells of its state: the network management (``firmware.can.nmt``)."""

    def node_booted(self, handler: NodeHandler) -> None: ...

    def node_failed(self, handler: NodeHandler, event: int) -> None: ...

    def set_node_state(self, address: int, on: bool) -> None: ...

    def set_node_diag(self, address: int, on: bool) -> None: ...


def wall_stamp(msg: can.Message) -> float | None:
    """The frame's time stamp when it is on this machine's wall clock, as virtual, shm and
    socketcan stamp; None for an adapter that counts from its own power-on, whose stamps
    would otherwise make every frame look older than the node's last reset or start."""
    stamp = msg.timestamp
    return stamp if stamp and abs(stamp - time.time()) < FOREIGN_CLOCK_S else None


class NodeHandler:
    def __init__(self, network: Network, events: NodeEvents, address: int,
                 params: NodeParameterSet) -> None:
        self.network = network
        self.events = events
        self.address = address
        self.params = params
        self.active = params.active
        """Configured to run (the parameters of a handler never change)."""
        self.state = State.WAITING if params.active else State.INACTIVE
        self.diag = Diagnosis()
        if not params.active:
            self.diag.status |= NodeStatus.DEACTIVATED
        self.operational_expected = True
        """False after the host stopped or pre-operated the node with NMT."""
        self.awaiting_start = False
        """The card has not asked the node to go OPERATIONAL: START is set in its
        bitConfigNdState, or the global Start_Node has not gone out yet. The node is supervised
        in the state it is in, and Nd_state shows whether it operates (seed 4.2, 4.3)."""
        self._diag_seen = (self.diag.status, self.diag.actual_error)
        """Nodestatus_1 and Actual_Error as the host last read them (COM_Node_Diag)."""
        self._host_started_at: float | None = None
        """Wall-clock time of a host's Start_Node that came while the node booted."""
        self.host_sdo = False
        """A host SDO transfer runs: the node's RPDOs are suppressed (seed 5.2.8)."""
        self.connected = False
        """The node reached data exchange since the network last started it: only then can
        losing it be auto-clear's "disconnected" (``NmtMaster.node_failed``)."""
        self._retry_at = 0.0
        self._generation = 0
        """Bumped on every (re)boot so a stale boot thread gives up."""
        self.control = ErrorControl(params, network.bus_send, network.heartbeats)
        self.boot = BootSequence(address, params, self.diag, network, self.control)
        self.emcy = EmcyConsumer(self.diag, params.usCobIDEmcy,
                                 lambda: events.set_node_diag(address, True))
        self.pdos = NodePdos(network, params, lambda: self.state is State.OPERATING)

    # --- wiring to the bus -----------------------------------------------------------------

    def attach(self) -> None:
        bus = self.network.bus
        assert bus is not None
        bus.subscribe(ERROR_CONTROL_BASE + self.address, self._on_error_control)
        self.boot.attach(bus)
        guard = self.params.usCobIDGuard
        if guard and guard != ERROR_CONTROL_BASE + self.address:
            bus.subscribe(guard, self._on_error_control)
        self.emcy.attach(bus)
        self.pdos.attach(bus)

    def detach(self) -> None:
        bus = self.network.bus
        if bus is None:
            return
        bus.unsubscribe(ERROR_CONTROL_BASE + self.address, self._on_error_control)
        self.control.unwatch()
        self.boot.detach(bus)
        bus.unsubscribe(self.params.usCobIDGuard, self._on_error_control)
        self.emcy.detach(bus)
        self.pdos.detach(bus)

    # --- boot-up ------------------------------------------------------------------------------

    def start_boot(self, reset_sent: bool = False) -> None:
        """Begin (or begin again) the boot sequence, driven by the node's answers.

        ``reset_sent``: the host resets the node itself (COM_NMT_Module_Protocol);
        the sequence then waits for that boot-up instead of resetting it twice,
        which would let the first boot-up answer for the second.
        """
        if self.state is State.INACTIVE:
            return
        self._generation += 1
        self.boot.arm()
        self.state = State.BOOTING
        self.operational_expected = True
        self._host_started_at = None
        self.events.set_node_state(self.address, False)
        generation = self._generation
        self.network.boot_slots.take(lambda: self._take_channel(generation, reset_sent))
        self.network.reschedule(self)

    def _take_channel(self, generation: int, reset_sent: bool) -> bool:
        """In a boot slot: begin the boot-up with the node's SDO channel; False when a newer
        start of the node came while this one waited for the slot."""
        if generation != self._generation:
            return False
        channel = self.network.sdo.channel(self.address)
        if channel.lock.acquire(blocking=False):
            self._begin_boot(generation, channel, reset_sent)
        else:
            # A host transfer, the gateway or a replaced boot-up holds the node's SDO
            # channel: a worker waits for it, as the seed's node handler waits.
            self.network.workers.submit(self._boot_when_free, generation, channel,
                                         reset_sent)
        return True

    def _boot_when_free(self, generation: int, channel: SdoChannel, reset_sent: bool) -> None:
        """In a worker thread: take the channel, then boot, unless a newer start of the node
        came meanwhile. Without that check, a host toggling NOTREADY queued boot after stale
        boot (up to 3 s each), and a new configuration waited behind all of them.

        The wait gives up when the card powers off: the boot-up holding the channel ends at
        its next answer or time-out, which the master's thread no longer times then, and a
        worker blocked for good kept the firmware process from exiting."""
        if not self.network.sdo.take(channel):
            self.network.boot_slots.free()
            return
        if generation != self._generation:
            channel.lock.release()
            self.network.boot_slots.free()
            return
        self._begin_boot(generation, channel, reset_sent)

    def _begin_boot(self, generation: int, channel: SdoChannel, reset_sent: bool) -> None:
        """Start the sequence with the channel taken; it gives the channel back when it ends.

        An unforeseen exception fails the node (34, no response during its configuration)
        and is logged, rather than leave it in BOOTING for good and the host without an
        Err_Event. Not while the card powers off: a boot-up cut short then (its bus shut,
        its image gone) is no error of the node.
        """
        bus = self.network.bus
        assert bus is not None

        def release() -> None:
            channel.lock.release()
            self.network.boot_slots.free()

        def done(event: int | None) -> None:
            if event is None:
                if generation == self._generation and self.state is State.BOOTING:
                    self._operate()
            else:
                self._fail_boot(generation, event)

        try:
            self.boot.start(bus, self.network.sdo, channel.sdo.RESPONSE_TIMEOUT, reset_sent,
                            release, lambda: generation == self._generation, done)
        except Exception:
            self.boot.stop()
            if self.network.closing:
                return
            log.exception("node %d: boot-up failed unexpectedly", self.address)
            self._fail_boot(generation, NodeEvent.NO_RESPONSE)

    def _operate(self) -> None:
        """The boot-up succeeded: the node exchanges data from now on (Nd_state)."""
        skip = self.params.bitConfigNdState
        recovered = self.diag.actual_error != 0
        self.diag.status &= ~(NodeStatus.NO_RESPONSE | NodeStatus.PRM_FAULT)
        self.diag.actual_error = 0  # the online error is over (seed 5.2.7 Actual_Error)
        now = time.monotonic()
        self.control.restart(now)
        self.control.started(now)
        # A host's Start_Node that came during the boot-up, after its reset, reached the
        # node: it is running already and waits for no other start. Without this, a host that
        # started it a moment early saw it operate in Nd_state and NEXC set for good.
        host_started = (self._host_started_at is not None
                        and self._host_started_at >= self.boot.reset_at)
        self.awaiting_start = ((bool(skip & ConfigNdState.START.value) or self.network.global_start)
                               and not host_started)
        # The first RX-PDOs go before Nd_state tells the host the node runs, and under the
        # outputs' lock: a host's change that follows waits for its inhibit time after them
        # (CiA 301), and one that came first is in them. Before, a change written as Nd_state
        # appeared went out a moment before them (two frames 0.35 ms apart at 100 ms inhibit).
        # A node that waits for its start gets them when it goes out (``start_sent``).
        with self.network.outputs_lock:
            self.pdos.forget_sent()
            self.state = State.OPERATING
            self.connected = True
            if not skip & ConfigNdState.TXRXPDO.value and not self.awaiting_start:
                self.send_outputs(force=True)
                self.pdos.request_first(now)
        if self.control.supervised:
            self.diag.status |= NodeStatus.GUARD_ACTIVE
        if recovered:  # before Nd_state, as above
            self.note_diag()
        else:  # [ours] a first boot is the normal state (seed 4.3: Nd_state 1, Nd_diag 0)
            self._diag_seen = (self.diag.status, self.diag.actual_error)
        self.events.node_booted(self)
        self.network.operating(self)  # supervision and remote requests from now on

    def start_sent(self, now: float, by_host: bool) -> bool:
        """A Start_Node went to the node (the global one, or the host's): from now on it must
        be OPERATIONAL, after the usual grace for the command to arrive. A node with START set
        in bitConfigNdState waits only for the host's.

        Returns True when the start put the node into data exchange and nothing will report
        it: a node without error control sends no state, so [ours] the card takes its own
        start for the node's state and sets Nd_state (seed 4.3, 5.2.9), as it does after a
        boot-up that ends with its Start_Node. A supervised node's state comes with its next
        heartbeat or guarding answer.
        """
        if self.state is not State.OPERATING:
            if self.state is State.BOOTING and by_host:
                self._host_started_at = time.time()  # for the boot-up's end (``_operate``)
            return False
        if self.awaiting_start:
            if not by_host and self.params.bitConfigNdState & ConfigNdState.START:
                return False
            self.awaiting_start = False
        elif not by_host:
            return False
        # else a node the host had stopped, or one running already
        self.control.started(now)
        if not self.params.bitConfigNdState & ConfigNdState.TXRXPDO:
            with self.network.outputs_lock:  # as in ``_operate``
                self.send_outputs(force=True)  # the first RX-PDO, now that the node takes it
            self.pdos.request_first(now)  # and the first TX-PDO
        self.network.reschedule(self)  # in data exchange now: NEXC, remote requests
        return not self.control.supervised

    def _fail_boot(self, generation: int, event: int) -> None:
        if generation == self._generation:
            self.fail(event)

    # --- steady operation ---------------------------------------------------------------------

    def set_emcy_consumer(self, cob_id: int | None) -> None:
        """COM_Set_Emcy_Consumer: collect EMCY frames of ``cob_id``, or none."""
        self.emcy.move(self.network.bus, cob_id)

    def set_supervision(self, heartbeat: bool, time_ms: int, life_time_factor: int) -> None:
        """Switch error control at run time (COM_Set_Guarding, COM_Set_Heartbeat_Consumer)."""
        self.control.configure(heartbeat, time_ms, life_time_factor)
        if self.control.supervised:
            self.diag.status |= NodeStatus.GUARD_ACTIVE
        else:
            self.diag.status &= ~NodeStatus.GUARD_ACTIVE
        self.network.reschedule(self)  # new deadlines

    def expect_operational(self, on: bool) -> None:
        """The host started (True) or stopped or pre-operated (False) the node with NMT."""
        self.operational_expected = on
        self.network.reschedule(self)  # in data exchange or not: NEXC, remote requests

    def fail(self, event: int) -> None:
        """The node left data exchange: report it; retry or let auto-clear stop all."""
        if self.state in (State.INACTIVE, State.DISCONNECTED):
            return
        log.info("node %d: Err_Event %d, %s", self.address, event, err_event_text(
            self.address, event, "heartbeat" if self.control.heartbeat else "guarding"))
        self.state = State.FAILED
        self.diag.actual_error = event
        self.diag.status &= ~NodeStatus.GUARD_ACTIVE
        if event == NodeEvent.GUARDING_FAILED:  # guarding or heartbeat: no answer any more
            self.diag.status |= NodeStatus.NO_RESPONSE
        self._retry_at = time.monotonic() + RETRY_DELAY
        self.note_diag()  # before Err_Event: a host that sees the event sees Nd_diag too
        self.events.node_failed(self, event)
        self.network.reschedule(self)  # the retry's deadline, a global start

    def note_diag(self) -> None:
        """Nd_diag: set when Nodestatus_1 or Actual_Error differ from what the host last
        read (seed 4.3), so a node that fails its restarts the same way again and again
        raises it once, and its recovery from a failure raises it again."""
        if (self.diag.status, self.diag.actual_error) != self._diag_seen:
            self.events.set_node_diag(self.address, True)

    def disconnect(self) -> None:
        """The host cleared the node's connection bit: stop it and leave it alone."""
        if self.state is State.INACTIVE:
            return
        self._generation += 1
        self.state = State.DISCONNECTED
        self.events.set_node_state(self.address, False)
        self.network.send_nmt(NMT_STOP, self.address)
        self.network.reschedule(self)

    def idle(self) -> None:
        """The network stopped (host not ready, watchdog, auto-clear)."""
        if self.state is not State.INACTIVE:
            self._generation += 1
            self.state = State.WAITING
            self.connected = False
            self.events.set_node_state(self.address, False)
            self.network.reschedule(self)

    def tick(self, now: float) -> None:
        """Supervision and retries; called by the master's thread when ``next_due`` has come
        (or after any node's change of state)."""
        if self.state is State.FAILED:
            if (not self.network.auto_clear or not self.connected) and now >= self._retry_at:
                self.start_boot()
            return
        if self.state is not State.OPERATING:
            return
        event = self.control.check(now) or (self.pdos.poll(now) if self.exchanging else 0)
        if event:
            self.fail(event)

    def overdue(self, now: float) -> bool:
        """Whether ``tick`` at ``now`` would fail the node for its error control."""
        return self.state is State.OPERATING and self.control.overdue(now)

    def next_due(self, timed: bool = False) -> float:
        """When ``tick`` has something to do next (monotonic seconds; inf: nothing).

        Every change that brings a deadline forward (a new state, a start, new supervision
        settings) asks the master to look again (``reschedule``); frames only push the
        deadlines back (a heartbeat, a guarding answer, an answered remote request).
        ``timed``: without the heartbeat consumer's deadline, which the receive thread keeps
        (``HeartbeatWatch``): what the master's own timer must meet.
        """
        if self.state is State.FAILED:
            retrying = not self.network.auto_clear or not self.connected
            return self._retry_at if retrying else math.inf
        if self.state is not State.OPERATING:
            return math.inf
        due = self.control.timed_due() if timed else self.control.next_due()
        return min(due, self.pdos.next_due()) if self.exchanging else due

    def on_sync(self, now: float) -> None:
        """At each SYNC: synchronous outputs, and remote requests of 252 inputs."""
        if self.state is not State.OPERATING:
            return
        self.send_outputs(sync=True)
        event = self.pdos.on_sync(now) if self.exchanging else 0
        if event:
            self.fail(event)

    @property
    def exchanging(self) -> bool:
        """In data exchange: operating and started. Only then must the node answer remote
        requests of its TX-PDOs (a node waiting for its start, or stopped by the host, sends
        none), and only then is it no NEXC (seed 4.3)."""
        return (self.state is State.OPERATING and not self.awaiting_start
                and self.operational_expected)

    def send_outputs(self, sync: bool = False, force: bool = False) -> float | None:
        """Send the RX-PDOs that are due (``NodePdos.send_outputs``) while the node runs.

        Returns when to ask again while a changed event-driven PDO waits: the end of its
        inhibit time, or ``HOST_SDO_RETRY_S`` from now while a host SDO transfer runs;
        None when nothing waits.
        """
        if self.state is not State.OPERATING or not self.operational_expected:
            return None
        if self.host_sdo:
            return time.monotonic() + HOST_SDO_RETRY_S
        return self.pdos.send_outputs(sync, force)

    # --- frames from the node -------------------------------------------------------------------

    def _on_error_control(self, msg: can.Message) -> None:
        if msg.is_remote_frame or not msg.data:
            return
        now = time.monotonic()
        stamp = wall_stamp(msg)
        value = msg.data[0]
        state = value & STATE_MASK
        if state == BOOT_UP and msg.arbitration_id == ERROR_CONTROL_BASE + self.address:
            # Seed 8.1: "Bootup Protocol, no reaction on Bootup Events of a Node": a node
            # without error control stays as it is. [ours] A supervised node's boot-up is its
            # state report as well (CiA 301: state 0), which its next heartbeat or guarding
            # answer would give a moment later: it left OPERATIONAL (31).
            self.boot.booted_up(stamp)
            if self.state is State.OPERATING and self.control.supervised:
                log.info("node %d: unexpected boot-up", self.address)
                self.fail(NodeEvent.LEFT_OPERATIONAL)
            return
        self.diag.node_state = state
        if self.state is not State.OPERATING:
            return
        event = self.control.answered(value, now)
        if event:
            self.fail(event)
            return
        operating = state == OPERATIONAL
        self.control.reported(operating)
        if self.operational_expected and not self.awaiting_start and not operating:
            if not self.control.predates_start(now, stamp):
                self.fail(NodeEvent.LEFT_OPERATIONAL)
            return
        self.events.set_node_state(self.address, operating)

    def read_diagnosis(self) -> bytes:
        """COM_Node_Diag: the 48-byte structure; reading clears the EMCY buffer."""
        raw = self.diag.encode()
        self._diag_seen = (self.diag.status, self.diag.actual_error)
        self.diag.emcy.clear()
        self.diag.status &= ~NodeStatus.EMCY_BUFFER_OVERFLOW
        return raw
