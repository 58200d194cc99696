"""The CANopen master: the network as a whole, its threads and its Task2State.

It owns the controller (``CanBus``), the node handlers and the configuration, and
composes the services, each in a module of its own with its frames and its state:
network management (``nmt``), the SYNC producer (``sync``), layer-2 access
(``layer2``), the SDO channels (``sdo``) and the PDO outputs (``pdo``). Its thread
evaluates the connection-status bits (seed 3), supervises the nodes and sends the
outputs that changed; it also counts the controller's error events into Task2State.

The thread sleeps until something is due, not for a fixed tick (issue 22): a wake from
the device loop when the host changed its connection bits or readiness (``notice_host``;
new outputs the device loop sends itself), a node's change of state (``reschedule``), or
the earliest deadline of what it times itself: supervision, boot retries, remote
requests, inhibit times, host SDO time-outs and the master's heartbeat. The heartbeat
consumers' deadlines, which every heartbeat moves later, are the receive thread's to keep
while it runs (``HeartbeatWatch``): it wakes the master when one came. A card nobody
uses costs (almost) nothing.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import can

from dbm_tools.parameters import (
    ACLR_ACTIVE,
    BAUD_RATES_KBIT,
    MOTOROLA,
    BusParameterSet,
    ExtendedBusParameterSet,
    ExtendedState,
    NodeParameterSet,
)
from dpm.cia301 import COB_ID_SYNC, ERROR_CONTROL_BASE, SDO_REQUEST_BASE, SDO_RESPONSE_BASE
from dpm.errors import ERR_NODE_DEVICE, DeviceEvent
from dpm.task2 import CanState, GlobalBits
from firmware.can.boot import BootSlots
from firmware.can.bus import (
    INTERFACE_ERRORS,
    LINK_CHECK_S,
    BusConfig,
    CanBus,
    ErrorEscalation,
)
from firmware.can.layer2 import Layer2
from firmware.can.nmt import NmtMaster
from firmware.can.node import NodeHandler
from firmware.can.pdo import FEW_NODES, OutputWatch, import_numpy_ahead, zero_outputs
from firmware.can.sdo import DEFAULT_SDO_TIMEOUT, SdoChannels
from firmware.can.supervision import HeartbeatWatch
from firmware.can.sync import SyncProducer
from firmware.can.workers import Workers
from firmware.frames import (
    CAN_ERR_ACK,
    CAN_ERR_BUSOFF,
    CAN_ERR_CRTL,
    CAN_ERR_CRTL_RX_OVERFLOW,
    CAN_ERR_TX_TIMEOUT,
)

if TYPE_CHECKING:
    from firmware.card import Card

log = logging.getLogger(__name__)


def _uses_sync(params: NodeParameterSet) -> bool:
    """An active node with a SYNC controlled PDO: the card sends SYNC for it (seed 4.2)."""
    return params.active and any(pdo.sync_controlled for pdo in params.atPdoCfgData)


class Master:
    def __init__(self, device: Card, config: BusConfig, publish: Callable[[], None]) -> None:
        self.device = device
        self.image = device.plc.image
        self.config = config
        self._publish = publish
        """Writes the card's facts beside the image (``firmware.card_info``) anew."""
        self.bus: CanBus | None = None
        self._escalation = ErrorEscalation()
        """Which error frames are a new overstep of the error limits (Bus_Error_Cnt)."""
        self.nodes: dict[int, NodeHandler] = {}
        self._sync_used = False
        """Whether a configured node has a SYNC controlled PDO (see ``sync_period``)."""
        self.bus_params: BusParameterSet | None = None
        self._ext = ExtendedBusParameterSet()
        self.workers = Workers()
        """Threads that wait: the 309 gateway's error-control writes, and a boot-up whose
        node's SDO channel another transfer holds (``NodeHandler.start_boot``)."""
        self.boot_slots = BootSlots()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._thread_id: int | None = None
        self._wakeup = threading.Event()
        """Set by ``wake``: the thread looks at once."""
        self._due_lock = threading.Lock()
        self._due = math.inf
        """When the thread looks next; inf while it is looking (``wake_at``)."""
        self._general = True
        """Set by ``reschedule()``: the next look supervises every node and recomputes NEXC."""
        self._changed: set[NodeHandler] = set()
        """Nodes whose state changed since the last look (``reschedule(handler)``, under
        ``_due_lock``): the next look supervises them, and the nodes whose deadline came."""
        self._dues: dict[NodeHandler, float] = {}
        """Each node's deadline (``NodeHandler.next_due``) as its last supervision left it."""
        self._timed_dues: dict[NodeHandler, float] = {}
        """The same without the heartbeat deadlines that the receive thread keeps."""
        self._supervise_due = 0.0
        self._timed_due = 0.0
        """The earliest of ``_timed_dues``: the master's own timer, while the receive thread
        keeps the heartbeat deadlines (``CanBus.receiving``)."""
        self._deadline_came = False
        """Set by ``deadline_came`` (under ``_due_lock``): the next look supervises every node."""
        self._verdict_ready = False
        """Set by ``_frames_taken`` (under ``_due_lock``): the frames the controller had
        received when a node was found late are taken; the next supervision judges."""
        self.heartbeats = HeartbeatWatch()
        """The heartbeat consumers' deadlines, kept by the controller's receive thread."""
        self._link_due = 0.0
        self._host_outputs = b""
        self._host_state: tuple[bytes, bool] | None = None
        """The outputs, and the connection bits and readiness, at the device loop's last turn."""
        self.outputs = OutputWatch()
        self._outputs_lock = threading.RLock()
        """``outputs`` is followed by the device loop (a host's change) and this thread; a
        node's first RX-PDOs go under it too (``outputs_lock``). Reentrant: a frame sent
        under it may be handled in the sending thread (firmware.inline)."""
        self.sdo = SdoChannels(self.wake_at)
        self.layer2 = Layer2(device, lambda: self.ext)
        self.nmt = NmtMaster(device, self, self.nodes, self.bus_send,
                             lambda: zero_outputs(self.image, self.nodes), self._sync_changed)
        self.sync = SyncProducer(self._stop, lambda: self.sync_cob_id, lambda: self.sync_period,
                                 self._sync_active, self._foreign_sync, self._on_sync)

    # --- life cycle ---------------------------------------------------------------------

    def open(self) -> None:
        """Connect the controller to the bus (once, at power-on)."""
        cfg = self.config
        self.bus = CanBus(cfg.interface, cfg.channel, cfg.bitrate, cfg.trace, cfg.tap,
                          cfg.options)
        self.bus.on_error_frame = self._on_error_frame
        self.bus.on_send_timeout = self._on_send_timeout
        self.bus.on_link_back = lambda: self._send_all_outputs(force=True)
        self.bus.deadlines = self.heartbeats
        self.bus.on_deadline = self.deadline_came
        self.bus.lingering = self.boot_slots.busy
        self.bus.subscribe_all(self.layer2.on_frame)
        self.sdo.open(self.bus)
        self._thread = threading.Thread(target=self._loop, name="can-master", daemon=True)
        self._thread.start()
        self.sync.start(self.bus)

    @property
    def closing(self) -> bool:
        return self._stop.is_set()

    def close(self) -> None:
        """Power off: the threads end, the worker jobs under way too (within
        ``WORKERS_JOIN_S``), before the controller leaves the bus; the card unmaps its image
        after this returns."""
        self._stop.set()
        self.sdo.close()
        self._wakeup.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        self.sync.join(timeout=2)
        self.workers.shutdown()
        if self.bus is not None:
            self.bus.shutdown()

    def reset(self) -> None:
        """A card start: the on-line configuration is gone."""
        for handler in self.nodes.values():
            handler.idle()
            handler.detach()
        self.nodes.clear()
        self._sync_used = False
        self.outputs.nodes_changed()
        self.bus_params = None
        self._ext = ExtendedBusParameterSet()
        self.nmt.reset()
        self.sync.wake()
        self.layer2.reset()
        self.sdo.set_timeout(0, DEFAULT_SDO_TIMEOUT)
        self.reschedule()

    # --- configuration ------------------------------------------------------------------------

    @property
    def ext(self) -> ExtendedBusParameterSet:
        """The extended bus parameters (seed 4.4): the master's node-ID and heartbeat."""
        return self._ext

    @ext.setter
    def ext(self, ext: ExtendedBusParameterSet) -> None:
        self._ext = ext
        self.wake()  # the master's heartbeat may start, stop or change its period

    @property
    def sync_cob_id(self) -> int:
        return self.bus_params.COB_ID_SYNC if self.bus_params else COB_ID_SYNC

    @property
    def sync_period(self) -> float:
        """SYNC_Timer in seconds; 0 (no SYNC) while no node has a SYNC controlled PDO.

        Seed 4.2 (node parameters, bTransType): "The SYNC mechanism will be activated only if
        at least one node uses SYNC controlled transmission types."
        """
        if not self.bus_params or not self._sync_used:
            return 0.0
        return self.bus_params.SYNC_Timer / 1000.0

    def _foreign_sync(self) -> bool:
        """SYNC_Timer 0 while a node has a SYNC controlled PDO: another station's SYNC
        drives them (seed revision 16)."""
        return bool(self.bus_params and self._sync_used and self.bus_params.SYNC_Timer == 0)

    @property
    def motorola(self) -> bool:
        return bool(self.bus_params and self.bus_params.Intel_Motorola == MOTOROLA)

    @property
    def outputs_lock(self) -> threading.RLock:
        """``Network.outputs_lock``: the lock the host's outputs are followed under."""
        return self._outputs_lock

    @property
    def auto_clear(self) -> bool:
        return bool(self.bus_params and self.bus_params.Auto_Clear == ACLR_ACTIVE)

    @property
    def nodes_stopped(self) -> bool:
        return self.nmt.nodes_stopped

    @property
    def global_start(self) -> bool:
        return bool(self.ext.bExtendedState & ExtendedState.biNoGobalStartNode.value)

    def configure_node(self, address: int, params: NodeParameterSet) -> None:
        old = self.nodes.pop(address, None)
        if old is not None:
            old.idle()
            old.detach()
        handler = NodeHandler(self, self.nmt, address, params)
        self.nodes[address] = handler
        self.outputs.nodes_changed()
        if len(self.nodes) > FEW_NODES:  # a smaller network compares without numpy
            import_numpy_ahead()
        # A new node can only add SYNC use; a replaced one may take it away. Asking every
        # node each time made a stored database of 127 nodes cost 127² questions at a start.
        sync_used = (_uses_sync(params) or self._sync_used) if old is None else any(
            _uses_sync(h.params) for h in self.nodes.values())
        sync_changed = sync_used != self._sync_used
        if sync_changed:
            self._sync_used = sync_used
            self.sync.wake()  # only SYNC use decides it here (``sync_period``)
        self.device.set_node_bit("abNd_cfg", address, params.active)
        self.device.set_node_bit("abNd_diag", address, False)
        if self.nmt.running:
            handler.attach()
            self.nmt.boot(handler)
            # Else nothing to look at: ``start_network`` reschedules. A change of SYNC use
            # moves every node's deadline of its 252 remote requests (``NodePdos.next_due``),
            # which only a look at every node notes.
            self.reschedule(None if sync_changed else handler)

    def start_network(self, params: BusParameterSet) -> None:
        """The bus parameter download: (re)start the whole network."""
        restart = self.nmt.running
        self.bus_params = params
        self._apply_baud_rate(BAUD_RATES_KBIT[params.Baud_rate] * 1000)
        with self._outputs_lock:
            self.outputs.restart(self.image.snapshot_outputs())
        self.nmt.start()
        self.sync.retry_now()  # a new configuration tries the SYNC timer at once
        self.sync.wake()
        for handler in self.nodes.values():
            if restart:
                handler.detach()
            handler.attach()
            if not self.nmt.halted:
                self.nmt.boot(handler)
        self.reschedule()

    def _apply_baud_rate(self, bitrate: int) -> None:
        """Seed 5.2.5.4: Baud_rate fixes the bus's rate. The controller takes it where the
        interface lets the card set one (``CanBus.takes_bitrate``); a rate the interface
        cannot run is [ours] the seed's device Err_Event 56, "baudrate out of range", and the
        controller keeps its rate. What runs goes to the card's facts (``cifemu status``)."""
        bus = self.bus
        if bus is not None and bus.takes_bitrate and bus.bitrate != bitrate:
            try:
                bus.set_bitrate(bitrate)
                log.info("controller at %d bit/s (Baud_rate)", bitrate)
            except INTERFACE_ERRORS as exc:
                log.error("the controller cannot run at %d bit/s: %s", bitrate, exc)
                self.device.report_error(ERR_NODE_DEVICE, DeviceEvent.BAUD_RATE, GlobalBits.CTRL)
        self._publish()

    def cob_id_in_use(self, cob_id: int) -> bool:
        """Whether the CANopen side already listens to or sends ``cob_id``."""
        if cob_id in (0, self.sync_cob_id):
            return True
        for address, handler in self.nodes.items():
            params = handler.params
            used = {SDO_RESPONSE_BASE + address, SDO_REQUEST_BASE + address,
                    ERROR_CONTROL_BASE + address, params.usCobIDEmcy,
                    params.usCobIDGuard, *(p.usPdoCOBId for p in params.atPdoCfgData)}
            if cob_id in used:
                return True
        return False

    # --- state seen by the device ------------------------------------------------------------

    def can_state(self) -> CanState:
        nmt = self.nmt
        if not nmt.running:
            return CanState.OFFLINE
        if nmt.cleared:
            return CanState.CLEAR
        if nmt.halted:
            return CanState.STOP
        return CanState.OPERATE

    # --- sending -------------------------------------------------------------------------------

    def bus_send_raw(self, ident: int, data: bytes, remote: bool, extended: bool,
                     dlc: int) -> bool:
        """A frame exactly as the host described it (transparent and layer-2 access)."""
        if self.bus is None:
            return False
        return self.bus.send(ident, data, remote=remote, extended=extended, dlc=dlc)

    def bus_send(self, can_id: int, data: bytes = b"", remote: bool = False,
                 dlc: int | None = None) -> bool:
        if self.bus is None:
            return False
        return self.bus.send(can_id, data, remote=remote, dlc=dlc)

    def send_nmt(self, command: int, node: int) -> None:
        """An NMT command to ``node`` (0: all); see ``NmtMaster.nmt``."""
        self.nmt.nmt(command, node)

    # --- the master's thread: asleep until something is due ---------------------------------

    def wake(self) -> None:
        """Look at once (any thread): something the thread follows may have changed."""
        self._wakeup.set()

    def wake_at(self, when: float) -> None:
        """Look no later than ``when`` (monotonic seconds; any thread): a new deadline."""
        with self._due_lock:
            if when < self._due:
                self._due = when
                self._wakeup.set()

    def deadline_came(self) -> None:
        """A heartbeat consumer's deadline came (the receive thread), or the receive thread
        stopped keeping them (a lost link): supervise every node at once, as at a deadline
        of the master's own."""
        with self._due_lock:
            self._deadline_came = True
        self._wakeup.set()

    def reschedule(self, handler: NodeHandler | None = None) -> None:
        """A node changed state (any thread): look at once, supervise ``handler`` (None:
        every node), recompute its deadlines and NEXC.

        Only the changed node: a boot of 127 nodes changes states some 250-400 times, and
        supervising every node each time was a quadratic 127 deadlines per change (issue 22).
        """
        if handler is None:
            self._general = True
        else:
            with self._due_lock:
                self._changed.add(handler)
        self._wakeup.set()

    def operating(self, handler: NodeHandler) -> None:
        """``handler``'s boot-up ended in data exchange (the receive thread): the master takes
        its deadlines at its next look, which comes no later than the node's first one, and
        at once only when a global start waits for that look.

        A boot of 127 nodes woke the master once per node for this: a look (SDO time-outs,
        the node's tick, NEXC again, the outputs) of about 100 us, and the receive thread's
        ``Event.set`` and NEXC lock handed the interpreter to it in the middle of the boot's
        frames (issue 22). The node's outputs, its first remote requests, NEXC and Nd_state
        went out in ``_operate`` already; what the look adds is its supervision, whose first
        deadline (``next_due(timed=True)``) is what ``wake_at`` is asked to meet."""
        with self._due_lock:
            self._changed.add(handler)
        if self.nmt.start_waits:
            self._wakeup.set()
        else:
            self.wake_at(handler.next_due(timed=True))

    def host_seen(self) -> tuple[bytes, bytes] | None:
        """The outputs and connection bits ``notice_host`` saw last (None before its first
        look): a turn that finds the image's the same has nothing to tell this thread (the
        device loop's turn in C, ``firmware.native_mailbox``, compares them)."""
        if self._host_state is None:
            return None
        return self._host_outputs, self._host_state[0]

    def notice_host(self) -> bool:
        """From the device loop after each turn: follow what the host changed since the last
        turn. True when it changed something, so that the loop's fallback poll counts it
        as activity.

        The device loop is the one that notices what a host writes: a host that rings
        wakes it at once, one that never rings at its next fallback poll (``AdaptivePoll``).
        New outputs alone are sent from the calling thread: waking this one for them would
        cost a thread switch per change, as much as the send itself. New connection bits or
        a change of the host's readiness (NOTREADY, watchdog) wake this thread, which
        follows them before any output. Comparing costs a copy of the output area per turn.
        """
        image = self.image
        outputs = image.snapshot_outputs()
        state = (self.nmt.connection_bits(), image.driving)
        if state != self._host_state:
            self._host_state = state
            self._host_outputs = outputs
            self._wakeup.set()
            return True
        if outputs == self._host_outputs:
            return False
        self._host_outputs = outputs
        if self.nmt.exchanging and image.driving:
            self._follow_outputs(outputs, time.monotonic(), False)
        return True

    def _follow_outputs(self, outputs: bytes, now: float, every: bool) -> float:
        """Send what ``outputs`` changed (``OutputWatch.follow``); when to look again."""
        with self._outputs_lock:
            due = self.outputs.follow(outputs, self.nodes, now, every)
        if threading.get_ident() != self._thread_id:
            self.wake_at(due)  # a PDO waits for its inhibit time
        return due

    def _loop(self) -> None:
        self._thread_id = threading.get_ident()
        timeout: float | None = None
        while True:
            self._wakeup.wait(timeout)
            if self._stop.is_set():
                return
            self._wakeup.clear()  # before looking: a wake from now on makes another look
            with self._due_lock:
                self._due = math.inf
            general, self._general = self._general, False
            now = time.monotonic()
            try:
                due = self._look(now, general)
            except Exception:
                log.exception("the CAN master failed to look")
                due = now + 1.0  # [ours] and again in a second, whatever failed
            with self._due_lock:
                self._due = due = min(due, self._due)
            timeout = None if math.isinf(due) else max(0.0, due - time.monotonic())

    def _look(self, now: float, general: bool) -> float:
        """One look: what is due now, and when the next look is due (inf: on a wake only).

        ``general``: the network changed since the last look (a start, a new node set), so
        every node is supervised now and their deadlines and NEXC computed again, as when
        the earliest deadline came; else only the nodes that changed state
        (``reschedule(handler)``).
        """
        return min(self._check_link(now), self._look_at_network(now, general))

    def _check_link(self, now: float) -> float:
        """A bridge whose closed connection its client hides is looked at every
        ``LINK_CHECK_S``, configured or not (``CanBus.check_link``); other buses cost no
        look."""
        bus = self.bus
        if bus is None or not bus.watches_link:
            return math.inf
        if now >= self._link_due:
            self._link_due = now + LINK_CHECK_S
            bus.check_link()
        return self._link_due

    def _look_at_network(self, now: float, general: bool) -> float:
        nmt = self.nmt
        if not nmt.running:
            return math.inf
        nmt.follow_host()
        due = self.sdo.check(now)
        if not nmt.follow(now):
            self._general |= general  # halted: every node again once it runs (changed wait)
            return due
        with self._due_lock:
            changed, self._changed = self._changed, set()
            came, self._deadline_came = self._deadline_came, False
        every = general or came or now >= self._supervise_due
        if every or changed:
            self._supervise(now, every, changed)
        outputs = self._follow_outputs(self.image.snapshot_outputs(), now,
                                       general or bool(changed))
        bus = self.bus
        supervise_due = (self._timed_due if bus is not None and bus.receiving
                         else self._supervise_due)
        return min(due, supervise_due, outputs, nmt.heartbeat(now))

    def _supervise(self, now: float, every: bool, changed: set[NodeHandler]) -> None:
        """Tick every node when ``every`` (the network changed, the earliest deadline came),
        else only the ``changed`` ones still configured; then their deadlines and NEXC anew.

        A deadline that came ticks every node, as before: frames push the others' deadlines
        back without a word (``NodeHandler.next_due``), and asking all of them at once
        keeps an idle network's wakes at one per real deadline, not one per stale one.
        """
        nodes = self.nodes
        handlers = list(nodes.values()) if every else sorted(
            (h for h in changed if nodes.get(h.address) is h), key=lambda h: h.address)
        if self._verdict_waits(now, handlers):
            return
        for handler in handlers:
            handler.tick(now)
        self.nmt.update_nexc()
        if every:
            self._dues = {h: h.next_due() for h in handlers}
            self._timed_dues = {h: h.next_due(timed=True) for h in handlers}
        else:
            for handler in changed:
                if nodes.get(handler.address) is handler:
                    self._dues[handler] = handler.next_due()
                    self._timed_dues[handler] = handler.next_due(timed=True)
                else:
                    self._dues.pop(handler, None)
                    self._timed_dues.pop(handler, None)
        self._supervise_due = min(self._dues.values(), default=math.inf)
        self._timed_due = min(self._timed_dues.values(), default=math.inf)

    def _verdict_waits(self, now: float, handlers: list[NodeHandler]) -> bool:
        """[ours] A node found late by its guarding or heartbeat is failed only after the
        frames the controller has received by now are taken: True while they are.

        Why: the receive thread can fall behind the bus (a loaded machine, a guest's one CPU
        under User-Mode Linux: SYNCs read 0.5-4.5 s after the kernel stamped them), and the
        master judged a node by the frames taken so far, so an answer that had come in time
        and waited unread failed the node. The controller's receive thread takes every frame
        it has by then and wakes the master again (``CanBus.take_then``); the wait costs one
        hand-over only when a node is late. Without a receive thread (a lost link reopening)
        there is nothing to wait for.
        """
        with self._due_lock:
            ready, self._verdict_ready = self._verdict_ready, False
        bus = self.bus
        if ready or bus is None or not bus.receiving or not any(
                handler.overdue(now) for handler in handlers):
            return False
        self._supervise_due = self._timed_due = math.inf  # until the frames are taken
        bus.take_then(self._frames_taken)
        return True

    def _frames_taken(self) -> None:
        """The receive thread took the frames it had (``_verdict_waits``): judge now."""
        with self._due_lock:
            self._verdict_ready = True
            self._deadline_came = True
        self._wakeup.set()

    def _sync_active(self) -> bool:
        """SYNC goes out while the network exchanges data and the controller is on the bus
        (an outside SYNC timer would go on sending through a bus-off, firmware/faults.py)."""
        return self.nmt.exchanging and not (self.bus is not None and self.bus.off_bus)

    def set_bus_off(self, off: bool) -> None:
        """[ours] The fault "bus-off" (``CanBus.set_bus_off``); SYNC follows at once."""
        if self.bus is not None:
            self.bus.set_bus_off(off)
            self.sync.wake()
            if not off:
                self._send_all_outputs(force=False)  # what the host wrote meanwhile goes out

    def _send_all_outputs(self, force: bool) -> None:
        """Every running node's outputs at the next look, which comes at once
        (``OutputWatch.ask_everyone``): the controller was off the bus or its link lost."""
        self.outputs.ask_everyone(force)
        self.wake()

    def _sync_changed(self) -> None:
        self.sync.wake()

    def _on_sync(self, now: float) -> None:
        for handler in list(self.nodes.values()):
            handler.on_sync(now)

    # --- the controller's error events ---------------------------------------------------------

    def _on_error_frame(self, msg: can.Message) -> None:
        """Error frames in SocketCAN's layout: the class bits are in the identifier."""
        overstep = self._escalation.update(msg)
        error_class = msg.arbitration_id
        if error_class & (CAN_ERR_TX_TIMEOUT | CAN_ERR_ACK):
            self._on_send_timeout()
            return
        if (error_class & CAN_ERR_CRTL and len(msg.data) > 1
                and msg.data[1] & CAN_ERR_CRTL_RX_OVERFLOW):
            # The controller's receive FIFO overflowed: frames the firmware lost.
            lost = self.bus.take_rx_overflows() if self.bus is not None else 1
            self.device.count("usRx_Overflow", lost)
            return
        if error_class & CAN_ERR_BUSOFF:
            self.device.count("usBus_Off_Cnt", bit=GlobalBits.EVE)
        elif overstep:
            # Seed 4.3: Bus_Error_Cnt counts the oversteps of the controller's error limits,
            # not each error frame (a protocol error alone is no event; bus.ErrorEscalation).
            self.device.count("usBus_Error_Cnt", bit=GlobalBits.EVE)

    def _on_send_timeout(self) -> None:
        self.device.count("usMsg_Time_Out", bit=GlobalBits.TOUT)
