"""MSG_STRUC and the extended telegram header, as pure codecs.

A message in a mailbox is ``rx tx ln nr a f b e`` followed by ``ln`` data
bytes; readers copy only ``ln + 8`` bytes, never the whole 288-byte slot, so
stale bytes of an earlier, longer message never leak into a new one.
"""

from __future__ import annotations

import mmap
import struct
from dataclasses import dataclass, field
from enum import IntEnum

from dpm.errors import DpmError
from dpm.layout import MSG_DATA_SIZE, MSG_HEADER_SIZE

MSG_MAX_SIZE = MSG_HEADER_SIZE + MSG_DATA_SIZE
"""A message is at most 263 bytes (the slot is 288 with its dummy tail)."""
HEADER = struct.Struct("8B")
"""MSG_STRUC's header: rx tx ln nr a f b e."""
LN_OFFSET = 2
"""Where msg.ln is in the header."""


class Task(IntEnum):
    """Values of msg.rx / msg.tx (seed manual 1.1 and 5; RcsDef.h)."""

    RCS = 0
    PLC = 2
    CAN = 3
    USER = 16
    SYSTEM = 0xFF


class Ext(IntEnum):
    """Bits of msg.e: answer suppression and the sequence of split transfers."""

    NORM = 0
    NAK = 2
    """RCS_NAK_MSK: no answer wanted."""
    FIRST = 4
    CONT = 8
    LAST = 0x0C
    SEQ_MASK = 0x0C


class Tfc(IntEnum):
    """TASK_TFC_*: msg.function of the extended telegram header."""

    READ = 1
    WRITE = 2
    QUERY = 3


class Tdt(IntEnum):
    """TASK_TDT_*: msg.data_type of the extended telegram header."""

    UINT8 = 5
    UINT16 = 6
    STRING = 10
    BIT = 14


TDT_INTEL = 0x80
"""Bit of data_type selecting Intel byte order."""


class MessageError(DpmError, ValueError):
    """A byte string that is not a well-formed message."""


@dataclass(slots=True)
class Message:
    """One mailbox message; ``ln`` is always ``len(data)``."""

    rx: int
    tx: int
    b: int = 0
    data: bytes = b""
    nr: int = 0
    a: int = 0
    f: int = 0
    e: int = 0

    @property
    def ln(self) -> int:
        return len(self.data)

    def encode(self) -> bytes:
        """The ``ln + 8`` bytes a sender writes into a mailbox."""
        if len(self.data) > MSG_DATA_SIZE:
            raise MessageError(f"message data of {len(self.data)} bytes exceeds 255")
        try:
            head = HEADER.pack(self.rx, self.tx, len(self.data), self.nr, self.a, self.f,
                               self.b, self.e)
        except struct.error:
            raise MessageError(f"a header field of {self!r} is not a byte") from None
        return head + self.data

    @classmethod
    def decode(cls, raw: bytes | bytearray | memoryview) -> Message:
        """Read a message from the start of ``raw`` (a mailbox slot or a copy)."""
        return cls.decode_at(raw, 0)

    @classmethod
    def decode_at(cls, buffer: bytes | bytearray | memoryview | mmap.mmap,
                  offset: int) -> Message:
        """Read a message at ``offset`` of ``buffer`` (a mailbox in the mapped image) with
        one copy of its data: ``decode`` of a slice copied it twice (the driver's get, on
        every mailbox round trip; issue 22)."""
        if len(buffer) < offset + MSG_HEADER_SIZE:
            raise MessageError(f"{len(buffer) - offset} bytes is shorter than a message header")
        rx, tx, ln, nr, a, f, b, e = HEADER.unpack_from(buffer, offset)
        start = offset + MSG_HEADER_SIZE
        if len(buffer) < start + ln:
            raise MessageError(f"msg.ln = {ln} but only {len(buffer) - start} data bytes")
        return cls(rx, tx, b, bytes(buffer[start : start + ln]), nr, a, f, e)

    def answer(self, f: int = 0, data: bytes = b"", e: int = 0) -> Message:
        """The answer a task gives to this command: rx/tx swapped, a = b, b = 0."""
        return Message(self.tx, self.rx, 0, data, self.nr, self.b, f, e)


def encode_answer(request: bytes, f: int = 0, data: bytes = b"", e: int = 0) -> bytes:
    """``Message.answer``'s answer, encoded, to the encoded command ``request`` (its header
    and as much after it as the caller has), without the two ``Message`` objects: the host's
    SDO requests that the device loop's turn in C hands over come and go as the mailbox's
    bytes (``firmware.can_host_sdo``, issue 22) [ours]."""
    return HEADER.pack(request[1], request[0], len(data), request[3], request[6], f, 0, e) + data


TELEGRAM_HEADER = struct.Struct("<BBHBBBB")


@dataclass(slots=True)
class TelegramHeader:
    """The extended telegram header: the first 8 data bytes of some messages."""

    device_adr: int = 0
    data_area: int = 0
    data_adr: int = 0
    data_idx: int = 0
    data_cnt: int = 0
    data_type: int = 0
    function: int = 0
    payload: bytes = field(default=b"", repr=False)
    """The data bytes after the header (msg.d[] in the seed's tables)."""

    SIZE = TELEGRAM_HEADER.size

    def encode(self) -> bytes:
        return (
            TELEGRAM_HEADER.pack(
                self.device_adr, self.data_area, self.data_adr, self.data_idx,
                self.data_cnt, self.data_type, self.function,
            )
            + self.payload
        )

    @classmethod
    def decode(cls, data: bytes) -> TelegramHeader:
        if len(data) < TELEGRAM_HEADER.size:
            raise MessageError(f"{len(data)} data bytes are too few for a telegram header")
        adr, area, data_adr, idx, cnt, data_type, function = TELEGRAM_HEADER.unpack_from(data)
        return cls(adr, area, data_adr, idx, cnt, data_type, function,
                   bytes(data[TELEGRAM_HEADER.size :]))
