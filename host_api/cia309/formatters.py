"""The 309-3 answers and event lines, spelled per dialect.

* success: ``[1] OK`` in both;
* 309-3 error: CANopenNode ``[1] ERROR:101 #Syntax error.``, Lely ``[1] ERROR: 101 (Syntax
  error)``;
* SDO abort: CANopenNode ``[1] ERROR:0x06020000 #<text>.``, Lely ``[1] ERROR: 06020000
  (<text>)``;
* line end: CANopenNode CR LF, Lely LF;
* an empty or comment-only request: CANopenNode answers an empty line (``cocomm -f`` waits
  for it), Lely nothing.

``cocomm`` only looks for ``"] ERROR:"``, ``"] OK\\r\\n"`` and the first ``"] "``, so the
text after the code is a comment for people.
"""

from __future__ import annotations

from datetime import datetime

from dpm.cia301 import (
    ABORT_BLOCK_SIZE,
    ABORT_CANNOT_STORE,
    ABORT_CRC,
    ABORT_DEVICE_STATE,
    ABORT_GENERAL,
    ABORT_HARDWARE,
    ABORT_INTERNAL_INCOMPATIBLE,
    ABORT_LOCAL_CONTROL,
    ABORT_MAX_BELOW_MIN,
    ABORT_NO_DATA,
    ABORT_NO_DICTIONARY,
    ABORT_NO_OBJECT,
    ABORT_NO_SDO_CONNECTION,
    ABORT_NO_SUBINDEX,
    ABORT_NOT_MAPPABLE,
    ABORT_OUT_OF_MEMORY,
    ABORT_PARAMETER_INCOMPATIBLE,
    ABORT_PDO_LENGTH,
    ABORT_READ_ONLY,
    ABORT_SEQUENCE_NUMBER,
    ABORT_TIMEOUT,
    ABORT_TOGGLE,
    ABORT_TYPE_LENGTH_HIGH,
    ABORT_TYPE_LENGTH_LOW,
    ABORT_TYPE_LENGTH_MISMATCH,
    ABORT_UNKNOWN_COMMAND,
    ABORT_UNSUPPORTED_ACCESS,
    ABORT_VALUE_HIGH,
    ABORT_VALUE_LOW,
    ABORT_VALUE_RANGE,
    ABORT_WRITE_ONLY,
)
from dpm.cia305 import LssAddress
from host_api.cia309._plainline import format_upload as _format_plain_upload
from host_api.cia309.datatypes import LINE_ENDS, DataTypeError, Dialect, format_value
from host_api.cia309.model import (
    BootUpEvent,
    DataType,
    EmergencyEvent,
    ErrorCode,
    ErrorControlEvent,
    Event,
    NmtState,
    RpdoEvent,
    VersionInfo,
)

_LELY_ERROR_TEXTS = {
    ErrorCode.CAN_ACTIVE: "CAN active",
    ErrorCode.LSS_IMPLEMENTATION_ERROR: "LSS error",
}
"""Lely's ``co_gw_iec2str`` shortens these two."""

SDO_ABORT_TEXTS: dict[int, str] = {
    ABORT_TOGGLE: "Toggle bit not alternated",
    ABORT_TIMEOUT: "SDO protocol timed out",
    ABORT_UNKNOWN_COMMAND: "Client/server command specifier not valid or unknown",
    ABORT_BLOCK_SIZE: "Invalid block size (block mode only)",
    ABORT_SEQUENCE_NUMBER: "Invalid sequence number (block mode only)",
    ABORT_CRC: "CRC error (block mode only)",
    ABORT_OUT_OF_MEMORY: "Out of memory",
    ABORT_UNSUPPORTED_ACCESS: "Unsupported access to an object",
    ABORT_WRITE_ONLY: "Attempt to read a write only object",
    ABORT_READ_ONLY: "Attempt to write a read only object",
    ABORT_NO_OBJECT: "Object does not exist in the object dictionary",
    ABORT_NOT_MAPPABLE: "Object cannot be mapped to the PDO",
    ABORT_PDO_LENGTH: "The number and length of the objects to be mapped would exceed PDO length",
    ABORT_PARAMETER_INCOMPATIBLE: "General parameter incompatibility reason",
    ABORT_INTERNAL_INCOMPATIBLE: "General internal incompatibility in the device",
    ABORT_HARDWARE: "Access failed due to a hardware error",
    ABORT_TYPE_LENGTH_MISMATCH: (
        "Data type does not match, length of service parameter does not match"
    ),
    ABORT_TYPE_LENGTH_HIGH: "Data type does not match, length of service parameter too high",
    ABORT_TYPE_LENGTH_LOW: "Data type does not match, length of service parameter too low",
    ABORT_NO_SUBINDEX: "Sub-index does not exist",
    ABORT_VALUE_RANGE: "Invalid value for parameter (download only)",
    ABORT_VALUE_HIGH: "Value of parameter written too high (download only)",
    ABORT_VALUE_LOW: "Value of parameter written too low (download only)",
    ABORT_MAX_BELOW_MIN: "Maximum value is less than minimum value",
    ABORT_NO_SDO_CONNECTION: "Resource not available: SDO connection",
    ABORT_GENERAL: "General error",
    ABORT_CANNOT_STORE: "Data cannot be transferred or stored to the application",
    ABORT_LOCAL_CONTROL: (
        "Data cannot be transferred or stored to the application because of local control"
    ),
    ABORT_DEVICE_STATE: (
        "Data cannot be transferred or stored to the application because of the present "
        "device state"
    ),
    ABORT_NO_DICTIONARY: (
        "Object dictionary dynamic generation fails or no object dictionary is present"
    ),
    ABORT_NO_DATA: "No data available",
}
"""The SDO abort codes of CiA 301 with the standard's texts; a 309-3 answer to a failed SDO
transfer carries the code instead of a 309-3 error number."""


def error_text(error: int, dialect: Dialect = Dialect.CANOPENNODE) -> str:
    """The description of a 309-3 error number, as the dialect's gateway words it."""
    try:
        code = ErrorCode(error)
    except ValueError:
        return "Unknown error code"
    if dialect is Dialect.LELY:
        return _LELY_ERROR_TEXTS.get(code, code.text)
    return code.text


def abort_text(abort_code: int) -> str:
    """The CiA 301 text of an SDO abort code."""
    return SDO_ABORT_TEXTS.get(abort_code, "Unknown abort code")



def _answer(sequence: int, body: str, dialect: Dialect) -> str:
    return f"[{sequence}] {body}{LINE_ENDS[dialect]}"


def format_ok(sequence: int, dialect: Dialect = Dialect.CANOPENNODE) -> str:
    """``[seq] OK``: the service succeeded and has no data."""
    return _answer(sequence, "OK", dialect)


def format_value_response(sequence: int, text: str, dialect: Dialect = Dialect.CANOPENNODE) -> str:
    """``[seq] <text>``: a success with data already in text."""
    return _answer(sequence, text, dialect)


DETAIL_LENGTH = 120
"""[ours] characters of an explanation after an error's description, at the most."""


def format_error(
    sequence: int, error: int, dialect: Dialect = Dialect.CANOPENNODE, *, describe: bool = True,
    detail: str | None = None,
) -> str:
    """A 309-3 error number: CANopenNode ``ERROR:101 #Syntax error.`` (the description is
    its default ``CO_CONFIG_GTW_ASCII_ERROR_DESC``), Lely ``ERROR: 101 (Syntax error)``.

    [ours] ``detail`` says what was wrong, after the description inside the same comment
    (``#Syntax error: index missing.``): clients read only the number, so the comment is
    free for people. Control characters become ``?`` so the answer stays one line.
    """
    text = error_text(error, dialect)
    if detail:
        clean = "".join(c if c.isprintable() else "?" for c in detail)
        if len(clean) > DETAIL_LENGTH:
            clean = clean[: DETAIL_LENGTH - 3] + "..."
        text = f"{text}: {clean}"
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


format_plain_upload = _format_plain_upload
"""``format_plain_upload(lely, line_end, sequence, dtype, data)``: ``format_upload``'s
answer (``lely``: the dialect is Lely's, ``line_end`` its ``LINE_ENDS``; bind them with
``functools.partial``) when ``dtype`` is
None, HEX or an integer type whose size is ``data``'s, else None (then ``format_upload``).
In C (``_plainline.c``): a 309-3 read's answer without the three Python calls of
``format_upload`` on the server's loop (issue 22); tests/test_cia309_ascii.py checks
it against ``format_upload``."""


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
    numbers = (address.vendor, address.product, address.revision, address.serial)
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
