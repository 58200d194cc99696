"""The on-line configuration's messages: COM_Start_Seq, COM_Download, COM_End_Seq, COM_Upload.

Why a module of its own: these four speak the download area's protocol (seed 5.2.3 to
5.2.6): a sequence in the 1000-byte area, its time-out, the Area_Codes, reading a data set
back. What a data set does once it is whole is the CAN task's (``CanTask.download_node`` and
its two siblings, which the stored database calls too); this module only gets it there.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

from dpm.com import DownloadRequest, StartSeqRequest, UploadRequest, encode_start_seq_confirm
from dpm.commands import (
    AREA_BUS,
    AREA_EXTENDED,
    COM_DOWNLOAD,
    COM_END_SEQ,
    COM_START_SEQ,
    COM_UPLOAD,
    DOWNLOAD_AREA_SIZE,
    MAX_LEN_DATA_UNIT,
)
from dpm.errors import CanF
from dpm.message import Message, MessageError
from firmware.card import Configurable
from firmware.task import Handler


class DataSets(Configurable, Protocol):
    """The CAN task as its download messages see it: the three entry points, and the data
    sets it took, which COM_Upload reads back."""

    @property
    def node_data(self) -> Mapping[int, bytes]: ...

    @property
    def bus_data(self) -> bytes | None: ...


@dataclass
class _Sequence:
    """A sequenced node download in the 1000-byte download area (COM_Start_Seq)."""

    area: int
    timeout_ms: int
    buffer: bytearray
    last: float
    length: int = 0

    def expired(self, now: float) -> bool:
        """Seed 5.2.3: more than Timeout ms since the sequence's last message (0: never)."""
        return bool(self.timeout_ms) and (now - self.last) * 1000 > self.timeout_ms


class OnlineDownload:
    """The four messages, and the one sequence that may be open."""

    def __init__(self, task: DataSets) -> None:
        self.task = task
        self._sequence: _Sequence | None = None

    def handlers(self) -> dict[int, Handler]:
        return {
            COM_START_SEQ: self.com_start_seq,
            COM_DOWNLOAD: self.com_download,
            COM_END_SEQ: self.com_end_seq,
            COM_UPLOAD: self.com_upload,
        }

    def reset(self) -> None:
        """A start ends any open sequence."""
        self._sequence = None

    def com_start_seq(self, msg: Message) -> Message:
        """Seed 5.2.3. Every answer, an error too, has the table's msg.ln 1 with
        Max_Len_Data_Unit 240: the table gives ln and d[0] as fixed values and only f as
        variable, so a host that reads d[0] whatever f says finds 240 there."""
        confirm = encode_start_seq_confirm(MAX_LEN_DATA_UNIT)
        if self.task.from_flash:
            return msg.answer(f=CanF.FLASH_DATABASE_RUNS, data=confirm)
        try:
            request = StartSeqRequest.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER, data=confirm)
        area = request.area
        if not 1 <= area <= 126:
            return msg.answer(f=CanF.AREA_CODE, data=confirm)
        self._sequence = _Sequence(area, request.timeout_ms, bytearray(DOWNLOAD_AREA_SIZE),
                                   time.monotonic())
        return msg.answer(data=confirm)

    def com_download(self, msg: Message) -> Message:
        if self.task.from_flash:
            return msg.answer(f=CanF.FLASH_DATABASE_RUNS)
        try:
            request = DownloadRequest.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        area, offset, data = request.area, request.offset, request.data
        if area == AREA_BUS:
            return msg.answer(f=self.task.download_bus(data))
        if area == AREA_EXTENDED:
            return msg.answer(f=self.task.download_extended(data))
        if not 1 <= area <= 126:
            return msg.answer(f=CanF.AREA_CODE)
        seq = self._sequence
        now = time.monotonic()
        if seq is not None and seq.expired(now):
            # Seed 5.2.3: the time-out ends the sequence; what comes after it for another
            # node is a download of its own, not a sequence error. Its own node hears 48.
            self._sequence = None
            if area == seq.area:
                return msg.answer(f=CanF.TIMEOUT)
            seq = None
        if seq is None:
            if offset:
                return msg.answer(f=CanF.SEQUENCE)  # an offset needs COM_Start_Seq first
            if len(data) > DOWNLOAD_AREA_SIZE:
                return msg.answer(f=CanF.BUFFER_LENGTH)
            return msg.answer(f=self.task.download_node(area, data))
        if area != seq.area:
            return msg.answer(f=CanF.SEQUENCE)
        if offset + len(data) > DOWNLOAD_AREA_SIZE:
            return msg.answer(f=CanF.BUFFER_LENGTH)
        seq.buffer[offset : offset + len(data)] = data
        seq.length = max(seq.length, offset + len(data))
        seq.last = now
        return msg.answer()

    def com_end_seq(self, msg: Message) -> Message:
        if self.task.from_flash:
            return msg.answer(f=CanF.FLASH_DATABASE_RUNS)
        seq, self._sequence = self._sequence, None
        if seq is None:
            return msg.answer(f=CanF.SEQUENCE)
        if seq.expired(time.monotonic()):
            return msg.answer(f=CanF.TIMEOUT)  # it expires with no message at all, too
        if seq.length < 2:
            return msg.answer(f=CanF.INCOMPLETE)
        (total,) = struct.unpack_from("<H", seq.buffer, 0)
        if total > seq.length or total < 2:
            return msg.answer(f=CanF.INCOMPLETE)
        return msg.answer(f=self.task.download_node(seq.area, bytes(seq.buffer[:total])))

    def com_upload(self, msg: Message) -> Message:
        try:
            request = UploadRequest.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.PARAMETER_FAULT)
        area, offset, length = request.area, request.offset, request.length
        if area == AREA_BUS:
            stored = self.task.bus_data
        elif 1 <= area <= 126:
            stored = self.task.node_data.get(area)
        else:
            return msg.answer(f=CanF.AREA_CODE)
        if stored is None:
            return msg.answer(f=CanF.LOCAL_RESOURCE)
        if not 1 <= length <= MAX_LEN_DATA_UNIT:
            return msg.answer(f=CanF.PARAMETER_FAULT)
        if offset > len(stored):
            return msg.answer(f=CanF.BUFFER_LENGTH)
        return msg.answer(data=stored[offset : offset + length])
