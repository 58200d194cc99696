"""The PLC task (msg.rx 2): process-data handshakes and COM_Shared_Memory.

Seed manual 5.1. The handshake mode comes from the protocol parameter bMode at
every start; the task then serves the PD channel of the flags in the device
loop, and answers COM_Shared_Memory in any mode.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dpm import flags as fl
from dpm import message
from dpm.commands import AREA_BY_FUNCTION, AREA_RECEIVE, AREA_SEND, COM_SHARED_MEMORY
from dpm.errors import ERR_NODE_DEVICE, DeviceEvent, PlcF
from dpm.layout import IO_AREA_SIZE
from dpm.message import Message, MessageError, Tdt, TelegramHeader, Tfc
from dpm.task2 import BMODE_TO_EXCHANGE_MODE, ComPlcParameter, GlobalBits
from firmware.process_image import ProcessImage
from firmware.task import Task

if TYPE_CHECKING:
    from firmware.card import Card

# Per data type: maximum address and count (seed 5.1.1).
_MAX_ADDRESS: dict[int, int] = {Tdt.UINT16: 1791, Tdt.UINT8: 3583, Tdt.STRING: 3583, Tdt.BIT: 1791}
_MAX_COUNT: dict[int, int] = {Tdt.UINT16: 119, Tdt.UINT8: 239, Tdt.STRING: 239, Tdt.BIT: 255}

DEVICE_CONTROLLED = (1, 2)
HOST_CONTROLLED = (4, 5)


class PlcTask(Task):
    number = message.Task.PLC
    name = "PLC"

    def __init__(self, device: Card) -> None:
        super().__init__(device)
        self.image = ProcessImage(device.mm)
        self.parameter = ComPlcParameter()
        self.handlers[COM_SHARED_MEMORY] = self.com_shared_memory

    # --- start-up ---------------------------------------------------------------

    def apply_parameters(self, parameter: ComPlcParameter) -> bool:
        """Take the protocol parameters; False (Err_Event 52) for an unknown bMode."""
        self.parameter = parameter
        mode = BMODE_TO_EXCHANGE_MODE.get(parameter.bMode, 0)
        self.image.mode = mode
        self.image.clear()
        self.device.set_exchange_mode(mode)
        if mode == 0:
            self.device.report_error(
                ERR_NODE_DEVICE, DeviceEvent.HANDSHAKE_MODE, GlobalBits.CTRL
            )
            return False
        return True

    # --- the PD channel, served from the device loop ----------------------------

    def service(self, host_flags: int, dev_flags: int) -> None:
        """Answer the host's process-data handshake in the buffered modes."""
        mode = self.image.mode
        if mode not in DEVICE_CONTROLLED and mode not in HOST_CONTROLLED:
            return
        pending = bool((host_flags ^ dev_flags) & fl.PD)
        # Device-controlled: equal bits are the device's turn (it produces a
        # cycle, then hands it over). Host-controlled: the host's toggle asks
        # for one.
        if pending == (mode in HOST_CONTROLLED):
            self.image.cycle()
            self.device.toggle_host_flags(fl.PDACK)

    # --- COM_Shared_Memory --------------------------------------------------------

    def com_shared_memory(self, msg: Message) -> Message:
        try:
            head = TelegramHeader.decode(msg.data)
        except MessageError:
            return msg.answer(f=PlcF.ILLEGAL_COUNT)
        f = self._check(head)
        if f:
            return msg.answer(f=f)
        area = head.data_area or (AREA_RECEIVE if head.function == Tfc.READ else AREA_SEND)
        data_type = head.data_type
        if head.function == Tfc.READ:
            payload = self._read(area, data_type, head)
            head.payload = payload
            return msg.answer(data=head.encode())
        if data_type == Tdt.BIT:
            expected = (head.data_cnt + 7) // 8
        else:
            expected = head.data_cnt * (2 if data_type == Tdt.UINT16 else 1)
        if len(head.payload) != expected:
            return msg.answer(f=PlcF.ILLEGAL_COUNT)
        self._write(area, data_type, head)
        head.payload = b""
        return msg.answer(data=head.encode())

    @staticmethod
    def _check(head: TelegramHeader) -> int:
        if head.function not in (Tfc.READ, Tfc.WRITE):
            return PlcF.UNKNOWN_FUNCTION
        if head.data_type not in _MAX_COUNT:
            return PlcF.UNKNOWN_DATA_TYPE
        if head.data_area not in (AREA_BY_FUNCTION, AREA_RECEIVE, AREA_SEND):
            return PlcF.ILLEGAL_AREA
        data_type = head.data_type
        if not 1 <= head.data_cnt <= _MAX_COUNT[data_type]:
            return PlcF.ILLEGAL_COUNT
        if data_type == Tdt.BIT:
            if head.data_idx > 15:
                return PlcF.BUFFER_OVERFLOW
            end_bit = head.data_adr * 16 + head.data_idx + head.data_cnt
            if head.data_adr > _MAX_ADDRESS[data_type] or end_bit > IO_AREA_SIZE * 8:
                return PlcF.BUFFER_OVERFLOW
            return 0
        width = 2 if data_type == Tdt.UINT16 else 1
        start = head.data_adr * width
        if head.data_adr > _MAX_ADDRESS[data_type] or start + head.data_cnt * width > IO_AREA_SIZE:
            return PlcF.BUFFER_OVERFLOW
        return 0

    def _area_read(self, area: int, offset: int, size: int) -> bytes:
        if area == AREA_RECEIVE:
            return self.image.read_inputs(offset, size)
        return self.image.read_send_area(offset, size)

    def _area_write(self, area: int, offset: int, data: bytes) -> None:
        if area == AREA_RECEIVE:
            self.image.write_inputs(offset, data)
        else:
            self.image.write_send_area(offset, data)

    def _read(self, area: int, data_type: int, head: TelegramHeader) -> bytes:
        if data_type != Tdt.BIT:
            width = 2 if data_type == Tdt.UINT16 else 1
            return self._area_read(area, head.data_adr * width, head.data_cnt * width)
        first = head.data_adr * 16 + head.data_idx
        span = self._area_read(area, first // 8, (first % 8 + head.data_cnt + 7) // 8)
        value = int.from_bytes(span, "little") >> (first % 8)
        value &= (1 << head.data_cnt) - 1
        return value.to_bytes((head.data_cnt + 7) // 8, "little")

    def _write(self, area: int, data_type: int, head: TelegramHeader) -> None:
        if data_type != Tdt.BIT:
            width = 2 if data_type == Tdt.UINT16 else 1
            self._area_write(area, head.data_adr * width, head.payload)
            return
        first = head.data_adr * 16 + head.data_idx
        shift = first % 8
        size = (shift + head.data_cnt + 7) // 8
        with self.image.lock:  # read-modify-write of the bits around the field
            span = int.from_bytes(self._area_read(area, first // 8, size), "little")
            mask = ((1 << head.data_cnt) - 1) << shift
            bits = (int.from_bytes(head.payload, "little") << shift) & mask
            new = ((span & ~mask) | bits).to_bytes(size, "little")
            self._area_write(area, first // 8, new)
