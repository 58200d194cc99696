"""PDO communication of a simulated node: SYNC consumer, RPDO reception, TPDO transmission.

canopen gives a ``LocalNode`` its PDO maps (1400h..1BFFh parsed into
``PdoMap`` objects with bit-exact packing) and RPDO reception into those maps,
but nothing that acts: received RPDOs never reach the object dictionary, and
TPDOs go out only when the application calls ``transmit``. This engine adds
the CiA 301 behaviour (7.2.2), all of it in OPERATIONAL only:

- RPDOs: asynchronous types (254, 255) are written to the object dictionary
  on reception, synchronous ones (0..240) at the next SYNC; a frame shorter
  than the mapping is dropped with EMCY 8210h.
- TPDOs: 0 at SYNC when the data changed; 1..240 at every n-th SYNC; 252
  sampled at SYNC and sent on a remote frame; 253 sent on a remote frame;
  254/255 on change of the mapped data, on their event timer, on a remote
  frame and once on entering OPERATIONAL. Inhibit time (100 us units) holds
  an event-driven transmission back; the newest data goes out when it ends.
- SYNC on the COB-ID in 1005h (0x80 when the object is missing).

Within one SYNC, received synchronous RPDOs are applied before the TPDOs are
sampled, so an echoing node answers a synchronous output in the same cycle.

A map of whole application objects on byte boundaries (every generic node's,
and most real devices') is copied byte-wise instead of through canopen's
bit-exact packing: the same bytes, for a fraction of the interpreter time a
busy simulated network spends per PDO.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from canopen.network import Callback
from canopen.pdo import PdoMap, PdoMaps

from dpm.cia301 import COB_ID_SYNC, EVENT_TYPES, OPERATIONAL, SYNC_RTR, SYNC_TYPES_MAX
from firmware.sim.scheduler import Timer

if TYPE_CHECKING:
    from firmware.sim.node import SimulatedNode

PDO_LENGTH_ERROR = 0x8210
"""EMCY code: PDO not processed due to length error (CiA 301 table 21)."""
INHIBIT_UNIT_S = 100e-6
APPLICATION_AREA = 0x2000
"""Objects from here on have no side effects on write: their PDOs may take the byte path."""

BytePlan = tuple[tuple[int, int, int, int], ...]
"""Index, subindex, first byte and end byte of each mapped object."""


def byte_plan(pdo_map: PdoMap) -> BytePlan | None:
    """The map as whole application objects on byte boundaries; None when it needs bit packing."""
    plan: list[tuple[int, int, int, int]] = []
    for var in pdo_map.map:
        if (var.offset is None or var.offset % 8 or var.length % 8
                or var.index < APPLICATION_AREA or var.length != len(var.od)):
            return None
        plan.append((var.index, var.subindex, var.offset // 8, (var.offset + var.length) // 8))
    return tuple(plan)


@dataclass
class _Rpdo:
    map: PdoMap
    plan: BytePlan | None
    size: int
    """Bytes the mapping needs; a shorter frame is a length error."""


@dataclass
class _Tpdo:
    map: PdoMap
    last: bytes | None = None
    """Payload of the last transmission (None: none since configuration)."""
    last_time: float = -math.inf
    sync_count: int = 0
    sampled: bytes | None = None
    """Type 252: the data sampled at the last SYNC."""
    deferred: Timer | None = None
    """An event-driven transmission waiting for the inhibit time to pass."""
    event_timer: Timer | None = None
    plan: BytePlan | None = None


class PdoEngine:
    def __init__(self, node: SimulatedNode) -> None:
        self._node = node
        self._tpdos: list[_Tpdo] = []
        self._rpdos: dict[int, _Rpdo] = {}
        """Valid RPDOs by COB-ID."""
        self._pending: dict[int, bytes] = {}
        """Synchronous RPDO payloads by COB-ID, applied at the next SYNC."""
        self._subscriptions: list[tuple[int, Callback]] = []

    @property
    def _operational(self) -> bool:
        return self._node.nmt.code == OPERATIONAL

    # --- configuration ---------------------------------------------------------------

    def configure(self) -> None:
        """(Re)read the PDO and SYNC parameters; after boot-up and every write to them."""
        self.release()
        network = self._node.network
        for rpdo in _maps(self._node.rpdo.map):
            rpdo.read()
            if rpdo.enabled and rpdo.cob_id is not None:
                # read() subscribed canopen's own reception; frames come here instead.
                network.unsubscribe(rpdo.cob_id, rpdo.on_message)
                self._rpdos[rpdo.cob_id] = _Rpdo(rpdo, byte_plan(rpdo),
                                                 math.ceil(rpdo.length / 8))
                network.subscribe(rpdo.cob_id, self._on_rpdo)
                self._subscriptions.append((rpdo.cob_id, self._on_rpdo))
        for tpdo in _maps(self._node.tpdo.map):
            tpdo.read()
            if tpdo.enabled and tpdo.cob_id is not None:
                # read() subscribed the TPDO for reception too; a frame of
                # another device on that COB-ID must not overwrite our data.
                network.unsubscribe(tpdo.cob_id, tpdo.on_message)
                self._tpdos.append(_Tpdo(tpdo, plan=byte_plan(tpdo)))
        sync = (self._node.value(0x1005, 0, COB_ID_SYNC) & 0x7FF, self.on_sync)
        network.subscribe(*sync)
        self._subscriptions.append(sync)

    def release(self) -> None:
        """Stop, and drop every subscription: the node leaves the bus or reconfigures."""
        self.stop()
        self._tpdos = []
        self._rpdos = {}
        for cob_id, callback in self._subscriptions:
            self._node.network.unsubscribe(cob_id, callback)
        self._subscriptions.clear()

    # --- NMT -------------------------------------------------------------------------

    def start(self) -> None:
        """Entering OPERATIONAL: event-driven TPDOs report their current data."""
        for tpdo in self._tpdos:
            tpdo.last, tpdo.sync_count, tpdo.sampled = None, 0, None
            if tpdo.map.trans_type in EVENT_TYPES:
                self._send(tpdo, self._payload(tpdo))

    def stop(self) -> None:
        """Leaving OPERATIONAL (or resetting): nothing pending survives."""
        self._pending.clear()
        for tpdo in self._tpdos:
            for timer in (tpdo.deferred, tpdo.event_timer):
                if timer is not None:
                    timer.cancel()
            tpdo.deferred = tpdo.event_timer = None

    # --- events ----------------------------------------------------------------------

    def data_changed(self) -> None:
        """The application changed object values: event-driven TPDOs send what changed."""
        if not self._operational:
            return
        for tpdo in self._tpdos:
            if tpdo.map.trans_type in EVENT_TYPES:
                payload = self._payload(tpdo)
                if payload != tpdo.last:
                    self._trigger(tpdo, payload)

    def on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        del can_id, data, timestamp
        with self._node.lock:
            if not self._operational:
                return
            pending, self._pending = self._pending, {}
            for cob_id, payload in pending.items():
                rpdo = self._rpdos.get(cob_id)
                if rpdo is not None:
                    self._apply(rpdo, payload)
            if pending:
                self._node.after_writes()
            for tpdo in self._tpdos:
                kind = tpdo.map.trans_type or 0
                if kind == 0:
                    payload = self._payload(tpdo)
                    if payload != tpdo.last:
                        self._send(tpdo, payload)
                elif kind <= SYNC_TYPES_MAX:
                    tpdo.sync_count += 1
                    if tpdo.sync_count >= kind:
                        tpdo.sync_count = 0
                        self._send(tpdo, self._payload(tpdo))
                elif kind == SYNC_RTR:
                    tpdo.sampled = self._payload(tpdo)

    def on_remote(self, cob_id: int) -> None:
        """A remote frame: answered by a TPDO of type 252..255 that allows it."""
        if not self._operational:
            return
        for tpdo in self._tpdos:
            if tpdo.map.cob_id != cob_id or not tpdo.map.rtr_allowed:
                continue
            kind = tpdo.map.trans_type or 0
            if kind == SYNC_RTR and tpdo.sampled is not None:
                self._send(tpdo, tpdo.sampled)
            elif kind > SYNC_RTR:
                self._send(tpdo, self._payload(tpdo))

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        del timestamp
        with self._node.lock:
            rpdo = self._rpdos.get(can_id)
            if not self._operational or rpdo is None:
                return
            if len(data) < rpdo.size:
                self._node.emergency(PDO_LENGTH_ERROR)
                return
            if (rpdo.map.trans_type or 0) <= SYNC_TYPES_MAX:
                self._pending[can_id] = bytes(data)
                return
            self._apply(rpdo, bytes(data))
            self._node.after_writes()

    # --- data ------------------------------------------------------------------------

    def _apply(self, rpdo: _Rpdo, data: bytes) -> None:
        node = self._node
        if rpdo.plan is not None:
            # What LocalNode.set_data does, minus its callbacks, which act on the
            # communication area only (the plan holds none of it).
            store, written = node.data_store, node.written
            for index, subindex, first, end in rpdo.plan:
                store.setdefault(index, {})[subindex] = data[first:end]
                written.append((index, subindex))
            return
        rpdo.map.data = bytearray(data)
        for var in rpdo.map.map:
            node.set_data(var.index, var.subindex, var.get_data())

    def _payload(self, tpdo: _Tpdo) -> bytes:
        if tpdo.plan is not None:
            # LocalNode.get_data's order minus read callbacks (a simulated node has none).
            store, node = self._node.data_store, self._node
            parts = []
            for index, subindex, _, _ in tpdo.plan:
                try:
                    parts.append(store[index][subindex])
                except KeyError:
                    parts.append(node.get_data(index, subindex))
            return b"".join(parts)
        pdo_map = tpdo.map
        pdo_map.data = bytearray(math.ceil(pdo_map.length / 8))
        for var in pdo_map.map:
            raw = self._node.get_data(var.index, var.subindex)
            if var.offset is not None and var.offset % 8 == 0 and var.length % 8 == 0:
                # canopen copies whole objects on byte boundaries; a mapping
                # shorter than its object takes only the low bytes.
                raw = raw[: var.length // 8]
            var.set_data(raw)
        return bytes(pdo_map.data)

    def _trigger(self, tpdo: _Tpdo, payload: bytes | None = None) -> None:
        if tpdo.deferred is not None:
            return  # the inhibit time's end sends the newest data anyway
        wait = tpdo.last_time + (tpdo.map.inhibit_time or 0) * INHIBIT_UNIT_S - time.monotonic()
        if wait > 0:
            tpdo.deferred = self._node.scheduler.call_later(wait, lambda: self._inhibit_over(tpdo))
        else:
            self._send(tpdo, self._payload(tpdo) if payload is None else payload)

    def _inhibit_over(self, tpdo: _Tpdo) -> None:
        tpdo.deferred = None
        if self._operational:
            self._send(tpdo, self._payload(tpdo))

    def _event_timer(self, tpdo: _Tpdo) -> None:
        tpdo.event_timer = None
        if self._operational:
            self._trigger(tpdo)

    def _send(self, tpdo: _Tpdo, payload: bytes) -> None:
        assert tpdo.map.cob_id is not None
        self._node.network.send_message(tpdo.map.cob_id, payload)
        tpdo.last, tpdo.last_time = payload, time.monotonic()
        if tpdo.map.trans_type in EVENT_TYPES and tpdo.map.event_timer:
            if tpdo.event_timer is not None:
                tpdo.event_timer.cancel()
            tpdo.event_timer = self._node.scheduler.call_later(
                tpdo.map.event_timer / 1000, lambda: self._event_timer(tpdo))


def _maps(maps: PdoMaps | None) -> list[PdoMap]:
    return list(maps.values()) if maps is not None else []
