"""The CiA 309-3 ASCII mapping: line framing, request parsing and answer formatting.

A 309-3 client writes one request per line, ``[<sequence>] [[<net>] <node>] <command> <args>``,
and reads ``[<sequence>] OK``, ``[<sequence>] <value>`` or ``[<sequence>] ERROR:<code>``, with
unsolicited event lines in between. This module is the codec of that text and nothing more:
no socket, no clock, no card. The TCP server feeds received bytes to a :class:`LineFramer`,
hands each line to :func:`parse_request`, gives the typed request to the 309-1 service layer
and writes the answer made by the ``format_*`` functions (the pymodbus split of framer, PDU
codec and transport, with the 309-1 services of Lely's ``gw.c`` as the typed core).

Clients that exist today must work unchanged, so the grammar is the union of the two open
gateways, CANopenNode's (``309/CO_gateway_ascii.c``, used by its ``cocomm`` tool) and Lely's
(``src/co/gw_txt.c``, ``doc/coctl.md``), and answers are spelled per :class:`Dialect`:

* success: ``[1] OK`` in both;
* 309-3 error: CANopenNode ``[1] ERROR:101 #Syntax error.``, Lely ``[1] ERROR: 101 (Syntax
  error)``;
* SDO abort: CANopenNode ``[1] ERROR:0x06020000 #<text>.``, Lely ``[1] ERROR: 06020000
  (<text>)``;
* line end: CANopenNode CR LF, Lely LF;
* an empty or comment-only request: CANopenNode answers an empty line (``cocomm -f`` waits
  for it), Lely nothing.

``cocomm`` only looks for ``"] ERROR:"``, ``"] OK\\r\\n"`` and the first ``"] "``, so the
text after the code is a comment for people. Default network and node are the caller's
business: a request field is None when the line did not give it.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from enum import IntEnum

from host_api.cia309.datatypes import (
    DataType,
    DataTypeError,
    Dialect,
    format_value,
    parse_integer,
    parse_value,
)

__all__ = [
    "DEFAULT_MAX_LINE",
    "LSS_UNCONFIGURED",
    "MAX_NODE_ID",
    "MAX_PDO_NUMBER",
    "MAX_PDO_OBJECTS",
    "SDO_ABORT_TEXTS",
    "TRANSMISSION_EVENT",
    "TRANSMISSION_RTR",
    "BootUpEvent",
    "ConfigureRpdo",
    "ConfigureTpdo",
    "DataType",
    "Dialect",
    "DisableGuarding",
    "DisableHeartbeat",
    "EmergencyEvent",
    "EnableGuarding",
    "EnableHeartbeat",
    "EnterPreoperational",
    "ErrorControlEvent",
    "Event",
    "GatewayError",
    "GetVersion",
    "Help",
    "InitGateway",
    "LineFramer",
    "Log",
    "LssActivateBitRate",
    "LssAddress",
    "LssAddressRange",
    "LssAssignNodeId",
    "LssCompleteConfiguration",
    "LssConfigureBitRate",
    "LssConfigureNodeId",
    "LssFastscan",
    "LssIdentifyFastscan",
    "LssIdentifyNonConfigured",
    "LssIdentifyRemoteSlave",
    "LssInquireAddress",
    "LssInquireNodeId",
    "LssScanCriterion",
    "LssSlowscan",
    "LssStore",
    "LssSwitchGlobal",
    "LssSwitchSelective",
    "NetworkRequest",
    "NmtState",
    "NodeRequest",
    "OverlongLine",
    "ParseError",
    "PdoMapping",
    "ReadPdo",
    "Request",
    "ResetCommunication",
    "ResetNode",
    "RestoreConfiguration",
    "RpdoEvent",
    "SdoDownload",
    "SdoProgressEvent",
    "SdoUpload",
    "SetBootUpForwarding",
    "SetCommandSize",
    "SetCommandTimeout",
    "SetDefaultNetwork",
    "SetDefaultNode",
    "SetHeartbeatProducer",
    "SetNodeId",
    "SetSdoBlock",
    "SetSdoTimeout",
    "StartNode",
    "StopNode",
    "StoreConfiguration",
    "VersionInfo",
    "WritePdo",
    "abort_text",
    "error_text",
    "format_abort",
    "format_empty",
    "format_error",
    "format_event",
    "format_help",
    "format_lss_address",
    "format_lss_node_id",
    "format_lss_number",
    "format_ok",
    "format_pdo_read",
    "format_upload",
    "format_value_response",
    "format_version",
    "parse_request",
]

DEFAULT_MAX_LINE = 16384
"""Longest request line accepted, in bytes without the line end. CANopenLinux's command
buffer is 2000 bytes but CANopenNode streams longer SDO writes through it; we hold whole lines,
so the default leaves room for a 12 KiB domain in base64. ``set command_size`` may change it."""

MAX_NODE_ID = 127
MAX_PDO_NUMBER = 512
MAX_PDO_OBJECTS = 64
LSS_UNCONFIGURED = 0xFF
"""The LSS node-ID of a slave without one; ``lss_set_node`` and ``set id`` accept it."""
_LSS_INQUIRE_FIRST_CS = 0x5A
"""CiA 305 command specifier of 'inquire vendor-ID'; Lely names the LSS number by it."""

_U16 = 0xFFFF
_U32 = 0xFFFF_FFFF


class GatewayError(IntEnum):
    """The CiA 309-3 error numbers (CIA309.md); ``text`` is the standard's wording."""

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


_GATEWAY_ERROR_TEXTS: dict[GatewayError, str] = {
    GatewayError.REQUEST_NOT_SUPPORTED: "Request not supported",
    GatewayError.SYNTAX_ERROR: "Syntax error",
    GatewayError.INTERNAL_STATE: "Request not processed due to internal state",
    GatewayError.TIME_OUT: "Time-out",
    GatewayError.NO_DEFAULT_NET: "No default net set",
    GatewayError.NO_DEFAULT_NODE: "No default node set",
    GatewayError.UNSUPPORTED_NET: "Unsupported net",
    GatewayError.UNSUPPORTED_NODE: "Unsupported node",
    GatewayError.LOST_GUARDING_MESSAGE: "Lost guarding message",
    GatewayError.LOST_CONNECTION: "Lost connection",
    GatewayError.HEARTBEAT_STARTED: "Heartbeat started",
    GatewayError.HEARTBEAT_LOST: "Heartbeat lost",
    GatewayError.WRONG_NMT_STATE: "Wrong NMT state",
    GatewayError.BOOT_UP: "Boot-up",
    GatewayError.ERROR_PASSIVE: "Error passive",
    GatewayError.BUS_OFF: "Bus off",
    GatewayError.CAN_BUFFER_OVERFLOW: "CAN buffer overflow",
    GatewayError.CAN_INIT: "CAN init",
    GatewayError.CAN_ACTIVE: "CAN active (at init or start-up)",
    GatewayError.PDO_ALREADY_USED: "PDO already used",
    GatewayError.PDO_LENGTH_EXCEEDED: "PDO length exceeded",
    GatewayError.LSS_IMPLEMENTATION_ERROR: "LSS implementation- / manufacturer-specific error",
    GatewayError.LSS_NODE_ID_NOT_SUPPORTED: "LSS node-ID not supported",
    GatewayError.LSS_BIT_RATE_NOT_SUPPORTED: "LSS bit-rate not supported",
    GatewayError.LSS_PARAMETER_STORING_FAILED: "LSS parameter storing failed",
    GatewayError.LSS_MEDIA_ERROR: "LSS command failed because of media error",
    GatewayError.OUT_OF_MEMORY: "Running out of memory",
}

_LELY_ERROR_TEXTS = {
    GatewayError.CAN_ACTIVE: "CAN active",
    GatewayError.LSS_IMPLEMENTATION_ERROR: "LSS error",
}
"""Lely's ``co_gw_iec2str`` shortens these two."""

SDO_ABORT_TEXTS: dict[int, str] = {
    0x0503_0000: "Toggle bit not alternated",
    0x0504_0000: "SDO protocol timed out",
    0x0504_0001: "Client/server command specifier not valid or unknown",
    0x0504_0002: "Invalid block size (block mode only)",
    0x0504_0003: "Invalid sequence number (block mode only)",
    0x0504_0004: "CRC error (block mode only)",
    0x0504_0005: "Out of memory",
    0x0601_0000: "Unsupported access to an object",
    0x0601_0001: "Attempt to read a write only object",
    0x0601_0002: "Attempt to write a read only object",
    0x0602_0000: "Object does not exist in the object dictionary",
    0x0604_0041: "Object cannot be mapped to the PDO",
    0x0604_0042: "The number and length of the objects to be mapped would exceed PDO length",
    0x0604_0043: "General parameter incompatibility reason",
    0x0604_0047: "General internal incompatibility in the device",
    0x0606_0000: "Access failed due to a hardware error",
    0x0607_0010: "Data type does not match, length of service parameter does not match",
    0x0607_0012: "Data type does not match, length of service parameter too high",
    0x0607_0013: "Data type does not match, length of service parameter too low",
    0x0609_0011: "Sub-index does not exist",
    0x0609_0030: "Invalid value for parameter (download only)",
    0x0609_0031: "Value of parameter written too high (download only)",
    0x0609_0032: "Value of parameter written too low (download only)",
    0x0609_0036: "Maximum value is less than minimum value",
    0x060A_0023: "Resource not available: SDO connection",
    0x0800_0000: "General error",
    0x0800_0020: "Data cannot be transferred or stored to the application",
    0x0800_0021: (
        "Data cannot be transferred or stored to the application because of local control"
    ),
    0x0800_0022: (
        "Data cannot be transferred or stored to the application because of the present "
        "device state"
    ),
    0x0800_0023: (
        "Object dictionary dynamic generation fails or no object dictionary is present"
    ),
    0x0800_0024: "No data available",
}
"""The SDO abort codes of CiA 301 with the standard's texts; a 309-3 answer to a failed SDO
transfer carries the code instead of a 309-3 error number."""


def error_text(error: int, dialect: Dialect = Dialect.CANOPENNODE) -> str:
    """The description of a 309-3 error number, as the dialect's gateway words it."""
    try:
        code = GatewayError(error)
    except ValueError:
        return "Unknown error code"
    if dialect is Dialect.LELY:
        return _LELY_ERROR_TEXTS.get(code, code.text)
    return code.text


def abort_text(abort_code: int) -> str:
    """The CiA 301 text of an SDO abort code."""
    return SDO_ABORT_TEXTS.get(abort_code, "Unknown abort code")


class ParseError(Exception):
    """A request line the gateway cannot accept; the answer is ``ERROR:<error>``.

    ``sequence`` is the request's sequence number when the line got that far, else None
    (CANopenNode then repeats the previous one, which is 0 on a fresh connection).
    """

    def __init__(self, error: GatewayError, sequence: int | None, message: str) -> None:
        super().__init__(message)
        self.error = error
        self.sequence = sequence


# --------------------------------------------------------------------------- framing

_SEQUENCE = re.compile(r"\[\s*([^\]]*?)\s*\]")
_LINE_BREAK = re.compile(rb"[\r\n]")
_OVERLONG_HEAD = 64


@dataclass(frozen=True)
class OverlongLine:
    """A request longer than the framer's limit; its bytes were dropped up to the next line end.

    ``head`` keeps the first bytes, so the answer can still echo the sequence number.
    """

    head: str

    @property
    def sequence(self) -> int | None:
        """The sequence number of the dropped request, when its head shows one."""
        match = _SEQUENCE.match(self.head.lstrip())
        if match is None:
            return None
        try:
            return parse_integer(match.group(1), 0, _U32, "sequence")
        except DataTypeError:
            return None

    def error(self) -> ParseError:
        """309-1 4.6.5: a command above the command size is refused for lack of memory."""
        return ParseError(
            GatewayError.OUT_OF_MEMORY, self.sequence, "request longer than the command size"
        )


class LineFramer:
    """Cuts a byte stream into request lines.

    CR, LF and CR LF each end a line (Lely's lexer treats all three as a break; CANopenNode
    needs LF and ignores CR as white space, so its clients send LF or CR LF). Lines come
    back as ``str`` decoded Latin-1, one character per byte, so no byte is ever an error
    here. A line over ``max_line`` bytes yields one :class:`OverlongLine` as soon as it
    grows past the limit; the rest of it is dropped and framing resumes after its line end.
    """

    def __init__(self, max_line: int = DEFAULT_MAX_LINE) -> None:
        self.max_line = max_line
        self._buffer = bytearray()
        self._discarding = False
        self._after_cr = False

    @property
    def pending(self) -> int:
        """Bytes held of a line whose end has not arrived yet."""
        return len(self._buffer)

    @property
    def partial(self) -> bool:
        """A line has begun and its end has not arrived (held, or dropped as overlong)."""
        return bool(self._buffer) or self._discarding

    def feed(self, data: bytes) -> list[str | OverlongLine]:
        """Take the next received bytes; return the lines (and overlong reports) they end."""
        out: list[str | OverlongLine] = []
        position = 1 if self._after_cr and data[:1] == b"\n" else 0
        self._after_cr = False
        while (match := _LINE_BREAK.search(data, position)) is not None:
            self._append(data[position : match.start()], out)
            if self._discarding:
                self._discarding = False
            else:
                out.append(self._buffer.decode("latin-1"))
            self._buffer.clear()
            position = match.end()
            if data[match.start()] == 0x0D:
                if position == len(data):
                    self._after_cr = True
                elif data[position] == 0x0A:
                    position += 1
        self._append(data[position:], out)
        return out

    def _append(self, chunk: bytes, out: list[str | OverlongLine]) -> None:
        if self._discarding or not chunk:
            return
        self._buffer += chunk
        if len(self._buffer) > self.max_line:
            # Only the first max_line + 1 bytes are certain to be here whatever the
            # chunking, so the report is made of no more than those.
            head = self._buffer[: min(_OVERLONG_HEAD, self.max_line + 1)]
            out.append(OverlongLine(head.decode("latin-1")))
            self._buffer.clear()
            self._discarding = True


# --------------------------------------------------------------------------- requests


@dataclass(frozen=True, kw_only=True)
class Request:
    """What every request has: the sequence number its answer must echo."""

    sequence: int


@dataclass(frozen=True, kw_only=True)
class NetworkRequest(Request):
    """A request to one network; ``net`` None means the default network."""

    net: int | None = None


@dataclass(frozen=True, kw_only=True)
class NodeRequest(NetworkRequest):
    """A request to one node; ``node`` None means the default node, 0 all nodes (NMT only)."""

    node: int | None = None


@dataclass(frozen=True, kw_only=True)
class SdoUpload(NodeRequest):
    """``r[ead] <index> <subindex> [<datatype>]``; no type means ``hex`` (CANopenNode)."""

    index: int
    subindex: int
    dtype: DataType | None = None


@dataclass(frozen=True, kw_only=True)
class SdoDownload(NodeRequest):
    """``w[rite] <index> <subindex> <datatype> <value>``, the value already in CiA 301 bytes."""

    index: int
    subindex: int
    dtype: DataType
    data: bytes


@dataclass(frozen=True, kw_only=True)
class StartNode(NodeRequest):
    """``start``: NMT start remote node."""


@dataclass(frozen=True, kw_only=True)
class StopNode(NodeRequest):
    """``stop``: NMT stop remote node."""


@dataclass(frozen=True, kw_only=True)
class EnterPreoperational(NodeRequest):
    """``preop[erational]``: NMT enter pre-operational."""


@dataclass(frozen=True, kw_only=True)
class ResetNode(NodeRequest):
    """``reset node``: NMT reset node (application)."""


@dataclass(frozen=True, kw_only=True)
class ResetCommunication(NodeRequest):
    """``reset comm[unication]``: NMT reset communication."""


@dataclass(frozen=True, kw_only=True)
class EnableGuarding(NodeRequest):
    """``enable guarding <guard time ms> <life time factor>``."""

    guard_time: int
    lifetime_factor: int


@dataclass(frozen=True, kw_only=True)
class DisableGuarding(NodeRequest):
    """``disable guarding``."""


@dataclass(frozen=True, kw_only=True)
class EnableHeartbeat(NodeRequest):
    """``enable heartbeat <consumer time ms>``: start the heartbeat consumer for the node."""

    consumer_time: int


@dataclass(frozen=True, kw_only=True)
class DisableHeartbeat(NodeRequest):
    """``disable heartbeat``: stop consuming the node's heartbeat."""


@dataclass(frozen=True, kw_only=True)
class SetSdoTimeout(NetworkRequest):
    """``set sdo_timeout <ms>``: the time-out of all client SDOs."""

    timeout_ms: int


@dataclass(frozen=True, kw_only=True)
class SetSdoBlock(NetworkRequest):
    """``set sdo_block <0|1>`` (CANopenNode): allow SDO block transfer."""

    enabled: bool


@dataclass(frozen=True)
class PdoMapping:
    """One mapped object: a multiplexer, a data type, or both (309-1 4.2.2 "selection").

    A type without a multiplexer is a dummy mapping; Lely maps it to the type's CiA 301 index.
    """

    index: int | None
    subindex: int | None
    dtype: DataType | None


TRANSMISSION_RTR = 0xFD
TRANSMISSION_EVENT = 0xFF


@dataclass(frozen=True, kw_only=True)
class ConfigureRpdo(NetworkRequest):
    """``set rpdo <nr> <COB-ID> <tx-type> <n> <mapping>...``; tx-type is ``event``, ``rtr``
    or ``sync<0..240>`` and is kept as its CiA 301 number (0xFF, 0xFD, 0..240)."""

    number: int
    cob_id: int
    transmission_type: int
    mappings: tuple[PdoMapping, ...]


@dataclass(frozen=True, kw_only=True)
class ConfigureTpdo(NetworkRequest):
    """``set tpdo`` as ``set rpdo``; ``set tpdox`` adds, as Lely spells it,
    ``event<inhibit ms> <event timer ms>``, ``rtr <event timer ms>`` or
    ``sync<n> <SYNC start value>``."""

    number: int
    cob_id: int
    transmission_type: int
    mappings: tuple[PdoMapping, ...]
    inhibit_time: int | None = None
    event_timer: int | None = None
    sync_start: int | None = None


@dataclass(frozen=True, kw_only=True)
class ReadPdo(NetworkRequest):
    """``r[ead] p[do] <nr>``: the last data of an RPDO (RTR for types 252/253)."""

    number: int


@dataclass(frozen=True, kw_only=True)
class WritePdo(NetworkRequest):
    """``w[rite] p[do] <nr> <n> <value>...``: the mapped objects' raw values, then send."""

    number: int
    values: tuple[int, ...]


@dataclass(frozen=True, kw_only=True)
class InitGateway(NetworkRequest):
    """``init <bit rate index 0..9>`` (the CiA 305 table, 9 = automatic detection)."""

    bit_rate_index: int


@dataclass(frozen=True, kw_only=True)
class StoreConfiguration(NetworkRequest):
    """``store [<specifier>]``: our spelling; neither open gateway implements 309-1 4.5.3."""

    specifier: int | None = None


@dataclass(frozen=True, kw_only=True)
class RestoreConfiguration(NetworkRequest):
    """``restore [<specifier>]``: our spelling; neither open gateway implements 309-1 4.5.4."""

    specifier: int | None = None


@dataclass(frozen=True, kw_only=True)
class SetHeartbeatProducer(NetworkRequest):
    """``set heartbeat <ms>``: the gateway's own heartbeat producer time (Lely)."""

    producer_time: int


@dataclass(frozen=True, kw_only=True)
class SetNodeId(NetworkRequest):
    """``set id <node-ID>``: the gateway's own node-ID on the network (Lely)."""

    node_id: int


@dataclass(frozen=True, kw_only=True)
class SetBootUpForwarding(NetworkRequest):
    """``boot_up_indication Enable|Disable`` (Lely): forward boot-up events or not."""

    enabled: bool


@dataclass(frozen=True, kw_only=True)
class SetDefaultNode(NetworkRequest):
    """``set node <node-ID>``."""

    node_id: int


@dataclass(frozen=True, kw_only=True)
class GetVersion(NetworkRequest):
    """``info version``."""


@dataclass(frozen=True, kw_only=True)
class SetDefaultNetwork(Request):
    """``set network <net>``."""

    network: int


@dataclass(frozen=True, kw_only=True)
class SetCommandTimeout(Request):
    """``set command_timeout <ms>``."""

    timeout_ms: int


@dataclass(frozen=True, kw_only=True)
class SetCommandSize(Request):
    """``set command_size <bytes>``: the longest request the client will send."""

    size: int


@dataclass(frozen=True, kw_only=True)
class Help(Request):
    """``help [datatype|lss]`` (CANopenNode)."""

    topic: str | None = None


@dataclass(frozen=True, kw_only=True)
class Log(Request):
    """``log`` (CANopenNode): print the message log, where CANopenNode's events go."""


@dataclass(frozen=True)
class LssAddress:
    """The four LSS numbers: object 1018h sub 1..4."""

    vendor_id: int
    product_code: int
    revision: int
    serial: int


@dataclass(frozen=True)
class LssAddressRange:
    """An LSS address with ranges for revision and serial (309-1 4.8.10 LSS_address_sel)."""

    vendor_id: int
    product_code: int
    revision_low: int
    revision_high: int
    serial_low: int
    serial_high: int


@dataclass(frozen=True)
class LssScanCriterion:
    """One LSS number in ``lss_allnodes``: scan 0 = fastscan it, 1 = ignore, 2 = match value."""

    scan: int
    value: int


@dataclass(frozen=True, kw_only=True)
class LssSwitchGlobal(NetworkRequest):
    """``lss_switch_glob <0|1>``: all slaves to waiting (0) or configuration (1) state."""

    configuration: bool


@dataclass(frozen=True, kw_only=True)
class LssSwitchSelective(NetworkRequest):
    """``lss_switch_sel <vendorID> <product code> <revisionNo> <serialNo>``."""

    address: LssAddress


@dataclass(frozen=True, kw_only=True)
class LssConfigureNodeId(NetworkRequest):
    """``lss_set_node <node-ID>`` (255 makes the slave unconfigured)."""

    node_id: int


@dataclass(frozen=True, kw_only=True)
class LssConfigureBitRate(NetworkRequest):
    """``lss_conf_bitrate <table_selector> <table_index>``."""

    table_selector: int
    table_index: int


@dataclass(frozen=True, kw_only=True)
class LssActivateBitRate(NetworkRequest):
    """``lss_activate_bitrate <switch_delay ms>``."""

    switch_delay_ms: int


@dataclass(frozen=True, kw_only=True)
class LssStore(NetworkRequest):
    """``lss_store``."""


@dataclass(frozen=True, kw_only=True)
class LssInquireAddress(NetworkRequest):
    """``lss_inquire_addr [<n>]``: LSS number 0..3 (vendor, product, revision, serial).

    CANopenNode writes 0..3 and without an argument asks for all four; Lely writes the
    CiA 305 command specifier 0x5A..0x5D, which is mapped here to 0..3.
    """

    lss_sub: int | None = None


@dataclass(frozen=True, kw_only=True)
class LssInquireNodeId(NetworkRequest):
    """``lss_get_node``."""


@dataclass(frozen=True, kw_only=True)
class LssIdentifyRemoteSlave(NetworkRequest):
    """``lss_identity <vendorID> <product> <rev low> <rev high> <serial low> <serial high>``."""

    selection: LssAddressRange


@dataclass(frozen=True, kw_only=True)
class LssIdentifyNonConfigured(NetworkRequest):
    """``lss_ident_nonconf``."""


@dataclass(frozen=True, kw_only=True)
class LssFastscan(NetworkRequest):
    """``lss_fastscan <IDNumber> <BitChecked> <LSSSub> <LSSNext>``: one CiA 305 fastscan
    frame, 309-1 4.8.12; the spelling is ours, by analogy with the other ``lss_`` commands."""

    id_number: int
    bit_checked: int
    lss_sub: int
    lss_next: int


@dataclass(frozen=True, kw_only=True)
class LssIdentifyFastscan(NetworkRequest):
    """``_lss_fastscan``: find one unconfigured slave and select it, both dialects' extension.

    CANopenNode writes ``_lss_fastscan [<timeout ms>]`` (all bits unknown); Lely writes the
    known bits and their masks, ``<vendorID> <mask> <product> <mask> <rev> <mask> <serial>
    <mask>``.
    """

    timeout_ms: int | None = None
    known: LssAddress = LssAddress(0, 0, 0, 0)
    mask: LssAddress = LssAddress(0, 0, 0, 0)


@dataclass(frozen=True, kw_only=True)
class LssSlowscan(NetworkRequest):
    """``_lss_slowscan`` (Lely): binary search with ``lss_identity``, then select the slave."""

    selection: LssAddressRange


@dataclass(frozen=True, kw_only=True)
class LssAssignNodeId(NetworkRequest):
    """``lss_assign <vendorID> <product> <revisionNo> <serialNo> <node-ID>``: 309-1 4.8.13;
    the spelling is ours (neither open gateway implements it)."""

    address: LssAddress
    node_id: int


@dataclass(frozen=True, kw_only=True)
class LssCompleteConfiguration(NetworkRequest):
    """``lss_allnodes [<timeout ms> [<first node-ID> <store 0|1> [<scan> <value>]*4]]``.

    309-1 4.8.14 without arguments; CANopenNode's optional arguments narrow the scan.
    None means the gateway's default (CANopenNode: 100 ms, node-ID 2, store, scan all).
    """

    timeout_ms: int | None = None
    first_node_id: int | None = None
    store: bool | None = None
    criteria: tuple[LssScanCriterion, ...] = ()


# --------------------------------------------------------------------------- parsing


@dataclass(frozen=True)
class _Token:
    text: str
    start: int
    end: int


class _Context:
    """The tokens of one request after its command word, and where its errors point."""

    def __init__(
        self,
        sequence: int,
        numbers: list[int],
        tokens: list[_Token],
        text: str,
        dialect: Dialect,
    ) -> None:
        self.sequence = sequence
        self.numbers = numbers
        self.tokens = tokens
        self.text = text
        self.dialect = dialect
        self.position = 0

    def fail(self, message: str, error: GatewayError = GatewayError.SYNTAX_ERROR) -> ParseError:
        return ParseError(error, self.sequence, message)

    def optional(self) -> str | None:
        if self.position == len(self.tokens):
            return None
        self.position += 1
        return self.tokens[self.position - 1].text

    def word(self, what: str) -> str:
        token = self.optional()
        if token is None:
            raise self.fail(f"{what} missing")
        return token

    def remaining(self) -> int:
        return len(self.tokens) - self.position

    def integer(self, what: str, low: int, high: int, error: GatewayError | None = None) -> int:
        return self.convert(self.word(what), what, low, high, error)

    def convert(
        self, token: str, what: str, low: int, high: int, error: GatewayError | None = None
    ) -> int:
        """A number argument; out of range is a syntax error unless ``error`` names another."""
        try:
            return parse_integer(token, low, high, what)
        except DataTypeError as exc:
            code = GatewayError.SYNTAX_ERROR
            if error is not None and _integer_or_none(token) is not None:
                code = error
            raise self.fail(str(exc), code) from None

    def node_id(self, what: str = "node-ID", *, unconfigured: bool = False) -> int:
        """A node-ID argument: 1..127 (or 255 where LSS allows it); others are error 107."""
        token = self.word(what)
        value = self.convert(token, what, 0, _U32, GatewayError.UNSUPPORTED_NODE)
        if 1 <= value <= MAX_NODE_ID or (unconfigured and value == LSS_UNCONFIGURED):
            return value
        raise self.fail(f"{what} {value} is not a node-ID", GatewayError.UNSUPPORTED_NODE)

    def rest(self, what: str) -> str:
        """The raw text of all remaining tokens, spaces inside quotes kept."""
        if self.position == len(self.tokens):
            raise self.fail(f"{what} missing")
        text = self.text[self.tokens[self.position].start : self.tokens[-1].end]
        self.position = len(self.tokens)
        return text

    def done(self) -> None:
        if self.position != len(self.tokens):
            raise self.fail(f"unexpected {self.tokens[self.position].text!r}")

    def dtype(self, token: str) -> DataType:
        try:
            return DataType.from_mnemonic(token)
        except DataTypeError as exc:
            raise self.fail(str(exc)) from None

    def node_level(self, *, all_nodes: bool = False) -> dict[str, int | None]:
        """``[[net] node]``: one number is the node, two are net and node."""
        net: int | None = None
        node: int | None = None
        if len(self.numbers) == 2:
            net = self._net(self.numbers[0])
        if self.numbers:
            node = self.numbers[-1]
            if node > MAX_NODE_ID or (node == 0 and not all_nodes):
                raise self.fail(f"node {node} is not addressable", GatewayError.UNSUPPORTED_NODE)
        return {"net": net, "node": node}

    def network_level(self) -> int | None:
        """``[net]``: a single number before a network-level command is the network (Lely)."""
        if len(self.numbers) == 2:
            raise self.fail("a node-ID before a network-level command")
        return self._net(self.numbers[0]) if self.numbers else None

    def global_level(self) -> None:
        if self.numbers:
            raise self.fail("a network or node-ID before a gateway command")

    def _net(self, net: int) -> int:
        if not 1 <= net <= _U16:
            raise self.fail(f"network {net} does not exist", GatewayError.UNSUPPORTED_NET)
        return net


def _integer_or_none(token: str) -> int | None:
    """The integer ``token`` spells in C syntax, whatever its size, or None."""
    try:
        return parse_integer(token, -(1 << 400), 1 << 400)
    except DataTypeError:
        return None


def parse_request(line: str, dialect: Dialect = Dialect.CANOPENNODE) -> Request | None:
    """The typed request of one line, or None for an empty or comment-only line.

    Raises ParseError only: 101 for a malformed line, 100 for an unknown command, 106/107
    for a network or node that cannot exist. ``dialect`` matters only for VISIBLE_STRING
    values (C escapes and unquoted multi-word strings are Lely's).
    """
    stripped = line.strip()
    if not stripped or stripped.startswith("#"):
        return None
    match = _SEQUENCE.match(stripped)
    if match is None:
        raise ParseError(GatewayError.SYNTAX_ERROR, None, "a request starts with [<sequence>]")
    try:
        sequence = parse_integer(match.group(1), 0, _U32, "sequence")
    except DataTypeError as exc:
        raise ParseError(GatewayError.SYNTAX_ERROR, None, str(exc)) from None
    text = stripped[match.end() :]
    tokens = _tokenize(text, dialect, sequence)
    numbers: list[int] = []
    while tokens and tokens[0].text[0].isdigit():
        if len(numbers) == 2:
            raise ParseError(GatewayError.SYNTAX_ERROR, sequence, "more than net and node")
        try:
            numbers.append(parse_integer(tokens.pop(0).text, 0, _U32, "net or node"))
        except DataTypeError as exc:
            raise ParseError(GatewayError.SYNTAX_ERROR, sequence, str(exc)) from None
    if not tokens:
        raise ParseError(GatewayError.SYNTAX_ERROR, sequence, "command missing")
    command = tokens[0].text.lower()
    handler = _COMMANDS.get(command)
    if handler is None:
        raise ParseError(
            GatewayError.REQUEST_NOT_SUPPORTED, sequence, f"unknown command {tokens[0].text!r}"
        )
    return handler(_Context(sequence, numbers, tokens[1:], text, dialect))


def _tokenize(text: str, dialect: Dialect, sequence: int) -> list[_Token]:
    """Split at white space; a ``"`` opens a string that runs to its closing quote (``""``
    inside, and in Lely's dialect a backslash escape, do not close it); ``#`` outside a
    string starts a comment, as in both gateways."""
    tokens: list[_Token] = []
    position = 0
    while position < len(text):
        character = text[position]
        if character.isspace():
            position += 1
            continue
        if character == "#":
            break
        start = position
        if character == '"':
            end = _string_end(text, position + 1, dialect)
            if end is None:
                raise ParseError(GatewayError.SYNTAX_ERROR, sequence, "unterminated string")
            position = end
            if position < len(text) and not text[position].isspace():
                raise ParseError(GatewayError.SYNTAX_ERROR, sequence, "text after a string")
        else:
            while position < len(text) and not text[position].isspace() and text[position] != "#":
                position += 1
        tokens.append(_Token(text[start:position], start, position))
    return tokens


def _string_end(text: str, position: int, dialect: Dialect) -> int | None:
    """Index just past the quote closing a string that starts before ``position``."""
    while position < len(text):
        character = text[position]
        if character == '"':
            if text[position + 1 : position + 2] != '"':
                return position + 1
            position += 2
        elif character == "\\" and dialect is Dialect.LELY:
            position += 2
        else:
            position += 1
    return None


_Handler = Callable[[_Context], Request]


def _sdo_or_pdo_read(ctx: _Context) -> Request:
    if ctx.remaining() and ctx.tokens[ctx.position].text.lower() in ("p", "pdo"):
        ctx.position += 1
        net = ctx.network_level()
        number = ctx.integer("PDO number", 1, MAX_PDO_NUMBER)
        ctx.done()
        return ReadPdo(sequence=ctx.sequence, net=net, number=number)
    address = ctx.node_level()
    index = ctx.integer("index", 0, _U16)
    subindex = ctx.integer("subindex", 0, 0xFF)
    token = ctx.optional()
    dtype = None if token is None else ctx.dtype(token)
    ctx.done()
    return SdoUpload(sequence=ctx.sequence, **address, index=index, subindex=subindex, dtype=dtype)


def _sdo_or_pdo_write(ctx: _Context) -> Request:
    if ctx.remaining() and ctx.tokens[ctx.position].text.lower() in ("p", "pdo"):
        ctx.position += 1
        net = ctx.network_level()
        number = ctx.integer("PDO number", 1, MAX_PDO_NUMBER)
        count = ctx.integer("number of values", 0, MAX_PDO_OBJECTS)
        values = tuple(ctx.integer("PDO value", -(1 << 63), (1 << 64) - 1) for _ in range(count))
        ctx.done()
        return WritePdo(sequence=ctx.sequence, net=net, number=number, values=values)
    address = ctx.node_level()
    index = ctx.integer("index", 0, _U16)
    subindex = ctx.integer("subindex", 0, 0xFF)
    dtype = ctx.dtype(ctx.word("data type"))
    try:
        data = parse_value(dtype, ctx.rest("value"), ctx.dialect)
    except DataTypeError as exc:
        raise ctx.fail(str(exc)) from None
    return SdoDownload(
        sequence=ctx.sequence, **address, index=index, subindex=subindex, dtype=dtype, data=data
    )


def _nmt(request: type[NodeRequest]) -> _Handler:
    def handler(ctx: _Context) -> Request:
        address = ctx.node_level(all_nodes=True)
        ctx.done()
        return request(sequence=ctx.sequence, **address)

    return handler


def _reset(ctx: _Context) -> Request:
    what = ctx.word("'node' or 'comm[unication]'").lower()
    requests: dict[str, type[NodeRequest]] = {
        "node": ResetNode,
        "comm": ResetCommunication,
        "communication": ResetCommunication,
    }
    if what not in requests:
        raise ctx.fail(f"reset {what!r}", GatewayError.REQUEST_NOT_SUPPORTED)
    return _nmt(requests[what])(ctx)


def _enable(ctx: _Context) -> Request:
    what = ctx.word("'guarding' or 'heartbeat'").lower()
    if what == "guarding":
        address = ctx.node_level()
        guard_time = ctx.integer("guard time", 0, _U16)
        factor = ctx.integer("life time factor", 0, 0xFF)
        ctx.done()
        return EnableGuarding(
            sequence=ctx.sequence, **address, guard_time=guard_time, lifetime_factor=factor
        )
    if what == "heartbeat":
        address = ctx.node_level()
        consumer_time = ctx.integer("heartbeat consumer time", 0, _U16)
        ctx.done()
        return EnableHeartbeat(sequence=ctx.sequence, **address, consumer_time=consumer_time)
    raise ctx.fail(f"enable {what!r}", GatewayError.REQUEST_NOT_SUPPORTED)


def _disable(ctx: _Context) -> Request:
    what = ctx.word("'guarding' or 'heartbeat'").lower()
    requests: dict[str, type[NodeRequest]] = {
        "guarding": DisableGuarding,
        "heartbeat": DisableHeartbeat,
    }
    if what not in requests:
        raise ctx.fail(f"disable {what!r}", GatewayError.REQUEST_NOT_SUPPORTED)
    address = ctx.node_level()
    ctx.done()
    return requests[what](sequence=ctx.sequence, **address)


def _set(ctx: _Context) -> Request:
    what = ctx.word("what to set").lower()
    handler = _SET_COMMANDS.get(what)
    if handler is None:
        raise ctx.fail(f"set {what!r}", GatewayError.REQUEST_NOT_SUPPORTED)
    return handler(ctx)


def _set_network(ctx: _Context) -> Request:
    ctx.global_level()
    network = ctx.integer("network", 1, _U16, GatewayError.UNSUPPORTED_NET)
    ctx.done()
    return SetDefaultNetwork(sequence=ctx.sequence, network=network)


def _set_node(ctx: _Context) -> Request:
    net = ctx.network_level()
    node_id = ctx.node_id()
    ctx.done()
    return SetDefaultNode(sequence=ctx.sequence, net=net, node_id=node_id)


def _set_sdo_timeout(ctx: _Context) -> Request:
    net = ctx.network_level()
    timeout = ctx.integer("SDO time-out", 1, _U32)
    ctx.done()
    return SetSdoTimeout(sequence=ctx.sequence, net=net, timeout_ms=timeout)


def _set_sdo_block(ctx: _Context) -> Request:
    net = ctx.network_level()
    enabled = ctx.integer("0 or 1", 0, 1)
    ctx.done()
    return SetSdoBlock(sequence=ctx.sequence, net=net, enabled=bool(enabled))


def _set_command_timeout(ctx: _Context) -> Request:
    ctx.global_level()
    timeout = ctx.integer("command time-out", 0, _U32)
    ctx.done()
    return SetCommandTimeout(sequence=ctx.sequence, timeout_ms=timeout)


def _set_command_size(ctx: _Context) -> Request:
    ctx.global_level()
    size = ctx.integer("command size", 1, _U32)
    ctx.done()
    return SetCommandSize(sequence=ctx.sequence, size=size)


def _set_heartbeat(ctx: _Context) -> Request:
    net = ctx.network_level()
    producer_time = ctx.integer("heartbeat producer time", 0, _U16)
    ctx.done()
    return SetHeartbeatProducer(sequence=ctx.sequence, net=net, producer_time=producer_time)


def _set_id(ctx: _Context) -> Request:
    net = ctx.network_level()
    node_id = ctx.node_id(unconfigured=True)
    ctx.done()
    return SetNodeId(sequence=ctx.sequence, net=net, node_id=node_id)


def _transmission(ctx: _Context, extended: bool) -> tuple[int, dict[str, int]]:
    """Lely's tx-type: ``event``, ``rtr`` or ``sync<n>``, glued numbers as Lely lexes them."""
    token = ctx.word("transmission type")
    lowered = token.lower()
    extra: dict[str, int] = {}
    if lowered.startswith("event") and (extended or lowered == "event"):
        if extended:
            extra["inhibit_time"] = ctx.convert(token[5:], "inhibit time", 0, _U16)
            extra["event_timer"] = ctx.integer("event timer", 0, _U16)
        return TRANSMISSION_EVENT, extra
    if lowered == "rtr":
        if extended:
            extra["event_timer"] = ctx.integer("event timer", 0, _U16)
        return TRANSMISSION_RTR, extra
    if lowered.startswith("sync"):
        period = ctx.convert(token[4:], "SYNC period", 0, 240)
        if extended:
            extra["sync_start"] = ctx.integer("SYNC start value", 0, 0xFF)
        return period, extra
    raise ctx.fail(f"transmission type {token!r} is not event, rtr or sync<0..240>")


def _mappings(ctx: _Context) -> tuple[PdoMapping, ...]:
    count = ctx.integer("number of mapped objects", 0, MAX_PDO_OBJECTS)
    mappings = []
    for _ in range(count):
        index = subindex = None
        dtype = None
        if ctx.remaining() and ctx.tokens[ctx.position].text[0].isdigit():
            index = ctx.integer("index", 0, _U16)
            subindex = ctx.integer("subindex", 0, 0xFF)
        if ctx.remaining() and not ctx.tokens[ctx.position].text[0].isdigit():
            dtype = ctx.dtype(ctx.word("data type"))
            if not dtype.pdo_mappable:
                raise ctx.fail(f"a {dtype.value} cannot be mapped to a PDO")
        if index is None and dtype is None:
            raise ctx.fail("mapped object missing")
        mappings.append(PdoMapping(index, subindex, dtype))
    return tuple(mappings)


def _set_pdo(kind: str) -> _Handler:
    def handler(ctx: _Context) -> Request:
        net = ctx.network_level()
        number = ctx.integer("PDO number", 1, MAX_PDO_NUMBER)
        cob_id = ctx.integer("COB-ID", 0, _U32)
        transmission, extra = _transmission(ctx, kind == "tpdox")
        mappings = _mappings(ctx)
        ctx.done()
        if kind == "rpdo":
            return ConfigureRpdo(
                sequence=ctx.sequence,
                net=net,
                number=number,
                cob_id=cob_id,
                transmission_type=transmission,
                mappings=mappings,
            )
        return ConfigureTpdo(
            sequence=ctx.sequence,
            net=net,
            number=number,
            cob_id=cob_id,
            transmission_type=transmission,
            mappings=mappings,
            **extra,
        )

    return handler


def _init(ctx: _Context) -> Request:
    net = ctx.network_level()
    index = ctx.integer("bit rate index", 0, 9)
    ctx.done()
    return InitGateway(sequence=ctx.sequence, net=net, bit_rate_index=index)


def _storage(request: type[StoreConfiguration | RestoreConfiguration]) -> _Handler:
    def handler(ctx: _Context) -> Request:
        net = ctx.network_level()
        token = ctx.optional()
        specifier = None if token is None else ctx.convert(token, "specifier", 0, 0xFF)
        ctx.done()
        return request(sequence=ctx.sequence, net=net, specifier=specifier)

    return handler


def _boot_up_indication(ctx: _Context) -> Request:
    net = ctx.network_level()
    what = ctx.word("Enable or Disable").lower()
    if what not in ("enable", "disable"):
        raise ctx.fail(f"boot_up_indication {what!r}")
    ctx.done()
    return SetBootUpForwarding(sequence=ctx.sequence, net=net, enabled=what == "enable")


def _info(ctx: _Context) -> Request:
    what = ctx.word("'version'").lower()
    if what != "version":
        raise ctx.fail(f"info {what!r}", GatewayError.REQUEST_NOT_SUPPORTED)
    net = ctx.network_level()
    ctx.done()
    return GetVersion(sequence=ctx.sequence, net=net)


def _help(ctx: _Context) -> Request:
    ctx.global_level()
    topic = ctx.optional()
    if topic is not None and topic.lower() not in ("datatype", "lss"):
        raise ctx.fail(f"no help on {topic!r}")
    ctx.done()
    return Help(sequence=ctx.sequence, topic=None if topic is None else topic.lower())


def _log(ctx: _Context) -> Request:
    ctx.global_level()
    ctx.done()
    return Log(sequence=ctx.sequence)


def _u32(ctx: _Context, what: str) -> int:
    return ctx.integer(what, 0, _U32)


def _lss_address(ctx: _Context) -> LssAddress:
    return LssAddress(
        _u32(ctx, "vendor-ID"),
        _u32(ctx, "product code"),
        _u32(ctx, "revision number"),
        _u32(ctx, "serial number"),
    )


def _lss_range(ctx: _Context) -> LssAddressRange:
    return LssAddressRange(
        _u32(ctx, "vendor-ID"),
        _u32(ctx, "product code"),
        _u32(ctx, "lowest revision number"),
        _u32(ctx, "highest revision number"),
        _u32(ctx, "lowest serial number"),
        _u32(ctx, "highest serial number"),
    )


def _lss_plain(request: type[NetworkRequest]) -> _Handler:
    def handler(ctx: _Context) -> Request:
        net = ctx.network_level()
        ctx.done()
        return request(sequence=ctx.sequence, net=net)

    return handler


def _lss_switch_glob(ctx: _Context) -> Request:
    net = ctx.network_level()
    mode = ctx.integer("0 or 1", 0, 1)
    ctx.done()
    return LssSwitchGlobal(sequence=ctx.sequence, net=net, configuration=bool(mode))


def _lss_switch_sel(ctx: _Context) -> Request:
    net = ctx.network_level()
    address = _lss_address(ctx)
    ctx.done()
    return LssSwitchSelective(sequence=ctx.sequence, net=net, address=address)


def _lss_set_node(ctx: _Context) -> Request:
    net = ctx.network_level()
    node_id = ctx.node_id(unconfigured=True)
    ctx.done()
    return LssConfigureNodeId(sequence=ctx.sequence, net=net, node_id=node_id)


def _lss_conf_bitrate(ctx: _Context) -> Request:
    net = ctx.network_level()
    selector = ctx.integer("table selector", 0, 0xFF)
    index = ctx.integer("table index", 0, 0xFF)
    ctx.done()
    return LssConfigureBitRate(
        sequence=ctx.sequence, net=net, table_selector=selector, table_index=index
    )


def _lss_activate_bitrate(ctx: _Context) -> Request:
    net = ctx.network_level()
    delay = ctx.integer("switch delay", 0, _U16)
    ctx.done()
    return LssActivateBitRate(sequence=ctx.sequence, net=net, switch_delay_ms=delay)


def _lss_inquire_addr(ctx: _Context) -> Request:
    net = ctx.network_level()
    token = ctx.optional()
    lss_sub = None
    if token is not None:
        value = ctx.convert(token, "LSS number", 0, 0xFF)
        if 0 <= value - _LSS_INQUIRE_FIRST_CS <= 3:
            value -= _LSS_INQUIRE_FIRST_CS
        if value > 3:
            raise ctx.fail(f"LSS number {token} is not 0..3 or 0x5A..0x5D")
        lss_sub = value
    ctx.done()
    return LssInquireAddress(sequence=ctx.sequence, net=net, lss_sub=lss_sub)


def _lss_identity(ctx: _Context) -> Request:
    net = ctx.network_level()
    selection = _lss_range(ctx)
    ctx.done()
    return LssIdentifyRemoteSlave(sequence=ctx.sequence, net=net, selection=selection)


def _lss_slowscan(ctx: _Context) -> Request:
    net = ctx.network_level()
    selection = _lss_range(ctx)
    ctx.done()
    return LssSlowscan(sequence=ctx.sequence, net=net, selection=selection)


def _lss_fastscan_step(ctx: _Context) -> Request:
    net = ctx.network_level()
    id_number = _u32(ctx, "IDNumber")
    bit_checked = ctx.integer("BitChecked", 0, 0x80)
    if 31 < bit_checked < 0x80:
        raise ctx.fail(f"BitChecked {bit_checked} is not 0..31 or 128")
    lss_sub = ctx.integer("LSSSub", 0, 3)
    lss_next = ctx.integer("LSSNext", 0, 3)
    ctx.done()
    return LssFastscan(
        sequence=ctx.sequence,
        net=net,
        id_number=id_number,
        bit_checked=bit_checked,
        lss_sub=lss_sub,
        lss_next=lss_next,
    )


def _lss_identify_fastscan(ctx: _Context) -> Request:
    net = ctx.network_level()
    if ctx.remaining() == 8:
        pairs = [(_u32(ctx, "LSS number"), _u32(ctx, "mask")) for _ in range(4)]
        ctx.done()
        return LssIdentifyFastscan(
            sequence=ctx.sequence,
            net=net,
            known=LssAddress(*(value for value, _ in pairs)),
            mask=LssAddress(*(mask for _, mask in pairs)),
        )
    token = ctx.optional()
    timeout = None if token is None else ctx.convert(token, "time-out", 0, _U16)
    ctx.done()
    return LssIdentifyFastscan(sequence=ctx.sequence, net=net, timeout_ms=timeout)


def _lss_assign(ctx: _Context) -> Request:
    net = ctx.network_level()
    address = _lss_address(ctx)
    node_id = ctx.node_id()
    ctx.done()
    return LssAssignNodeId(sequence=ctx.sequence, net=net, address=address, node_id=node_id)


def _lss_allnodes(ctx: _Context) -> Request:
    net = ctx.network_level()
    if ctx.remaining() not in (0, 1, 3, 11):
        raise ctx.fail("lss_allnodes takes 0, 1, 3 or 11 arguments")
    timeout = first = store = None
    criteria: list[LssScanCriterion] = []
    if ctx.remaining():
        timeout = ctx.integer("time-out", 0, _U16)
    if ctx.remaining():
        first = ctx.node_id("first node-ID")
        store = bool(ctx.integer("store 0 or 1", 0, 1))
    while ctx.remaining():
        scan = ctx.integer("scan type", 0, 2)
        criteria.append(LssScanCriterion(scan, _u32(ctx, "LSS number")))
    return LssCompleteConfiguration(
        sequence=ctx.sequence,
        net=net,
        timeout_ms=timeout,
        first_node_id=first,
        store=store,
        criteria=tuple(criteria),
    )


_SET_COMMANDS: dict[str, _Handler] = {
    "network": _set_network,
    "node": _set_node,
    "sdo_timeout": _set_sdo_timeout,
    "sdo_block": _set_sdo_block,
    "command_timeout": _set_command_timeout,
    "command_size": _set_command_size,
    "heartbeat": _set_heartbeat,
    "id": _set_id,
    "rpdo": _set_pdo("rpdo"),
    "tpdo": _set_pdo("tpdo"),
    "tpdox": _set_pdo("tpdox"),
}

_COMMANDS: dict[str, _Handler] = {
    "r": _sdo_or_pdo_read,
    "read": _sdo_or_pdo_read,
    "w": _sdo_or_pdo_write,
    "write": _sdo_or_pdo_write,
    "start": _nmt(StartNode),
    "stop": _nmt(StopNode),
    "preop": _nmt(EnterPreoperational),
    "preoperational": _nmt(EnterPreoperational),
    "reset": _reset,
    "enable": _enable,
    "disable": _disable,
    "set": _set,
    "init": _init,
    "store": _storage(StoreConfiguration),
    "restore": _storage(RestoreConfiguration),
    "boot_up_indication": _boot_up_indication,
    "info": _info,
    "help": _help,
    "log": _log,
    "lss_switch_glob": _lss_switch_glob,
    "lss_switch_sel": _lss_switch_sel,
    "lss_set_node": _lss_set_node,
    "lss_conf_bitrate": _lss_conf_bitrate,
    "lss_activate_bitrate": _lss_activate_bitrate,
    "lss_store": _lss_plain(LssStore),
    "lss_inquire_addr": _lss_inquire_addr,
    "lss_get_node": _lss_plain(LssInquireNodeId),
    "lss_identity": _lss_identity,
    "lss_ident_nonconf": _lss_plain(LssIdentifyNonConfigured),
    "lss_fastscan": _lss_fastscan_step,
    "_lss_fastscan": _lss_identify_fastscan,
    "_lss_slowscan": _lss_slowscan,
    "lss_assign": _lss_assign,
    "lss_allnodes": _lss_allnodes,
}


# --------------------------------------------------------------------------- answers


def _answer(sequence: int, body: str, dialect: Dialect) -> str:
    return f"[{sequence}] {body}{dialect.line_end}"


def format_ok(sequence: int, dialect: Dialect = Dialect.CANOPENNODE) -> str:
    """``[seq] OK``: the service succeeded and has no data."""
    return _answer(sequence, "OK", dialect)


def format_value_response(sequence: int, text: str, dialect: Dialect = Dialect.CANOPENNODE) -> str:
    """``[seq] <text>``: a success with data already in text."""
    return _answer(sequence, text, dialect)


def format_error(
    sequence: int, error: int, dialect: Dialect = Dialect.CANOPENNODE, *, describe: bool = True
) -> str:
    """A 309-3 error number: CANopenNode ``ERROR:101 #Syntax error.`` (the description is
    its default ``CO_CONFIG_GTW_ASCII_ERROR_DESC``), Lely ``ERROR: 101 (Syntax error)``."""
    text = error_text(error, dialect)
    if dialect is Dialect.LELY:
        body = f"ERROR: {error}" + (f" ({text})" if describe else "")
    else:
        body = f"ERROR:{error}" + (f" #{text}." if describe else "")
    return _answer(sequence, body, dialect)


def format_abort(
    sequence: int, abort_code: int, dialect: Dialect = Dialect.CANOPENNODE, *, describe: bool = True
) -> str:
    """An SDO abort: CANopenNode ``ERROR:0x06020000 #...``, Lely ``ERROR: 06020000 (...)``."""
    text = abort_text(abort_code)
    if dialect is Dialect.LELY:
        body = f"ERROR: {abort_code:08X}" + (f" ({text})" if describe else "")
    else:
        body = f"ERROR:0x{abort_code:08X}" + (f" #{text}." if describe else "")
    return _answer(sequence, body, dialect)


def format_empty(dialect: Dialect = Dialect.CANOPENNODE) -> str | None:
    """The answer to an empty or comment-only line: CANopenNode sends an empty line (and
    ``cocomm -f`` waits for it), Lely nothing."""
    return "\r\n" if dialect is Dialect.CANOPENNODE else None


def format_upload(
    sequence: int, dtype: DataType | None, data: bytes, dialect: Dialect = Dialect.CANOPENNODE
) -> str:
    """The answer to an SDO upload.

    Without a type, or when the bytes do not fit the type, CANopenNode shows ``hex``; Lely
    answers the length mismatch with its SDO abort code.
    """
    if dtype is None:
        return _answer(sequence, format_value(DataType.HEX, data, dialect), dialect)
    try:
        return _answer(sequence, format_value(dtype, data, dialect), dialect)
    except DataTypeError as exc:
        if dialect is Dialect.LELY and exc.abort_code is not None:
            return format_abort(sequence, exc.abort_code, dialect)
        return _answer(sequence, format_value(DataType.HEX, data, dialect), dialect)


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


def format_version(
    sequence: int, info: VersionInfo, dialect: Dialect = Dialect.CANOPENNODE
) -> str:
    """Lely's layout (CANopenNode has no ``info version``): vendor, product, revision as
    major.minor, serial, gateway class, protocol version, implementation class version."""
    body = (
        f"{info.vendor_id} {info.product_code} {info.revision >> 16}.{info.revision & 0xFFFF} "
        f"{info.serial} {info.gateway_class} "
        f"{info.protocol_version[0]}.{info.protocol_version[1]} "
        f"{info.implementation_version[0]}.{info.implementation_version[1]}"
    )
    return _answer(sequence, body, dialect)


def _lss_hex(value: int, dialect: Dialect) -> str:
    return f"0x{value:08x}" if dialect is Dialect.LELY else f"0x{value:08X}"


def format_lss_number(sequence: int, value: int, dialect: Dialect = Dialect.CANOPENNODE) -> str:
    """One LSS number (``lss_inquire_addr <n>``): ``0x%08X`` (CANopenNode), ``0x%08x`` (Lely)."""
    return _answer(sequence, _lss_hex(value, dialect), dialect)


def format_lss_address(
    sequence: int, address: LssAddress, dialect: Dialect = Dialect.CANOPENNODE
) -> str:
    """A whole LSS address (``lss_inquire_addr`` without argument, ``_lss_fastscan``)."""
    numbers = (address.vendor_id, address.product_code, address.revision, address.serial)
    return _answer(sequence, " ".join(_lss_hex(number, dialect) for number in numbers), dialect)


def format_lss_node_id(sequence: int, node_id: int, dialect: Dialect = Dialect.CANOPENNODE) -> str:
    """``lss_get_node``: CANopenNode ``0x%02X``, Lely decimal."""
    body = str(node_id) if dialect is Dialect.LELY else f"0x{node_id:02X}"
    return _answer(sequence, body, dialect)


def format_pdo_read(
    sequence: int,
    net: int,
    number: int,
    values: tuple[int, ...],
    dialect: Dialect = Dialect.CANOPENNODE,
) -> str:
    """``r p`` answer: ``<net> pdo <nr> <n> 0x<value>...``, the layout of Lely's RPDO event
    with the PDO number 309-1 Table 7 requires (Lely's own answer leaves it out)."""
    return _answer(sequence, _pdo_text(net, number, values), dialect)


def _pdo_text(net: int, number: int, values: tuple[int, ...]) -> str:
    return " ".join([f"{net} pdo {number} {len(values)}", *(f"0x{value:x}" for value in values)])


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
    error: GatewayError | None = None


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

_LELY_STATES = {
    NmtState.STOPPED: "ERRORx STOP",
    NmtState.OPERATIONAL: "ERRORx OPER",
    NmtState.PRE_OPERATIONAL: "ERRORx PREO",
}
"""Lely's ``co_gw_txt_recv_ec`` spelling, ``ERRORx`` included; other states print ``ERROR``."""

_CANOPENNODE_STATES = {
    NmtState.INITIALIZING: "initializing",
    NmtState.STOPPED: "stopped",
    NmtState.OPERATIONAL: "operational",
    NmtState.PRE_OPERATIONAL: "pre-operational",
}


def format_event(
    event: Event, dialect: Dialect = Dialect.CANOPENNODE, *, stamp: datetime | None = None
) -> str | None:
    """The unsolicited line of an event, or None where the dialect has none.

    Lely writes 309-3 event lines without a sequence number (``1 5 BOOT_UP``,
    ``1 5 EMCY 8130 11 0 0 0 0 0``, ``1 pdo 1 2 0x1 0x2``). CANopenNode never sends
    unsolicited lines (``cocomm`` would take them for the answer); it writes EMCY and
    heartbeat state changes to the log that ``log`` prints, as ``CO_main_basic.c`` words
    them, after a ``%Y-%m-%d %H:%M:%S: `` time ``stamp``. RPDO and progress events are not
    logged there.
    """
    if dialect is Dialect.LELY:
        return _lely_event(event) + dialect.line_end
    message = _canopennode_event(event)
    if message is None:
        return None
    prefix = "" if stamp is None else stamp.strftime("%Y-%m-%d %H:%M:%S: ")
    return prefix + message + dialect.line_end


def _lely_event(event: Event) -> str:
    if isinstance(event, BootUpEvent):
        return f"{event.net} {event.node} BOOT_UP"
    if isinstance(event, ErrorControlEvent):
        state = "ERROR" if event.state is None else _LELY_STATES.get(event.state, "ERROR")
        text = f"{event.net} {event.node} {state}"
        if event.error is not None:
            text += f" {int(event.error)} ({error_text(event.error, Dialect.LELY)})"
        return text
    if isinstance(event, EmergencyEvent):
        manufacturer = " ".join(str(byte) for byte in event.manufacturer.ljust(5, b"\0")[:5])
        return f"{event.net} {event.node} EMCY {event.code:04X} {event.register:02X} {manufacturer}"
    if isinstance(event, RpdoEvent):
        return _pdo_text(event.net, event.number, event.values)
    direction = "r" if event.upload else "w"
    return f"{event.net} {event.node} SDO{direction} {event.transferred}"


def _canopennode_event(event: Event) -> str | None:
    if isinstance(event, EmergencyEvent):
        manufacturer = event.manufacturer.ljust(5, b"\0")
        info_code = int.from_bytes(manufacturer[1:5], "little")
        return (
            f"CANopen Emergency message from node 0x{event.node:02X}: "
            f"errorCode=0x{event.code:04X}, errorRegister=0x{event.register:02X}, "
            f"errorBit=0x{manufacturer[0]:02X}, infoCode=0x{info_code:08X}"
        )
    if isinstance(event, BootUpEvent | ErrorControlEvent):
        state = NmtState.INITIALIZING if isinstance(event, BootUpEvent) else event.state
        name, number = ("unknown", -1) if state is None else (_CANOPENNODE_STATES[state], state)
        return (
            f"CANopen Remote node ID = 0x{event.node:02X}: "
            f'NMT state changed to: "{name}" ({int(number)})'
        )
    return None


_HELP = {
    None: [
        "Command strings start with '[<sequence>]' followed by:",
        "[[<net>] <node>] r[ead] <index> <subindex> [<datatype>]   # SDO upload",
        "[[<net>] <node>] w[rite] <index> <subindex> <datatype> <value>   # SDO download",
        "[[<net>] <node>] start | stop | preop[erational]   # NMT (node 0: all nodes)",
        "[[<net>] <node>] reset node | reset comm[unication]",
        "[[<net>] <node>] enable guarding <guard time> <life time factor> | disable guarding",
        "[[<net>] <node>] enable heartbeat <consumer time> | disable heartbeat",
        "[<net>] set sdo_timeout <ms> | set sdo_block <0|1> | set node <node>",
        "[<net>] set rpdo|tpdo <nr> <COB-ID> event|rtr|sync<n> <n> [<index> <sub>] [<type>]..",
        "[<net>] set tpdox <nr> <COB-ID> event<inhibit> <event timer>|rtr <event timer>|"
        "sync<n> <start> <n> ...",
        "[<net>] r[ead] p[do] <nr> | w[rite] p[do] <nr> <n> <value>...",
        "[<net>] init <bit rate index> | store [<specifier>] | restore [<specifier>]",
        "[<net>] set heartbeat <ms> | set id <node> | boot_up_indication Enable|Disable",
        "[<net>] info version",
        "set network <net> | set command_timeout <ms> | set command_size <bytes>",
        "help [datatype|lss] | log",
        "Response: [<sequence>] OK | <value> | ERROR:<error> | ERROR:0x<SDO abort code>",
    ],
    "datatype": [
        "b  i8 i16 i24 i32 i40 i48 i56 i64  u8 u16 u24 u32 u40 u48 u56 u64",
        "x8 x16 x32 x64 (unsigned, shown in hex)  r32 r64  t td (<days> <ms>)",
        'vs (visible string, "quoted" if several words, "" for a quote)',
        "os us d (base64)  hex (hex bytes, optionally space separated)",
    ],
    "lss": [
        "[<net>] lss_switch_glob <0|1> | lss_switch_sel <vendor> <product> <rev> <serial>",
        "[<net>] lss_set_node <node> | lss_conf_bitrate <table selector> <table index>",
        "[<net>] lss_activate_bitrate <switch delay ms> | lss_store | lss_get_node",
        "[<net>] lss_inquire_addr [<0..3 or 0x5A..0x5D>]",
        "[<net>] lss_identity <vendor> <product> <rev low> <rev high> <serial low> <serial high>",
        "[<net>] lss_ident_nonconf | lss_fastscan <IDNumber> <BitChecked> <LSSSub> <LSSNext>",
        "[<net>] _lss_fastscan [<timeout ms> | <vendor> <mask> <product> <mask> <rev> <mask> "
        "<serial> <mask>]",
        "[<net>] _lss_slowscan <vendor> <product> <rev low> <rev high> <serial low> <serial high>",
        "[<net>] lss_assign <vendor> <product> <rev> <serial> <node>",
        "[<net>] lss_allnodes [<timeout ms> [<first node> <store> [<scan> <value>]x4]]",
    ],
}


def format_help(topic: str | None = None, dialect: Dialect = Dialect.CANOPENNODE) -> str:
    """The ``help`` text: lines joined by LF and closed by the dialect's line end, as
    CANopenNode does so that ``cocomm`` reads it as one answer."""
    return "\n".join(_HELP[topic]) + dialect.line_end
