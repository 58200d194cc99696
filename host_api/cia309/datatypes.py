"""CiA 309-3 values in text: the codecs between ASCII values and CiA 301 bytes.

An SDO request names a data type (``u16``, ``vs``, ...; :class:`~host_api.cia309.model.DataType`
with its sizes is in the model) and, for a download, a value in text. The gateway needs the
value as the little-endian bytes CiA 301 puts on the bus, and an upload answer needs those
bytes back in text. Both directions are pure functions here, tested against byte vectors,
part of the text layer (the typed service layer has its own codec of Python values,
``model.encode_value``), touching no I/O (the same split as cantools' message codecs).

Two gateways that exist today define what clients expect, and they disagree in places:

* CANopenNode's gateway (``309/CO_gateway_ascii.c``, values in ``301/CO_fifo.c``): integers in
  C syntax (``strtol`` base 0: decimal, ``0x`` hex, leading ``0`` octal); ``u*`` printed in
  decimal, ``x8``..``x64`` as ``0x%0NX``; ``vs`` quoted with ``""`` for a quote, NUL and CR
  dropped on output, no backslash escapes; ``os``/``us``/``d`` MIME base64 on one line;
  non-standard ``hex`` (byte pairs, optionally space separated, printed ``%02X`` with spaces).
* Lely's ``co_gw_txt`` (``src/co/gw_txt.c``, ``src/co/val.c``): the 309-3 type list with the
  24/40/48/56-bit types and ``t``/``td`` as two integers ``<days> <ms>``; unsigned printed as
  ``0x%0Nx``; ``vs`` quoted, ``""`` for a quote, plus C escapes (``\\n``, ``\\x41``, ...).

Where they disagree the caller picks a :class:`Dialect`. Deliberate differences from both:
REAL32/REAL64 are printed with the fewest ``%g`` digits that read back to the same bits (C's
``%g`` keeps six digits and loses precision), and a value outside its type's range is an
error, where C's ``strtoul`` would wrap ``-1`` to ``0xFFFFFFFF``.
"""

from __future__ import annotations

import base64
import math
import re
import struct
from enum import Enum, StrEnum

from dpm.cia301 import ABORT_TYPE_LENGTH_MISMATCH
from host_api.cia309.model import (
    SIZES,
    TIME_MS_MASK,
    Cia309Error,
    DataType,
    ErrorCode,
)


class Dialect(StrEnum):
    """Which existing gateway's spelling a client expects where 309-3 leaves room."""

    CANOPENNODE = "canopennode"
    LELY = "lely"

    @property
    def line_end(self) -> str:
        """CANopenNode closes every answer with CR LF; Lely's gateway writes a bare LF."""
        return LINE_ENDS[self]


LINE_ENDS = {Dialect.CANOPENNODE: "\r\n", Dialect.LELY: "\n"}
"""``Dialect.line_end`` of each dialect, for the answer of every 309-3 request (a look-up,
not the property's Python call, on every read: issue 22)."""


class DataTypeError(Cia309Error, ValueError):
    """A value that is not of its data type, or bytes that cannot be one.

    ``abort_code`` is None for malformed or out-of-range text, which a 309-3 answer reports
    as error 101 (syntax, ``error``). For bytes of the wrong length it is the CiA 301 abort
    code the answer carries instead (:data:`~dpm.cia301.ABORT_TYPE_LENGTH_MISMATCH`).
    """

    def __init__(self, message: str, *, abort_code: int | None = None) -> None:
        error = ErrorCode.SYNTAX_ERROR if abort_code is None else None
        super().__init__(error, message, abort_code=abort_code)


def parse_data_type(token: str) -> DataType:
    """The type a request names; both gateways compare mnemonics case-insensitively."""
    try:
        return DataType(token.lower())
    except ValueError:
        raise DataTypeError(f"unknown data type {token!r}") from None


class _Kind(Enum):
    BOOLEAN = "boolean"
    SIGNED = "signed"
    UNSIGNED = "unsigned"
    HEX_UNSIGNED = "hex unsigned"
    REAL = "real"
    TIME = "time"
    VISIBLE = "visible string"
    BASE64 = "base64"
    HEX_BYTES = "hex bytes"


_KINDS: dict[DataType, _Kind] = {
    DataType.BOOLEAN: _Kind.BOOLEAN,
    DataType.INTEGER8: _Kind.SIGNED,
    DataType.INTEGER16: _Kind.SIGNED,
    DataType.INTEGER24: _Kind.SIGNED,
    DataType.INTEGER32: _Kind.SIGNED,
    DataType.INTEGER40: _Kind.SIGNED,
    DataType.INTEGER48: _Kind.SIGNED,
    DataType.INTEGER56: _Kind.SIGNED,
    DataType.INTEGER64: _Kind.SIGNED,
    DataType.UNSIGNED8: _Kind.UNSIGNED,
    DataType.UNSIGNED16: _Kind.UNSIGNED,
    DataType.UNSIGNED24: _Kind.UNSIGNED,
    DataType.UNSIGNED32: _Kind.UNSIGNED,
    DataType.UNSIGNED40: _Kind.UNSIGNED,
    DataType.UNSIGNED48: _Kind.UNSIGNED,
    DataType.UNSIGNED56: _Kind.UNSIGNED,
    DataType.UNSIGNED64: _Kind.UNSIGNED,
    DataType.HEX8: _Kind.HEX_UNSIGNED,
    DataType.HEX16: _Kind.HEX_UNSIGNED,
    DataType.HEX32: _Kind.HEX_UNSIGNED,
    DataType.HEX64: _Kind.HEX_UNSIGNED,
    DataType.REAL32: _Kind.REAL,
    DataType.REAL64: _Kind.REAL,
    DataType.TIME_OF_DAY: _Kind.TIME,
    DataType.TIME_DIFFERENCE: _Kind.TIME,
    DataType.VISIBLE_STRING: _Kind.VISIBLE,
    DataType.OCTET_STRING: _Kind.BASE64,
    DataType.UNICODE_STRING: _Kind.BASE64,
    DataType.DOMAIN: _Kind.BASE64,
    DataType.HEX: _Kind.HEX_BYTES,
}


def _integer_range(kind: _Kind, size: int | None) -> tuple[int, int]:
    assert size is not None  # every integer type has a fixed size
    bits = 8 * size
    if kind is _Kind.BOOLEAN:
        return 0, 1
    if kind is _Kind.SIGNED:
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    return 0, (1 << bits) - 1


INTEGER_RANGES: dict[DataType, tuple[int, int]] = {
    dtype: _integer_range(kind, SIZES[dtype])
    for dtype, kind in _KINDS.items()
    if kind in (_Kind.BOOLEAN, _Kind.SIGNED, _Kind.UNSIGNED, _Kind.HEX_UNSIGNED)
}
"""The lowest and highest value of each integer type (BOOLEAN, INTEGERn, UNSIGNEDn, HEXn),
which ``parse_value`` checks and the parser's plain write too (issue 22); a signed type is
one whose lowest value is negative."""

_MAX_NUMBER_TEXT = 128
"""No integer needs more characters; longer text is refused before Python converts it."""
_C_INTEGER = re.compile(r"([+-]?)(?:0[xX]([0-9a-fA-F]+)|(0[0-7]*)|([1-9][0-9]*))")
_C_DECIMAL_FLOAT = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_C_HEX_FLOAT = re.compile(
    r"[+-]?0[xX](?:[0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)(?:[pP][+-]?[0-9]+)?"
)
_C_SPECIAL_FLOAT = re.compile(r"[+-]?(?:inf|infinity|nan)", re.IGNORECASE)
_BASE64_TEXT = re.compile(r"[A-Za-z0-9+/]*={0,2}")
_HEX_GROUP = re.compile(r"[0-9a-fA-F]+")
_C_ESCAPES = {
    "'": "'",
    '"': '"',
    "\\": "\\",
    "a": "\a",
    "b": "\b",
    "f": "\f",
    "n": "\n",
    "r": "\r",
    "t": "\t",
    "v": "\v",
}
_C_ESCAPES_OUT = {value: "\\" + key for key, value in _C_ESCAPES.items() if key != '"'}


def parse_integer(token: str, low: int, high: int, what: str = "value") -> int:
    """Read an integer the way both gateways do (C ``strtol`` with base 0) within [low, high].

    So ``0x1017``, ``4119`` and ``010`` (octal 8) are accepted and ``08`` is not, as in C; a
    sign is allowed, but unlike ``strtoul`` a negative number is never wrapped into range.
    Raises DataTypeError (101) for anything else.
    """
    match = _C_INTEGER.fullmatch(token) if len(token) <= _MAX_NUMBER_TEXT else None
    if match is None:
        raise DataTypeError(f"{what} {token!r} is not an integer")
    sign, hex_digits, octal_digits, decimal_digits = match.groups()
    if hex_digits is not None:
        magnitude = int(hex_digits, 16)
    elif octal_digits is not None:
        magnitude = int(octal_digits, 8)
    else:
        magnitude = int(decimal_digits, 10)
    value = -magnitude if sign == "-" else magnitude
    if not low <= value <= high:
        raise DataTypeError(f"{what} {token} is outside {low}..{high}")
    return value


def parse_value(dtype: DataType, text: str, dialect: Dialect = Dialect.CANOPENNODE) -> bytes:
    """The CiA 301 bytes of ``text``, the value part of a download request.

    ``text`` is everything after the data type with the comment removed; only the
    variable-length types and ``t``/``td`` may span several words. Raises DataTypeError
    (101) for text that is no value of the type.
    """
    kind = _KINDS[dtype]
    text = text.strip()
    if not text:
        raise DataTypeError(f"no value for data type {dtype.value}")
    if kind is _Kind.TIME:
        return _parse_time(text)
    if kind is _Kind.VISIBLE:
        return _parse_visible_string(text, dialect)
    if kind is _Kind.HEX_BYTES:
        return _parse_hex_bytes(text)
    if any(character.isspace() for character in text):
        raise DataTypeError(f"a {dtype.value} value is one word, not {text!r}")
    if kind is _Kind.BASE64:
        data = _parse_base64(text)
        if dtype is DataType.UNICODE_STRING and len(data) % 2:
            raise DataTypeError("a UNICODE_STRING is a whole number of 16-bit characters")
        return data
    if kind is _Kind.REAL:
        return _parse_real(text, single=dtype is DataType.REAL32)
    size = SIZES[dtype]
    assert size is not None  # every remaining kind has a fixed size
    low, high = INTEGER_RANGES[dtype]  # every remaining kind is an integer
    value = parse_integer(text, low, high, dtype.name)
    return value.to_bytes(size, "little", signed=low < 0)


def format_value(dtype: DataType, data: bytes, dialect: Dialect = Dialect.CANOPENNODE) -> str:
    """The text an upload answer carries for ``data`` of type ``dtype``.

    Raises DataTypeError with :data:`~dpm.cia301.ABORT_TYPE_LENGTH_MISMATCH` when a
    fixed-size type gets a different number of bytes; CANopenNode's gateway then falls back
    to ``hex`` (see ``format_upload`` in the formatters module), Lely's answers with the
    abort code.
    """
    size = SIZES[dtype]
    if size is not None and len(data) != size:
        raise DataTypeError(
            f"{len(data)} bytes are no {dtype.value} value ({size} bytes)",
            abort_code=ABORT_TYPE_LENGTH_MISMATCH,
        )
    kind = _KINDS[dtype]
    if kind is _Kind.BOOLEAN:
        if dialect is Dialect.LELY:
            return "1" if data[0] else "0"
        return str(data[0])
    if kind is _Kind.SIGNED:
        return str(int.from_bytes(data, "little", signed=True))
    if kind in (_Kind.UNSIGNED, _Kind.HEX_UNSIGNED):
        value = int.from_bytes(data, "little")
        if dialect is Dialect.LELY:
            return f"0x{value:0{2 * len(data)}x}"
        if kind is _Kind.HEX_UNSIGNED:
            return f"0x{value:0{2 * len(data)}X}"
        return str(value)
    if kind is _Kind.REAL:
        return _format_real(data)
    if kind is _Kind.TIME:
        milliseconds = int.from_bytes(data[:4], "little") & TIME_MS_MASK
        return f"{int.from_bytes(data[4:], 'little')} {milliseconds}"
    if kind is _Kind.VISIBLE:
        return _format_visible_string(data, dialect)
    if kind is _Kind.BASE64:
        return base64.b64encode(data).decode("ascii")
    return " ".join(f"{byte:02X}" for byte in data)


def _parse_real(token: str, *, single: bool) -> bytes:
    """C ``strtod`` syntax: decimal, hexadecimal (``0x1.8p3``), ``inf`` and ``nan``."""
    if _C_SPECIAL_FLOAT.fullmatch(token):
        return struct.pack("<f" if single else "<d", float(token))
    try:
        if _C_DECIMAL_FLOAT.fullmatch(token):
            value = float(token)
        elif _C_HEX_FLOAT.fullmatch(token):
            value = float.fromhex(token)
        else:
            raise DataTypeError(f"{token!r} is not a real number")
    except OverflowError:  # float.fromhex with a huge exponent
        value = math.inf
    packed = None if math.isinf(value) else _pack_real(value, single=single)
    if packed is None:
        raise DataTypeError(f"{token} is outside the REAL{32 if single else 64} range")
    return packed


def _pack_real(value: float, *, single: bool) -> bytes | None:
    """IEEE 754 little-endian bytes, or None when a REAL32 cannot hold the value."""
    try:
        return struct.pack("<f" if single else "<d", value)
    except OverflowError:
        return None


def _format_real(data: bytes) -> str:
    """``%g`` with the fewest digits that give back the same bits, so nothing is lost."""
    single = len(data) == 4
    value: float = struct.unpack("<f" if single else "<d", data)[0]
    if math.isnan(value):
        return "nan"
    if math.isinf(value):
        return "-inf" if value < 0 else "inf"
    for digits in range(1, 17):
        text = f"{value:.{digits}g}"
        if _pack_real(float(text), single=single) == data:
            return text
    return f"{value:.17g}"


def _parse_time(text: str) -> bytes:
    """Lely's form ``<days> <ms>``: days since 1984-01-01 and milliseconds (28 bits)."""
    words = text.split()
    if len(words) != 2:
        raise DataTypeError(f"a time value is '<days> <ms>', not {text!r}")
    days = parse_integer(words[0], 0, 0xFFFF, "days")
    milliseconds = parse_integer(words[1], 0, TIME_MS_MASK, "milliseconds")
    return milliseconds.to_bytes(4, "little") + days.to_bytes(2, "little")


def _parse_base64(token: str) -> bytes:
    """MIME base64 (RFC 2045 alphabet) on one line; the ``=`` padding may be left out."""
    if _BASE64_TEXT.fullmatch(token) is None:
        raise DataTypeError(f"{token!r} is not base64")
    body = token.rstrip("=")
    if not body or len(body) % 4 == 1 or len(token) - len(body) > (-len(body)) % 4:
        raise DataTypeError(f"{token!r} is not base64")
    return base64.b64decode(body + "=" * ((-len(body)) % 4), validate=True)


def _parse_hex_bytes(text: str) -> bytes:
    """CANopenNode's ``hex``: digit pairs, groups separated by spaces; a lone last digit of
    a group is a byte of its own (``1 2`` and ``0102`` are both 01 02)."""
    data = bytearray()
    for group in text.split():
        if _HEX_GROUP.fullmatch(group) is None:
            raise DataTypeError(f"{group!r} is not hexadecimal")
        data += bytes(int(group[i : i + 2], 16) for i in range(0, len(group), 2))
    return bytes(data)


def _parse_visible_string(text: str, dialect: Dialect) -> bytes:
    """A quoted string (``""`` inside stands for one quote) or a bare word.

    Lely's gateway also reads C escapes and takes an unquoted value to the end of the line;
    CANopenNode's reads backslashes literally and an unquoted value is a single word.
    """
    if text.startswith('"'):
        if len(text) < 2 or not text.endswith('"'):
            raise DataTypeError(f"unterminated string {text!r}")
        body = text[1:-1]
    elif dialect is Dialect.CANOPENNODE and any(character.isspace() for character in text):
        raise DataTypeError(f"a string of several words must be quoted: {text!r}")
    else:
        body = text
    chars: list[str] = []
    position = 0
    while position < len(body):
        character = body[position]
        if character == '"':
            if body[position + 1 : position + 2] != '"':
                raise DataTypeError(f"a quote inside a string is written twice: {text!r}")
            chars.append('"')
            position += 2
        elif character == "\\" and dialect is Dialect.LELY:
            decoded, position = _c_escape(body, position)
            chars.append(decoded)
        else:
            chars.append(character)
            position += 1
    try:
        return "".join(chars).encode("latin-1")
    except UnicodeEncodeError:
        raise DataTypeError(f"{text!r} has characters outside one byte") from None


def _c_escape(body: str, position: int) -> tuple[str, int]:
    """Decode the C escape at ``body[position]`` (a backslash); invalid ones stay literal,
    as in Lely's lexer."""
    following = body[position + 1 : position + 2]
    if following in _C_ESCAPES:
        return _C_ESCAPES[following], position + 2
    octal = re.match(r"[0-7]{1,3}", body[position + 1 :])
    if octal is not None:
        return chr(int(octal.group(), 8)), position + 1 + len(octal.group())
    hexadecimal = re.match(r"x([0-9a-fA-F]{1,2})", body[position + 1 :])
    if hexadecimal is not None:
        return chr(int(hexadecimal.group(1), 16)), position + 1 + len(hexadecimal.group())
    return "\\", position + 1


def _format_visible_string(data: bytes, dialect: Dialect) -> str:
    """Quote for the answer line; bytes map 1:1 to characters (latin-1)."""
    if dialect is Dialect.CANOPENNODE:
        text = data.decode("latin-1").replace("\0", "").replace("\r", "")
        return '"' + text.replace('"', '""') + '"'
    out = ['"']
    for character in data.split(b"\0", 1)[0].decode("latin-1"):
        if character == '"':
            out.append('""')
        elif character in _C_ESCAPES_OUT:
            out.append(_C_ESCAPES_OUT[character])
        elif " " <= character <= "~":
            out.append(character)
        else:
            out.append(f"\\{ord(character):03o}")
    out.append('"')
    return "".join(out)
