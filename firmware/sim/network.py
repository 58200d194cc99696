"""The simulated nodes of a network description, live on one python-can bus.

One ``canopen.Network`` over the given bus carries every node; its notifier
thread delivers frames to the nodes (on ``virtual``, the card's host SDO
requests may be handled by the card's thread instead: ``_NodeNotifier``), a
``Scheduler`` thread runs their timers, and one lock serialises both. The
bus belongs to the caller: it is neither opened nor shut down here.

A python-can bus object hears only other bus objects, never its own frames,
and feeds a single ``can.Notifier``. So a master in the same process needs
its own bus object on the same channel (for ``virtual``, the same channel
name); it cannot share the one given here.

Every live device is also a CiA 305 LSS slave (``firmware.sim.lss``): a node
with ``id = 255`` and an ``lss`` address is silent but for LSS until a master
gives it a node-ID, then boots up as a node of its own (its ``eds``, else the
generic I/O module); a configured node can be given another node-ID. No key
of the network description is needed for that.
"""

from __future__ import annotations

import logging
import queue
import threading
from dataclasses import dataclass
from types import TracebackType

import can
import canopen
from can.interfaces.virtual import VirtualBus
from canopen.objectdictionary import ObjectDictionary

from dbm_tools.eds import import_od
from dbm_tools.network import (
    BusDescription,
    Network,
    NetworkError,
    NodeDescription,
)
from dpm.cia305 import UNCONFIGURED, LssAddress
from firmware.inline import CopyingVirtualBus, InlineQueue
from firmware.sim.generic import generic_object_dictionary
from firmware.sim.lss import LssBus
from firmware.sim.node import SimulatedNode
from firmware.sim.scheduler import Scheduler

log = logging.getLogger(__name__)

NOTIFIER_CYCLE_S = 0.1
"""How long a stopping network waits at most for its receive thread."""
POWER_ON_WAIT_S = 10.0
"""[ours] How long ``start`` waits at most for the nodes' power-on: their boot-up messages
and heartbeat producers (a boot delay of the node's ``[node.sim]`` is not waited for)."""


def object_dictionary(node: NodeDescription, bus: BusDescription) -> ObjectDictionary:
    """The node's EDS/DCF when it names one, else the built-in generic I/O module."""
    if node.eds is None:
        return generic_object_dictionary(node, bus.sync_cob_id)
    try:
        return import_od(node.eds, node.id)  # type: ignore[no-any-return]
    except Exception as exc:  # canopen's parser lets any error of a bad file through
        raise NetworkError(f"node {node.id}: cannot load {node.eds}: {exc!r}") from exc


@dataclass
class UnconfiguredSlave:
    """A node without node-ID (255): present, silent until LSS configures it."""

    description: NodeDescription

    @property
    def address(self) -> LssAddress:
        assert self.description.lss is not None  # load_network demands it for id 255
        return self.description.lss


class _NodeFrames(can.Listener):
    """The nodes' one listener: canopen's network for data frames, and the remote frames
    that canopen drops before its subscribers (guarding and RTR PDOs need them).

    In place of canopen's ``MessageListener`` and a listener of remote frames beside it:
    one call per frame to the nodes, where those two and canopen's ``notify`` were three,
    for every frame the nodes take (a host SDO request in the card's device loop among
    them, issue 22). What reaches the subscribers is canopen's: every subscriber of the
    identifier with the frame's data and time stamp, then the network's node scanner; an
    exception of a subscriber is logged, as canopen's listener logs it, not raised into
    the sender."""

    def __init__(self, network: canopen.Network, nodes: list[SimulatedNode]) -> None:
        self._subscribers = network.subscribers
        self._scanner = network.scanner
        self._nodes = nodes

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_remote_frame:
            for node in self._nodes:
                node.on_remote(msg.arbitration_id)
            return
        if msg.is_error_frame:
            return
        can_id = msg.arbitration_id
        try:
            callbacks = self._subscribers.get(can_id)
            if callbacks:
                data, timestamp = msg.data, msg.timestamp
                for callback in callbacks:
                    callback(can_id, data, timestamp)
            self._scanner.on_message_received(can_id)
        except Exception as exc:
            log.error("simulated node failed on frame 0x%X: %s", can_id, exc)


class _Sending(threading.local):
    """Per thread: whether it is inside a node's send (``_NodesNetwork.send_message``).

    The only way into ``_NodeNotifier.try_dispatch`` for a thread that runs node code (and
    holds the network's lock) is a frame its node sends, which a station handles in the
    sending thread (the card's controller, then a host SDO request ``answered_here``).
    This record says so with an attribute read: RLock's owner test is private
    (``_is_owned``), and a lock that kept a record of its owner would cost every node entry
    point's ``with`` two Python calls."""

    active = False


_sending = _Sending()


class _NodesNetwork(canopen.Network):
    """canopen's network of the nodes, with ``send_message`` as canopen's less its calls.

    canopen lets a subclass replace ``send_message`` for a backend of its own. This one
    makes the frame and sends it under the network's send lock as canopen's does, and
    looks at the notifier's failure itself instead of calling ``check``: a node's answer
    to the card's host SDO request is sent from the card's device loop (``_NodeNotifier``),
    where every call counts (issue 22)."""

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        bus = self.bus
        if bus is None:
            raise RuntimeError("the simulated nodes' network has no bus")
        frame = can.Message(arbitration_id=can_id, is_extended_id=can_id > 0x7FF,
                            is_remote_frame=remote, data=data)
        with self.send_lock:
            _sending.active = True
            try:
                bus.send(frame)
            finally:
                _sending.active = False
        notifier = self.notifier
        if notifier is not None and notifier.exception is not None:
            self.check()  # canopen's report of a receive thread that failed: it raises


class _NodeNotifier(can.Notifier):
    """The nodes' receive thread (python-can's ``Notifier``, as canopen's ``connect`` makes
    it), whose frames may also be handled by their sender's thread (``InlineQueue``).

    On ``virtual`` the nodes handle a frame sent inside ``firmware.inline.answered_here``
    (the card's host SDO requests, with ``--simulate`` in the card's process) in the
    sender's thread when this thread is idle: an expedited host SDO then crosses the card's
    device loop alone, request, node and answer (issue 22). Every other frame waits for
    this thread as before. The sender runs the handlers only when it can take, without
    waiting, the notifier's lock (held while this thread handles a frame) and the network's
    lock (held by the timers and the nodes' entry points), and is not inside a node's send
    (``_Sending``, where it holds the network's lock already): a node's own thread that
    sends (its timers) never runs node code inside node code, and a card thread never waits
    for a node's.
    """

    def __init__(self, bus: can.BusABC, listeners: list[can.Listener], timeout: float,
                 lock: threading.RLock) -> None:
        self._network_lock = lock
        self._ready = False
        """Set once ``Notifier.__init__`` has made the lock that ``try_dispatch`` takes: the
        queue takes frames for it from the moment it is installed, before the thread runs."""
        self._inline: InlineQueue | None = None
        station = getattr(bus, "queue", None)
        if (isinstance(bus, VirtualBus)
                and isinstance(station, queue.Queue) and not bus.receive_own_messages):
            self._inline = InlineQueue.install(station, self, asked_only=True)
        CopyingVirtualBus.install(bus)  # the nodes' frames copied without ``copy.deepcopy``
        self._receivers = tuple(listener.on_message_received for listener in listeners)
        """Each listener's ``on_message_received``, called as python-can's ``Notifier`` calls
        the listener, without its ``__call__`` and its look for a coroutine: three Python
        calls fewer per frame, a host SDO request among them (issue 22). The nodes'
        listeners are fixed: ``add_listener`` and ``remove_listener`` refuse. Set before
        ``Notifier.__init__``, which starts the thread that reads it: a frame already queued
        (the card's NMT at a node's start) is handled at once."""
        super().__init__(bus, listeners, timeout)
        self._ready = True

    def add_listener(self, listener: can.notifier.MessageRecipient) -> None:
        raise NotImplementedError("the simulated nodes' listeners are fixed at the start")

    def remove_listener(self, listener: can.notifier.MessageRecipient) -> None:
        raise NotImplementedError("the simulated nodes' listeners are fixed at the start")

    def _on_message_received(self, msg: can.Message) -> None:
        """This thread's handling (after ``recv`` took ``msg`` from the queue)."""
        try:
            for receive in self._receivers:
                receive(msg)
        finally:
            if self._inline is not None:
                self._inline.dispatched()

    def try_dispatch(self, msg: can.Message) -> bool:
        if (not self._ready or self._stopped or _sending.active
                or not self._lock.acquire(blocking=False)):
            return False
        lock = self._network_lock
        try:
            if not lock.acquire(blocking=False):
                return False
            try:
                for receive in self._receivers:
                    receive(msg)
            except Exception:  # the sender's send must not fail for a node's fault
                log.exception("simulated node failed on frame 0x%X", msg.arbitration_id)
            finally:
                lock.release()
        finally:
            self._lock.release()
        return True


class SimulatedNetwork:
    """Every node of ``network`` as a simulated CiA 301 device on ``bus``.

    ``start`` powers all nodes on (each sends its boot-up after its boot
    delay), ``stop`` powers them off; also a context manager. Silent nodes
    exist in ``nodes`` but never touch the bus.

    ``start`` returns once every node without a boot delay has booted (boot-up sent,
    heartbeat producer running) **[ours]**: before, it returned when the boot-ups were
    only queued, and the power-on of 127 nodes (about 0.15 s and 110 ms of the simulator's
    CPU: 127 boot-ups and 127 heartbeat threads started) ran on into the first thing a
    master asked of them, the first boot of ``bench.can``'s boot phase among them.
    """

    def __init__(self, network: Network, bus: can.BusABC) -> None:
        self.description = network
        self.bus = bus
        self.lock = threading.RLock()
        self.scheduler = Scheduler(self.lock)
        self.nodes: dict[int, SimulatedNode] = {}
        unconfigured: list[NodeDescription] = []
        for node in network.nodes:
            if node.id == UNCONFIGURED:
                unconfigured.append(node)
            else:
                self.nodes[node.id] = SimulatedNode(
                    node, object_dictionary(node, network.bus), self.scheduler, self.lock)
        self.canopen = _NodesNetwork(bus)
        self._live = [node for node in self.nodes.values() if not node.description.sim.silent]
        self.lss = LssBus(self, self._live, unconfigured)
        self.running = False

    @property
    def unconfigured(self) -> list[UnconfiguredSlave]:
        """The devices without node-ID now (LSS may have configured some of the file's)."""
        return [UnconfiguredSlave(node) for node in self.lss.unconfigured()]

    def add_node(self, description: NodeDescription) -> SimulatedNode:
        """A device that got its node-ID by LSS: created, and powered on if the network runs."""
        node = SimulatedNode(description, object_dictionary(description, self.description.bus),
                             self.scheduler, self.lock)
        self.nodes[node.node_id] = node
        self._live.append(node)
        if self.running:
            self.canopen.add_node(node)
            node.power_on()
        return node

    def remove_node(self, node: SimulatedNode) -> None:
        """A device that leaves its node-ID (LSS): powered off and detached if running."""
        self._live.remove(node)
        del self.nodes[node.node_id]
        if self.running:
            node.power_off()
            del self.canopen[node.node_id]

    def start(self) -> None:
        for node in self._live:
            self.canopen.add_node(node)
        try:  # canopen's ``connect`` with a notifier of its own (``_NodeNotifier``)
            self.canopen.notifier = _NodeNotifier(
                self.bus, [_NodeFrames(self.canopen, self._live)],
                NOTIFIER_CYCLE_S, self.lock)
        except ValueError as exc:
            raise ValueError(f"{exc}: give the simulation its own bus object on the channel, "
                             "not the master's") from exc
        self.scheduler.start()
        with self.lock:
            for node in self._live:
                node.power_on()
        self.running = True
        if not self.scheduler.settle(POWER_ON_WAIT_S):
            log.warning("the nodes' power-on took more than %g s", POWER_ON_WAIT_S)
        log.info("simulating %d node(s) on %s", len(self._live), self.bus.channel_info)

    def stop(self) -> None:
        if not self.running:
            return
        self.running = False
        self.scheduler.stop()
        with self.lock:
            for node in self._live:
                node.power_off()
        if self.canopen.notifier is not None:
            self.canopen.notifier.stop(self.canopen.NOTIFIER_SHUTDOWN_TIMEOUT)
        for node in self._live:
            del self.canopen[node.node_id]
        self.lss.power_cycle()  # the next start is a power-on: stored LSS configuration

    def __enter__(self) -> SimulatedNetwork:
        self.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.stop()
