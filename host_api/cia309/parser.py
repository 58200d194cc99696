"""The 309-3 request parser: one line in, one typed request out (``parse_request``).

The grammar is the union of CANopenNode's gateway (``309/CO_gateway_ascii.c``, ``cocomm``)
and Lely's (``src/co/gw_txt.c``, ``coctl``), so clients of either work unchanged; a line
it cannot accept raises :class:`~host_api.cia309.requests.ParseError` with the 309-3 error
number the answer carries (101 syntax, 100 unknown command, 106/107 for a network or node
out of range). No socket, no clock, no card.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
from typing import NamedTuple

from dpm.cia301 import ASYNC_RTR, EVENT_PROFILE
from dpm.cia305 import UNCONFIGURED, LssAddress
from host_api.cia309._plainline import read_line as _read_plain_line
from host_api.cia309.datatypes import (
    INTEGER_RANGES,
    DataTypeError,
    Dialect,
    parse_data_type,
    parse_integer,
    parse_value,
)
from host_api.cia309.framing import SEQUENCE
from host_api.cia309.model import (
    MAX_NODE_ID,
    MAX_PDO_NUMBER,
    MAX_PDO_OBJECTS,
    SIZES,
    DataType,
    ErrorCode,
    PdoMapping,
)
from host_api.cia309.requests import (
    ConfigureRpdo,
    ConfigureTpdo,
    DisableGuarding,
    DisableHeartbeat,
    EnableGuarding,
    EnableHeartbeat,
    EnterPreoperational,
    GetVersion,
    Help,
    InitGateway,
    Log,
    LssActivateBitRate,
    LssAddressRange,
    LssAssignNodeId,
    LssCompleteConfiguration,
    LssConfigureBitRate,
    LssConfigureNodeId,
    LssFastscan,
    LssIdentifyFastscan,
    LssIdentifyNonConfigured,
    LssIdentifyRemoteSlave,
    LssInquireAddress,
    LssInquireNodeId,
    LssScanCriterion,
    LssSlowscan,
    LssStore,
    LssSwitchGlobal,
    LssSwitchSelective,
    NetworkRequest,
    NodeRequest,
    ParseError,
    ReadPdo,
    Request,
    ResetCommunication,
    ResetNode,
    RestoreConfiguration,
    SdoDownload,
    SdoUpload,
    SetBootUpForwarding,
    SetCommandSize,
    SetCommandTimeout,
    SetDefaultNetwork,
    SetDefaultNode,
    SetHeartbeatProducer,
    SetNodeId,
    SetSdoBlock,
    SetSdoTimeout,
    StartNode,
    StopNode,
    StoreConfiguration,
    WritePdo,
)

_LSS_INQUIRE_FIRST_CS = 0x5A
"""CiA 305 command specifier of 'inquire vendor-ID'; Lely names the LSS number by it."""

_U16 = 0xFFFF
_U32 = 0xFFFF_FFFF
_WORD = re.compile(r"\S+")
_PLAIN_NODE = r"\[(0|[1-9][0-9]{0,8})\] (?:([1-9][0-9]{0,4}) )?([1-9][0-9]{0,2}) "
_PLAIN_OBJECT = r" (0x[0-9A-Fa-f]{1,4}|0|[1-9][0-9]{0,4}) (0x[0-9A-Fa-f]{1,2}|0|[1-9][0-9]{0,2})"
_PLAIN_READ = re.compile(_PLAIN_NODE + "r(?:ead)?" + _PLAIN_OBJECT + "(?: ([0-9a-z]{1,3}))?")
"""``_plain_read``'s lines: the sequence below 10**9, so within 32 bits; net, node, index
and subindex decimal without a leading zero (C reads one as octal) or hex with a lower-case
``0x``; their ranges are checked after."""
_PLAIN_WRITE = re.compile(
    _PLAIN_NODE + "w(?:rite)?" + _PLAIN_OBJECT
    + " ([0-9a-z]{1,3}) (-?(?:0|[1-9][0-9]{0,19})|0[xX][0-9A-Fa-f]{1,16})")
"""``_plain_write``'s lines: ``_PLAIN_READ``'s numbers, a type and one integer value,
decimal (a sign only for minus) or hex, at most 64 bits' digits; its range is checked after."""
_TYPES_BY_NAME = {dtype.value: dtype for dtype in DataType}
_INTEGER_TYPES_BY_NAME = {
    dtype.value: (dtype, low, high) for dtype, (low, high) in INTEGER_RANGES.items()
}
"""``_plain_write``'s types: the integer ones, whose values both dialects read alike."""

plain_read_line: Callable[[bytes, int], SdoUpload | None] = functools.partial(
    _read_plain_line, SdoUpload, _TYPES_BY_NAME, MAX_NODE_ID)
"""``plain_read_line(data, max_line)``: the SDO upload ``data`` makes when it is one whole
line (ended by LF or CR LF, at most ``max_line`` bytes without it) in ``_plain_read``'s
form with no white space around it: the request ``parse_request`` makes of that line. None
otherwise (then frame and parse it as any line). In C (``_plainline.c``), bound here by
``functools.partial``, so a 309-3 read's line costs the server's loop no Python call
(issue 22); tests/test_cia309_ascii.py checks it against ``_plain_read``."""

class _Token(NamedTuple):
    """A word of the request and where it stands in the line (for ``rest``). A named tuple:
    a frozen dataclass cost 1 us per word to build, a third of parsing a read."""

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

    def fail(self, message: str, error: ErrorCode = ErrorCode.SYNTAX_ERROR) -> ParseError:
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

    def integer(self, what: str, low: int, high: int, error: ErrorCode | None = None) -> int:
        return self.convert(self.word(what), what, low, high, error)

    def convert(
        self, token: str, what: str, low: int, high: int, error: ErrorCode | None = None
    ) -> int:
        """A number argument; out of range is a syntax error unless ``error`` names another."""
        try:
            return parse_integer(token, low, high, what)
        except DataTypeError as exc:
            code = ErrorCode.SYNTAX_ERROR
            if error is not None and _integer_or_none(token) is not None:
                code = error
            raise self.fail(str(exc), code) from None

    def node_id(self, what: str = "node-ID", *, unconfigured: bool = False) -> int:
        """A node-ID argument: 1..127 (or 255 where LSS allows it); others are error 107."""
        token = self.word(what)
        value = self.convert(token, what, 0, _U32, ErrorCode.UNSUPPORTED_NODE)
        if 1 <= value <= MAX_NODE_ID or (unconfigured and value == UNCONFIGURED):
            return value
        raise self.fail(f"{what} {value} is not a node-ID", ErrorCode.UNSUPPORTED_NODE)

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
            return parse_data_type(token)
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
                raise self.fail(f"node {node} is not addressable", ErrorCode.UNSUPPORTED_NODE)
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
            raise self.fail(f"network {net} does not exist", ErrorCode.UNSUPPORTED_NET)
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
    plain = _plain_read(stripped) or _plain_write(stripped)
    if plain is not None:
        return plain
    return _parse_stripped(stripped, dialect)


def _plain_read(stripped: str) -> SdoUpload | None:
    """The SDO upload a line in the plain form of a read makes (``[seq] [net] node r[ead]
    index subindex [type]``: single spaces, no leading zeros, a lower-case command and
    type, every number in range), else None: the general parser (``_parse_stripped``)
    then reads it, and gives the same request for every line this one accepts
    (tests/test_cia309_ascii.py checks it).

    Why: it is the line a 309-3 client sends most, and the server parses it on every
    read; one regular expression and four ``int`` calls cost a fifth of the tokens,
    context and ``parse_integer`` calls of the general parser (issue 22)."""
    match = _PLAIN_READ.fullmatch(stripped)
    if match is None:
        return None
    sequence, net, node, index, subindex, type_name = match.groups()
    dtype = None
    if type_name is not None:
        dtype = _TYPES_BY_NAME.get(type_name)
        if dtype is None:
            return None
    node_id = int(node)
    index_value = int(index, 0)
    subindex_value = int(subindex, 0)
    network = None if net is None else int(net)
    if (node_id > MAX_NODE_ID or index_value > _U16 or subindex_value > 0xFF
            or (network is not None and network > _U16)):
        return None
    return SdoUpload(sequence=int(sequence), net=network, node=node_id, index=index_value,
                     subindex=subindex_value, dtype=dtype)


def _plain_write(stripped: str) -> SdoDownload | None:
    """The SDO download a line in the plain form of a write of an integer makes (``[seq]
    [net] node w[rite] index subindex type value``: ``_plain_read``'s form, a lower-case
    integer type, BOOLEAN to HEX64, and a value in its range, decimal or hex), else None:
    the general parser reads it, with the same request for every line this one accepts,
    in either dialect (tests/test_cia309_ascii.py). Strings, reals, times and byte values
    are left to it: their text may span words, take C's several spellings of a float, or
    read differently in the two dialects.

    Why: a write is the line a client sends most after the read, and since fastwrite the
    server sends it from its event loop as a read; the general parser made 28 of the 67
    Python calls of the gateway per write there, one regular expression takes 27 off
    (issue 22)."""
    match = _PLAIN_WRITE.fullmatch(stripped)
    if match is None:
        return None
    sequence, net, node, index, subindex, type_name, value = match.groups()
    integer_type = _INTEGER_TYPES_BY_NAME.get(type_name)
    if integer_type is None:
        return None
    dtype, low, high = integer_type
    node_id = int(node)
    index_value = int(index, 0)
    subindex_value = int(subindex, 0)
    network = None if net is None else int(net)
    number = int(value, 0)
    if (node_id > MAX_NODE_ID or index_value > _U16 or subindex_value > 0xFF
            or (network is not None and network > _U16) or not low <= number <= high):
        return None
    size = SIZES[dtype]
    assert size is not None  # an integer type
    return SdoDownload(sequence=int(sequence), net=network, node=node_id, index=index_value,
                       subindex=subindex_value, dtype=dtype,
                       data=number.to_bytes(size, "little", signed=low < 0))


def _parse_stripped(stripped: str, dialect: Dialect) -> Request | None:
    """``parse_request`` of a line without its surrounding white space."""
    if not stripped or stripped.startswith("#"):
        return None
    match = SEQUENCE.match(stripped)
    if match is None:
        raise ParseError(ErrorCode.SYNTAX_ERROR, None, "a request starts with [<sequence>]")
    try:
        sequence = parse_integer(match.group(1), 0, _U32, "sequence")
    except DataTypeError as exc:
        raise ParseError(ErrorCode.SYNTAX_ERROR, None, str(exc)) from None
    text = stripped[match.end() :]
    tokens = _tokenize(text, dialect, sequence)
    numbers: list[int] = []
    while tokens and tokens[0].text[0].isdigit():
        if len(numbers) == 2:
            raise ParseError(ErrorCode.SYNTAX_ERROR, sequence, "more than net and node")
        try:
            numbers.append(parse_integer(tokens.pop(0).text, 0, _U32, "net or node"))
        except DataTypeError as exc:
            raise ParseError(ErrorCode.SYNTAX_ERROR, sequence, str(exc)) from None
    if not tokens:
        raise ParseError(ErrorCode.SYNTAX_ERROR, sequence, "command missing")
    command = tokens[0].text.lower()
    handler = _COMMANDS.get(command)
    if handler is None:
        raise ParseError(
            ErrorCode.REQUEST_NOT_SUPPORTED, sequence, f"unknown command {tokens[0].text!r}"
        )
    return handler(_Context(sequence, numbers, tokens[1:], text, dialect))


def _tokenize(text: str, dialect: Dialect, sequence: int) -> list[_Token]:
    """Split at white space; a ``"`` opens a string that runs to its closing quote (``""``
    inside, and in Lely's dialect a backslash escape, do not close it); ``#`` outside a
    string starts a comment, as in both gateways.

    A line without a quote or ``#`` (every read, most requests) is split by one regular
    expression, which the server pays for each line: parsing a read took 15.4 us with
    the character loop below, 14.4 without (2026-12-02). ``\\S`` is ``not str.isspace()``,
    so both ways give the same tokens."""
    if '"' not in text and "#" not in text:
        return [_Token(match.group(), match.start(), match.end())
                for match in _WORD.finditer(text)]
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
                raise ParseError(ErrorCode.SYNTAX_ERROR, sequence, "unterminated string")
            position = end
            if position < len(text) and not text[position].isspace():
                raise ParseError(ErrorCode.SYNTAX_ERROR, sequence, "text after a string")
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
        raise ctx.fail(f"reset {what!r}", ErrorCode.REQUEST_NOT_SUPPORTED)
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
    raise ctx.fail(f"enable {what!r}", ErrorCode.REQUEST_NOT_SUPPORTED)


def _disable(ctx: _Context) -> Request:
    what = ctx.word("'guarding' or 'heartbeat'").lower()
    requests: dict[str, type[NodeRequest]] = {
        "guarding": DisableGuarding,
        "heartbeat": DisableHeartbeat,
    }
    if what not in requests:
        raise ctx.fail(f"disable {what!r}", ErrorCode.REQUEST_NOT_SUPPORTED)
    address = ctx.node_level()
    ctx.done()
    return requests[what](sequence=ctx.sequence, **address)


def _set(ctx: _Context) -> Request:
    what = ctx.word("what to set").lower()
    handler = _SET_COMMANDS.get(what)
    if handler is None:
        raise ctx.fail(f"set {what!r}", ErrorCode.REQUEST_NOT_SUPPORTED)
    return handler(ctx)


def _set_network(ctx: _Context) -> Request:
    ctx.global_level()
    network = ctx.integer("network", 1, _U16, ErrorCode.UNSUPPORTED_NET)
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
        return EVENT_PROFILE, extra
    if lowered == "rtr":
        if extended:
            extra["event_timer"] = ctx.integer("event timer", 0, _U16)
        return ASYNC_RTR, extra
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
        raise ctx.fail(f"info {what!r}", ErrorCode.REQUEST_NOT_SUPPORTED)
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
