"""The host's own traffic: COM_NMT_Module_Protocol, transparent CAN messages, layer 2.

Why a module of its own: with these four the host, not the card, decides what goes on the
bus (seed 5.2.9 NMT commands, 5.2.10 a transparent message, 5.3 layer-2 frames and the
receive filters). They check the request and hand it to the master; none waits on an answer
from the bus.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dpm.cia301 import NODE_ID_MAX
from dpm.com import NmtRequest, decode_layer2_frames, decode_rx_filters, decode_transparent
from dpm.commands import (
    COM_CFGRX_LAYER2,
    COM_NMT_MODULE_PROTOCOL,
    COM_SEND_CANMSG_TRANSPARENT,
    COM_TX_CAN_LAYER2,
    NMT_COMMANDS,
)
from dpm.errors import CanF
from dpm.message import Message, MessageError
from firmware.task import Handler

if TYPE_CHECKING:
    from firmware.can.master import Master


class BusAccess:
    """The four messages over the master."""

    def __init__(self, master: Master) -> None:
        self.master = master

    def handlers(self) -> dict[int, Handler]:
        return {
            COM_NMT_MODULE_PROTOCOL: self.com_nmt_module_protocol,
            COM_SEND_CANMSG_TRANSPARENT: self.com_send_canmsg_transparent,
            COM_CFGRX_LAYER2: self.com_cfgrx_layer2,
            COM_TX_CAN_LAYER2: self.com_tx_can_layer2,
        }

    def com_nmt_module_protocol(self, msg: Message) -> Message:
        try:
            request = NmtRequest.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if request.command not in NMT_COMMANDS or request.node > NODE_ID_MAX:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if not self.master.nmt.running:
            return msg.answer(f=CanF.NOT_CONFIGURED)
        self.master.nmt.host_nmt(request.command, request.node)
        return msg.answer()

    def com_send_canmsg_transparent(self, msg: Message) -> Message:
        try:
            frame = decode_transparent(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        dlc = frame.length_code  # a remote frame carries the data bytes as given, as before
        if not self.master.bus_send_raw(frame.ident, frame.data[: min(dlc, 8)], frame.rtr,
                                        frame.extended, dlc):
            return msg.answer(f=CanF.TIMEOUT)
        return msg.answer()

    def com_cfgrx_layer2(self, msg: Message) -> Message:
        try:
            idents = decode_rx_filters(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if any(self.master.cob_id_in_use(i) for i in idents):
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        self.master.layer2.filters.update(idents)
        return msg.answer()

    def com_tx_can_layer2(self, msg: Message) -> Message | None:
        """Up to 127 frames, each 2 identifier bytes plus DLC data bytes; no answer."""
        try:
            frames = decode_layer2_frames(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        for frame in frames:
            self.master.bus_send_raw(frame.ident, frame.payload, frame.rtr, False,
                                     frame.length_code)
        return None
