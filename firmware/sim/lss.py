"""CiA 305 layer setting services (LSS) of the simulated devices.

Every live simulated device is an LSS slave: requests arrive on 0x7E5, answers leave on 0x7E4,
always 8 bytes (shorter frames are ignored, as CANopenNode does). A configured node takes its
LSS address from its object 1018h sub 1..4; a device described with ``id = 255`` takes it from
its ``lss`` table and, having no node-ID, stays in NMT initialisation, where it speaks only LSS.

The slave's state machine follows CiA 305 (as Lely's ``lss.c`` implements its figures):

* LSS waiting: switch state global (04h), switch state selective (40h..43h, answered with
  44h after a matching serial number), identify remote slave (46h..4Bh, answered with 4Fh
  when vendor and product match and revision and serial lie in the ranges), identify
  non-configured remote slave (4Ch, answered with 50h), fastscan (51h, answered with 4Fh).
* LSS configuration: switch state global, configure node-ID (11h), configure bit timing
  (13h), activate bit timing (15h), store configuration (17h), inquire identity (5Ah..5Dh)
  and node-ID (5Eh), both identify services.

Answers of the configure services carry CiA 305's error codes: node-ID 0 = success, 1 =
node-ID out of range (valid: 1..127, and 255 to make the device unconfigured); bit timing 0 =
success, 1 = not supported (table selector other than 0, index 5 "reserved", 9 "automatic",
or beyond the table); store 0 = success.

Node-IDs: configure node-ID sets the *pending* node-ID; inquire node-ID reports the *active*
one (FFh while unconfigured). The pending one becomes active

* on an unconfigured device (active and pending FFh before) when the master switches it
  back to LSS waiting: it continues its initialisation and boots up as a CANopen node with
  that ID (its ``eds``, else the generic I/O module; 1018h keeps the LSS address);
* on a configured device at the next NMT reset communication or reset node addressed to
  it: it boots up under the new node-ID (255: it drops back to an unconfigured device).

Only unconfigured devices (active and pending node-ID FFh) take part in fastscan and answer
"identify non-configured remote slave": 309-1 4.8.12 scans for unconfigured devices, and
CANopenNode's slave behaves so.

Decisions [ours]:

* A device that changes its node-ID comes back as a fresh device: the object dictionary
  is built anew (as after reset node), the LSS state stays with the device.
* NMT reset node activates the pending node-ID as reset communication does; the *stored*
  configuration is what a power cycle (``SimulatedNetwork.stop`` / ``start``) restores.
* Activate bit timing: the device ignores LSS for twice the switch delay (CiA 305: silent
  for the delay, switch, silent for the delay again), then runs at the new rate. Bit
  rates are bookkeeping only: python-can's virtual bus has none, and the node's other
  traffic is not interrupted.
* A device whose new node-ID another live device already uses stays off the CANopen side
  (a warning is logged) instead of corrupting that node's traffic.
* Several slaves answering one request each send their own frame, as separate devices do;
  a master must expect duplicates.
"""

from __future__ import annotations

import logging
import struct
import time
from dataclasses import replace
from functools import partial
from typing import TYPE_CHECKING

from dbm_tools.network import NodeDescription
from dpm.cia301 import NODE_ID_MAX
from dpm.cia305 import (
    ACTIVATE_BIT_TIMING,
    BIT_TIMING_TABLE,
    CONFIGURATION,
    CONFIGURE_BIT_TIMING,
    CONFIGURE_NODE_ID,
    ERROR_BIT_TIMING_NOT_SUPPORTED,
    ERROR_NODE_ID_RANGE,
    ERROR_NONE,
    FASTSCAN,
    FASTSCAN_RESET,
    IDENTIFY_NON_CONFIGURED_REMOTE,
    IDENTIFY_NON_CONFIGURED_SLAVE,
    IDENTIFY_REMOTE_SERIAL_HIGH,
    IDENTIFY_REMOTE_VENDOR,
    IDENTIFY_SLAVE,
    INQUIRE_NODE_ID,
    INQUIRE_SERIAL,
    INQUIRE_VENDOR,
    LSS_ANSWER_COB_ID,
    LSS_REQUEST_COB_ID,
    STORE_CONFIGURATION,
    SWITCH_SELECTIVE_ANSWER,
    SWITCH_SELECTIVE_SERIAL,
    SWITCH_SELECTIVE_VENDOR,
    SWITCH_STATE_GLOBAL,
    UNCONFIGURED,
    WAITING,
    LssAddress,
)
from firmware.sim.nmt import COB_ID as NMT_COB_ID
from firmware.sim.nmt import RESET_COMMUNICATION as NMT_RESET_COMMUNICATION
from firmware.sim.nmt import RESET_NODE as NMT_RESET_NODE

if TYPE_CHECKING:
    from firmware.sim.network import SimulatedNetwork
    from firmware.sim.node import SimulatedNode

log = logging.getLogger(__name__)


def _valid_node_id(node_id: int) -> bool:
    return 1 <= node_id <= NODE_ID_MAX or node_id == UNCONFIGURED


def _answer(cs: int, payload: bytes = b"") -> bytes:
    return bytes([cs]) + payload.ljust(7, b"\0")


class LssSlave:
    """The LSS side of one device: its state machine and its pending and stored configuration.

    It outlives the device's CANopen node object, which is replaced whenever the node-ID
    changes; ``node`` is None while the device has no (usable) node-ID.
    """

    def __init__(self, description: NodeDescription, node: SimulatedNode | None,
                 bitrate: int) -> None:
        self.description = description
        self.node = node
        self.state = WAITING
        self.active_node_id = self.pending_node_id = self.stored_node_id = description.id
        self.bitrate = self.pending_bitrate = self.stored_bitrate = bitrate
        """The rate the device runs at; bookkeeping, since the virtual bus has none."""
        self.silent_until = 0.0
        """End of the switch delays of an activate bit timing: no LSS until then."""
        self._select_next = 0
        """The switch-selective command specifier expected next (0: a new sequence)."""
        self._identify_next = 0
        """The identify-remote-slave command specifier expected next."""
        self._fastscan_pos = 0
        """LSSPos: the LSS number (0 vendor .. 3 serial) the next fastscan step checks."""
        self.start_up_due = False
        """Switched to waiting with a first node-ID pending: the device starts up under it."""

    @property
    def address(self) -> LssAddress:
        """The LSS address: 1018h of the live node, else the description's ``lss``."""
        if self.node is not None:
            return LssAddress(*(self.node.value(0x1018, sub, 0) for sub in range(1, 5)))
        assert self.description.lss is not None  # load_network demands it for id 255
        return self.description.lss

    def number(self, lss_sub: int) -> int:
        """LSS number ``lss_sub``: 0 vendor-ID, 1 product code, 2 revision, 3 serial."""
        address = self.address
        return (address.vendor, address.product, address.revision, address.serial)[lss_sub]

    @property
    def unconfigured(self) -> bool:
        """No node-ID now and none pending: the devices fastscan looks for."""
        return self.active_node_id == UNCONFIGURED and self.pending_node_id == UNCONFIGURED

    @property
    def activation_due(self) -> bool:
        """A node-ID other than the active one is pending (255 included)."""
        return self.pending_node_id != self.active_node_id

    def reset_state(self) -> None:
        """LSS waiting with every sequence forgotten (power-on, switch to waiting)."""
        self.state = WAITING
        self._select_next = self._identify_next = self._fastscan_pos = 0

    def power_cycle(self) -> None:
        """The stored configuration becomes pending; the caller re-creates the node."""
        self.reset_state()
        self.pending_node_id = self.stored_node_id
        self.bitrate = self.pending_bitrate = self.stored_bitrate
        self.silent_until = 0.0

    def on_request(self, data: bytes, now: float) -> bytes | None:
        """One LSS request; the answer frame's data, or None when this slave stays silent."""
        if now < self.silent_until:
            return None
        cs = data[0]
        number = int.from_bytes(data[1:5], "little")
        if cs == SWITCH_STATE_GLOBAL:
            if data[1] == WAITING:
                self.start_up_due = (self.active_node_id == UNCONFIGURED
                                     and self.activation_due)
                self.reset_state()
            elif data[1] == CONFIGURATION:
                self.state = CONFIGURATION
            return None
        if IDENTIFY_REMOTE_VENDOR <= cs <= IDENTIFY_REMOTE_SERIAL_HIGH:
            return self._identify_remote(cs, number)
        if cs == IDENTIFY_NON_CONFIGURED_REMOTE:
            return _answer(IDENTIFY_NON_CONFIGURED_SLAVE) if self.unconfigured else None
        if self.state == WAITING:
            if SWITCH_SELECTIVE_VENDOR <= cs <= SWITCH_SELECTIVE_SERIAL:
                return self._switch_selective(cs, number)
            if cs == FASTSCAN:
                return self._fastscan(number, data[5], data[6], data[7])
            return None
        return self._configure(cs, data, now)

    def _switch_selective(self, cs: int, number: int) -> bytes | None:
        """Vendor, product, revision, serial in this order; any mismatch starts over."""
        index = cs - SWITCH_SELECTIVE_VENDOR
        in_sequence = cs in (SWITCH_SELECTIVE_VENDOR, self._select_next)
        if not in_sequence or number != self.number(index):
            self._select_next = 0
            return None
        if cs != SWITCH_SELECTIVE_SERIAL:
            self._select_next = cs + 1
            return None
        self._select_next = 0
        self.state = CONFIGURATION
        return _answer(SWITCH_SELECTIVE_ANSWER)

    def _identify_remote(self, cs: int, number: int) -> bytes | None:
        """Vendor and product equal, revision and serial within [low, high]; 4Fh at the end."""
        if cs != IDENTIFY_REMOTE_VENDOR and cs != self._identify_next:
            self._identify_next = 0
            return None
        step = cs - IDENTIFY_REMOTE_VENDOR  # 0 vendor, 1 product, 2/3 revision, 4/5 serial
        if step < 2:
            match = number == self.number(step)
        else:
            value = self.number(2 if step < 4 else 3)
            match = value >= number if step % 2 == 0 else value <= number
        if not match:
            self._identify_next = 0
            return None
        if cs != IDENTIFY_REMOTE_SERIAL_HIGH:
            self._identify_next = cs + 1
            return None
        self._identify_next = 0
        return _answer(IDENTIFY_SLAVE)

    def _fastscan(self, id_number: int, bit_checked: int, lss_sub: int,
                  lss_next: int) -> bytes | None:
        """CiA 305 fastscan: answer when bits 31..BitChecked of LSS number LSSSub match."""
        if not self.unconfigured:
            return None
        if bit_checked == FASTSCAN_RESET:
            self._fastscan_pos = 0
            return _answer(IDENTIFY_SLAVE)
        if bit_checked > 31 or lss_sub > 3 or lss_next > 3 or lss_sub != self._fastscan_pos:
            return None
        mask = (0xFFFF_FFFF << bit_checked) & 0xFFFF_FFFF
        if (id_number ^ self.number(lss_sub)) & mask:
            return None
        self._fastscan_pos = lss_next
        if bit_checked == 0 and lss_next < lss_sub:  # the last number confirmed: selected
            self.state = CONFIGURATION
        return _answer(IDENTIFY_SLAVE)

    def _configure(self, cs: int, data: bytes, now: float) -> bytes | None:
        """The services of LSS configuration state."""
        if cs == CONFIGURE_NODE_ID:
            if not _valid_node_id(data[1]):
                return _answer(cs, bytes([ERROR_NODE_ID_RANGE]))
            self.pending_node_id = data[1]
            return _answer(cs, bytes([ERROR_NONE]))
        if cs == CONFIGURE_BIT_TIMING:
            rate = BIT_TIMING_TABLE.get(data[2]) if data[1] == 0 else None
            if rate is None:
                return _answer(cs, bytes([ERROR_BIT_TIMING_NOT_SUPPORTED]))
            self.pending_bitrate = rate
            return _answer(cs, bytes([ERROR_NONE]))
        if cs == ACTIVATE_BIT_TIMING:
            (delay_ms,) = struct.unpack_from("<H", data, 1)
            self.bitrate = self.pending_bitrate
            self.silent_until = now + 2 * delay_ms / 1000.0
            return None
        if cs == STORE_CONFIGURATION:
            self.stored_node_id = self.pending_node_id
            self.stored_bitrate = self.pending_bitrate
            return _answer(cs, bytes([ERROR_NONE]))
        if INQUIRE_VENDOR <= cs <= INQUIRE_SERIAL:
            return _answer(cs, struct.pack("<I", self.number(cs - INQUIRE_VENDOR)))
        if cs == INQUIRE_NODE_ID:
            return _answer(cs, bytes([self.active_node_id]))
        return None


class LssBus:
    """The LSS slaves of a ``SimulatedNetwork``: request dispatch and node-ID activation.

    It subscribes to 0x7E5 and to NMT before any node does, so it sees an NMT reset
    before the node acts on it: a node whose node-ID is about to change is powered off
    at once (it then ignores the reset) and comes back under its new node-ID from the
    network's timer thread, outside canopen's dispatch of that frame.
    """

    def __init__(self, network: SimulatedNetwork, configured: list[SimulatedNode],
                 unconfigured: list[NodeDescription]) -> None:
        self.network = network
        bitrate = network.description.bus.bitrate
        self.slaves = [LssSlave(node.description, node, bitrate) for node in configured]
        self.slaves += [LssSlave(description, None, bitrate) for description in unconfigured]
        network.canopen.subscribe(LSS_REQUEST_COB_ID, self._on_request)
        network.canopen.subscribe(NMT_COB_ID, self._on_nmt)

    def unconfigured(self) -> list[NodeDescription]:
        """The descriptions of the devices without node-ID now."""
        return [slave.description for slave in self.slaves
                if slave.active_node_id == UNCONFIGURED]

    def _on_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        del can_id, timestamp
        if len(data) != 8:
            return
        request = bytes(data)
        now = time.monotonic()
        with self.network.lock:
            for slave in self.slaves:
                if slave.description.sim.silent:
                    continue  # a silent device never touches the bus
                answer = slave.on_request(request, now)
                if answer is not None:
                    self.network.canopen.send_message(LSS_ANSWER_COB_ID, answer)
                if slave.start_up_due:
                    # CiA 305: an unconfigured device given a node-ID continues its start-up
                    slave.start_up_due = False
                    self.network.scheduler.call_later(0.0, partial(self._activate, slave))

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        del can_id, timestamp
        if len(data) != 2 or data[0] not in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
            return
        with self.network.lock:
            for slave in self.slaves:
                node = slave.node
                if node is None or data[1] not in (0, node.node_id) or not slave.activation_due:
                    continue
                node.power_off()  # the node ignores the reset; it boots under its new ID
                self.network.scheduler.call_later(0.0, partial(self._activate, slave))

    def _activate(self, slave: LssSlave) -> None:
        """The pending node-ID becomes active: the device boots up under it (runs locked)."""
        if not slave.activation_due:
            return
        address = slave.address
        if slave.node is not None:
            self.network.remove_node(slave.node)
            slave.node = None
        node_id = slave.active_node_id = slave.pending_node_id
        slave.description = replace(slave.description, id=node_id, lss=address)
        if node_id == UNCONFIGURED:
            log.info("LSS slave %s: node-ID removed, unconfigured", address)
        elif node_id in self.network.nodes:
            log.warning("LSS slave %s: node-ID %d is taken by another device; it stays off "
                        "the CANopen side", address, node_id)
        else:
            log.info("LSS slave %s: node-ID %d active, booting", address, node_id)
            slave.node = self.network.add_node(slave.description)

    def power_cycle(self) -> None:
        """Power off: every device restarts with its stored configuration (network stopped)."""
        for slave in self.slaves:
            slave.power_cycle()
            self._activate(slave)
