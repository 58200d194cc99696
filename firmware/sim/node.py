"""A simulated CANopen device: canopen's ``LocalNode`` behaving like a real CiA 301 slave.

``LocalNode`` gives the object dictionary with its stored values, the SDO
server, the PDO maps, an NMT state with a heartbeat producer and an EMCY
frame encoder. Around them this class adds the device: power-on and the two
NMT resets with their boot-up message and restored parameters, the state
machine's effect on every service, node and life guarding, EMCY on the COB-ID
in 1014h with the error register 1001h and the error history 1003h, PDO
communication (``PdoEngine``), the I/O echo and the injected faults of the
node's ``[node.sim]`` table.

Every entry point (bus callbacks and timers) runs under the network's lock.
"""

from __future__ import annotations

import logging
import threading

import can
from canopen import LocalNode
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable
from canopen.objectdictionary.datatypes import UNSIGNED32
from canopen.sdo.exceptions import SdoAbortedError

from dbm_tools.network import NodeDescription
from dpm.cia301 import (
    ABORT_VALUE_RANGE,
    EMCY_BASE,
    ERROR_CONTROL_BASE,
    INITIALISING,
    OPERATIONAL,
    PRE_OPERATIONAL,
    STOPPED,
)
from firmware.frames import (
    CAN_ERR_ACK,
    CAN_ERR_BUSOFF,
    CAN_ERR_CRTL,
    CAN_ERR_CRTL_RX_OVERFLOW,
    CAN_ERR_CRTL_RX_WARNING,
    CAN_ERR_CRTL_TX_WARNING,
    CAN_ERR_PROT,
)
from firmware.sim.generic import INPUTS, OUTPUTS
from firmware.sim.nmt import (
    ENTER_PRE_OPERATIONAL,
    RESET_COMMUNICATION,
    RESET_NODE,
    START,
    STOP,
    NodeGuarding,
    SimNmt,
)
from firmware.sim.pdo import PdoEngine
from firmware.sim.scheduler import Scheduler, Timer
from firmware.sim.sdo import SimSdoServer

log = logging.getLogger(__name__)

ERROR_REGISTER = 0x1001
ERROR_FIELD = 0x1003
ERROR_BEHAVIOUR = 0x1029
GUARD_COB_ID = 0x100E
COMMUNICATION_AREA = range(0x1000, 0x2000)
PDO_PARAMETERS = range(0x1400, 0x1C00)
EMCY_INVALID = 1 << 31
STATE_NAMES = {INITIALISING: "INITIALISING", STOPPED: "STOPPED", OPERATIONAL: "OPERATIONAL",
               PRE_OPERATIONAL: "PRE-OPERATIONAL"}


def error_frame(kind: str) -> can.Message:
    """An error frame as a CAN controller driver reports it (SocketCAN layout)."""
    if kind == "bus_off":
        return can.Message(is_error_frame=True, arbitration_id=CAN_ERR_BUSOFF, dlc=8,
                           data=bytes(8))
    if kind == "ack":
        return can.Message(is_error_frame=True, arbitration_id=CAN_ERR_ACK, dlc=8,
                           data=bytes(8))
    if kind == "protocol":  # a form error in a frame: the error counters only move
        return can.Message(is_error_frame=True, arbitration_id=CAN_ERR_PROT, dlc=8,
                           data=bytes([0, 0, 0x02]) + bytes(5))
    status = (CAN_ERR_CRTL_RX_OVERFLOW if kind == "rx_overflow"
              else CAN_ERR_CRTL_RX_WARNING | CAN_ERR_CRTL_TX_WARNING)
    return can.Message(is_error_frame=True, arbitration_id=CAN_ERR_CRTL, dlc=8,
                       data=bytes([0, status]) + bytes(6))


def error_register_bits(code: int) -> int:
    """The 1001h bits an EMCY error code sets (CiA 301 table 47): generic plus its class."""
    bits = 0x01
    if code >> 12 == 0x2:
        bits |= 0x02  # current
    elif code >> 12 == 0x3:
        bits |= 0x04  # voltage
    elif code >> 12 == 0x4:
        bits |= 0x08  # temperature
    elif code >> 8 in (0x81, 0x82):
        bits |= 0x10  # communication
    elif code >> 8 == 0xFF:
        bits |= 0x80  # manufacturer specific
    return bits


class SimulatedNode(LocalNode):
    nmt: SimNmt
    sdo: SimSdoServer

    def __init__(self, description: NodeDescription, dictionary: ObjectDictionary,
                 scheduler: Scheduler, lock: threading.RLock) -> None:
        super().__init__(description.id, dictionary)
        self.description = description
        self.node_id: int = description.id
        """The node-ID as a plain int (canopen's ``id`` may be None)."""
        self.scheduler = scheduler
        self.lock = lock
        # LocalNode hooks its own NmtSlave to 1017h writes; SimNmt takes that slave's place.
        self._write_callbacks.remove(self.nmt.on_write)
        self.nmt = SimNmt(self)
        self.add_write_callback(self.nmt.on_write)  # type: ignore[no-untyped-call]
        self.add_write_callback(self._on_write)  # type: ignore[no-untyped-call]
        self.sdo = SimSdoServer(self)
        self.guarding = NodeGuarding(self)
        self.pdo_engine = PdoEngine(self)
        inputs = dictionary.get(INPUTS)
        subs = inputs.subindices if isinstance(inputs, (ODArray, ODRecord)) else {}
        self._echoed = frozenset(sub for sub in subs if sub)
        """Subindices of 6000h that echo 6200h's."""
        self.written: list[tuple[int, int]] = []
        """Objects written since the last ``after_writes`` (by SDO, RPDO or the byte path)."""
        self._errors: set[int] = set()
        self._power_timers: list[Timer] = []
        self._burst_pending = False
        """The EMCY burst waits for the first OPERATIONAL after power-on."""
        self._cycle_timers: list[Timer] = []
        """Timers of the current boot cycle (boot-up, faults), cancelled by a reset."""
        self._leave_operational: Timer | None = None
        self._guard_cob_id: int | None = None
        """``guard_cob_id`` as last read; None: read 100Eh again."""
        if description.sim.device_type is not None:
            self._device_type_var().value = description.sim.device_type

    def _device_type_var(self) -> ODVariable:
        var = self.object_dictionary.get(0x1000)
        if not isinstance(var, ODVariable):
            var = ODVariable("Device type", 0x1000)
            var.data_type, var.access_type = UNSIGNED32, "ro"
            self.object_dictionary.add_object(var)
        return var

    # --- object access for the services ----------------------------------------------

    @property
    def state(self) -> str:
        return STATE_NAMES[self.nmt.code]

    @property
    def serves_sdo(self) -> bool:
        return self.nmt.code in (PRE_OPERATIONAL, OPERATIONAL)

    @property
    def guard_cob_id(self) -> int:
        """Where guarding requests come and answers go: 100Eh where the node has it.

        Kept once read until 100Eh is written or the node resets: every remote frame on
        the bus asks every node (``on_remote``), and reading the dictionary each time made
        one remote frame cost 127 nodes 0.4 ms of the simulator's time, which the SDO
        answers of a booting network waited behind."""
        cob_id = self._guard_cob_id
        if cob_id is None:
            cob_id = self._guard_cob_id = (
                self.value(GUARD_COB_ID, 0, self.description.cob_id_guard) & 0x7FF)
        return cob_id

    def value(self, index: int, subindex: int, default: int) -> int:
        """An unsigned object's current value; ``default`` where the dictionary has none."""
        try:
            return int.from_bytes(self.get_data(index, subindex), "little")
        except SdoAbortedError:
            return default

    def store(self, index: int, subindex: int, value: int) -> None:
        """Set a value as the device itself does: no write checks, no write callbacks."""
        var = self.object_dictionary.get_variable(index, subindex)
        if var is not None:
            self.data_store.setdefault(index, {})[subindex] = var.encode_raw(value)
            if index == GUARD_COB_ID:
                self._guard_cob_id = None

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        """canopen calls this before it stores a written value; raising aborts the SDO."""
        del od
        if index == ERROR_FIELD and subindex == 0 and any(data):
            raise SdoAbortedError(ABORT_VALUE_RANGE)  # only 0 (clear the history) is allowed
        self.written.append((index, subindex))
        if index == GUARD_COB_ID:
            self._guard_cob_id = None

    def after_writes(self) -> None:
        """Act on values stored by an SDO download or an RPDO."""
        written, self.written = self.written, []
        if not written:
            return
        if any(index == GUARD_COB_ID for index, _ in written):
            self._guard_cob_id = None  # stored now (the write callback comes before the store)
        if any(index in PDO_PARAMETERS or index == 0x1005 for index, _ in written):
            self.pdo_engine.configure()
        if (ERROR_FIELD, 0) in written:
            for sub in self._error_field_subs():
                self.store(ERROR_FIELD, sub, 0)
        self._echo([sub for index, sub in written if index == OUTPUTS])
        self.pdo_engine.data_changed()

    def _echo(self, subs: list[int]) -> None:
        """Inputs echo outputs: a CiA 401 module with 6000h and 6200h reads back what it drives."""
        echoed = self._echoed
        if not echoed:
            return
        outputs = self.data_store.get(OUTPUTS, {})
        inputs = self.data_store.setdefault(INPUTS, {})
        for sub in subs:
            if sub in echoed:
                data = outputs.get(sub)
                inputs[sub] = data if data is not None else self.get_data(OUTPUTS, sub)

    # --- power and NMT ---------------------------------------------------------------

    def power_on(self) -> None:
        # [ours] the EMCY burst counts from the node's first OPERATIONAL, not from power-on:
        # a master that configures the node later (another process, a slow machine) still
        # hears it, as it would hear a fault of a device in operation
        self._power_timers = []
        self._burst_pending = self.description.sim.emcy_burst is not None
        errors = self.description.sim.bus_errors
        if errors is not None:
            frame = error_frame(errors.kind)
            self._power_timers += [
                self.scheduler.call_later(errors.after_s + n * 0.01,
                                          lambda: self._send_error_frame(frame))
                for n in range(errors.count)]
        self._reset(application=True)

    def _send_error_frame(self, frame: can.Message) -> None:
        if self.network.bus is not None:
            self.network.bus.send(frame)

    def power_off(self) -> None:
        for timer in self._power_timers:
            timer.cancel()
        self._cancel_cycle()
        self.pdo_engine.release()
        self.nmt.stop_heartbeat()  # type: ignore[no-untyped-call]
        self.nmt.enter(INITIALISING)

    def on_nmt_command(self, data: bytes) -> None:
        with self.lock:
            if len(data) != 2 or data[1] not in (0, self.node_id) or self.nmt.code == INITIALISING:
                return
            command = data[0]
            if command == START:
                self._enter(OPERATIONAL)
            elif command == STOP:
                self._enter(STOPPED)
            elif command == ENTER_PRE_OPERATIONAL:
                self._enter(PRE_OPERATIONAL)
            elif command == RESET_NODE:
                self._reset(application=True)
            elif command == RESET_COMMUNICATION:
                self._reset(application=False)

    def _reset(self, application: bool) -> None:
        """Reset node (application) or communication: INITIALISING, then the boot-up."""
        log.info("node %d: reset %s", self.node_id, "node" if application else "communication")
        self._cancel_cycle()
        self.pdo_engine.stop()
        self.nmt.stop_heartbeat()  # type: ignore[no-untyped-call]
        self.nmt.heartbeat_failed = False
        self.nmt.enter(INITIALISING)
        self.guarding.reset()
        self._errors.clear()
        self.written.clear()
        for index in list(self.data_store):
            if application or index in COMMUNICATION_AREA:
                del self.data_store[index]
        self._guard_cob_id = None
        delay = self.description.sim.boot_delay_s if application else 0.0
        self._cycle_timers = [self.scheduler.call_later(delay, self._boot)]

    def _cancel_cycle(self) -> None:
        for timer in self._cycle_timers:
            timer.cancel()
        if self._leave_operational is not None:
            self._leave_operational.cancel()

    def _boot(self) -> None:
        sim = self.description.sim
        # PRE-OPERATIONAL before the boot-up is out: on SocketCAN a master hears it at
        # once and may look at the node's state (or send it a request) right away.
        self.nmt.enter(PRE_OPERATIONAL)
        if not sim.no_bootup:
            self.network.send_message(ERROR_CONTROL_BASE + self.node_id, b"\x00")
        log.info("node %d: boot-up, PRE-OPERATIONAL", self.node_id)
        self.pdo_engine.configure()
        self.nmt.start_heartbeat(self.value(0x1017, 0, 0))
        if sim.heartbeat_stop_after_s is not None:
            self._cycle_timers.append(
                self.scheduler.call_later(sim.heartbeat_stop_after_s, self._kill_heartbeat))
        if sim.guarding_fail_after_s is not None:
            self._cycle_timers.append(
                self.scheduler.call_later(sim.guarding_fail_after_s, self._fail_guarding))

    def _kill_heartbeat(self) -> None:
        log.info("node %d: fault: heartbeat stops", self.node_id)
        self.nmt.kill_heartbeat()

    def _fail_guarding(self) -> None:
        log.info("node %d: fault: guarding stops", self.node_id)
        self.guarding.failed = True

    def _enter(self, state: int) -> None:
        old = self.nmt.code
        if state == old:
            return
        log.info("node %d: %s -> %s", self.node_id, STATE_NAMES[old], STATE_NAMES[state])
        self.nmt.enter(state)
        if old == OPERATIONAL:
            self.pdo_engine.stop()
            if self._leave_operational is not None:
                self._leave_operational.cancel()
        if state == OPERATIONAL:
            self.pdo_engine.start()
            burst = self.description.sim.emcy_burst
            if self._burst_pending and burst is not None:
                self._burst_pending = False
                self._power_timers += [
                    self.scheduler.call_later(burst.after_s + n * burst.interval_s,
                                              lambda: self.emergency(burst.code))
                    for n in range(burst.count)]
            after = self.description.sim.leave_operational_after_s
            if after is not None:
                self._leave_operational = self.scheduler.call_later(
                    after, lambda: self._enter(PRE_OPERATIONAL))

    def on_remote(self, cob_id: int) -> None:
        """A remote frame from the bus: a guarding request or a TPDO request."""
        with self.lock:
            if cob_id == self.guard_cob_id:
                self.guarding.on_request()
            else:
                self.pdo_engine.on_remote(cob_id)

    # --- errors ----------------------------------------------------------------------

    def emergency(self, code: int) -> None:
        """An error occurred: set 1001h, log it in 1003h and send its EMCY."""
        self._errors.add(code)
        self.store(ERROR_REGISTER, 0, self._register())
        subs = self._error_field_subs()
        if subs:
            count = min(self.value(ERROR_FIELD, 0, 0) + 1, len(subs))
            for sub in range(count, 1, -1):
                self.store(ERROR_FIELD, sub, self.value(ERROR_FIELD, sub - 1, 0))
            self.store(ERROR_FIELD, 1, code)
            self.store(ERROR_FIELD, 0, count)
        self._send_emcy(code)

    def clear_error(self, code: int) -> None:
        """An error has gone: EMCY 0000h ("error reset") with the errors that remain."""
        self._errors.discard(code)
        self.store(ERROR_REGISTER, 0, self._register())
        self._send_emcy(0)

    def communication_error(self, code: int) -> None:
        """EMCY, then the error behaviour of 1029h sub 1 (default: leave OPERATIONAL)."""
        self.emergency(code)
        behaviour = self.value(ERROR_BEHAVIOUR, 1, 0)
        if behaviour == 0 and self.nmt.code == OPERATIONAL:
            self._enter(PRE_OPERATIONAL)
        elif behaviour == 2:
            self._enter(STOPPED)

    def _register(self) -> int:
        register = 0
        for code in self._errors:
            register |= error_register_bits(code)
        return register

    def _error_field_subs(self) -> list[int]:
        field = self.object_dictionary.get(ERROR_FIELD)
        if not isinstance(field, (ODArray, ODRecord)):
            return []
        return [sub for sub in field.subindices if sub]

    def _send_emcy(self, code: int) -> None:
        cob_id = self.value(0x1014, 0, EMCY_BASE + self.node_id)
        if self.nmt.code not in (PRE_OPERATIONAL, OPERATIONAL) or cob_id & EMCY_INVALID:
            return
        self.emcy.cob_id = cob_id & 0x7FF
        self.emcy.send(code, self.value(ERROR_REGISTER, 0, 0))
