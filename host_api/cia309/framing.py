"""CiA 309-3 line framing: a byte stream cut into request lines.

The first layer of the text side (pymodbus's framer): bytes in, lines out, a line over the
client's command size reported once and dropped. It knows neither requests nor answers.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from host_api.cia309.datatypes import DataTypeError, parse_integer
from host_api.cia309.model import ErrorCode
from host_api.cia309.requests import ParseError

DEFAULT_MAX_LINE = 16384
"""Longest request line accepted, in bytes without the line end. CANopenLinux's command
buffer is 2000 bytes but CANopenNode streams longer SDO writes through it; we hold whole lines,
so the default leaves room for a 12 KiB domain in base64. ``set command_size`` may change it."""

_U32 = 0xFFFF_FFFF
SEQUENCE = re.compile(r"\[\s*([^\]]*?)\s*\]")
"""The ``[<sequence>]`` a request starts with; the parser reads it with the same pattern."""
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
        match = SEQUENCE.match(self.head.lstrip())
        if match is None:
            return None
        try:
            return parse_integer(match.group(1), 0, _U32, "sequence")
        except DataTypeError:
            return None

    def error(self) -> ParseError:
        """309-1 4.6.5: a command above the command size is refused for lack of memory."""
        return ParseError(
            ErrorCode.OUT_OF_MEMORY, self.sequence, "request longer than the command size"
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
        self.between_lines = True
        """Nothing of a line is held or dropped, and no CR waits for its LF: the next bytes
        begin a line. An attribute, not a property: the server's fast path looks at it on
        every read without a Python call (issue 22)."""

    @property
    def pending(self) -> int:
        """Bytes held of a line whose end has not arrived yet."""
        return len(self._buffer)

    @property
    def partial(self) -> bool:
        """A line has begun and its end has not arrived (held, or dropped as overlong)."""
        return bool(self._buffer) or self._discarding

    def whole_line(self, data: bytes) -> str | None:
        """The line ``data`` is, when it is exactly one whole line (ended by LF or CR LF,
        within ``max_line``) and nothing of an earlier line is held; else None, with
        nothing taken (``feed`` it then). What ``feed`` would return for it, without its
        search: a client that waits for each answer sends one line at a time, and the
        server's fast path (``Server``) answers such a line without its client's task."""
        if not self.between_lines:
            return None
        if data.endswith(b"\r\n"):
            body = data[:-2]
        elif data.endswith(b"\n"):
            body = data[:-1]
        else:
            return None
        if len(body) > self.max_line or b"\n" in body or b"\r" in body:
            return None
        return body.decode("latin-1")

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
        self.between_lines = not (self._buffer or self._discarding or self._after_cr)
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
