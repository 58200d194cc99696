"""What ``cifemu top`` knows about a card, fed from image snapshots and tapped frames (no I/O).

The image gives the card's own view (Task2State: Nd_cfg/Nd_state/Nd_diag,
Err_Event, counters; the process image); the frames give what only the bus
shows (NMT state from heartbeats and guarding answers and their age, EMCY
codes, boot-ups, NMT commands, the bus load). Both arrive here as plain values,
so the model is tested without a card or a terminal.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field

from dbm_tools.network import Network
from dpm.cia301 import BOOT_UP, STATE_MASK
from dpm.errors import ERR_NODE_DEVICE, err_event_text
from dpm.layout import IO_AREA_SIZE, RCV_PD, SND_PD, TASK2_STATE, TASK_STATE_SIZE
from dpm.task2 import ComDiagnostics
from host_api.monitor.cia301 import emcy_text, nmt_state_text
from host_api.monitor.codec import decode
from host_api.monitor.framebits import frame_bits
from host_api.network_view import NetworkView, PdoSlot

EVENT_LIMIT = 200
HISTORY_LIMIT = 60
CHANGE_HIGHLIGHT_S = 1.0
LOAD_WINDOW_S = 1.0


@dataclass
class NodeRow:
    node: int
    name: str = ""
    control: str = ""
    nmt_state: str = "?"
    last_seen: float | None = None
    configured: bool = False
    running: bool = False
    diagnostic: bool = False
    last_error: tuple[int, str] | None = None
    last_emcy: tuple[int, str] | None = None


@dataclass
class PdoRow:
    slot: PdoSlot
    data: bytes
    changed_at: float | None


@dataclass
class BusFigures:
    counters: dict[str, int]
    can_state: str
    frames_per_s: float
    load_percent: float | None
    bitrate: int | None
    tap_lost: int = 0
    """Frames the card's tap sent that this view lost (its reader too slow) [ours]: the
    figures above undercount by them."""


@dataclass
class _Pdo:
    data: bytes = b""
    changed_at: float | None = None


@dataclass
class CardModel:
    view: NetworkView = field(default_factory=NetworkView)
    network: Network | None = None
    bitrate: int | None = None
    events: deque[str] = field(default_factory=lambda: deque(maxlen=EVENT_LIMIT))
    selected_value: int = 0
    """Index into ``view.slots`` of the PDO whose value the sparkline follows."""
    history: deque[int] = field(default_factory=lambda: deque(maxlen=HISTORY_LIMIT))

    def __post_init__(self) -> None:
        self._lock = threading.Lock()
        self._events_lock = threading.Lock()
        self.event_total = 0
        """Events logged so far (the deque keeps the last ``EVENT_LIMIT``)."""
        self._nodes: dict[int, NodeRow] = {}
        self._diag = ComDiagnostics()
        self._pdos: dict[int, _Pdo] = {}
        self._frames: deque[tuple[float, int]] = deque()
        self._tap_lost = 0
        self._last_error = (0, 0)
        self._error_control: dict[int, str] = {}
        """Node -> "heartbeat" or "guarding": the words of its Err_Event 30."""
        if self.network is not None:
            if self.bitrate is None:
                self.bitrate = self.network.bus.bitrate
            for node in self.network.nodes:
                self._error_control[node.id] = node.error_control
                row = self._node(node.id)
                row.control = (f"guarding {node.guard_time_ms} ms x{node.life_time_factor}"
                               if node.error_control == "guarding"
                               else f"heartbeat {node.heartbeat_ms} ms")
        for node_id, name in self.view.names.items():
            self._node(node_id).name = name

    def _node(self, node: int) -> NodeRow:
        if node not in self._nodes:
            self._nodes[node] = NodeRow(node, self.view.name(node))
        return self._nodes[node]

    def log(self, when: float, text: str) -> None:
        """An event-log line, stamped with the local time of day."""
        stamp = time.strftime("%H:%M:%S", time.localtime(when)) + f".{int(when * 1000) % 1000:03d}"
        with self._events_lock:
            self.events.append(f"{stamp} {text}")
            self.event_total += 1

    # --- feeding ---------------------------------------------------------------------------

    def update_image(self, image: bytes, now: float) -> None:
        """One snapshot of the card's image."""
        diag = ComDiagnostics.decode(image[TASK2_STATE : TASK2_STATE + TASK_STATE_SIZE])
        with self._lock:
            self._diag = diag
            configured, running, diagnostic = (set(diag.configured()), set(diag.operating()),
                                               set(diag.diagnostic()))
            for node in configured | running | diagnostic | set(self._nodes):
                row = self._node(node)
                row.configured, row.running = node in configured, node in running
                row.diagnostic = node in diagnostic
            error = (diag.bErr_rem_adr, diag.bErr_event)
            if error != self._last_error and diag.bErr_event:
                where = ("device" if diag.bErr_rem_adr == ERR_NODE_DEVICE
                         else f"node {diag.bErr_rem_adr}")
                text = err_event_text(diag.bErr_rem_adr, diag.bErr_event,
                                      self._error_control.get(diag.bErr_rem_adr))
                self.log(now, f"Err_Event {diag.bErr_event} at {where}: {text}")
                if diag.bErr_rem_adr != ERR_NODE_DEVICE:
                    self._node(diag.bErr_rem_adr).last_error = (diag.bErr_event, text)
            self._last_error = error
            for number, slot in enumerate(self.view.slots):
                base = RCV_PD if slot.direction == "input" else SND_PD
                start = base + slot.offset
                data = bytes(image[start : start + min(slot.length, IO_AREA_SIZE)])
                pdo = self._pdos.setdefault(number, _Pdo())
                if data != pdo.data:
                    pdo.changed_at = now if pdo.data else None
                    pdo.data = data
                if number == self.selected_value:
                    self.history.append(self._value(slot, data))

    @staticmethod
    def _value(slot: PdoSlot, data: bytes) -> int:
        """The followed value of a PDO: its first mapped object, else its first byte."""
        values = slot.values(data)
        if values:
            return values[0][1]
        return data[0] if data else 0

    def on_frame(self, can_id: int, data: bytes, *, remote: bool = False,
                 extended: bool = False, error: bool = False, timestamp: float) -> None:
        """One frame from the card's tap (or any bus the card is on)."""
        meaning = decode(can_id, data, extended=extended, remote=remote, error=error)
        with self._lock:
            if not error:  # an error frame's length is the fault's, not the sender's
                bits = frame_bits(can_id, data, extended=extended, remote=remote)
                self._frames.append((timestamp, bits))
            node = meaning.node
            if meaning.kind == "heartbeat" and node is not None and data:
                row = self._node(node)
                row.last_seen = timestamp
                state = nmt_state_text(data[0])
                if data[0] & STATE_MASK == BOOT_UP:
                    self.log(timestamp, f"boot-up node {node}")
                row.nmt_state = "PRE-OPERATIONAL" if state == "BOOT-UP" else state
            elif meaning.kind == "emcy" and node is not None:
                code = int.from_bytes(data[:2].ljust(2, b"\0"), "little")
                self._node(node).last_emcy = (code, emcy_text(code))
                self.log(timestamp, meaning.text)
            elif meaning.kind == "nmt":
                self.log(timestamp, meaning.text)

    def on_frames_lost(self, count: int, timestamp: float) -> None:
        """``count`` frames from the card's tap missing before the next one (``TapBus``)."""
        with self._lock:
            self._tap_lost += count
        self.log(timestamp, f"{count} frames lost (tap reader too slow)")

    def select_next_value(self) -> None:
        with self._lock:
            if self.view.slots:
                self.selected_value = (self.selected_value + 1) % len(self.view.slots)
                self.history.clear()

    # --- reading -------------------------------------------------------------------------------

    def new_events(self, seen: int) -> list[str]:
        """The events after the first ``seen`` ones (as many as are still kept)."""
        with self._events_lock:
            count = min(self.event_total - seen, len(self.events))
            return list(self.events)[len(self.events) - count :] if count > 0 else []

    def node_rows(self) -> list[NodeRow]:
        with self._lock:
            return [NodeRow(**vars(row)) for _, row in sorted(self._nodes.items())]

    def pdo_rows(self) -> list[PdoRow]:
        with self._lock:
            return [PdoRow(slot, self._pdos.get(n, _Pdo()).data,
                           self._pdos.get(n, _Pdo()).changed_at)
                    for n, slot in enumerate(self.view.slots)]

    def selected_slot(self) -> PdoSlot | None:
        slots = self.view.slots
        return slots[self.selected_value] if slots else None

    def bus(self, now: float) -> BusFigures:
        with self._lock:
            while self._frames and self._frames[0][0] < now - LOAD_WINDOW_S:
                self._frames.popleft()
            frames = len(self._frames)
            bits = sum(b for _, b in self._frames)
            diag = self._diag
        load = 100.0 * bits / LOAD_WINDOW_S / self.bitrate if self.bitrate else None
        return BusFigures(
            counters={"Bus_Error_Cnt": diag.usBus_Error_Cnt, "Bus_Off_Cnt": diag.usBus_Off_Cnt,
                      "Msg_Time_Out": diag.usMsg_Time_Out, "Rx_Overflow": diag.usRx_Overflow},
            can_state=diag.can_state_name, frames_per_s=frames / LOAD_WINDOW_S,
            load_percent=load, bitrate=self.bitrate, tap_lost=self._tap_lost)
