"""The CAN task (msg.rx 3): the CANopen master behind the image.

So far the task knows one message, the bus parameter download (COM_Download
with Area_Code 127), which starts the network: the card reaches RUN, and COM
while the host is ready. Node parameter sets, the node handlers and the other
CAN-task messages arrive with the CAN-task issue; until then they are
answered "unknown command, DEVICE needs newer firmware" (f 152).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dbm_tools.parameters import BusParameterSet
from dbm_tools.validate import check_bus_parameters
from dpm.errors import F_UNKNOWN_COMMAND
from dpm.message import Message
from firmware.task import Task

if TYPE_CHECKING:
    from firmware.device import Device

COM_DOWNLOAD = 68
AREA_BUS_PARAMETER = 127
F_FAULTY_PARAMETER = 55


class CanTask(Task):
    number = 3
    name = "CAN"

    def __init__(self, device: Device) -> None:
        super().__init__(device)
        self.configured = False
        self.communicating = False
        self.bus_parameters: BusParameterSet | None = None
        self.handlers[COM_DOWNLOAD] = self.com_download

    def reset(self, cold: bool) -> None:
        del cold
        self.configured = False
        self.communicating = False
        self.bus_parameters = None

    def com_download(self, msg: Message) -> Message:
        """COM_Download: d[0] Req_Adr, d[1] Area_Code, d[2..3] Add_Offset, d[4..] data."""
        if msg.ln < 4:
            return msg.answer(f=F_FAULTY_PARAMETER)
        area = msg.data[1]
        if area != AREA_BUS_PARAMETER:
            return msg.answer(f=F_UNKNOWN_COMMAND)
        data = msg.data[4:]
        findings = [f for f in check_bus_parameters(data) if f.severity == "error"]
        if findings:
            return msg.answer(f=findings[0].number)
        self.bus_parameters = BusParameterSet.decode(data)
        self.configured = True
        self.communicating = True
        return msg.answer()
