"""The CiA 309-1 model: what the typed service layer and the 309-3 text layer share.

The split follows Lely's ``gw`` and ``gw_txt``: the services (``host_api.cia309.gateway``)
take and give the types of this module and never import the text layer (``framing``,
``requests``, ``parser``, ``formatters``, ``datatypes``), which turns lines into these types
and these types into lines. Here: the limits of the 309-1 tables, the 309-3 error numbers
and the exception that carries them, the data types with their CiA 301 value codec, the
results of services and the events. No I/O, no card.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum, StrEnum

from dpm.cia301 import (
    ABORT_OUT_OF_MEMORY,
    ABORT_PDO_LENGTH,
    ABORT_TIMEOUT,
    ABORT_TYPE_LENGTH_MISMATCH,
    NODE_ID_MAX,
)

# --------------------------------------------------------------------------- limits

ALL_NODES = 0
"""The node-ID that addresses every node in the NMT services (309-1 "All")."""
MAX_COMMAND_SIZE = 131072
"""[ours] the largest command size ``set_command_size`` accepts: a 64 KiB DOMAIN in
base64 on one 309-3 line, with room for the rest of the request."""

MAX_NODE_ID = NODE_ID_MAX
MAX_PDO_NUMBER = 512
MAX_PDO_OBJECTS = 64

TIME_MS_MASK = 0x0FFF_FFFF
"""TIME_OF_DAY / TIME_DIFFERENCE keep milliseconds in the low 28 bits; the top 4 are reserved."""


# --------------------------------------------------------------------------- errors


class ErrorCode(IntEnum):
    """The CiA 309-3 error numbers (the ``<code>`` of ``ERROR:<code>``); ``text`` is the
    standard's wording. A number, not an exception: :class:`Cia309Error` carries it."""

    REQUEST_NOT_SUPPORTED = 100
    SYNTAX_ERROR = 101
    INTERNAL_STATE = 102
    TIME_OUT = 103
    NO_DEFAULT_NET = 104
    NO_DEFAULT_NODE = 105
    UNSUPPORTED_NET = 106
    UNSUPPORTED_NODE = 107
    LOST_GUARDING_MESSAGE = 200
    LOST_CONNECTION = 201
    HEARTBEAT_STARTED = 202
    HEARTBEAT_LOST = 203
    WRONG_NMT_STATE = 204
    BOOT_UP = 205
    ERROR_PASSIVE = 300
    BUS_OFF = 301
    CAN_BUFFER_OVERFLOW = 303
    CAN_INIT = 304
    CAN_ACTIVE = 305
    PDO_ALREADY_USED = 400
    PDO_LENGTH_EXCEEDED = 401
    LSS_IMPLEMENTATION_ERROR = 501
    LSS_NODE_ID_NOT_SUPPORTED = 502
    LSS_BIT_RATE_NOT_SUPPORTED = 503
    LSS_PARAMETER_STORING_FAILED = 504
    LSS_MEDIA_ERROR = 505
    OUT_OF_MEMORY = 600

    @property
    def text(self) -> str:
        """The 309-3 description, as CANopenNode's ``errorDescs`` table has it."""
        return _GATEWAY_ERROR_TEXTS[self]


_GATEWAY_ERROR_TEXTS: dict[ErrorCode, str] = {
    ErrorCode.REQUEST_NOT_SUPPORTED: "Request not supported",
    ErrorCode.SYNTAX_ERROR: "Syntax error",
    ErrorCode.INTERNAL_STATE: "Request not processed due to internal state",
    ErrorCode.TIME_OUT: "Time-out",
    ErrorCode.NO_DEFAULT_NET: "No default net set",
    ErrorCode.NO_DEFAULT_NODE: "No default node set",
    ErrorCode.UNSUPPORTED_NET: "Unsupported net",
    ErrorCode.UNSUPPORTED_NODE: "Unsupported node",
    ErrorCode.LOST_GUARDING_MESSAGE: "Lost guarding message",
    ErrorCode.LOST_CONNECTION: "Lost connection",
    ErrorCode.HEARTBEAT_STARTED: "Heartbeat started",
    ErrorCode.HEARTBEAT_LOST: "Heartbeat lost",
    ErrorCode.WRONG_NMT_STATE: "Wrong NMT state",
    ErrorCode.BOOT_UP: "Boot-up",
    ErrorCode.ERROR_PASSIVE: "Error passive",
    ErrorCode.BUS_OFF: "Bus off",
    ErrorCode.CAN_BUFFER_OVERFLOW: "CAN buffer overflow",
    ErrorCode.CAN_INIT: "CAN init",
    ErrorCode.CAN_ACTIVE: "CAN active (at init or start-up)",
    ErrorCode.PDO_ALREADY_USED: "PDO already used",
    ErrorCode.PDO_LENGTH_EXCEEDED: "PDO length exceeded",
    ErrorCode.LSS_IMPLEMENTATION_ERROR: "LSS implementation- / manufacturer-specific error",
    ErrorCode.LSS_NODE_ID_NOT_SUPPORTED: "LSS node-ID not supported",
    ErrorCode.LSS_BIT_RATE_NOT_SUPPORTED: "LSS bit-rate not supported",
    ErrorCode.LSS_PARAMETER_STORING_FAILED: "LSS parameter storing failed",
    ErrorCode.LSS_MEDIA_ERROR: "LSS command failed because of media error",
    ErrorCode.OUT_OF_MEMORY: "Running out of memory",
}


_ABORT_ERRORS: dict[int, ErrorCode] = {
    ABORT_TIMEOUT: ErrorCode.TIME_OUT,
    ABORT_OUT_OF_MEMORY: ErrorCode.OUT_OF_MEMORY,
    ABORT_PDO_LENGTH: ErrorCode.PDO_LENGTH_EXCEEDED,
}
"""SDO abort codes that have a 309-3 error number of their own (as Lely's gateway maps them)."""


class Cia309Error(Exception):
    """The root of every exception of ``host_api.cia309``: a 309-1 service, a 309-3 line or
    value, or an LSS service failed; ``reason`` is what a 309-3 answer carries.

    Exactly one of ``error`` (a 309-3 error number) and ``abort_code`` (the node's SDO
    abort) is set; ``f`` is the card's msg.f when the card refused the request. The
    subclasses say where it failed: ``requests.ParseError`` (a request line),
    ``datatypes.DataTypeError`` (a value in text), ``lss.LssError`` (an LSS service).
    """

    def __init__(
        self,
        error: ErrorCode | None,
        message: str,
        *,
        abort_code: int | None = None,
        f: int | None = None,
    ) -> None:
        self.error = error
        self.abort_code = abort_code
        self.f = f
        super().__init__(message)

    @property
    def reason(self) -> int:
        """The abort code or the 309-3 error number."""
        if self.abort_code is not None:
            return self.abort_code
        assert self.error is not None
        return int(self.error)

    @classmethod
    def abort(cls, code: int, what: str) -> Cia309Error:
        """An SDO abort; the few codes 309-3 has numbers for become those numbers."""
        error = _ABORT_ERRORS.get(code)
        if error is not None:
            return cls(error, f"{what}: SDO abort 0x{code:08X}")
        return cls(None, f"{what}: SDO abort 0x{code:08X}", abort_code=code)


def syntax_error(message: str) -> Cia309Error:
    """A value or request the 309-1 tables do not allow: 309-3 error 101."""
    return Cia309Error(ErrorCode.SYNTAX_ERROR, message)


# --------------------------------------------------------------------------- data types


class DataType(StrEnum):
    """The 309-3 data type mnemonics; the value is the mnemonic as written on the line."""

    BOOLEAN = "b"
    INTEGER8 = "i8"
    INTEGER16 = "i16"
    INTEGER24 = "i24"
    INTEGER32 = "i32"
    INTEGER40 = "i40"
    INTEGER48 = "i48"
    INTEGER56 = "i56"
    INTEGER64 = "i64"
    UNSIGNED8 = "u8"
    UNSIGNED16 = "u16"
    UNSIGNED24 = "u24"
    UNSIGNED32 = "u32"
    UNSIGNED40 = "u40"
    UNSIGNED48 = "u48"
    UNSIGNED56 = "u56"
    UNSIGNED64 = "u64"
    HEX8 = "x8"
    HEX16 = "x16"
    HEX32 = "x32"
    HEX64 = "x64"
    REAL32 = "r32"
    REAL64 = "r64"
    TIME_OF_DAY = "t"
    TIME_DIFFERENCE = "td"
    VISIBLE_STRING = "vs"
    OCTET_STRING = "os"
    UNICODE_STRING = "us"
    DOMAIN = "d"
    HEX = "hex"

    @property
    def size(self) -> int | None:
        """Bytes on the bus, or None for the variable-length types."""
        return SIZES[self]

    @property
    def cia301_index(self) -> int | None:
        """The CiA 301 data type index (object 0x0001..0x001B), also the index of a dummy
        PDO mapping; None for the non-standard ``hex``."""
        return _INDICES[self]

    @property
    def pdo_mappable(self) -> bool:
        """309-1 4.2.1: strings and domains are not PDO access data types."""
        return self.size is not None


SIZES: dict[DataType, int | None] = {
    DataType.BOOLEAN: 1,
    DataType.INTEGER8: 1,
    DataType.INTEGER16: 2,
    DataType.INTEGER24: 3,
    DataType.INTEGER32: 4,
    DataType.INTEGER40: 5,
    DataType.INTEGER48: 6,
    DataType.INTEGER56: 7,
    DataType.INTEGER64: 8,
    DataType.UNSIGNED8: 1,
    DataType.UNSIGNED16: 2,
    DataType.UNSIGNED24: 3,
    DataType.UNSIGNED32: 4,
    DataType.UNSIGNED40: 5,
    DataType.UNSIGNED48: 6,
    DataType.UNSIGNED56: 7,
    DataType.UNSIGNED64: 8,
    DataType.HEX8: 1,
    DataType.HEX16: 2,
    DataType.HEX32: 4,
    DataType.HEX64: 8,
    DataType.REAL32: 4,
    DataType.REAL64: 8,
    DataType.TIME_OF_DAY: 6,
    DataType.TIME_DIFFERENCE: 6,
    DataType.VISIBLE_STRING: None,
    DataType.OCTET_STRING: None,
    DataType.UNICODE_STRING: None,
    DataType.DOMAIN: None,
    DataType.HEX: None,
}
"""``DataType.size`` of each type, for a caller on every read's and write's path: a dict
look-up where the property is a Python call (issue 22)."""
_INDICES: dict[DataType, int | None] = {
    DataType.BOOLEAN: 0x0001,
    DataType.INTEGER8: 0x0002,
    DataType.INTEGER16: 0x0003,
    DataType.INTEGER24: 0x0010,
    DataType.INTEGER32: 0x0004,
    DataType.INTEGER40: 0x0012,
    DataType.INTEGER48: 0x0013,
    DataType.INTEGER56: 0x0014,
    DataType.INTEGER64: 0x0015,
    DataType.UNSIGNED8: 0x0005,
    DataType.UNSIGNED16: 0x0006,
    DataType.UNSIGNED24: 0x0016,
    DataType.UNSIGNED32: 0x0007,
    DataType.UNSIGNED40: 0x0018,
    DataType.UNSIGNED48: 0x0019,
    DataType.UNSIGNED56: 0x001A,
    DataType.UNSIGNED64: 0x001B,
    DataType.HEX8: 0x0005,
    DataType.HEX16: 0x0006,
    DataType.HEX32: 0x0007,
    DataType.HEX64: 0x001B,
    DataType.REAL32: 0x0008,
    DataType.REAL64: 0x0011,
    DataType.TIME_OF_DAY: 0x000C,
    DataType.TIME_DIFFERENCE: 0x000D,
    DataType.VISIBLE_STRING: 0x0009,
    DataType.OCTET_STRING: 0x000A,
    DataType.UNICODE_STRING: 0x000B,
    DataType.DOMAIN: 0x000F,
    DataType.HEX: None,
}


# --------------------------------------------------------------------------- values


Value = bytes | bytearray | int | float | str | tuple[int, int]
"""What ``sdo_download`` accepts: CiA 301 bytes, or a Python value of the data type
(``(days, ms)`` for TIME_OF_DAY and TIME_DIFFERENCE)."""

"""What ``sdo_download`` accepts: CiA 301 bytes, or a Python value of the data type
(``(days, ms)`` for TIME_OF_DAY and TIME_DIFFERENCE)."""

_SIGNED = {
    DataType.INTEGER8, DataType.INTEGER16, DataType.INTEGER24, DataType.INTEGER32,
    DataType.INTEGER40, DataType.INTEGER48, DataType.INTEGER56, DataType.INTEGER64,
}
_TIMES = {DataType.TIME_OF_DAY, DataType.TIME_DIFFERENCE}


def encode_value(data_type: DataType, value: Value) -> bytes:
    """The CiA 301 bytes of a Python value; bytes pass unchanged (their length is checked).

    Raises Cia309Error 101 for a value that is not of the type, as a 309-3 gateway
    answers a value it cannot parse.
    """
    size = data_type.size
    if isinstance(value, bytes | bytearray):
        if size is not None and len(value) != size:
            raise syntax_error(f"{len(value)} bytes are no {data_type.value} value ({size} bytes)")
        return bytes(value)
    try:
        if data_type in _TIMES:
            assert isinstance(value, tuple)
            days, milliseconds = value
            return (milliseconds & TIME_MS_MASK).to_bytes(4, "little") + days.to_bytes(
                2, "little"
            )
        if data_type is DataType.REAL32:
            assert isinstance(value, int | float)
            return struct.pack("<f", value)
        if data_type is DataType.REAL64:
            assert isinstance(value, int | float)
            return struct.pack("<d", value)
        if data_type is DataType.VISIBLE_STRING:
            assert isinstance(value, str)
            return value.encode("latin-1")
        if data_type is DataType.UNICODE_STRING:
            assert isinstance(value, str)
            return value.encode("utf-16-le")
        assert isinstance(value, int) and size is not None
        return value.to_bytes(size, "little", signed=data_type in _SIGNED)
    except (AssertionError, OverflowError, UnicodeEncodeError, struct.error, ValueError):
        raise syntax_error(f"{value!r} is no {data_type.value} value") from None


def decode_value(data_type: DataType, data: bytes) -> int | float | str | bytes | tuple[int, int]:
    """The Python value of uploaded bytes; a length that does not fit the type raises the
    SDO abort 06070010h, as Lely's gateway answers it."""
    size = data_type.size
    if size is not None and len(data) != size:
        raise Cia309Error(None, f"{len(data)} bytes are no {data_type.value} value",
                          abort_code=ABORT_TYPE_LENGTH_MISMATCH)
    if data_type in _TIMES:
        return int.from_bytes(data[4:], "little"), int.from_bytes(data[:4], "little") & (
            TIME_MS_MASK
        )
    if data_type is DataType.REAL32:
        return float(struct.unpack("<f", data)[0])
    if data_type is DataType.REAL64:
        return float(struct.unpack("<d", data)[0])
    if data_type is DataType.VISIBLE_STRING:
        return data.decode("latin-1")
    if data_type is DataType.UNICODE_STRING:
        return data.decode("utf-16-le", errors="replace")
    if size is None:
        return bytes(data)
    return int.from_bytes(data, "little", signed=data_type in _SIGNED)


# --------------------------------------------------------------------------- results



# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class PdoMapping:
    """One mapped object: a multiplexer, a data type, or both (309-1 4.2.2 "selection").

    A type without a multiplexer is a dummy mapping; Lely maps it to the type's CiA 301 index.
    """

    index: int | None
    subindex: int | None
    dtype: DataType | None



@dataclass(frozen=True)
class VersionInfo:
    """309-1 Table 33: what ``info version`` answers."""

    vendor_id: int
    product_code: int
    revision: int
    serial: int
    gateway_class: int = 3
    protocol_version: tuple[int, int] = (2, 0)
    implementation_version: tuple[int, int] = (1, 0)


@dataclass(frozen=True)
class DeviceError:
    """309-1 Table 20, the remote result of ``read_device_error``.

    ``error`` is the node's actual error as the card records it (its Err_Event number,
    0 for none) with the seed's text; ``emergencies`` are the EMCYs received since the
    previous ``read_device_error`` (the gateway keeps the last 64 per node).
    """

    network: int
    node_id: int
    error: int
    error_text: str
    emergencies: tuple[EmergencyEvent, ...]



# --------------------------------------------------------------------------- events


class NmtState(IntEnum):
    """NMT states as the heartbeat reports them (CiA 301)."""

    INITIALIZING = 0
    STOPPED = 4
    OPERATIONAL = 5
    PRE_OPERATIONAL = 127


@dataclass(frozen=True)
class BootUpEvent:
    """A node's boot-up message (309-1 4.3.11 with boot-up), when forwarding is on."""

    net: int
    node: int


@dataclass(frozen=True)
class ErrorControlEvent:
    """A node changed NMT state and/or an error control event happened (309-1 4.3.11)."""

    net: int
    node: int
    state: NmtState | None = None
    error: ErrorCode | None = None


@dataclass(frozen=True)
class EmergencyEvent:
    """An EMCY received (309-1 4.4.3): error code, error register, 5 manufacturer bytes."""

    net: int
    node: int
    code: int
    register: int
    manufacturer: bytes = bytes(5)


@dataclass(frozen=True)
class RpdoEvent:
    """New RPDO data (309-1 4.2.6), one raw value per mapped object."""

    net: int
    number: int
    values: tuple[int, ...]


@dataclass(frozen=True)
class SdoProgressEvent:
    """Bytes transferred so far of a long SDO transfer (309-1 5.4)."""

    net: int
    node: int
    upload: bool
    transferred: int


Event = BootUpEvent | ErrorControlEvent | EmergencyEvent | RpdoEvent | SdoProgressEvent
