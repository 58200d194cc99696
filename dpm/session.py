"""The recorded session: its files and its record codec, apart from any I/O [ours].

A session is a directory (docs/recording.md): ``meta.json`` says what was recorded,
``session.jsonl`` holds one host-side event per line, ``can.log`` every CAN frame in
candump's log format (python-can's ``CanutilsLogWriter`` writes it, candump's tools and
``can.LogReader`` read it). The firmware writes sessions and the host side reads them;
neither imports the other, so the format lives here, beside the image it describes, as
the doorbell's contract does.

Every record carries ``t`` (CLOCK_MONOTONIC, seconds, as every process on the machine
reads it), ``wall`` (Unix time) and ``pid``: the host process behind a message where the
transaction ledger names it, else null.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from dpm.errors import DpmError
from dpm.layout import IO_AREA_SIZE, MSG_HEADER_SIZE, TASK_STATE_SIZE
from dpm.ledger import decode_line, ledger_text
from dpm.message import HEADER, Message, MessageError

FORMAT = "cifemu-session"
VERSION = 1
META = "meta.json"
EVENTS = "session.jsonl"
CAN_LOG = "can.log"

PUT = "put"
"""A message the card took from DevMbx (host to card)."""
ANSWER = "answer"
"""A message the card put into PcMbx (card to host: answers and indications)."""
HOST_FLAGS = "host_flags"
"""HostFlags changed (the card writes them)."""
DEV_FLAGS = "dev_flags"
"""DevFlags changed (the host writes them; seen once per turn of the device loop)."""
EXCHANGE = "exchange"
"""A process-data handshake: the bytes of SndPd and RcvPd that changed since the last one."""
KINDS = (PUT, ANSWER, HOST_FLAGS, DEV_FLAGS, EXCHANGE)

AREAS = ("SndPd", "RcvPd")

# --- the spool: the pipe from the recording firmware to its writer process, and the file
# the writer keeps it in until the recording ends (firmware/recorder.py,
# firmware/session_writer.py). Both ends are the same build; nothing else reads it.

SPOOL_PIECE = struct.Struct("<BI")
"""Before each piece on the pipe: what it holds (``SPOOL_EVENTS``, ``SPOOL_FRAMES``) and its
length. The events' pieces are one stream: a piece may end inside an event."""
SPOOL_EVENTS, SPOOL_FRAMES = 0, 1
SPOOL_FRAME_LENGTH = struct.Struct("<H")
"""Before each CAN frame (``dpm.tap``'s datagram) of a ``SPOOL_FRAMES`` piece."""
CAN_FRAME = "can"
"""What the writer makes of a spooled frame: ``(CAN_FRAME, datagram)``, for ``can.log``."""

# Each event: its code, ``t`` (CLOCK_MONOTONIC, a double), the HostFlags or DevFlags byte
# before and after; then by kind:
SPOOL_PUT = struct.Struct("<BdBBHH")
"""... the message's length and the ledger's (up to its ``END``); then both."""
SPOOL_ANSWER = struct.Struct("<BdBBH")
"""... the message's length; then the message and Task2State (``TASK_STATE_SIZE``)."""
SPOOL_HOST_FLAGS = struct.Struct("<BdBB")
SPOOL_DEV_FLAGS = struct.Struct("<BdBBB")
"""... 1 when Task2Parameter (``PARAMETER_SIZE`` bytes) follows, else 0."""
SPOOL_EXCHANGE = struct.Struct("<BdBBB")
"""... 1 when SndPd and RcvPd (2 x ``IO_AREA_SIZE``) follow, else 0 (both unchanged since
the last exchange); then Task2State."""
SPOOL_CODES = {PUT: 0, ANSWER: 1, HOST_FLAGS: 2, DEV_FLAGS: 3, EXCHANGE: 4}


@dataclass(frozen=True, slots=True)
class SpoolLayout:
    """How one event kind lies in the spool: its head, and the lengths of the byte strings
    that follow it, from the head's fields after the flags. One table for the decoder
    (firmware/session_writer.py), so that every kind is read by the same code."""

    kind: str
    head: struct.Struct
    tails: Callable[..., tuple[int, ...]]


SPOOL_LAYOUTS = {SPOOL_CODES[layout.kind]: layout for layout in (
    SpoolLayout(PUT, SPOOL_PUT, lambda length, lines: (length, lines)),
    SpoolLayout(ANSWER, SPOOL_ANSWER, lambda length: (length, TASK_STATE_SIZE)),
    SpoolLayout(HOST_FLAGS, SPOOL_HOST_FLAGS, lambda: ()),
    SpoolLayout(DEV_FLAGS, SPOOL_DEV_FLAGS,
                lambda started: (PARAMETER_SIZE if started else 0,)),
    SpoolLayout(EXCHANGE, SPOOL_EXCHANGE,
                lambda changed: (2 * IO_AREA_SIZE if changed else 0, TASK_STATE_SIZE)),
)}
"""Event code -> its ``SpoolLayout``: a PUT is followed by the message and the ledger's lines,
an ANSWER by the message and Task2State, a DEV_FLAGS by Task2Parameter when a start follows,
an EXCHANGE by SndPd and RcvPd when they changed, then Task2State."""


class SessionError(DpmError, ValueError):
    """A session file that is not in the documented format."""


Runs = list[tuple[int, bytes]]
"""Changed bytes of one area: (offset, the bytes from there), in rising order."""


@dataclass(slots=True)
class Record:
    """One event of a session."""

    kind: str
    t: float
    wall: float
    pid: int | None = None
    msg: Message | None = None
    """PUT and ANSWER."""
    before: int = 0
    after: int = 0
    """HOST_FLAGS and DEV_FLAGS: the byte before and after."""
    changes: dict[str, Runs] = field(default_factory=dict)
    """EXCHANGE: per area (``AREAS``), the runs of bytes that changed."""
    state: bytes = b""
    """ANSWER and EXCHANGE: Task2State as the image held it then (64 bytes)."""
    parameter: bytes = b""
    """DEV_FLAGS raising RESET or INIT: the host's part of Task2Parameter, which the
    start is about to read (``PARAMETER_SIZE`` bytes)."""


PARAMETER_SIZE = 48
"""Task2Parameter's bytes before abConnStatus: what a host writes for the next start."""


_CHUNK = 64


def changed_runs(old: bytes, new: bytes) -> Runs:
    """The runs of ``new`` that differ from ``old`` (both the same length). Compared a
    chunk at a time first: an exchange usually changes a few bytes of 3584, or none."""
    runs: Runs = []
    if old == new:
        return runs
    start = -1
    for chunk in range(0, len(new), _CHUNK):
        end = min(chunk + _CHUNK, len(new))
        if old[chunk:end] == new[chunk:end]:
            if start >= 0:
                runs.append((start, new[start:chunk]))
                start = -1
            continue
        for i in range(chunk, end):
            if old[i] != new[i] and start < 0:
                start = i
            elif old[i] == new[i] and start >= 0:
                runs.append((start, new[start:i]))
                start = -1
    if start >= 0:
        runs.append((start, new[start:]))
    return runs


def apply_runs(image: bytearray, runs: Runs) -> None:
    for offset, data in runs:
        image[offset : offset + len(data)] = data


def ledger_pid(ledger: bytes, msg: Message) -> int | None:
    """The pid of the host that sent ``msg``, from the board's transaction ledger
    (``dpm.ledger``, written by host_api and libcif before a request reaches the card);
    None when no line names it."""
    return request_pid(ledger, msg.nr, msg.b, msg.rx, msg.tx)


def request_pid(ledger: bytes, nr: int, b: int, rx: int, tx: int) -> int | None:
    """``ledger_pid`` of the message with these header fields."""
    wanted = (nr, b, rx, tx)
    for line in ledger_text(ledger).splitlines():
        entry = decode_line(line)
        if entry is not None and entry.pid >= 0 and entry[2:6] == wanted:
            return entry.pid
    return None


# --- the codec ----------------------------------------------------------------------------


_HEAD = '{"kind":"%s","t":%.6f,"wall":%.6f,"pid":%s'
_MESSAGE = (',"msg":{"rx":%d,"tx":%d,"ln":%d,"nr":%d,"a":%d,"f":%d,"b":%d,"e":%d,'
            '"data":"%s"}')
_FLAGS = ',"before":%d,"after":%d'


def _head(kind: str, t: float, wall: float, pid: int | None) -> str:
    return _HEAD % (kind, t, wall, "null" if pid is None else int(pid))


def _message(raw: bytes) -> str:
    rx, tx, ln, nr, a, f, b, e = HEADER.unpack_from(raw)
    data = raw[MSG_HEADER_SIZE : MSG_HEADER_SIZE + ln]
    return _MESSAGE % (rx, tx, len(data), nr, a, f, b, e, data.hex())


def encode_record(record: Record) -> str:
    """One line of ``session.jsonl`` (without its newline). Formatted by hand, not by
    ``json.dumps``: the recorder's writer encodes several lines per mailbox round trip,
    and a third of the cost went to the generic encoder."""
    line = _head(record.kind, record.t, record.wall, record.pid)
    if record.msg is not None:
        line += _message(record.msg.encode())
    if record.kind in (HOST_FLAGS, DEV_FLAGS):
        line += _FLAGS % (record.before, record.after)
    if record.changes:
        line += ',"changes":' + json.dumps(
            {area: [[offset, data.hex()] for offset, data in runs]
             for area, runs in record.changes.items()}, separators=(",", ":"))
    if record.state:
        line += f',"Task2State":"{record.state.hex()}"'
    if record.parameter:
        line += f',"Task2Parameter":"{record.parameter.hex()}"'
    return line + "}"


def encode_message(kind: str, t: float, wall: float, pid: int | None, raw: bytes,
                   state: bytes = b"") -> str:
    """The line ``encode_record`` makes of a put or an answer, straight from the message's
    mailbox bytes (``raw``: header and data): the writer's path, in half the time, since
    it builds no Message and no Record (docs/recording.md, what recording costs)."""
    line = _head(kind, t, wall, pid) + _message(raw)
    if state:
        line += ',"Task2State":"%s"' % state.hex()  # noqa: UP031 (% is the fastest here)
    return line + "}"


def encode_flags(kind: str, t: float, wall: float, before: int, after: int,
                 parameter: bytes = b"") -> str:
    """The line ``encode_record`` makes of a flags record (no pid: the image does not say
    who wrote a byte), without a Record: the writer's path, as ``encode_message``."""
    line = _HEAD % (kind, t, wall, "null") + _FLAGS % (before, after)
    if parameter:
        line += ',"Task2Parameter":"%s"' % parameter.hex()  # noqa: UP031
    return line + "}"


def _int(obj: dict[str, Any], key: str, top: int = 255) -> int:
    value = obj.get(key)
    if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= top:
        raise SessionError(f"{key!r} is not an integer 0..{top}")
    return value


def _hex(obj: dict[str, Any], key: str) -> bytes:
    value = obj.get(key, "")
    if not isinstance(value, str):
        raise SessionError(f"{key!r} is not a hex string")
    try:
        return bytes.fromhex(value)
    except ValueError:
        raise SessionError(f"{key!r} is not a hex string") from None


def _time(obj: dict[str, Any], key: str) -> float:
    value = obj.get(key)
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        raise SessionError(f"{key!r} is not a number")
    return float(value)


def decode_record(line: str) -> Record:
    """One line of ``session.jsonl``; SessionError when it is malformed."""
    try:
        obj = json.loads(line)
    except json.JSONDecodeError as exc:
        raise SessionError(f"not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise SessionError("a record is not a JSON object")
    kind = obj.get("kind")
    if kind not in KINDS:
        raise SessionError(f"unknown kind {kind!r}")
    pid = obj.get("pid")
    if pid is not None and (not isinstance(pid, int) or isinstance(pid, bool) or pid <= 0):
        raise SessionError("'pid' is not a process id")
    record = Record(kind, _time(obj, "t"), _time(obj, "wall"), pid)
    if kind in (PUT, ANSWER):
        msg = obj.get("msg")
        if not isinstance(msg, dict):
            raise SessionError("'msg' is missing")
        data = _hex(msg, "data")
        if _int(msg, "ln") != len(data):
            raise SessionError("msg.ln is not the length of msg.data")
        try:
            record.msg = Message(_int(msg, "rx"), _int(msg, "tx"), _int(msg, "b"), data,
                                 _int(msg, "nr"), _int(msg, "a"), _int(msg, "f"), _int(msg, "e"))
        except MessageError as exc:
            raise SessionError(str(exc)) from None
    if kind in (HOST_FLAGS, DEV_FLAGS):
        record.before, record.after = _int(obj, "before"), _int(obj, "after")
    if kind == EXCHANGE:
        record.changes = _decode_changes(obj.get("changes", {}))
    if "Task2State" in obj:
        record.state = _hex(obj, "Task2State")
    if "Task2Parameter" in obj:
        record.parameter = _hex(obj, "Task2Parameter")
    return record


def _decode_changes(changes: Any) -> dict[str, Runs]:
    if not isinstance(changes, dict) or not set(changes) <= set(AREAS):
        raise SessionError(f"'changes' is not an object of the areas {', '.join(AREAS)}")
    out: dict[str, Runs] = {}
    for area, runs in changes.items():
        if not isinstance(runs, list):
            raise SessionError(f"changes of {area} are not a list")
        decoded: Runs = []
        for run in runs:
            if (not isinstance(run, list) or len(run) != 2 or not isinstance(run[0], int)
                    or not isinstance(run[1], str)):
                raise SessionError(f"a change of {area} is not [offset, hex]")
            try:
                decoded.append((run[0], bytes.fromhex(run[1])))
            except ValueError:
                raise SessionError(f"a change of {area} is not [offset, hex]") from None
        out[area] = decoded
    return out


def decode_events(text: str) -> list[Record]:
    """Every record of a ``session.jsonl``; SessionError names the line of the first bad one."""
    records = []
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            records.append(decode_record(line))
        except SessionError as exc:
            raise SessionError(f"{EVENTS} line {number}: {exc}") from None
    return records


def encode_meta(board: int, started_wall: float, started_t: float, firmware_pid: int,
                can_log: bool, attached_by: int | None = None) -> str:
    """``attached_by``: the pid of the ``cifemu record`` that attached to a running card,
    None for a recording from the card's start (``cifemu firmware --record``)."""
    return json.dumps({"format": FORMAT, "version": VERSION, "board": board,
                       "started_wall": started_wall, "started_t": started_t,
                       "firmware_pid": firmware_pid,
                       "can_log": CAN_LOG if can_log else None,
                       "attached_by": attached_by}, indent=1) + "\n"


def decode_meta(text: str) -> dict[str, Any]:
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SessionError(f"{META}: not JSON: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise SessionError(f"{META}: not a {FORMAT}")
    if meta.get("version") != VERSION:
        raise SessionError(f"{META}: version {meta.get('version')!r}, this reader knows "
                           f"{VERSION}")
    return meta
