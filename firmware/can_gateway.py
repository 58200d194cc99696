"""The CAN-task commands of our own that the CiA 309 gateway needs [ours] (docs/card-commands.md).

Why a module of its own: the seed's CAN task has no message to change a node's error
control, the SDO time-out, the master's node-ID or heartbeat, or to forward boot-up
messages; a CiA 309 gateway must do all of these. They are ours (msg.b 110 to 116), so
they live apart from the seed's messages, and the table in docs/card-commands.md says
what each takes and answers.
"""

from __future__ import annotations

import struct
from typing import TYPE_CHECKING

from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from dpm.cia301 import EMCY_BASE, NODE_ID_MAX
from dpm.com import NodeSwitch, SdoTimeoutRequest, decode_word
from dpm.commands import (
    COM_BOOTUP_FORWARDING,
    COM_SET_EMCY_CONSUMER,
    COM_SET_GUARDING,
    COM_SET_HEARTBEAT_CONSUMER,
    COM_SET_HEARTBEAT_PRODUCER,
    COM_SET_NODE_ID,
    COM_SET_SDO_TIMEOUT,
)
from dpm.errors import CanF
from dpm.message import Message, MessageError
from firmware.can.node import NodeHandler
from firmware.card import Card
from firmware.task import Handler

if TYPE_CHECKING:
    from firmware.can.master import Master


class GatewayCommands:
    """Commands 110 to 116 over the master; an answer that waits on SDO goes by ``Card.post``."""

    def __init__(self, card: Card, master: Master) -> None:
        self.card = card
        self.master = master

    def handlers(self) -> dict[int, Handler]:
        return {
            COM_SET_SDO_TIMEOUT: self.com_set_sdo_timeout,
            COM_SET_GUARDING: self.com_set_guarding,
            COM_SET_HEARTBEAT_CONSUMER: self.com_set_heartbeat_consumer,
            COM_SET_EMCY_CONSUMER: self.com_set_emcy_consumer,
            COM_SET_HEARTBEAT_PRODUCER: self.com_set_heartbeat_producer,
            COM_SET_NODE_ID: self.com_set_node_id,
            COM_BOOTUP_FORWARDING: self.com_bootup_forwarding,
        }

    def _node_switch(self, msg: Message, ln: int) -> Message | tuple[NodeHandler, int, int]:
        """Parse d[0] node, d[1] 0 off / 1 on, d[2..3] u16: the node, on, value; or an error."""
        try:
            request = NodeSwitch.decode(msg.data, guarding=ln == 5)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if not 1 <= request.node <= NODE_ID_MAX:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if not self.master.nmt.running:
            return msg.answer(f=CanF.NOT_CONFIGURED)
        handler = self.master.nodes.get(request.node)
        if handler is None:
            return msg.answer(f=CanF.LOCAL_RESOURCE)
        return handler, int(request.on), request.value

    def com_set_sdo_timeout(self, msg: Message) -> Message:
        try:
            request = SdoTimeoutRequest.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if request.node > NODE_ID_MAX or request.timeout_ms == 0:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if request.node and self.master.bus is None:
            return msg.answer(f=CanF.NOT_CONFIGURED)
        self.master.sdo.set_timeout(request.node, request.timeout_ms / 1000.0)
        return msg.answer()

    def com_set_guarding(self, msg: Message) -> Message | None:
        parsed = self._node_switch(msg, 5)
        if isinstance(parsed, Message):
            return parsed
        handler, on, guard_time = parsed
        factor = msg.data[4]
        if on and not guard_time:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        guard_time = guard_time if on else 0
        writes = [(0x100C, struct.pack("<H", guard_time)), (0x100D, bytes([factor]))]
        if on:
            writes.insert(0, (0x1017, b"\0\0"))  # CiA 301: guarding only without heartbeat
        self.master.workers.submit(self._configure_error_control, msg, handler, writes,
                                    False, guard_time, factor)
        return None

    def com_set_heartbeat_consumer(self, msg: Message) -> Message:
        parsed = self._node_switch(msg, 4)
        if isinstance(parsed, Message):
            return parsed
        handler, on, consumer_time = parsed
        if on and not consumer_time:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        handler.set_supervision(True, consumer_time if on else 0, 0)
        return msg.answer()

    def _configure_error_control(self, msg: Message, handler: NodeHandler,
                                 writes: list[tuple[int, bytes]], heartbeat: bool,
                                 time_ms: int, factor: int) -> None:
        channel = self.master.sdo.channel(handler.address)
        if not self.master.sdo.take(channel):
            return  # the card powers off
        answer = msg.answer()
        try:
            for index, value in writes:
                channel.sdo.download(index, 0, value)
        except SdoAbortedError as exc:
            answer = msg.answer(f=CanF.SDO_ABORT, data=struct.pack("<I", exc.code))
        except SdoCommunicationError:
            answer = msg.answer(f=CanF.NO_RESPONSE)
        finally:
            channel.lock.release()
        if self.master.closing:
            return  # cut short by the power-off (``SdoChannels.close``): no answer
        if answer.f == 0:
            handler.set_supervision(heartbeat, time_ms, factor)
        self.card.post(answer)

    def com_set_emcy_consumer(self, msg: Message) -> Message:
        parsed = self._node_switch(msg, 4)
        if isinstance(parsed, Message):
            return parsed
        handler, on, cob_id = parsed
        if cob_id > 0x7FF:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        handler.set_emcy_consumer((cob_id or EMCY_BASE + handler.address) if on else None)
        return msg.answer()

    def com_set_heartbeat_producer(self, msg: Message) -> Message:
        try:
            self.master.ext.usProducerHeartbeatTime = decode_word(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        self.master.wake()  # the master's heartbeat starts, stops or changes its period
        return msg.answer()

    def com_set_node_id(self, msg: Message) -> Message:
        if msg.ln != 1 or not 1 <= msg.data[0] <= NODE_ID_MAX:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if msg.data[0] in self.master.nodes:
            return msg.answer(f=CanF.DOUBLE_ADDRESS)
        self.master.ext.bNodeID = msg.data[0]
        self.master.wake()  # the master's heartbeat may start now
        return msg.answer()

    def com_bootup_forwarding(self, msg: Message) -> Message:
        if msg.ln != 1 or msg.data[0] not in (0, 1):
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        self.master.layer2.bootup_forwarding = bool(msg.data[0])
        return msg.answer()
