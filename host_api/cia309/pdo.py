"""PDOs the gateway creates (309-1 4.2.2/4.2.3), served by layer-2 access: their mapping
sizes, values and identifiers. No I/O: the link routes frames to them, the services
configure them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from dpm.cia301 import ASYNC_RTR, EVENT_MANUFACTURER, EVENT_PROFILE, SYNC_RTR, SYNC_TYPES_MAX
from host_api.cia309.model import (
    MAX_PDO_NUMBER,
    MAX_PDO_OBJECTS,
    Cia309Error,
    DataType,
    ErrorCode,
    PdoMapping,
    syntax_error,
)

COB_ID_INVALID = 1 << 31
COB_ID_29_BIT = 1 << 29
COB_ID_MASK = 0x7FF
PDO_BYTES = 8


@dataclass
class Pdo:
    """A PDO the gateway created (309-1 4.2.2/4.2.3), served by layer-2 access."""

    number: int
    cob_id: int
    transmission_type: int
    sizes: tuple[int, ...]
    inhibit_s: float = 0.0
    last: bytes | None = None
    sent_at: float = 0.0

    @property
    def length(self) -> int:
        return sum(self.sizes)

    @property
    def rtr(self) -> bool:
        return self.transmission_type in (SYNC_RTR, ASYNC_RTR)

    def unpack(self, data: bytes) -> tuple[int, ...]:
        values = []
        at = 0
        for size in self.sizes:
            values.append(int.from_bytes(data[at : at + size], "little"))
            at += size
        return tuple(values)

    def pack(self, values: Sequence[int]) -> bytes:
        if len(values) != len(self.sizes):
            raise Cia309Error(ErrorCode.PDO_LENGTH_EXCEEDED,
                              f"PDO {self.number} maps {len(self.sizes)} objects, "
                              f"not {len(values)}")
        data = b""
        for value, size in zip(values, self.sizes, strict=True):
            if not -(1 << (8 * size - 1)) <= value < (1 << (8 * size)):
                raise syntax_error(f"{value} does not fit {size} bytes")
            data += (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")
        return data


def pdo_sizes(mapped_objects: Sequence[PdoMapping]) -> tuple[int, ...]:
    if not 1 <= len(mapped_objects) <= MAX_PDO_OBJECTS:
        raise syntax_error(f"a PDO maps 1..{MAX_PDO_OBJECTS} objects, not {len(mapped_objects)}")
    sizes = []
    for mapping in mapped_objects:
        dtype = mapping.dtype
        if dtype is None and mapping.index is not None:
            dtype = DUMMY_TYPES.get(mapping.index)
        size = None if dtype is None else dtype.size
        if size is None:
            raise syntax_error("a mapped object needs a data type of fixed size, or a dummy index "
                               "(0001h..001Bh): the gateway has no object dictionary to look "
                               "sizes up in")
        sizes.append(size)
    if sum(sizes) > PDO_BYTES:
        raise Cia309Error(ErrorCode.PDO_LENGTH_EXCEEDED,
                          f"the mapped objects take {sum(sizes)} bytes, a PDO has 8")
    return tuple(sizes)


DUMMY_TYPES = {dtype.cia301_index: dtype for dtype in reversed(DataType)
                if dtype.cia301_index is not None and dtype.size is not None}
"""CiA 301 data type index -> its type: Lely's ``set rpdo`` maps dummies by index alone."""


def pdo_cob_id(cob_id: int) -> int | None:
    """The 11-bit identifier, or None when bit 31 marks the PDO invalid (CiA 301)."""
    if cob_id & COB_ID_INVALID:
        return None
    if cob_id & COB_ID_29_BIT or cob_id & ~(COB_ID_INVALID | 0x4000_0000 | COB_ID_MASK):
        raise Cia309Error(ErrorCode.REQUEST_NOT_SUPPORTED,
                          f"COB-ID 0x{cob_id:X}: layer-2 access has 11-bit identifiers only")
    return cob_id & COB_ID_MASK


def check_pdo_number(number: int) -> None:
    if not 1 <= number <= MAX_PDO_NUMBER:
        raise syntax_error(f"PDO number {number} is not 1..{MAX_PDO_NUMBER}")


def check_tx_type(tx_type: int) -> None:
    if not (0 <= tx_type <= SYNC_TYPES_MAX
            or tx_type in (SYNC_RTR, ASYNC_RTR, EVENT_MANUFACTURER, EVENT_PROFILE)):
        raise syntax_error(f"transmission type {tx_type}")

