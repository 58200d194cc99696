"""Network management: the master's state over its nodes, and the NMT commands it sends.

Why a module of its own: NMT is where the network as a whole is decided (CiA 301 7.2.8;
seed 4.3): the nodes start, stop, are left alone or start again, at the command of the
host (COM_NMT_Module_Protocol, the connection-status bits, HOST_NOT_READY and the
watchdog) or of the network itself (the global Start_Node, auto-clear). It owns the
network's state (running, halted, cleared), the NMT frames (000h) and the master's own
heartbeat (700h + its node-ID), and writes what follows into Task2State: Nd_state,
Nd_diag, NEXC, ACLR, Err_Event. Node handlers report to it (``NodeEvents``); the
master's thread drives it (``follow_host``, ``follow``) whenever it looks, and wakes for
the master heartbeat when ``heartbeat`` says it is due.
"""

from __future__ import annotations

import itertools
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

from dbm_tools.parameters import ExtendedBusParameterSet
from dpm.cia301 import ERROR_CONTROL_BASE
from dpm.commands import NMT_RESET_COMM, NMT_START, NMT_STOP
from dpm.commands import NMT_RESET_NODE as NMT_RESET
from dpm.errors import NodeEvent
from dpm.layout import CONN_STATUS
from dpm.task2 import GlobalBits
from firmware.can.node import NodeHandler, State

if TYPE_CHECKING:
    from firmware.card import Card

log = logging.getLogger("firmware.can.master")
"""The master's log, as before NMT had a module of its own."""


class Settings(Protocol):
    """The master's configuration as NMT reads it (seed 4.2 Auto_Clear, 4.4 extended)."""

    @property
    def auto_clear(self) -> bool: ...

    @property
    def global_start(self) -> bool: ...

    @property
    def ext(self) -> ExtendedBusParameterSet: ...


class NmtMaster:
    """The network's state over ``nodes`` (shared with the master, which configures them).

    ``send`` puts a frame on the bus (the master's ``bus_send``); ``zero_outputs`` drives
    every RX-PDO to zero once; ``sync_changed`` tells the SYNC producer to look again.
    """

    def __init__(self, card: Card, settings: Settings, nodes: dict[int, NodeHandler],
                 send: Callable[[int, bytes], bool], zero_outputs: Callable[[], None],
                 sync_changed: Callable[[], None]) -> None:
        self._card = card
        self._settings = settings
        self._nodes = nodes
        self._send = send
        self._zero_outputs = zero_outputs
        self._sync_changed = sync_changed
        self.running = False
        self.halted = False
        """Outputs zeroed and PDO traffic stopped: host not ready or watchdog expired."""
        self.cleared = False
        """Auto-clear end state: one lost node stopped all."""
        self._booting: set[int] = set()
        self._global_start_due = False
        self._last_conn = b""
        self._heartbeat_due = 0.0
        self._nexc_lock = threading.Lock()
        self._missing_at = 0
        """Where in the nodes the last NEXC look found one out of data exchange."""

    @property
    def exchanging(self) -> bool:
        """Running, neither halted nor cleared: PDOs and SYNC go out."""
        return self.running and not self.halted and not self.cleared

    def reset(self) -> None:
        """A card start: nothing runs, nothing boots."""
        self.running = self.halted = self.cleared = False
        self._booting.clear()
        self._last_conn = b""

    def start(self) -> None:
        """The bus parameters came: the network runs, unless the host holds it (seed 4.3)."""
        self.running = True
        self.cleared = False
        self.halted = not self._card.plc.image.driving
        self._card.set_global_bit(GlobalBits.ACLR, False)

    @property
    def nodes_stopped(self) -> bool:
        """Auto-clear or HOST_NOT_READY hold every node in STOPPED (seed 4.3, 39); the
        watchdog's halt (220) leaves them running."""
        return self.cleared or (self.halted and self._card.rcs.host_not_ready)

    def nmt(self, command: int, node: int) -> None:
        self._send(0x000, bytes([command, node]))

    def boot(self, handler: NodeHandler) -> None:
        if handler.state is State.INACTIVE:
            return
        if not self._conn_bit(handler.address):
            handler.disconnect()
            return
        self._booting.add(handler.address)
        handler.start_boot()

    # --- what the node handlers report (``NodeEvents``) -----------------------------------

    def node_booted(self, handler: NodeHandler) -> None:
        self._booting.discard(handler.address)
        if self.nodes_stopped:
            # Auto-clear or HOST_NOT_READY came first: they stop this node too (seed 4.3,
            # 39 "node in stop"). Their broadcast Stop went out before its boot-up ended;
            # the boot-up sends no Start_Node then (``BootLink.nodes_stopped``), but one
            # that came just before them did: it gets a Stop of its own, so the field device
            # does not run while the card reports it stopped.
            self.nmt(NMT_STOP, handler.address)
            self._stop_node(handler)
            self.update_nexc()
            return
        self._card.clear_error(handler.address)
        self.update_nexc()  # before Nd_state: a host that sees all nodes up sees NEXC clear
        self.set_node_state(handler.address, not handler.awaiting_start)
        if self._settings.global_start and not self._booting:
            self._global_start_due = True

    def node_failed(self, handler: NodeHandler, event: int) -> None:
        self._booting.discard(handler.address)
        self.set_node_state(handler.address, False)
        self.update_nexc()  # with Err_Event, not a supervision tick later
        self._card.report_error(handler.address, event)
        # Seed 5.2.5.4.1: auto-clear stops all "if one as active classified node has been
        # disconnected". [ours] A node that has not reached data exchange since the network
        # started it was never connected: its failed boot-up is reported and retried, as with
        # auto-clear off, and the others run on.
        if (self._settings.auto_clear and handler.connected and not self.cleared
                and self.running):
            self._auto_clear()
        elif self._settings.global_start and not self._booting:
            self._global_start_due = True

    def set_node_state(self, address: int, on: bool) -> None:
        self._card.set_node_bit("abNd_state", address, on)

    def set_node_diag(self, address: int, on: bool) -> None:
        self._card.set_node_bit("abNd_diag", address, on)

    # --- stopping -----------------------------------------------------------------------------

    def _auto_clear(self) -> None:
        """One lost node stops all: outputs to zero, every node stopped (seed 4.3 ACLR)."""
        log.warning("auto-clear: stopping all nodes")
        self._zero_outputs()
        self.cleared = True
        self._card.can_state_changed()
        self._sync_changed()  # an outside SYNC timer stops now, not at the next look
        self._stop_nodes()
        self._card.set_global_bit(GlobalBits.ACLR, True)

    def _stop_nodes(self) -> None:
        """Every node to STOPPED, with Err_Event 39 (seed 4.3: "node not handled, node in
        stop", after auto-clear or when the host is not ready)."""
        self.nmt(NMT_STOP, 0)
        for handler in list(self._nodes.values()):
            if handler.state is State.OPERATING:
                self._stop_node(handler)
        self.update_nexc()  # the master, which would, stops looking while the network is halted

    def _stop_node(self, handler: NodeHandler) -> None:
        handler.idle()
        handler.diag.actual_error = NodeEvent.NODE_STOPPED
        handler.note_diag()  # Actual_Error changed: Nd_diag (seed 4.3)
        self._card.report_error(handler.address, NodeEvent.NODE_STOPPED)

    # --- the host's commands ------------------------------------------------------------------

    def host_nmt(self, command: int, node: int) -> None:
        """COM_NMT_Module_Protocol: the host drives node states by hand."""
        targets = list(self._nodes.values()) if node == 0 else (
            [self._nodes[node]] if node in self._nodes else [])
        resetting = command in (NMT_RESET, NMT_RESET_COMM)
        for handler in targets:
            if resetting:
                if handler.state not in (State.INACTIVE, State.DISCONNECTED):
                    handler.start_boot(reset_sent=True)  # armed before the boot-up can come
            else:
                handler.expect_operational(command == NMT_START)
                if not handler.operational_expected:
                    self.set_node_state(handler.address, False)
        self.nmt(command, node)
        if command == NMT_START:
            now = time.monotonic()
            self._started([h for h in targets if h.start_sent(now, by_host=True)])

    def _started(self, handlers: list[NodeHandler]) -> None:
        """Nodes a start put into data exchange that report no state (``start_sent``):
        NEXC first, then their Nd_state, as after a boot-up."""
        if handlers:
            self.update_nexc()
        for handler in handlers:
            self.set_node_state(handler.address, True)

    # --- from the master's thread -------------------------------------------------------------

    @property
    def start_waits(self) -> bool:
        """A global Start_Node waits for the master's next look (``follow``)."""
        return self._global_start_due

    def follow(self, now: float) -> bool:
        """The global start and the connection bits; False while the network does not
        exchange data (halted or cleared), for the master to stop there."""
        if self.halted or self.cleared:
            return False
        if self._global_start_due:
            self._global_start_due = False
            self.nmt(NMT_START, 0)
            self._started([h for h in list(self._nodes.values())
                           if h.start_sent(now, by_host=False)])
        self._follow_connection_bits()
        return True

    def _conn_bit(self, address: int) -> bool:
        return bool(self._card.mm[CONN_STATUS + (address >> 3)] & (1 << (address & 7)))

    def connection_bits(self) -> bytes:
        """Task2Parameter's abConnStatus as the host left it: bit n = node n (seed 3)."""
        return self._card.mm[CONN_STATUS : CONN_STATUS + 16]

    def _follow_connection_bits(self) -> None:
        """Seed 3: a cleared bit stops the node, a set bit starts it again at once.

        The seed evaluates them "at least every millisecond"; here [ours] whenever the master
        looks, which a host's ring causes within a millisecond (docs/dpm.md 2: a host that
        never rings is seen at the device loop's next fallback poll).
        """
        conn = self.connection_bits()
        if conn == self._last_conn:
            return
        self._last_conn = conn
        for address, handler in list(self._nodes.items()):
            connected = bool(conn[address >> 3] & (1 << (address & 7)))
            if not connected and handler.state not in (State.DISCONNECTED, State.INACTIVE):
                handler.disconnect()
            elif connected and handler.state is State.DISCONNECTED:
                self.boot(handler)

    def follow_host(self) -> None:
        """HOST_NOT_READY or a watchdog expiry stop the bus and zero the outputs."""
        driving = self._card.plc.image.driving
        if not driving and not self.halted:
            log.info("host stopped: outputs to zero, PDO traffic stopped")
            self._zero_outputs()
            self.halted = True
            self._card.can_state_changed()
            self._sync_changed()
            if self._card.rcs.host_not_ready:  # HOST_NOT_READY, not the watchdog's 220
                self._stop_nodes()
        elif driving and self.halted and not self.cleared:
            self.halted = False
            self._card.can_state_changed()
            self._sync_changed()
            for handler in self._nodes.values():
                if handler.state in (State.WAITING, State.FAILED):
                    self.boot(handler)
                else:
                    handler.send_outputs(force=True)

    def update_nexc(self) -> None:
        """NEXC from every node's state; called by boot threads, the bus thread and the
        master's thread after every change of a node's state (``Master.reschedule``).

        Seed 4.3: "At least one node has not reached the data exchange state and no process
        data are exchanged with it": a node that waits for its start (START skipped) or that
        the host stopped counts, as does every node HOST_NOT_READY or auto-clear stopped.

        Under a lock: two boot threads finishing together could otherwise write
        their answers in the wrong order, the stale one last.
        """
        with self._nexc_lock:
            self._card.set_global_bit(GlobalBits.NEXC, self._node_missing())

    def _node_missing(self) -> bool:
        """Whether a node counts for NEXC, asked from where the last look found one: while
        a boot of 127 nodes changes their states some 250 times, that node stays out of
        data exchange until its own boot-up ends, and the next one missing mostly follows
        it. Asking every node up to the first one missing, from the first, cost such a
        boot some 15,000 questions (issue 22)."""
        handlers = list(self._nodes.values())
        at = self._missing_at if self._missing_at < len(handlers) else 0
        for index in itertools.chain(range(at, len(handlers)), range(at)):
            if _counts(handlers[index]):
                self._missing_at = index
                return True
        return False

    def heartbeat(self, now: float) -> float:
        """The master's own heartbeat, when it has a node-ID and a producer time (seed 4.4).

        Returns when the next one is due (inf: none is produced); a host that changes the
        producer time or the node-ID wakes the master (``Master.wake``).
        """
        ext = self._settings.ext
        period = ext.usProducerHeartbeatTime / 1000.0
        if not period or not ext.bNodeID:
            return math.inf
        if now >= self._heartbeat_due:
            self._heartbeat_due = now + period
            self._send(ERROR_CONTROL_BASE + ext.bNodeID, b"\x05")
        return self._heartbeat_due


def _counts(handler: NodeHandler) -> bool:
    """A node that NEXC counts (``NmtMaster.update_nexc``): active, not disconnected by
    the host, and not in data exchange."""
    return (handler.active and handler.state is not State.DISCONNECTED
            and not handler.exchanging)
