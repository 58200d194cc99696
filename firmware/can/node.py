"""One node handler per configured node: boot-up, supervision, diagnosis, PDOs.

The seed calls them node handlers: "for every node station one state machine
is implemented" (seed 5.2). The boot sequence runs in a worker thread because
it waits on SDO answers; supervision, PDO output and the connection bits are
served from the master's tick; received frames arrive on the bus thread.
"""

from __future__ import annotations

import contextlib
import enum
import logging
import struct
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import can
from canopen.sdo.client import SdoClient
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from dbm_tools.parameters import (
    ASYNC_RTR,
    MSK_WORD_PDO,
    SYNC_RTR,
    ConfigNdState,
    NdFlag,
    NodeParameterSet,
    PdoData,
)
from dpm.com import EMCY_ENTRIES, NodeStatus
from dpm.com import NodeDiagnosis as Diagnosis
from dpm.commands import NMT_RESET_NODE as NMT_RESET
from dpm.commands import NMT_START, NMT_STOP
from dpm.errors import NodeEvent, err_event_text
from firmware.frames import SDO_FRAME_LENGTH

if TYPE_CHECKING:
    from firmware.can.master import Master

log = logging.getLogger(__name__)

BOOTUP_TIMEOUT = 3.0
"""[ours] seconds a reset node has to answer: its boot-up message, or 1000h read."""
RESET_GRACE = 1.0
"""[ours] seconds the card waits after a reset for a boot-up message before it reads 1000h."""
RETRY_DELAY = 1.0
"""[ours] seconds before a lost node is booted again when auto-clear is off."""
RTR_PERIOD = 0.1
"""[ours] seconds between remote requests of an RTR-only (253) input PDO without SYNC."""
START_GRACE = 0.5
"""[ours] seconds after the NMT start in which a node may still report its old state: an
error-control frame it sent before the start can reach the master after it."""
FOREIGN_CLOCK_S = 60.0
"""[ours] A frame stamped further than this from the wall clock is stamped by the adapter's
own clock: its stamp says nothing about when it was on the bus relative to the card's
resets and starts (``wall_stamp``)."""

# Err_Event numbers for nodes (seed 4.3)
GUARDING_FAILED = NodeEvent.GUARDING_FAILED
LEFT_OPERATIONAL = NodeEvent.LEFT_OPERATIONAL
GUARD_SEQUENCE = NodeEvent.GUARD_SEQUENCE
NO_RTR_RESPONSE = NodeEvent.NO_RTR_RESPONSE
NO_RESPONSE = NodeEvent.NO_RESPONSE
PROFILE_MISMATCH = NodeEvent.PROFILE_MISMATCH
DEVICE_TYPE_MISMATCH = NodeEvent.DEVICE_TYPE_MISMATCH
UNKNOWN_SDO_RESPONSE = NodeEvent.UNKNOWN_SDO_RESPONSE
SDO_LENGTH = NodeEvent.SDO_LENGTH
NODE_STOPPED = NodeEvent.NODE_STOPPED

# Nodestatus_1 bits (seed 5.2.7)
NO_RESPONSE_BIT = NodeStatus.NO_RESPONSE
EMCY_OVERFLOW_BIT = NodeStatus.EMCY_BUFFER_OVERFLOW
PRM_FAULT_BIT = NodeStatus.PRM_FAULT
GUARD_ACTIVE_BIT = NodeStatus.GUARD_ACTIVE
DEACTIVATED_BIT = NodeStatus.DEACTIVATED

OPERATIONAL, STOPPED, PRE_OPERATIONAL, BOOT_UP = 5, 4, 127, 0


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


@dataclass
class OutputPdo:
    pdo: PdoData
    offset: int
    last: bytes | None = None
    last_time: float = 0.0
    syncs: int = 0


@dataclass
class InputPdo:
    pdo: PdoData
    offset: int
    requested: float = 0.0
    """When the last remote request went out, 0 when answered."""


def swap_words(data: bytes) -> bytes:
    """Motorola order for a word-oriented PDO: swap the bytes of each word."""
    out = bytearray(data)
    for i in range(0, len(out) - 1, 2):
        out[i], out[i + 1] = out[i + 1], out[i]
    return bytes(out)


def wall_stamp(msg: can.Message) -> float | None:
    """The frame's time stamp when it is on this machine's wall clock, as virtual, shm and
    socketcan stamp; None for an adapter that counts from its own power-on, whose stamps
    would otherwise make every frame look older than the node's last reset or start."""
    stamp = msg.timestamp
    return stamp if stamp and abs(stamp - time.time()) < FOREIGN_CLOCK_S else None


class NodeHandler:
    def __init__(self, master: Master, address: int, params: NodeParameterSet) -> None:
        self.master = master
        self.address = address
        self.params = params
        self.active = params.active
        """Configured to run (the parameters of a handler never change)."""
        self.heartbeat = bool(params.bNd_Flag & NdFlag.HRTBT)
        self.guard_time = params.usGuardTime
        """Supervision time in ms (guard time or heartbeat consumer time); 0 = none."""
        self.life_time_factor = params.bLifeTimeFactor
        self.emcy_cob_id: int | None = params.usCobIDEmcy
        """EMCY COB-ID collected for COM_Node_Diag; None while the EMCY consumer is off."""
        self.state = State.WAITING if params.active else State.INACTIVE
        self.diag = Diagnosis()
        if not params.active:
            self.diag.status |= DEACTIVATED_BIT
        self.operational_expected = True
        """False after the host stopped or pre-operated the node with NMT."""
        self.awaiting_start = False
        """The card has not asked the node to go OPERATIONAL: START is set in its
        bitConfigNdState, or the global Start_Node has not gone out yet. The node is supervised
        in the state it is in, and Nd_state shows whether it operates (seed 4.2, 4.3)."""
        self._diag_seen = (self.diag.status, self.diag.actual_error)
        """Nodestatus_1 and Actual_Error as the host last read them (COM_Node_Diag)."""
        self.host_sdo = False
        """A host SDO transfer runs: the node's RPDOs are suppressed (seed 5.2.8)."""
        self._bootup = threading.Event()
        self._reset_at = 0.0
        """Wall-clock time (as frames are stamped) of the last NMT reset the card sent it."""
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
        self._sdo_length_error = False
        """An SDO response of another length than 8 came since the boot-up began. The
        controller keeps it from canopen's client, which then times out: Err_Event 38."""
        self._retry_at = 0.0
        self._generation = 0
        """Bumped on every (re)boot so a stale boot thread gives up."""
        self.outputs = [OutputPdo(p, o) for p, o in zip(
            [p for p in params.atPdoCfgData if not p.is_input], params.ausOutputOffsets,
            strict=False)]
        self.inputs = [InputPdo(p, o) for p, o in zip(
            [p for p in params.atPdoCfgData if p.is_input], params.ausInputOffsets,
            strict=False)]
        self._polled = [e for e in self.inputs if e.pdo.bTransType in (SYNC_RTR, ASYNC_RTR)]
        """Inputs that come only when asked by a remote frame (252, 253)."""
        self._synchronous = [e for e in self.outputs if e.pdo.bTransType <= 240]
        """Outputs a SYNC may send: at 1,000 SYNCs/s the others are not even read then
        (the master's tick sends a changed event-driven output)."""

    # --- wiring to the bus -----------------------------------------------------------------

    def attach(self) -> None:
        bus = self.master.bus
        assert bus is not None
        bus.subscribe(0x700 + self.address, self._on_error_control)
        bus.subscribe(0x580 + self.address, self._on_sdo_response)
        if self.params.usCobIDGuard and self.params.usCobIDGuard != 0x700 + self.address:
            bus.subscribe(self.params.usCobIDGuard, self._on_error_control)
        if self.emcy_cob_id is not None:
            bus.subscribe(self.emcy_cob_id, self._on_emcy)
        for entry in self.inputs:
            bus.subscribe(entry.pdo.usPdoCOBId, self._on_input)

    def detach(self) -> None:
        bus = self.master.bus
        if bus is None:
            return
        bus.unsubscribe(0x700 + self.address, self._on_error_control)
        bus.unsubscribe(0x580 + self.address, self._on_sdo_response)
        bus.unsubscribe(self.params.usCobIDGuard, self._on_error_control)
        if self.emcy_cob_id is not None:
            bus.unsubscribe(self.emcy_cob_id, self._on_emcy)
        for entry in self.inputs:
            bus.unsubscribe(entry.pdo.usPdoCOBId, self._on_input)

    # --- boot-up ------------------------------------------------------------------------------

    def start_boot(self, reset_sent: bool = False) -> None:
        """Begin (or begin again) the boot sequence in a worker thread.

        ``reset_sent``: the host resets the node itself (COM_NMT_Module_Protocol);
        the sequence then waits for that boot-up instead of resetting it twice,
        which would let the first boot-up answer for the second.
        """
        if self.state is State.INACTIVE:
            return
        self._generation += 1
        self._bootup.clear()
        self.state = State.BOOTING
        self.operational_expected = True
        self.master.set_node_state(self.address, False)
        self.master.executor.submit(self._boot, self._generation, reset_sent)

    def _boot(self, generation: int, reset_sent: bool) -> None:
        """The boot-up in its worker thread, which nobody joins.

        The executor would keep any exception in a future nobody reads, leaving
        the node in BOOTING for good and the host without an Err_Event; so an
        unforeseen one fails the node (34, no response during its configuration)
        and is logged. Not while the card powers off: a boot-up cut short then
        (its bus shut, its image gone) is no error of the node.
        """
        try:
            self._run_boot(generation, reset_sent)
        except Exception:
            if self.master.closing:
                return
            log.exception("node %d: boot-up failed unexpectedly", self.address)
            self._fail_boot(generation, NO_RESPONSE)

    def _run_boot(self, generation: int, reset_sent: bool) -> None:
        skip = self.params.bitConfigNdState
        try:
            channel = self.master.sdo_client(self.address)
            with channel.lock:
                if generation != self._generation:
                    # A newer start of the node came while this one waited for the channel:
                    # that one boots it. Without this, a host toggling NOTREADY queued boot
                    # after stale boot (up to 3 s each), and a new configuration waited
                    # behind all of them.
                    return
                self._sdo_length_error = False
                self._boot_steps(skip, channel.sdo, reset_sent)
        except SdoAbortedError as exc:
            log.info("node %d: configuration aborted 0x%08X", self.address, exc.code)
            self.diag.status |= PRM_FAULT_BIT
            self._fail_boot(generation, NO_RESPONSE)
            return
        except SdoCommunicationError as exc:
            message = str(exc)
            log.info("node %d: no configuration answer: %s", self.address, message)
            unknown = "Unexpected response" in message or "unexpected" in message.lower()
            if self._sdo_length_error and not unknown:
                # The node did answer, with a frame the controller kept from canopen.
                self._fail_boot(generation, SDO_LENGTH)
                return
            self.diag.status |= 0 if unknown else NO_RESPONSE_BIT
            self._fail_boot(generation, UNKNOWN_SDO_RESPONSE if unknown else NO_RESPONSE)
            return
        except _BootFailure as failure:
            self._fail_boot(generation, failure.event)
            return
        if generation != self._generation or self.state is not State.BOOTING:
            return
        recovered = self.diag.actual_error != 0
        self.diag.status &= ~(NO_RESPONSE_BIT | PRM_FAULT_BIT)
        self.diag.actual_error = 0  # the online error is over (seed 5.2.7 Actual_Error)
        now = time.monotonic()
        self._last_heartbeat = now
        self._next_guard = now
        self._guard_pending = False
        self._guard_misses = 0
        self._toggle = None
        self._started_at = now
        self._start_stamp = time.time()
        self._confirmed = False
        self.awaiting_start = bool(skip & ConfigNdState.START) or self.master.global_start
        for output in self.outputs:
            output.last = None
        self.state = State.OPERATING
        if self.supervised:
            self.diag.status |= GUARD_ACTIVE_BIT
        if recovered:  # before Nd_state, as above
            self.note_diag()
        else:  # [ours] a first boot is the normal state (seed 4.3: Nd_state 1, Nd_diag 0)
            self._diag_seen = (self.diag.status, self.diag.actual_error)
        self.master.node_booted(self)
        if not skip & ConfigNdState.TXRXPDO:
            self.send_outputs(force=True)
            for entry in self._polled:
                self._request(entry, now)

    def _boot_steps(self, skip: int, sdo: SdoClient, reset_sent: bool) -> None:
        params = self.params
        if self.master.closing:
            raise _BootFailure(NO_RESPONSE)
        if reset_sent or not skip & ConfigNdState.RESET:
            if not reset_sent:
                self._bootup.clear()
                self._reset_at = time.time()
                self.master.nmt(NMT_RESET, self.address)
            deadline = time.monotonic() + BOOTUP_TIMEOUT
            if not self.master.wait_for(self._bootup, RESET_GRACE):
                self._identify(sdo, deadline)
        if not skip & ConfigNdState.DEVICE:
            raw = sdo.upload(0x1000, 0)
            if len(raw) < 4:
                raise _BootFailure(UNKNOWN_SDO_RESPONSE)
            device_type = int.from_bytes(raw[:4], "little")
            self.diag.profile = device_type & 0xFFFF
            self.diag.add_info = device_type >> 16
            # [ours] a configured 0 means "any": a host may not know one of the two.
            if params.usDevProfNum and params.usDevProfNum != self.diag.profile:
                self.diag.status |= PRM_FAULT_BIT
                raise _BootFailure(PROFILE_MISMATCH)
            if params.usAddTypeInfo and params.usAddTypeInfo != self.diag.add_info:
                self.diag.status |= PRM_FAULT_BIT
                raise _BootFailure(DEVICE_TYPE_MISMATCH)
        if not skip & ConfigNdState.GUARD:
            if self.heartbeat:
                if params.usGuardTime:
                    # [ours] the node produces at half the master's consumer time
                    sdo.download(0x1017, 0, struct.pack("<H", max(1, params.usGuardTime // 2)))
            else:
                if params.usGuardTime:
                    # CiA 301: a node that produces heartbeats does not answer guarding;
                    # switch its producer off (a node without 1017h may refuse: fine).
                    with contextlib.suppress(SdoAbortedError):
                        sdo.download(0x1017, 0, b"\0\0")
                sdo.download(0x100C, 0, struct.pack("<H", params.usGuardTime))
                sdo.download(0x100D, 0, struct.pack("<B", params.bLifeTimeFactor))
                self._write_guard_cob_id(sdo)
        if not skip & ConfigNdState.SYNC:
            sdo.download(0x1005, 0, struct.pack("<I", self.master.sync_cob_id))
        if not skip & ConfigNdState.EMCY:
            sdo.download(0x1014, 0, struct.pack("<I", params.usCobIDEmcy))
        if not skip & ConfigNdState.SDO:
            for entry in params.atSdoCfgData:
                sdo.download(entry.usIndex, entry.bSubindex,
                                  bytes(entry.abSdoValue[: entry.bLength]))
        if not skip & ConfigNdState.START and not self.master.global_start:
            self.master.nmt(NMT_START, self.address)

    def start_sent(self, now: float, by_host: bool) -> None:
        """A Start_Node went to the node (the global one, or the host's): from now on it must
        be OPERATIONAL, after the usual grace for the command to arrive. A node with START set
        in bitConfigNdState waits only for the host's."""
        if self.state is not State.OPERATING or not self.awaiting_start:
            return
        if not by_host and self.params.bitConfigNdState & ConfigNdState.START:
            return
        self.awaiting_start = False
        self._started_at = now
        self._start_stamp = time.time()
        self._confirmed = False
        if not self.params.bitConfigNdState & ConfigNdState.TXRXPDO:
            self.send_outputs(force=True)  # the first RX-PDO, now that the node takes it

    def _identify(self, sdo: SdoClient, deadline: float) -> None:
        """A reset node that sent no boot-up message: read 1000h until it answers.

        The seed's card does not react to boot-up events (appendix: "Bootup Protocol, no
        reaction on Bootup Events of a Node"); its boot-up is "simple, reading object 1000H".
        So a node of CiA 301 before 4.0, which sends none, boots as well; a boot-up message
        only spares the wait. No answer within ``BOOTUP_TIMEOUT`` of the reset: 34.
        """
        while True:
            if self.master.closing:
                raise _BootFailure(NO_RESPONSE)
            try:
                sdo.upload(0x1000, 0)
                return
            except SdoCommunicationError:
                if time.monotonic() >= deadline:
                    self.diag.status |= NO_RESPONSE_BIT
                    raise _BootFailure(NO_RESPONSE) from None

    def _write_guard_cob_id(self, sdo: SdoClient) -> None:
        """usCobIDGuard into the node's COB-ID guarding object 100Eh (seed 4.2: written into
        the node's object directory during its start-up; CiA 301 before 4.0 defines 100Eh).
        [ours] A node without 100Eh may refuse the default 700h + node-ID, which it uses
        anyway; it must take any other value, or its configuration fails (34, Prm_Fault)."""
        try:
            sdo.download(0x100E, 0, struct.pack("<I", self.params.usCobIDGuard))
        except SdoAbortedError:
            if self.params.usCobIDGuard != 0x700 + self.address:
                raise

    def _fail_boot(self, generation: int, event: int) -> None:
        if generation == self._generation:
            self.fail(event)

    # --- steady operation ---------------------------------------------------------------------

    @property
    def supervised(self) -> bool:
        return self.guard_time > 0

    def set_emcy_consumer(self, cob_id: int | None) -> None:
        """COM_Set_Emcy_Consumer: collect EMCY frames of ``cob_id``, or none."""
        bus = self.master.bus
        if bus is not None and self.emcy_cob_id is not None:
            bus.unsubscribe(self.emcy_cob_id, self._on_emcy)
        self.emcy_cob_id = cob_id
        if bus is not None and cob_id is not None:
            bus.subscribe(cob_id, self._on_emcy)

    def set_supervision(self, heartbeat: bool, time_ms: int, life_time_factor: int) -> None:
        """Switch error control at run time (COM_Set_Guarding, COM_Set_Heartbeat_Consumer)."""
        self.heartbeat = heartbeat
        self.guard_time = time_ms
        self.life_time_factor = life_time_factor
        now = time.monotonic()
        self._last_heartbeat = now
        self._next_guard = now
        self._guard_pending = False
        self._guard_misses = 0
        self._toggle = None
        if self.supervised:
            self.diag.status |= GUARD_ACTIVE_BIT
        else:
            self.diag.status &= ~GUARD_ACTIVE_BIT

    def fail(self, event: int) -> None:
        """The node left data exchange: report it; retry or let auto-clear stop all."""
        if self.state in (State.INACTIVE, State.DISCONNECTED):
            return
        log.info("node %d: Err_Event %d, %s", self.address, event, err_event_text(
            self.address, event, "heartbeat" if self.heartbeat else "guarding"))
        self.state = State.FAILED
        self.diag.actual_error = event
        self.diag.status &= ~GUARD_ACTIVE_BIT
        if event == GUARDING_FAILED:  # guarding or heartbeat: the node no longer answers
            self.diag.status |= NO_RESPONSE_BIT
        self._retry_at = time.monotonic() + RETRY_DELAY
        self.note_diag()  # before Err_Event: a host that sees the event sees Nd_diag too
        self.master.node_failed(self, event)

    def note_diag(self) -> None:
        """Nd_diag: set when Nodestatus_1 or Actual_Error differ from what the host last
        read (seed 4.3), so a node that fails its restarts the same way again and again
        raises it once, and its recovery from a failure raises it again."""
        if (self.diag.status, self.diag.actual_error) != self._diag_seen:
            self.master.set_node_diag(self.address, True)

    def disconnect(self) -> None:
        """The host cleared the node's connection bit: stop it and leave it alone."""
        if self.state is State.INACTIVE:
            return
        self._generation += 1
        self.state = State.DISCONNECTED
        self.master.set_node_state(self.address, False)
        self.master.nmt(NMT_STOP, self.address)

    def idle(self) -> None:
        """The network stopped (host not ready, watchdog, auto-clear)."""
        if self.state is not State.INACTIVE:
            self._generation += 1
            self.state = State.WAITING
            self.master.set_node_state(self.address, False)

    def tick(self, now: float) -> None:
        """Supervision and retries; called from the master's tick."""
        if self.state is State.FAILED:
            if not self.master.auto_clear and now >= self._retry_at:
                self.start_boot()
            return
        if self.state is not State.OPERATING:
            return
        params = self.params
        if self.supervised:
            period = self.guard_time / 1000.0
            if self.heartbeat:
                if now - self._last_heartbeat > period:
                    self.fail(GUARDING_FAILED)
                    return
            elif now >= self._next_guard:
                if self._guard_pending:
                    self._guard_misses += 1
                    if self._guard_misses >= max(1, self.life_time_factor):
                        self.fail(GUARDING_FAILED)
                        return
                self._guard_pending = True
                self._next_guard = now + period
                self.master.bus_send(params.usCobIDGuard, remote=True, dlc=1)
        for entry in self._polled:
            if entry.pdo.bTransType == ASYNC_RTR or not self.master.sync_period:
                if entry.requested and now - entry.requested > RTR_PERIOD:
                    self.fail(NO_RTR_RESPONSE)
                    return
                if not entry.requested:
                    self._request(entry, now)

    def _request(self, entry: InputPdo, now: float) -> None:
        entry.requested = now
        self.master.bus_send(entry.pdo.usPdoCOBId, remote=True, dlc=entry.pdo.data_length)

    def on_sync(self, now: float) -> None:
        """At each SYNC: synchronous outputs, and remote requests of 252 inputs."""
        if self.state is not State.OPERATING:
            return
        self.send_outputs(sync=True)
        for entry in self._polled:
            if entry.pdo.bTransType == SYNC_RTR:
                if entry.requested and now - entry.requested > 2 * self.master.sync_period:
                    self.fail(NO_RTR_RESPONSE)
                    return
                self._request(entry, now)

    def outputs_changed(self, now: bytes, before: bytes) -> bool:
        """Whether any of this node's output PDOs reads differently in ``now``."""
        for entry in self.outputs:
            end = entry.offset + entry.pdo.data_length
            if now[entry.offset : end] != before[entry.offset : end]:
                return True
        return False

    def send_outputs(self, sync: bool = False, force: bool = False) -> bool:
        """Send the RX-PDOs that are due: synchronous ones at SYNC, the rest on change.

        Returns True while a changed event-driven PDO waits for its inhibit time
        (or for a host SDO transfer to end), so the master asks again.
        """
        if self.state is not State.OPERATING or not self.operational_expected:
            return False
        if self.host_sdo:
            return True
        waiting = False
        image = self.master.image
        now = time.monotonic()
        for entry in self._synchronous if sync and not force else self.outputs:
            pdo = entry.pdo
            data = image.read_outputs(entry.offset, pdo.data_length)
            if pdo.bLength & MSK_WORD_PDO and self.master.motorola:
                data = swap_words(data)
            kind = pdo.bTransType
            if kind <= 240:
                if not sync and not force:
                    continue
                entry.syncs += 1
                due = force or (data != entry.last if kind == 0 else entry.syncs >= kind)
                if not due:
                    continue
                entry.syncs = 0
            else:
                if data == entry.last and not force:
                    continue
                inhibit = pdo.usInhibitCycle / 10000.0  # CiA 301: multiples of 100 us
                if not force and now - entry.last_time < inhibit:
                    waiting = True
                    continue
            if self.master.bus_send(pdo.usPdoCOBId, data):
                entry.last = data
                entry.last_time = now
        return waiting

    # --- frames from the node -------------------------------------------------------------------

    def _on_error_control(self, msg: can.Message) -> None:
        if msg.is_remote_frame or not msg.data:
            return
        now = time.monotonic()
        stamp = wall_stamp(msg)
        value = msg.data[0]
        state = value & 0x7F
        if state == BOOT_UP and msg.arbitration_id == 0x700 + self.address:
            # One sent before our reset (at power-on, say) must not pass for its answer:
            # the node would still be resetting when the first SDO request comes.
            if stamp is None or stamp >= self._reset_at:
                self._bootup.set()
            if self.state is State.OPERATING:
                log.info("node %d: unexpected boot-up", self.address)
                self.fail(LEFT_OPERATIONAL)
            return
        self.diag.node_state = state
        if self.state is not State.OPERATING:
            return
        if self.heartbeat:
            self._last_heartbeat = now
        elif self.supervised:  # guarding; [ours] unsupervised: the node's own heartbeat
            self._guard_pending = False
            self._guard_misses = 0
            toggle = value & 0x80
            if self._toggle is not None and toggle == self._toggle:
                self.fail(GUARD_SEQUENCE)
                return
            self._toggle = toggle
        operating = state == OPERATIONAL
        self._confirmed |= operating
        if self.operational_expected and not self.awaiting_start and not operating:
            if not self._confirmed and now - self._started_at < START_GRACE:
                return  # sent before the start reached it
            if stamp is not None and stamp < self._start_stamp:
                return  # [ours] on the bus before the start, read late by a busy card
            self.fail(LEFT_OPERATIONAL)
            return
        self.master.set_node_state(self.address, operating)

    def _on_sdo_response(self, msg: can.Message) -> None:
        """Notes a response of the wrong length; canopen's client never sees it (``CanBus``)."""
        if not msg.is_remote_frame and len(msg.data) != SDO_FRAME_LENGTH:
            log.info("node %d: SDO response of %d bytes", self.address, len(msg.data))
            self._sdo_length_error = True

    def _on_emcy(self, msg: can.Message) -> None:
        if msg.is_remote_frame:
            return
        if len(self.diag.emcy) == EMCY_ENTRIES:
            self.diag.status |= EMCY_OVERFLOW_BIT
        self.diag.emcy.append(bytes(msg.data).ljust(8, b"\0")[:8])
        self.master.set_node_diag(self.address, True)

    def _on_input(self, msg: can.Message) -> None:
        if msg.is_remote_frame or self.state is not State.OPERATING:
            return
        for entry in self.inputs:
            if entry.pdo.usPdoCOBId == msg.arbitration_id:
                entry.requested = 0.0
                data = bytes(msg.data[: entry.pdo.data_length])
                if entry.pdo.bLength & MSK_WORD_PDO and self.master.motorola:
                    data = swap_words(data)
                self.master.image.write_inputs(entry.offset, data)

    def read_diagnosis(self) -> bytes:
        """COM_Node_Diag: the 48-byte structure; reading clears the EMCY buffer."""
        raw = self.diag.encode()
        self._diag_seen = (self.diag.status, self.diag.actual_error)
        self.diag.emcy.clear()
        self.diag.status &= ~EMCY_OVERFLOW_BIT
        return raw


class _BootFailure(Exception):
    def __init__(self, event: int) -> None:
        super().__init__(event)
        self.event = event
