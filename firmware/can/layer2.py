"""Layer-2 access: the frames the host asked to see, queued as indications (seed 5.3.2).

Why a module of its own: this is the one path on which the card passes bus frames to the
host as they are, outside every CANopen service: layer-2 frames of the identifiers the
host chose (COM_CFGRX_Layer2), 29-bit frames through the acceptance filter
(COM_Receive_Transparent), and [ours] the boot-up messages forwarded on request
(COM_Bootup_Indication). It owns the filters and the queue, hears every frame on the bus
thread and hands the device loop one indication at a time (``next_indication``).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable

import can

from dbm_tools.parameters import ExtendedBusParameterSet, ExtendedState
from dpm.cia301 import ERROR_CONTROL_BASE
from dpm.com import (
    CanFrame,
    accepts_extended,
    encode_bootup_indication,
    encode_layer2_frame,
    encode_transparent_2b,
)
from dpm.commands import COM_BOOTUP_INDICATION, COM_RECEIVE_TRANSPARENT, COM_RX_CAN_LAYER2
from dpm.message import Message, Task
from firmware.card import Card

QUEUE_LIMIT = 150
"""Layer-2 frames the card holds for the host (seed 5.3.2.2)."""
INDICATION_LIMIT = 254


class Layer2:
    """The filters and the indication queue; ``ext`` gives the extended bus parameters
    (the 29-bit acceptance filter), which a download replaces."""

    def __init__(self, card: Card, ext: Callable[[], ExtendedBusParameterSet]) -> None:
        self._card = card
        self._ext = ext
        self.filters: set[int] = set()
        self.bootup_forwarding = False
        self.indications: deque[tuple[int, can.Message]] = deque()
        self._queue_lock = threading.Lock()

    def reset(self) -> None:
        """A card start: no filters, no forwarding, nothing queued."""
        self.filters.clear()
        self.bootup_forwarding = False
        with self._queue_lock:
            self.indications.clear()

    def stop(self) -> None:
        """The host stopped communication (seed 5.3.2.1): its filters go, and [ours] so do the
        frames they let in that the host has not taken yet: a host that starts again has asked
        for none of them. Under the queue's lock, as ``_queue`` checks the filter again under
        it: no frame matched before the stop is queued after it."""
        with self._queue_lock:
            self.filters.clear()
            kept = [item for item in self.indications if item[0] != COM_RX_CAN_LAYER2]
            self.indications.clear()
            self.indications.extend(kept)

    def on_frame(self, msg: can.Message) -> None:
        """Every frame on the bus, from the bus thread."""
        if (self.bootup_forwarding and not msg.is_extended_id and not msg.is_remote_frame
                and 0x701 <= msg.arbitration_id <= 0x77F and bytes(msg.data) == b"\x00"):
            self._queue(COM_BOOTUP_INDICATION, msg)
        if msg.is_extended_id:
            ext = self._ext()
            if not ext.bExtendedState & ExtendedState.bi11Bit29BitSelector:
                return
            if not accepts_extended(ext.ulAcceptCode, ext.ulAcceptMask, msg.arbitration_id):
                return
            self._queue(COM_RECEIVE_TRANSPARENT, msg)
        elif msg.arbitration_id in self.filters:
            self._queue(COM_RX_CAN_LAYER2, msg)

    def _queue(self, kind: int, msg: can.Message) -> None:
        with self._queue_lock:
            if kind == COM_RX_CAN_LAYER2 and msg.arbitration_id not in self.filters:
                return  # ``stop`` came since ``on_frame`` looked
            if len(self.indications) >= QUEUE_LIMIT:
                self._card.count("usRx_Overflow")
                return
            self.indications.append((kind, msg))
        self._card.bell.ring_self()

    def next_indication(self) -> Message | None:
        """The next indication for the host mailbox, or None (pulled by the device loop)."""
        with self._queue_lock:
            if not self.indications:
                return None
            kind, msg = self.indications.popleft()
            if kind == COM_BOOTUP_INDICATION:
                return Message(rx=Task.USER, tx=Task.CAN, b=COM_BOOTUP_INDICATION,
                               data=encode_bootup_indication(
                                   msg.arbitration_id - ERROR_CONTROL_BASE))
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
