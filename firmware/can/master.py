"""The CANopen master: the network as a whole, its threads and its Task2State.

It owns the controller (``CanBus``), the node handlers, the SYNC producer,
the master's own heartbeat, layer-2 access and the 1-ms tick that evaluates
the connection-status bits (seed 3) and supervises the nodes.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import can
import numpy as np
import numpy.typing as npt
from can.broadcastmanager import CyclicSendTaskABC
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo.client import SdoClient

from dbm_tools.parameters import (
    ACLR_ACTIVE,
    BAUD_RATES_KBIT,
    MOTOROLA,
    BusParameterSet,
    ExtendedBusParameterSet,
    ExtendedState,
    NodeParameterSet,
)
from dpm.com import (
    CanFrame,
    encode_bootup_indication,
    encode_layer2_frame,
    encode_transparent_2b,
)
from dpm.commands import (
    COM_BOOTUP_INDICATION,
    COM_RECEIVE_TRANSPARENT,
    COM_RX_CAN_LAYER2,
    NMT_RESET_COMM,
    NMT_START,
    NMT_STOP,
)
from dpm.commands import NMT_RESET_NODE as NMT_RESET
from dpm.errors import ERR_NODE_DEVICE, DeviceEvent
from dpm.layout import CONN_STATUS, IO_AREA_SIZE
from dpm.message import Message, Task
from dpm.task2 import CanState, GlobalBits
from firmware.can.bus import INTERFACE_ERRORS, PERIODIC_OUTSIDE_INTERFACES, BusConfig, CanBus
from firmware.can.node import NODE_STOPPED, NodeHandler, State
from firmware.can.sdo import HostSdoTransfer
from firmware.frames import (
    CAN_ERR_ACK,
    CAN_ERR_BUSOFF,
    CAN_ERR_CRTL,
    CAN_ERR_CRTL_LIMITS,
    CAN_ERR_CRTL_RX_OVERFLOW,
    CAN_ERR_TX_TIMEOUT,
)

if TYPE_CHECKING:
    from firmware.card import Card

log = logging.getLogger(__name__)

TICK = 0.001
"""The connection bits are evaluated at least every millisecond (seed 3)."""
SUPERVISION_PERIOD = 0.005
"""[ours] heartbeat and guarding deadlines are checked every 5 ms."""
SYNC_RETRY_MAX_S = 5.0
"""[ours] the longest pause between tries to start an outside SYNC timer that fails."""
QUEUE_LIMIT = 150
"""Layer-2 frames the card holds for the host (seed 5.3.2.2)."""
INDICATION_LIMIT = 254
DEFAULT_SDO_TIMEOUT = 0.5
"""[ours] seconds an SDO request waits for its answer until COM_Set_SDO_Timeout; canopen's
0.3 s lets a busy 2-core machine abort boot-ups that would have succeeded."""


@dataclass
class SdoChannel:
    """A node's SDO channel: one client, taken in turn by boot-up and host transfers."""

    sdo: SdoClient
    lock: threading.Lock


class Master:
    def __init__(self, device: Card, config: BusConfig, publish: Callable[[], None]) -> None:
        self.device = device
        self.image = device.plc.image
        self.config = config
        self._publish = publish
        """Writes the card's facts beside the image (``firmware.card_info``) anew."""
        self.bus: CanBus | None = None
        self.nodes: dict[int, NodeHandler] = {}
        self._sync_used = False
        """Whether a configured node has a SYNC controlled PDO (see ``sync_period``)."""
        self._owners: npt.NDArray[np.uint8] | None = None
        """Which node's output PDO each output byte belongs to (0: none); see ``_owner_map``."""
        self._nexc_lock = threading.Lock()
        self.bus_params: BusParameterSet | None = None
        self.ext = ExtendedBusParameterSet()
        self.executor = ThreadPoolExecutor(max_workers=32, thread_name_prefix="node-boot")
        self.running = False
        self.halted = False
        """Outputs zeroed and PDO traffic stopped: host not ready or watchdog expired."""
        self.cleared = False
        """Auto-clear end state: one lost node stopped all."""
        self._booting: set[int] = set()
        self._global_start_due = False
        self._stop = threading.Event()
        self._tick_thread: threading.Thread | None = None
        self._sync_thread: threading.Thread | None = None
        self._sync_wakeup = threading.Event()
        self._sync_timer: tuple[tuple[int, float], CyclicSendTaskABC] | None = None
        """The outside SYNC timer, with the (COB-ID, period) it runs for."""
        self._sync_on = False
        """Whether SYNC frames coming back drive the synchronous PDOs (outside timer)."""
        self._sync_retry_at = 0.0
        self._sync_retry_s = 0.0
        self.layer2_filters: set[int] = set()
        self.indications: deque[tuple[int, can.Message]] = deque()
        self._queue_lock = threading.Lock()
        self._heartbeat_due = 0.0
        self._sdo: dict[int, SdoChannel] = {}
        self._last_conn = b""
        self._supervise_due = 0.0
        self._outputs_waiting: set[NodeHandler] = set()
        self.bootup_forwarding = False
        self.sdo_timeout = DEFAULT_SDO_TIMEOUT
        self._host_transfers: list[HostSdoTransfer] = []

    # --- life cycle ---------------------------------------------------------------------

    def open(self) -> None:
        """Connect the controller to the bus (once, at power-on)."""
        cfg = self.config
        self.bus = CanBus(cfg.interface, cfg.channel, cfg.bitrate, cfg.trace, cfg.tap)
        self.bus.on_error_frame = self._on_error_frame
        self.bus.on_send_timeout = self._on_send_timeout
        self.bus.subscribe_all(self._on_any_frame)
        self._tick_thread = threading.Thread(target=self._tick_loop, name="can-tick", daemon=True)
        self._tick_thread.start()
        self._sync_thread = threading.Thread(target=self._sync_loop, name="can-sync", daemon=True)
        self._sync_thread.start()

    @property
    def closing(self) -> bool:
        return self._stop.is_set()

    def wait_for(self, event: threading.Event, timeout: float) -> bool:
        """Wait for ``event`` but give up at once when the card powers off."""
        deadline = time.monotonic() + timeout
        while not event.wait(min(0.05, max(0.0, deadline - time.monotonic()))):
            if self._stop.is_set() or time.monotonic() >= deadline:
                return False
        return True

    def close(self) -> None:
        self._stop.set()
        self._sync_wakeup.set()
        for thread in (self._tick_thread, self._sync_thread):
            if thread is not None:
                thread.join(timeout=2)
        self.executor.shutdown(wait=False, cancel_futures=True)
        if self.bus is not None:
            self.bus.shutdown()

    def reset(self) -> None:
        """A card start: the on-line configuration is gone."""
        for handler in self.nodes.values():
            handler.idle()
            handler.detach()
        self.nodes.clear()
        self._sync_used = False
        self._owners = None
        self.bus_params = None
        self.ext = ExtendedBusParameterSet()
        self.running = self.halted = self.cleared = False
        self._sync_wakeup.set()
        self._booting.clear()
        self._last_conn = b""
        self.layer2_filters.clear()
        self.bootup_forwarding = False
        self.set_sdo_timeout(0, DEFAULT_SDO_TIMEOUT)
        with self._queue_lock:
            self.indications.clear()

    # --- configuration ------------------------------------------------------------------------

    @property
    def sync_cob_id(self) -> int:
        return self.bus_params.COB_ID_SYNC if self.bus_params else 0x80

    @property
    def sync_period(self) -> float:
        """SYNC_Timer in seconds; 0 (no SYNC) while no node has a SYNC controlled PDO.

        Seed 4.2 (node parameters, bTransType): "The SYNC mechanism will be activated only if
        at least one node uses SYNC controlled transmission types."
        """
        if not self.bus_params or not self._sync_used:
            return 0.0
        return self.bus_params.SYNC_Timer / 1000.0

    @property
    def motorola(self) -> bool:
        return bool(self.bus_params and self.bus_params.Intel_Motorola == MOTOROLA)

    @property
    def auto_clear(self) -> bool:
        return bool(self.bus_params and self.bus_params.Auto_Clear == ACLR_ACTIVE)

    @property
    def global_start(self) -> bool:
        return bool(self.ext.bExtendedState & ExtendedState.biNoGobalStartNode)

    def configure_node(self, address: int, params: NodeParameterSet) -> None:
        old = self.nodes.pop(address, None)
        if old is not None:
            old.idle()
            old.detach()
        handler = NodeHandler(self, address, params)
        self.nodes[address] = handler
        self._owners = None
        self._sync_used = any(
            h.params.active and any(pdo.sync_controlled for pdo in h.params.atPdoCfgData)
            for h in self.nodes.values())
        self._sync_wakeup.set()
        self.device.set_node_bit("abNd_cfg", address, params.active)
        self.device.set_node_bit("abNd_diag", address, False)
        if self.running:
            handler.attach()
            self._boot(handler)

    def start_network(self, params: BusParameterSet) -> None:
        """The bus parameter download: (re)start the whole network."""
        restart = self.running
        self.bus_params = params
        self._apply_baud_rate(BAUD_RATES_KBIT[params.Baud_rate] * 1000)
        self.running = True
        self.cleared = False
        self.halted = not self.image.driving
        self.device.set_global_bit(GlobalBits.ACLR, False)
        self._sync_retry_at = 0.0  # a new configuration tries the SYNC timer at once
        self._sync_wakeup.set()
        for handler in self.nodes.values():
            if restart:
                handler.detach()
            handler.attach()
            if not self.halted:
                self._boot(handler)

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

    def _boot(self, handler: NodeHandler) -> None:
        if handler.state is State.INACTIVE:
            return
        if not self._conn_bit(handler.address):
            handler.disconnect()
            return
        self._booting.add(handler.address)
        handler.start_boot()

    # --- state seen by the device ------------------------------------------------------------

    def can_state(self) -> CanState:
        if not self.running:
            return CanState.OFFLINE
        if self.cleared:
            return CanState.CLEAR
        if self.halted:
            return CanState.STOP
        return CanState.OPERATE

    # --- callbacks from node handlers ----------------------------------------------------------

    def node_booted(self, handler: NodeHandler) -> None:
        self._booting.discard(handler.address)
        if self.cleared or (self.halted and self.device.rcs.host_not_ready):
            # auto-clear or HOST_NOT_READY came first: they stop this node too (seed 4.3)
            self._stop_node(handler)
            self._update_nexc()
            return
        self.device.clear_error(handler.address)
        self._update_nexc()  # before Nd_state: a host that sees all nodes up sees NEXC clear
        self.set_node_state(handler.address, not handler.awaiting_start)
        if self.global_start and not self._booting:
            self._global_start_due = True

    def node_failed(self, handler: NodeHandler, event: int) -> None:
        self._booting.discard(handler.address)
        self.set_node_state(handler.address, False)
        self._update_nexc()  # with Err_Event, not a supervision tick later
        self.device.report_error(handler.address, event)
        if self.auto_clear and not self.cleared and self.running:
            self._auto_clear()
        elif self.global_start and not self._booting:
            self._global_start_due = True

    def _auto_clear(self) -> None:
        """One lost node stops all: outputs to zero, every node stopped (seed 4.3 ACLR)."""
        log.warning("auto-clear: stopping all nodes")
        self._zero_outputs()
        self.cleared = True
        self._sync_wakeup.set()  # an outside SYNC timer stops now, not at the next look
        self._stop_nodes()
        self.device.set_global_bit(GlobalBits.ACLR, True)

    def _stop_nodes(self) -> None:
        """Every node to STOPPED, with Err_Event 39 (seed 4.3: "node not handled, node in
        stop", after auto-clear or when the host is not ready)."""
        self.nmt(NMT_STOP, 0)
        for handler in list(self.nodes.values()):
            if handler.state is State.OPERATING:
                self._stop_node(handler)

    def _stop_node(self, handler: NodeHandler) -> None:
        handler.idle()
        handler.diag.actual_error = NODE_STOPPED
        handler.note_diag()  # Actual_Error changed: Nd_diag (seed 4.3)
        self.device.report_error(handler.address, NODE_STOPPED)

    def set_node_state(self, address: int, on: bool) -> None:
        self.device.set_node_bit("abNd_state", address, on)

    def set_node_diag(self, address: int, on: bool) -> None:
        self.device.set_node_bit("abNd_diag", address, on)

    def sdo_client(self, address: int) -> SdoChannel:
        """The SDO channel to ``address`` (created on first use, kept for the card's life)."""
        channel = self._sdo.get(address)
        if channel is None:
            assert self.bus is not None
            client = SdoClient(  # type: ignore[no-untyped-call]
                0x600 + address, 0x580 + address, ObjectDictionary()  # type: ignore[no-untyped-call]
            )
            client.network = self.bus.network
            client.RESPONSE_TIMEOUT = self.sdo_timeout
            self.bus.network.subscribe(0x580 + address, client.on_response)
            channel = self._sdo[address] = SdoChannel(client, threading.Lock())
        return channel

    def start_host_sdo(self, transfer: HostSdoTransfer) -> None:
        """A host SDO transfer; the tick watches its time-out."""
        self._host_transfers = [t for t in self._host_transfers if not t.finished] + [transfer]
        transfer.start()

    def set_sdo_timeout(self, node: int, seconds: float) -> None:
        """COM_Set_SDO_Timeout: one node's channel, or (node 0) every channel and the default."""
        if node == 0:
            self.sdo_timeout = seconds
            for channel in self._sdo.values():
                channel.sdo.RESPONSE_TIMEOUT = seconds
        else:
            self.sdo_client(node).sdo.RESPONSE_TIMEOUT = seconds

    def host_nmt(self, command: int, node: int) -> None:
        """COM_NMT_Module_Protocol: the host drives node states by hand."""
        targets = list(self.nodes.values()) if node == 0 else (
            [self.nodes[node]] if node in self.nodes else [])
        resetting = command in (NMT_RESET, NMT_RESET_COMM)
        for handler in targets:
            if resetting:
                if handler.state not in (State.INACTIVE, State.DISCONNECTED):
                    handler.start_boot(reset_sent=True)  # armed before the boot-up can come
            else:
                handler.operational_expected = command == NMT_START
                if not handler.operational_expected:
                    self.set_node_state(handler.address, False)
        self.nmt(command, node)
        if command == NMT_START:
            now = time.monotonic()
            for handler in targets:
                handler.start_sent(now, by_host=True)

    def cob_id_in_use(self, cob_id: int) -> bool:
        """Whether the CANopen side already listens to or sends ``cob_id``."""
        if cob_id in (0, self.sync_cob_id):
            return True
        for address, handler in self.nodes.items():
            params = handler.params
            used = {0x580 + address, 0x600 + address, 0x700 + address, params.usCobIDEmcy,
                    params.usCobIDGuard, *(p.usPdoCOBId for p in params.atPdoCfgData)}
            if cob_id in used:
                return True
        return False

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

    def nmt(self, command: int, node: int) -> None:
        self.bus_send(0x000, bytes([command, node]))

    def _zero_outputs(self) -> None:
        """Drive every RX-PDO to zero once (seed 5.2.1.2), then stop PDO traffic."""
        driving = self.image.driving
        self.image.driving = False  # read_outputs answers zeros now
        try:
            for handler in self.nodes.values():
                handler.send_outputs(force=True)
        finally:
            self.image.driving = driving

    # --- the tick ------------------------------------------------------------------------------

    def _conn_bit(self, address: int) -> bool:
        return bool(self.device.mm[CONN_STATUS + (address >> 3)] & (1 << (address & 7)))

    def _tick_loop(self) -> None:
        last_outputs = b""
        while not self._stop.wait(TICK):
            try:
                last_outputs = self._tick(time.monotonic(), last_outputs)
            except Exception:
                log.exception("CAN tick failed")

    def _tick(self, now: float, last_outputs: bytes) -> bytes:
        if not self.running:
            return last_outputs
        self._follow_host()
        for transfer in self._host_transfers:
            transfer.check(now)
        if self.halted or self.cleared:
            return last_outputs
        if self._global_start_due:
            self._global_start_due = False
            self.nmt(NMT_START, 0)
            for handler in list(self.nodes.values()):
                handler.start_sent(now, by_host=False)
        self._follow_connection_bits()
        if now >= self._supervise_due:
            self._supervise_due = now + SUPERVISION_PERIOD
            for handler in list(self.nodes.values()):
                handler.tick(now)
            self._update_nexc()
        outputs = self.image.snapshot_outputs()
        changed = outputs != last_outputs
        if changed or self._outputs_waiting:
            due = self._changed_nodes(outputs, last_outputs) if changed else set()
            due |= self._outputs_waiting
            self._outputs_waiting = {h for h in sorted(due, key=_address) if h.send_outputs()}
        self._heartbeat(now)
        return outputs

    def _changed_nodes(self, outputs: bytes, before: bytes) -> set[NodeHandler]:
        """The nodes whose output PDOs read differently in ``outputs`` than in ``before``.

        One vectorised comparison of the whole area instead of every node's
        slices: at full bus load this runs a thousand times a second.
        """
        owners = self._owner_map()
        if owners is None or len(before) != len(outputs):
            return {h for h in self.nodes.values() if h.outputs_changed(outputs, before)}
        diff = np.frombuffer(outputs, np.uint8) != np.frombuffer(before, np.uint8)
        nodes = self.nodes
        return {nodes[a] for a in np.unique(owners[diff]).tolist() if a in nodes}

    def _owner_map(self) -> npt.NDArray[np.uint8] | None:
        """Output byte -> node address; None when two nodes share output bytes."""
        if self._owners is None:
            owners = np.zeros(IO_AREA_SIZE, np.uint8)
            for address, handler in list(self.nodes.items()):
                for entry in handler.outputs:
                    span = owners[entry.offset:entry.offset + entry.pdo.data_length]
                    if np.any((span != 0) & (span != address)):
                        return None
                    span[:] = address
            self._owners = owners
        return self._owners

    def _follow_connection_bits(self) -> None:
        """Seed 3: a cleared bit stops the node, a set bit starts it again at once."""
        conn = self.device.mm[CONN_STATUS : CONN_STATUS + 16]
        if conn == self._last_conn:
            return
        self._last_conn = conn
        for address, handler in list(self.nodes.items()):
            connected = bool(conn[address >> 3] & (1 << (address & 7)))
            if not connected and handler.state not in (State.DISCONNECTED, State.INACTIVE):
                handler.disconnect()
            elif connected and handler.state is State.DISCONNECTED:
                self._boot(handler)

    def _follow_host(self) -> None:
        """HOST_NOT_READY or a watchdog expiry stop the bus and zero the outputs."""
        driving = self.image.driving
        if not driving and not self.halted:
            log.info("host stopped: outputs to zero, PDO traffic stopped")
            self._zero_outputs()
            self.halted = True
            self._sync_wakeup.set()
            if self.device.rcs.host_not_ready:  # HOST_NOT_READY, not the watchdog's 220
                self._stop_nodes()
        elif driving and self.halted and not self.cleared:
            self.halted = False
            self._sync_wakeup.set()
            for handler in self.nodes.values():
                if handler.state in (State.WAITING, State.FAILED):
                    self._boot(handler)
                else:
                    handler.send_outputs(force=True)

    def _update_nexc(self) -> None:
        """NEXC from every node's state; called by boot threads, the bus thread and the tick.

        Under a lock: two boot threads finishing together could otherwise write
        their answers in the wrong order, the stale one last.
        """
        with self._nexc_lock:
            missing = any(h.state is not State.OPERATING for h in list(self.nodes.values())
                          if h.active and h.state is not State.DISCONNECTED)
            self.device.set_global_bit(GlobalBits.NEXC, missing)

    def _heartbeat(self, now: float) -> None:
        period = self.ext.usProducerHeartbeatTime / 1000.0
        if not period or not self.ext.bNodeID or now < self._heartbeat_due:
            return
        self._heartbeat_due = now + period
        self.bus_send(0x700 + self.ext.bNodeID, b"\x05")

    # --- SYNC ----------------------------------------------------------------------------------

    def _sync_loop(self) -> None:
        """SYNC producer: a timer outside the interpreter where the bus has one, else this thread.

        The thread sleeps most of the period, then watches the clock for the
        rest; under PDO load it still waits for the interpreter lock behind the
        receive and tick threads (milliseconds, see README "Benchmarks"). With an
        outside timer, the synchronous PDOs follow the SYNC frame as it comes back
        from the bus, as on a real bus they follow it on the wire.
        """
        outside = self.bus is not None and self.bus.interface in PERIODIC_OUTSIDE_INTERFACES
        next_sync = time.perf_counter()
        while not self._stop.is_set():
            period = self.sync_period
            if not (self.running and period) or self.halted or self.cleared:
                self._stop_sync_timer()
                self._await_sync_change()
                next_sync = time.perf_counter()
                continue
            if outside:
                self._run_sync_timer(self.sync_cob_id, period)
                self._await_sync_change()
                continue
            next_sync += period
            remaining = next_sync - time.perf_counter()
            if remaining < -period:  # fell behind (the machine stalled): resynchronise
                next_sync = time.perf_counter()
            elif remaining > 0.0008:
                self._stop.wait(remaining - 0.0005)
            while time.perf_counter() < next_sync:
                time.sleep(0)  # let the other threads have the GIL meanwhile
            self.bus_send(self.sync_cob_id)
            self._on_sync()
        self._stop_sync_timer()

    def _await_sync_change(self) -> None:
        """Until a start, halt or reset rings, or 50 ms pass (a timer may have died)."""
        self._sync_wakeup.wait(0.05)
        self._sync_wakeup.clear()

    def _run_sync_timer(self, cob_id: int, period: float) -> None:
        """(Re)start the outside SYNC timer when it is not running as configured.

        A timer that ended (its process was killed) starts again; one that
        will not start is tried again after a pause that doubles up to
        ``SYNC_RETRY_MAX_S``, since each try may cost an interpreter start.
        """
        timer = self._sync_timer
        if timer is not None:
            if timer[0] == (cob_id, period):
                if getattr(timer[1], "alive", True):
                    return
                log.warning("the SYNC timer ended unasked; starting it again")
            self._stop_sync_timer()
        now = time.monotonic()
        if now < self._sync_retry_at:
            return
        assert self.bus is not None
        self._sync_on = True  # before the first frame can come back
        self.bus.subscribe(cob_id, self._on_sync_frame)
        try:
            task = self.bus.send_periodic(cob_id, period)
        except (can.CanError, OSError) as exc:
            self._sync_on = False
            self.bus.unsubscribe(cob_id, self._on_sync_frame)
            if self._sync_retry_s:
                log.warning("SYNC timer did not start again: %s", exc)
            else:
                log.exception("SYNC timer did not start; trying again")
            self._sync_retry_s = min(SYNC_RETRY_MAX_S, max(0.1, 2 * self._sync_retry_s))
            self._sync_retry_at = now + self._sync_retry_s
            return
        self._sync_retry_s = 0.0
        self._sync_timer = ((cob_id, period), task)
        if getattr(task, "realtime", True) is False:
            log.warning("the SYNC timer process runs without SCHED_FIFO (no CAP_SYS_NICE): "
                        "its jitter is the machine's")

    def _stop_sync_timer(self) -> None:
        if self._sync_timer is None:
            return
        (cob_id, _), task = self._sync_timer
        self._sync_timer = None
        self._sync_on = False
        task.stop()
        if self.bus is not None:
            self.bus.unsubscribe(cob_id, self._on_sync_frame)

    def _on_sync_frame(self, msg: can.Message) -> None:
        """The outside timer's SYNC as it comes back; not after a halt the timer has yet
        to hear of (the sync thread stops it within its next look)."""
        if (self._sync_on and not msg.data and self.running and not self.halted
                and not self.cleared):
            self._on_sync()

    def _on_sync(self) -> None:
        now = time.monotonic()
        for handler in list(self.nodes.values()):
            handler.on_sync(now)

    # --- bus events, layer 2 and transparent reception -----------------------------------------

    def _on_error_frame(self, msg: can.Message) -> None:
        """Error frames in SocketCAN's layout: the class bits are in the identifier."""
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
            self.device.count("usBus_Off_Cnt")
        elif (error_class & CAN_ERR_CRTL and len(msg.data) > 1
              and msg.data[1] & CAN_ERR_CRTL_LIMITS):
            # Seed 4.3: Bus_Error_Cnt counts the times the controller's error counter reached
            # the warning limit, not each error frame (a protocol error alone is no event).
            self.device.count("usBus_Error_Cnt")
        else:
            return
        self.device.set_global_bit(GlobalBits.EVE, True)

    def _on_send_timeout(self) -> None:
        self.device.count("usMsg_Time_Out")
        self.device.set_global_bit(GlobalBits.TOUT, True)

    def _on_any_frame(self, msg: can.Message) -> None:
        if (self.bootup_forwarding and not msg.is_extended_id and not msg.is_remote_frame
                and 0x701 <= msg.arbitration_id <= 0x77F and bytes(msg.data) == b"\x00"):
            self._queue(COM_BOOTUP_INDICATION, msg)
        if msg.is_extended_id:
            if not self.ext.bExtendedState & ExtendedState.bi11Bit29BitSelector:
                return
            mask = self.ext.ulAcceptMask & 0x1FFFFFFF
            if (msg.arbitration_id & mask) != (self.ext.ulAcceptCode & mask):
                return
            self._queue(COM_RECEIVE_TRANSPARENT, msg)
        elif msg.arbitration_id in self.layer2_filters:
            self._queue(COM_RX_CAN_LAYER2, msg)

    def _queue(self, kind: int, msg: can.Message) -> None:
        with self._queue_lock:
            if len(self.indications) >= QUEUE_LIMIT:
                self.device.count("usRx_Overflow")
                return
            self.indications.append((kind, msg))
        self.device.bell.ring_self()

    def next_indication(self) -> Message | None:
        """The next indication for the host mailbox, or None (pulled by the device loop)."""
        with self._queue_lock:
            if not self.indications:
                return None
            kind, msg = self.indications.popleft()
            if kind == COM_BOOTUP_INDICATION:
                return Message(rx=Task.USER, tx=Task.CAN, b=COM_BOOTUP_INDICATION,
                               data=encode_bootup_indication(msg.arbitration_id - 0x700))
            if kind == COM_RECEIVE_TRANSPARENT:
                data = encode_transparent_2b(CanFrame(msg.arbitration_id, bytes(msg.data),
                                                      msg.is_remote_frame, msg.dlc, True))
                return Message(rx=Task.USER, tx=Task.CAN, b=COM_RECEIVE_TRANSPARENT, data=data)
            data = layer2_frame(msg)
            while self.indications and self.indications[0][0] == COM_RX_CAN_LAYER2:
                more = layer2_frame(self.indications[0][1])
                if len(data) + len(more) > INDICATION_LIMIT:
                    break
                data += more
                self.indications.popleft()
            return Message(rx=Task.USER, tx=Task.CAN, b=COM_RX_CAN_LAYER2, data=data)


def layer2_frame(msg: can.Message) -> bytes:
    """A received frame in the layer-2 indication format (seed 5.3.2.2)."""
    return encode_layer2_frame(CanFrame(msg.arbitration_id, bytes(msg.data),
                                        msg.is_remote_frame, msg.dlc))


def _address(handler: NodeHandler) -> int:
    return handler.address
