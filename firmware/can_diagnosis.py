"""The CAN task's diagnosis messages: COM_Node_Diag, COM_Reset_Err_Event, GET_CONFIGURATION.

Why a module of its own: these three only read what the card already knows (a node
handler's diagnosis, the DESCRIPT table) or clear its counters; none of them configures
or sends anything on the bus (seed 5.2.7, 5.2.12; GET_CONFIGURATION in docs/dbm.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dpm.cia301 import NODE_ID_MAX
from dpm.com import NodeDiagnosis, NodeStatus, configuration_answer, node_diag_answer
from dpm.commands import COM_NODE_DIAG, COM_RESET_ERR_EVENT, GET_CONFIGURATION
from dpm.errors import CanF
from dpm.message import Message, MessageError, TelegramHeader
from dpm.task2 import GlobalBits
from firmware.card import Card
from firmware.task import Handler

if TYPE_CHECKING:
    from firmware.can.master import Master


class Diagnosis:
    """The three messages over the card and its master."""

    def __init__(self, card: Card, master: Master) -> None:
        self.card = card
        self.master = master

    def handlers(self) -> dict[int, Handler]:
        return {
            COM_NODE_DIAG: self.com_node_diag,
            COM_RESET_ERR_EVENT: self.com_reset_err_event,
            GET_CONFIGURATION: self.get_configuration,
        }

    def com_node_diag(self, msg: Message) -> Message:
        try:
            head = TelegramHeader.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        address = head.device_adr
        if not 1 <= address <= NODE_ID_MAX:
            return msg.answer(f=CanF.NODE_DIAG_ADDRESS)
        handler = self.master.nodes.get(address)
        raw = (handler.read_diagnosis() if handler
               else NodeDiagnosis(status=NodeStatus.DEACTIVATED).encode())
        self.card.set_node_bit("abNd_diag", address, False)
        return msg.answer(data=node_diag_answer(head, raw))

    def com_reset_err_event(self, msg: Message) -> Message:
        """Clear TOUT, EVE and the four counters (seed 5.2.12); never an error."""
        self.card.reset_counters(GlobalBits.TOUT | GlobalBits.EVE)
        return msg.answer()

    def get_configuration(self, msg: Message) -> Message:
        """The node's DESCRIPT record without its first byte (docs/dbm.md section 2)."""
        try:
            head = TelegramHeader.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        descript = self.card.descript_records()
        if descript is None:
            return msg.answer(f=CanF.NO_DESCRIPT_TABLE)
        record = descript.get(head.device_adr)
        if record is None:
            return msg.answer(f=CanF.NO_DESCRIPT_RECORD)
        return msg.answer(data=configuration_answer(head, record))
