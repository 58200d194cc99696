"""PDO communication of the master: the RX-PDOs it sends, the TX-PDOs it takes in.

Why a module of its own: the PDOs are the one service that runs at bus speed on every
change of the host's outputs and every SYNC, and it shares nothing with boot-up or
supervision but the node's state, which it is asked about (``operating``) and never
changes; a PDO that goes wrong is reported back as an Err_Event for the node handler to
act on. The network-wide part, which nodes the host's outputs changed (``OutputWatch``),
sits here too: it exists only to call ``NodePdos.send_outputs`` seldom enough.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Protocol

import can

from dbm_tools.parameters import MSK_WORD_PDO, NodeParameterSet, PdoData
from dpm.cia301 import ASYNC_RTR, SYNC_RTR
from dpm.errors import NodeEvent
from dpm.layout import IO_AREA_SIZE
from firmware.can.bus import CanBus
from firmware.process_image import ProcessImage

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

class _Numpy:
    """numpy for ``OutputWatch``, imported beside the card's work when a node past the
    first ``FEW_NODES`` is configured (``import_ahead``), not with this module: a card that
    is never configured, or whose network is small, does not pay its 0.1 s of CPU
    (docs/testing.md, *Start-up*). Not on first use either:
    that is the device loop's turn, which an import under load held past a host's
    2 s DevExchangeIO. Until it is in, ``OutputWatch`` compares node by node, as it does
    when two nodes share output bytes."""

    module: ModuleType | None = None
    _started = False
    _lock = threading.Lock()
    _thread: threading.Thread | None = None

    @classmethod
    def import_ahead(cls) -> None:
        with cls._lock:
            if cls._started:
                return
            cls._started = True
            cls._thread = threading.Thread(target=cls._load, name="numpy-import", daemon=True)
        cls._thread.start()

    @classmethod
    def wait(cls, timeout: float) -> None:
        """Until the import ``import_ahead`` began is done, at most ``timeout`` seconds (at
        once when none began or it is done)."""
        thread = cls._thread
        if thread is not None:
            thread.join(timeout)

    @classmethod
    def _load(cls) -> None:
        import numpy

        cls.module = numpy  # only once whole: a half-imported module is in sys.modules


import_numpy_ahead = _Numpy.import_ahead
await_numpy = _Numpy.wait


FEW_NODES = 16
"""Networks up to this many nodes are compared node by node (``OutputWatch``), and do not
import numpy: numpy's compare of the whole area cost this machine 4.3 us of CPU whatever
changed, one node's slices 0.8 us and sixteen nodes' 3.5 us (2026-12-03, in isolation,
hot caches, load 10). On a one-node PDO loop numpy was the biggest piece of the device
loop's own work between the host's ring and the RPDO: the card's CPU per round trip fell
from 210-283 to 130-230 us without it (alternating runs, load 20; issue 22)."""

RTR_PERIOD = 0.1
"""[ours] seconds between remote requests of an RTR-only (253) input PDO without SYNC, the
time a node has to answer one, and the least time it has to answer a remote request of a
252 input (``on_sync``)."""


class PdoLink(Protocol):
    """What PDOs use of the network: the process data, the byte order, SYNC, the bus."""

    @property
    def image(self) -> ProcessImage: ...

    @property
    def motorola(self) -> bool: ...

    @property
    def sync_period(self) -> float: ...

    def bus_send(self, can_id: int, data: bytes = b"", remote: bool = False,
                 dlc: int | None = None) -> bool: ...


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
    """When the first remote request still unanswered went out, 0 when answered."""
    asked: float = 0.0
    """When the last remote request went out (0: none since the node's boot-up)."""


def swap_words(data: bytes) -> bytes:
    """Motorola order for a word-oriented PDO: swap the bytes of each word."""
    out = bytearray(data)
    for i in range(0, len(out) - 1, 2):
        out[i], out[i + 1] = out[i + 1], out[i]
    return bytes(out)


class NodePdos:
    """One node's PDOs, as its node parameter data set configures them (seed 4.2)."""

    def __init__(self, link: PdoLink, params: NodeParameterSet,
                 operating: Callable[[], bool]) -> None:
        self.link = link
        self._operating = operating
        """Whether the node exchanges data: its TX-PDOs count only then."""
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
        (the master sends a changed event-driven output when it looks)."""
        self._by_cob_id: dict[int, tuple[tuple[InputPdo, int, int, bool], ...]] = {}
        """Per TX-PDO identifier: its inputs with their offset, length and word order, so
        that a received frame (thousands a second) finds its place without a search."""
        for entry in self.inputs:
            pdo = entry.pdo
            self._by_cob_id[pdo.usPdoCOBId] = (*self._by_cob_id.get(pdo.usPdoCOBId, ()), (
                entry, entry.offset, pdo.data_length, bool(pdo.bLength & MSK_WORD_PDO)))

    def attach(self, bus: CanBus) -> None:
        for entry in self.inputs:
            bus.subscribe(entry.pdo.usPdoCOBId, self._on_input)

    def detach(self, bus: CanBus) -> None:
        for entry in self.inputs:
            bus.unsubscribe(entry.pdo.usPdoCOBId, self._on_input)

    def forget_sent(self) -> None:
        """A (re)booted node has none of the card's outputs yet, and owes no answer to a
        remote request sent before its boot-up."""
        for output in self.outputs:
            output.last = None
        for entry in self.inputs:
            entry.requested = entry.asked = 0.0

    def request_first(self, now: float) -> None:
        """Seed 5.2.5.1.1, TXRXPDO: "Request first TX ... PDO after initialization sequence is
        finished": one remote request of every input, whatever its type, once the node runs,
        so the input image holds the node's data before it next sends on its own. Only the
        RTR-only inputs (252, 253) must answer (Err_Event 33); [ours] a node may refuse remote
        frames of the others (1800h bit 30), which come anyway. Requests from before a stop
        are forgotten: a stopped node owes no answer."""
        for entry in self.inputs:
            entry.requested = 0.0
            if entry in self._polled:
                self._request(entry, now)
            else:
                self.link.bus_send(entry.pdo.usPdoCOBId, remote=True, dlc=entry.pdo.data_length)

    def poll(self, now: float) -> int:
        """RTR-only inputs without SYNC: NO_RTR_RESPONSE when a request stayed unanswered
        for ``RTR_PERIOD`` (0: all well), else the next request every ``RTR_PERIOD``."""
        for entry in self._unsynced():
            if entry.requested and now >= entry.requested + RTR_PERIOD:
                return NodeEvent.NO_RTR_RESPONSE
            if not entry.requested and now >= entry.asked + RTR_PERIOD:
                self._request(entry, now)
        return 0

    def next_due(self) -> float:
        """When ``poll`` has something to do (monotonic seconds; inf: nothing): a request's
        answer is late, or the next request is due."""
        return min(((e.requested or e.asked) + RTR_PERIOD for e in self._unsynced()),
                   default=math.inf)

    def _unsynced(self) -> list[InputPdo]:
        """The RTR-only inputs that no SYNC asks for: 253, and 252 while there is no SYNC."""
        if self.link.sync_period:
            return [e for e in self._polled if e.pdo.bTransType == ASYNC_RTR]
        return self._polled

    def on_sync(self, now: float) -> int:
        """Remote requests of 252 inputs at a SYNC, or NO_RTR_RESPONSE (0: all well).

        Seed 4.3, Err_Event 33: "no response to a configured remote frame PDO". The seed
        gives no time; [ours] a request unanswered for two SYNC periods (at least
        ``RTR_PERIOD``) is 33. The clock runs from the first unanswered request: the
        requests at the SYNCs between do not restart it, or a node that never answers
        would be reported only when a SYNC happened to come late.
        """
        limit = max(2 * self.link.sync_period, RTR_PERIOD)
        for entry in self._polled:
            if entry.pdo.bTransType == SYNC_RTR:
                if entry.requested and now - entry.requested > limit:
                    return NodeEvent.NO_RTR_RESPONSE
                self._request(entry, now)
        return 0

    def _request(self, entry: InputPdo, now: float) -> None:
        if not entry.requested:
            entry.requested = now
        entry.asked = now
        self.link.bus_send(entry.pdo.usPdoCOBId, remote=True, dlc=entry.pdo.data_length)

    def outputs_changed(self, now: bytes, before: bytes) -> bool:
        """Whether any of this node's output PDOs reads differently in ``now``."""
        for entry in self.outputs:
            end = entry.offset + entry.pdo.data_length
            if now[entry.offset : end] != before[entry.offset : end]:
                return True
        return False

    def send_outputs(self, sync: bool, force: bool) -> float | None:
        """Send the RX-PDOs that are due: synchronous ones at SYNC, the rest on change.

        Returns when the first changed event-driven PDO that waits for its inhibit time may
        go (monotonic seconds), None when none waits.
        """
        waiting: float | None = None
        link = self.link
        image = link.image
        now = time.monotonic()
        for entry in self._synchronous if sync and not force else self.outputs:
            pdo = entry.pdo
            data = image.read_outputs(entry.offset, pdo.data_length)
            if pdo.bLength & MSK_WORD_PDO and link.motorola:
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
                    free = entry.last_time + inhibit
                    waiting = free if waiting is None else min(waiting, free)
                    continue
            if link.bus_send(pdo.usPdoCOBId, data):
                entry.last = data
                entry.last_time = now
        return waiting

    def _on_input(self, msg: can.Message) -> None:
        if msg.is_remote_frame or not self._operating():
            return
        link = self.link
        for entry, offset, length, word in self._by_cob_id.get(msg.arbitration_id, ()):
            entry.requested = 0.0
            data = bytes(msg.data[:length])
            if word and link.motorola:
                data = swap_words(data)
            link.image.write_inputs(offset, data)


class OutputSender(Protocol):
    """A node as ``OutputWatch`` sees it: its address, its PDOs, and its gate to the bus."""

    @property
    def address(self) -> int: ...

    @property
    def pdos(self) -> NodePdos: ...

    def send_outputs(self, sync: bool = False, force: bool = False) -> float | None: ...


class OutputWatch:
    """Which nodes' RX-PDOs the host's outputs changed, asked each time the master looks.

    It keeps the outputs as the master last saw them and the nodes whose PDO still waits
    (inhibit time, a host SDO transfer) with the time to ask them again, and asks only
    those nodes to send.
    """

    def __init__(self) -> None:
        self._owners: npt.NDArray[np.uint8] | None = None
        """Which node's output PDO each output byte belongs to (0: none); see ``_owner_map``."""
        self._waiting: dict[OutputSender, float] = {}
        """Nodes with a changed PDO that waits, and when to ask them again."""
        self._last = b""
        self._everyone = False
        """Ask every node at the next look (``ask_everyone``)."""
        self._force = False
        """... to send all its outputs, carried or not (``ask_everyone(force=True)``)."""
        self._ask_lock = threading.Lock()
        """``ask_everyone`` comes from other threads (a fault, the controller's reopening):
        a request taken while it is being made would be lost, and with it the outputs."""

    def nodes_changed(self) -> None:
        """A node came or went: the owner map is built again at the next look."""
        self._owners = None

    def ask_everyone(self, force: bool = False) -> None:
        """[ours] At the next look every running node sends the outputs the bus has not
        carried yet: after a bus-off (firmware/faults.py) the outputs the host changed
        meanwhile go out, as after any change. The caller wakes the master for that look.

        ``force``: all its outputs, as after a host's start (``send_outputs(force=True)``):
        after a bridge's link came back (``CanBus.on_link_back``). The card cannot know
        which of its frames crossed: a frame the client wrote into a connection whose peer
        was already gone was taken without an error and lost, and one refused meanwhile is
        not sent again on its own (event-driven PDOs go on change only). Without this the
        node would run on stale outputs while the host believes its outputs went out."""
        with self._ask_lock:
            self._force = self._force or force
            self._everyone = True

    def restart(self, outputs: bytes) -> None:
        """The network starts: ``outputs`` as they are now are no change. Each node gets
        them when its boot-up ends (unless TXRXPDO skips that), and only later changes go
        out on their own; without this, a first look that comes after a node's boot-up (a
        busy machine) took every output for new and sent them to a node that skips it."""
        self._last = outputs

    def follow(self, outputs: bytes, nodes: Mapping[int, OutputSender], now: float,
               every: bool = False) -> float:
        """Send the PDOs of the nodes whose outputs changed since the last call, and of the
        waiting nodes whose time has come (``every``: of all waiting nodes, after a change of
        the nodes' states). Returns when to look again for a waiting node (inf: none waits).
        """
        last = self._last
        waiting = self._waiting
        with self._ask_lock:
            everyone, self._everyone = self._everyone, False
            force, self._force = self._force, False
        due = self._changed_nodes(outputs, last, nodes) if outputs != last else set()
        if waiting:
            due.update(h for h, when in waiting.items() if every or when <= now)
        if everyone:
            due.update(nodes.values())
        for handler in sorted(due, key=_address):
            retry = handler.send_outputs(force=force)
            if retry is None:
                waiting.pop(handler, None)
            else:
                waiting[handler] = retry
        self._last = outputs
        return min(waiting.values(), default=math.inf)

    def _changed_nodes(self, outputs: bytes, before: bytes,
                       nodes: Mapping[int, OutputSender]) -> set[OutputSender]:
        """The nodes whose output PDOs read differently in ``outputs`` than in ``before``.

        One vectorised comparison of the whole area instead of every node's
        slices: at full bus load this runs thousands of times a second (once numpy is
        in, ``_Numpy``). Up to ``FEW_NODES`` nodes, their slices: numpy's fixed cost is
        more than comparing them.
        """
        numpy = _Numpy.module
        if numpy is None or len(nodes) <= FEW_NODES:
            return {h for h in nodes.values() if h.pdos.outputs_changed(outputs, before)}
        owners = self._owner_map(numpy, nodes)
        if owners is None or len(before) != len(outputs):
            return {h for h in nodes.values() if h.pdos.outputs_changed(outputs, before)}
        diff = numpy.frombuffer(outputs, numpy.uint8) != numpy.frombuffer(before, numpy.uint8)
        return {nodes[a] for a in numpy.unique(owners[diff]).tolist() if a in nodes}

    def _owner_map(self, numpy: ModuleType,
                   nodes: Mapping[int, OutputSender]) -> npt.NDArray[np.uint8] | None:
        """Output byte -> node address; None when two nodes share output bytes."""
        if self._owners is None:
            owners = numpy.zeros(IO_AREA_SIZE, numpy.uint8)
            for address, handler in list(nodes.items()):
                for entry in handler.pdos.outputs:
                    span = owners[entry.offset:entry.offset + entry.pdo.data_length]
                    if numpy.any((span != 0) & (span != address)):
                        return None
                    span[:] = address
            self._owners = owners
        return self._owners


def zero_outputs(image: ProcessImage, nodes: Mapping[int, OutputSender]) -> None:
    """Drive every RX-PDO to zero once (seed 5.2.1.2), then stop PDO traffic."""
    driving = image.driving
    image.driving = False  # read_outputs answers zeros now
    try:
        for handler in nodes.values():
            handler.send_outputs(force=True)
    finally:
        image.driving = driving


def _address(handler: OutputSender) -> int:
    return handler.address
