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
from dpm.message import TELEGRAM_HEADER, Message, Tdt, Tfc
from dpm.task2 import BMODE_TO_EXCHANGE_MODE, ComPlcParameter, GlobalBits
from firmware.process_image import ProcessImage
from firmware.task import Task

if TYPE_CHECKING:
    from firmware.card import Card

# Per data type: maximum address and count (seed 5.1.1).
_MAX_ADDRESS: dict[int, int] = {
    int(Tdt.UINT16): 1791, int(Tdt.UINT8): 3583, int(Tdt.STRING): 3583, int(Tdt.BIT): 1791}
_MAX_COUNT: dict[int, int] = {
    int(Tdt.UINT16): 119, int(Tdt.UINT8): 239, int(Tdt.STRING): 239, int(Tdt.BIT): 255}

_READ, _WRITE = int(Tfc.READ), int(Tfc.WRITE)
_UINT16, _BIT = int(Tdt.UINT16), int(Tdt.BIT)
"""The telegram header's codes as plain ints: an enum member looked up on its class costs
more than the comparison it serves, on every COM_Shared_Memory."""
_AREAS = (AREA_BY_FUNCTION, AREA_RECEIVE, AREA_SEND)


def data_type_limits() -> tuple[tuple[int, int, int], ...]:
    """Per data type its code, highest address and highest count, for the device loop's
    turn in C (``firmware.native_mailbox``), which checks a request as ``_check`` does."""
    return tuple((code, _MAX_ADDRESS[code], count) for code, count in _MAX_COUNT.items())


def _check(area: int, adr: int, idx: int, cnt: int, data_type: int, function: int) -> int:
    """msg.f for a COM_Shared_Memory header that asks for too much, 0 when it is good."""
    if function != _READ and function != _WRITE:
        return PlcF.UNKNOWN_FUNCTION
    limit = _MAX_COUNT.get(data_type)
    if limit is None:
        return PlcF.UNKNOWN_DATA_TYPE
    if area not in _AREAS:
        return PlcF.ILLEGAL_AREA
    if not 1 <= cnt <= limit:
        return PlcF.ILLEGAL_COUNT
    if data_type == _BIT:
        if idx > 15:
            return PlcF.BUFFER_OVERFLOW
        if adr > _MAX_ADDRESS[data_type] or adr * 16 + idx + cnt > IO_AREA_SIZE * 8:
            return PlcF.BUFFER_OVERFLOW
        return 0
    width = 2 if data_type == _UINT16 else 1
    if adr > _MAX_ADDRESS[data_type] or (adr + cnt) * width > IO_AREA_SIZE:
        return PlcF.BUFFER_OVERFLOW
    return 0


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

    def handshake_due(self, host_flags: int, dev_flags: int) -> bool:
        """Whether ``service`` exchanges the process data at these flags."""
        mode = self.image.mode
        if mode not in DEVICE_CONTROLLED and mode not in HOST_CONTROLLED:
            return False
        pending = bool((host_flags ^ dev_flags) & fl.PD)
        # Device-controlled: equal bits are the device's turn (it produces a
        # cycle, then hands it over). Host-controlled: the host's toggle asks
        # for one.
        return pending == (mode in HOST_CONTROLLED)

    def service(self, host_flags: int, dev_flags: int) -> None:
        """Answer the host's process-data handshake in the buffered modes."""
        if self.handshake_due(host_flags, dev_flags):
            self.image.cycle()
            self.device.toggle_host_flags(fl.PDACK)

    # --- COM_Shared_Memory --------------------------------------------------------

    def com_shared_memory(self, msg: Message) -> Message:
        """Read or write the process image. The answer's telegram header is the request's
        own eight bytes (every field comes back unchanged), so it is copied, not packed
        again: this runs on every mailbox round trip of a host that polls the image."""
        data = msg.data
        if len(data) < TELEGRAM_HEADER.size:
            return msg.answer(f=PlcF.ILLEGAL_COUNT)
        _, area, adr, idx, cnt, data_type, function = TELEGRAM_HEADER.unpack_from(data)
        f = _check(area, adr, idx, cnt, data_type, function)
        if f:
            return msg.answer(f=f)
        if not area:
            area = AREA_RECEIVE if function == _READ else AREA_SEND
        head = data[:TELEGRAM_HEADER.size]
        if function == _READ:
            return msg.answer(data=head + self._read(area, data_type, adr, idx, cnt))
        payload = data[TELEGRAM_HEADER.size :]
        expected = (cnt + 7) // 8 if data_type == _BIT else cnt * (2 if data_type == _UINT16 else 1)
        if len(payload) != expected:
            return msg.answer(f=PlcF.ILLEGAL_COUNT)
        self._write(area, data_type, adr, idx, cnt, payload)
        return msg.answer(data=head)

    def _area_read(self, area: int, offset: int, size: int) -> bytes:
        if area == AREA_RECEIVE:
            return self.image.read_inputs(offset, size)
        return self.image.read_send_area(offset, size)

    def _area_write(self, area: int, offset: int, data: bytes) -> None:
        if area == AREA_RECEIVE:
            self.image.write_inputs(offset, data)
        else:
            self.image.write_send_area(offset, data)

    def _read(self, area: int, data_type: int, adr: int, idx: int, cnt: int) -> bytes:
        if data_type != _BIT:
            width = 2 if data_type == _UINT16 else 1
            return self._area_read(area, adr * width, cnt * width)
        first = adr * 16 + idx
        span = self._area_read(area, first // 8, (first % 8 + cnt + 7) // 8)
        value = int.from_bytes(span, "little") >> (first % 8)
        value &= (1 << cnt) - 1
        return value.to_bytes((cnt + 7) // 8, "little")

    def _write(self, area: int, data_type: int, adr: int, idx: int, cnt: int,
               payload: bytes) -> None:
        if data_type != _BIT:
            width = 2 if data_type == _UINT16 else 1
            self._area_write(area, adr * width, payload)
            return
        first = adr * 16 + idx
        shift = first % 8
        size = (shift + cnt + 7) // 8
        with self.image.lock:  # read-modify-write of the bits around the field
            span = int.from_bytes(self._area_read(area, first // 8, size), "little")
            mask = ((1 << cnt) - 1) << shift
            bits = (int.from_bytes(payload, "little") << shift) & mask
            new = ((span & ~mask) | bits).to_bytes(size, "little")
            self._area_write(area, first // 8, new)
