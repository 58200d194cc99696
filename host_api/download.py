"""DevDownload and the other services of the RCS load function (msg.b 6), host side.

``DevDownload(board, CONFIGURATION_DOWNLOAD, "net.dbm")`` puts a DBM into the
card's flash by the driver's procedure (docs/dbm.md section 3): a first message
(e = 4, nr = 1, ln = 51: mode 3, the root words w0..w7, the 34-byte GLOBAL
record), then the whole data area in 240-byte messages (e = 8, the last
e = 0x0C), each answered by the card. The file header is never sent. The
database takes effect at the card's next start.

Return codes, as the C driver's (docs/dpm.md section 4):

- 0 stored; 1000 + f when the card answers f != 0 (1020 not a CANopen
  database, 1022 wrong message number, 1023 wrong size, 1024 wrong
  sequence, 1025 checksum);
- -105 (file name not valid) for an empty name, -100 (file not opened) when
  the file cannot be opened, -103 (file read failed) when reading fails,
  -101 (file size zero) for an empty file, -104 (file type invalid) for a
  name not ending in .dbm or content that is no DBM file (magic, header
  length, or no GLOBAL record in root slot 8);
- FIRMWARE_DOWNLOAD (mode 1) answers -25 (DEVICE function call failed)
  [ours]: the emulated card's firmware is this program, there is none to
  replace; any other mode -37;
- the mailbox errors of DevPutMessage/DevGetMessage (-11, -17, -18 ...), and
  -4 when another host holds the board's transaction lock for longer than
  ``LOCK_WAIT_MS``.

The data to send may also be given as bytes: a whole DBM file, or a bare data
area as ``upload_database`` returns it. Like the C driver, DevDownload reads
only what it must send (GLOBAL through root slot 8), so a file with a broken
checksum reaches the card and gets the card's answer (1025).

[ours] ``upload_database`` (mode 2), ``delete_database`` (mode 4) and
``flash_directory`` (mode 5) return the same kinds of codes; the protocol is
described in ``firmware.flash``. This side implements it on its own, as a C
driver and the card's firmware do (host_api never imports firmware), so the
few protocol numbers appear on both sides. Every service holds the board's
transaction lock for its whole exchange, so two hosts never interleave.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from dbm_tools.container import BLOCK_HEADER_SIZE as BLOCK_HEADER
from dbm_tools.container import FILE_HEADER_SIZE, FILE_MAGIC, MAX_DATA_AREA
from dbm_tools.container import FIRST_TABLE as GLOBAL_SLOT
from dbm_tools.tables import DBM_SET_GLOBAL_SIZE as GLOBAL_SIZE
from dpm.commands import (
    DIRECTORY_ENTRY,
    LOAD_FUNCTION,
    MODE_DELETE,
    MODE_DIRECTORY,
    MODE_DOWNLOAD,
    MODE_UPLOAD,
)
from dpm.commands import LOAD_CHUNK as CHUNK
from dpm.commands import LOAD_ROOT_BYTES as ROOT_BYTES
from dpm.commands import LOAD_SEGMENT as SEGMENT
from dpm.errors import Drv
from dpm.message import Ext, Message, Task
from host_api.driver import MSG_BUFFER_SIZE, DevGetMessage, DevPutMessage
from host_api.locks import Transaction
from host_api.registry import MappedBoard, ready_board

FIRMWARE_DOWNLOAD = 1
CONFIGURATION_DOWNLOAD = 2

MESSAGE_TIMEOUT_MS = 5000
"""Per answer; a real card takes up to 3 s to erase its flash (seed 5.2.2)."""
LOCK_WAIT_MS = 30_000
"""How long a service waits for another host's transfer to finish."""

Progress = Callable[[int, int], None]
"""Called with (bytes done, bytes in all) after every answered piece."""


@dataclass(frozen=True)
class FlashEntry:
    """One entry of the card's flash directory."""

    segment: int
    name: str
    length: int
    checksum: int
    stored: int
    """Unix time of the store."""


def _global_record(area: bytes) -> bytes | None:
    """GLOBAL's record, found as drivers find it: root slot 8 -> directory -> slot 1."""
    try:
        (directory,) = struct.unpack_from("<H", area, 2 * GLOBAL_SLOT)
        (record,) = struct.unpack_from("<H", area, 2 * directory + BLOCK_HEADER + 2)
        pad, length = struct.unpack_from("<HH", area, 2 * record + 8)
    except struct.error:
        return None
    payload = area[2 * record + BLOCK_HEADER : 2 * record + length - pad]
    return payload if len(payload) == GLOBAL_SIZE else None


def _data_area(source: bytes | bytearray | memoryview | str | Path) -> tuple[int, bytes]:
    """The data area to send, or the driver's file error."""
    if isinstance(source, bytes | bytearray | memoryview):
        raw = bytes(source)
        if not raw:
            return Drv.DRV_USR_FILE_SIZE_ZERO, b""
        if not raw.startswith(FILE_MAGIC):
            return Drv.DRV_NO_ERROR, raw  # a bare data area
    else:
        if not str(source):
            return Drv.DRV_USR_FILENAME_INVALID, b""
        path = Path(source)
        if path.suffix.lower() != ".dbm":
            return Drv.DRV_USR_INVALID_FILETYPE, b""
        try:
            with path.open("rb") as file:
                try:
                    raw = file.read()
                except OSError:
                    return Drv.DRV_USR_FILE_READ_FAILED, b""
        except OSError:
            return Drv.DRV_USR_FILE_OPEN_FAILED, b""
        if not raw:
            return Drv.DRV_USR_FILE_SIZE_ZERO, b""
        if not raw.startswith(FILE_MAGIC):
            return Drv.DRV_USR_INVALID_FILETYPE, b""
    if len(raw) < FILE_HEADER_SIZE:
        return Drv.DRV_USR_INVALID_FILETYPE, b""
    length, start = struct.unpack_from("<HI", raw, 38)
    if start != FILE_HEADER_SIZE or len(raw) != FILE_HEADER_SIZE + length:
        return Drv.DRV_USR_INVALID_FILETYPE, b""
    return Drv.DRV_NO_ERROR, raw[FILE_HEADER_SIZE:]


class _Session:
    """One host's exclusive use of the load function: the board's transaction lock."""

    def __init__(self, number: int) -> None:
        self.number = number
        self.nr = 0
        self.lock: Transaction | None = None

    def __enter__(self) -> int:
        board = ready_board(self.number)
        if not isinstance(board, MappedBoard):
            return int(board)
        if not board.transaction.acquire(LOCK_WAIT_MS / 1000.0):
            return Drv.DRV_CMD_ACTIVE
        self.lock = board.transaction
        return Drv.DRV_NO_ERROR

    def __exit__(self, *exc: object) -> None:
        if self.lock is not None:
            self.lock.release()

    def send(self, data: bytes, e: int) -> tuple[int, Message | None]:
        """One request and its answer; rc is 1000 + f when the card refused."""
        self.nr = (self.nr + 1) & 0xFF
        msg = Message(rx=Task.RCS, tx=Task.USER, b=LOAD_FUNCTION, data=data, nr=self.nr, e=e)
        rc = DevPutMessage(self.number, msg, MESSAGE_TIMEOUT_MS)
        if rc != Drv.DRV_NO_ERROR:
            return int(rc), None
        while True:
            rc, answer = DevGetMessage(self.number, MSG_BUFFER_SIZE, MESSAGE_TIMEOUT_MS)
            if rc != Drv.DRV_NO_ERROR or answer is None:
                return int(rc), None
            if answer.nr == msg.nr and answer.a == LOAD_FUNCTION:
                break  # anything else is an indication or a late answer of someone else's
        if answer.f:
            return Drv.DRV_RCS_ERROR_OFFSET + answer.f, answer
        return Drv.DRV_NO_ERROR, answer


def DevDownload(
    number: int,
    mode: int,
    source: bytes | bytearray | memoryview | str | Path,
    progress: Progress | None = None,
) -> int:
    """Download a DBM (mode 2, CONFIGURATION_DOWNLOAD) into the card's flash."""
    if mode == FIRMWARE_DOWNLOAD:
        return Drv.DRV_DEV_FUNCTION_FAILED
    if mode != CONFIGURATION_DOWNLOAD:
        return Drv.DRV_USR_MODE_INVALID
    rc, area = _data_area(source)
    if rc != Drv.DRV_NO_ERROR:
        return rc
    record = _global_record(area)
    if record is None or len(area) < ROOT_BYTES:
        return Drv.DRV_USR_INVALID_FILETYPE
    session = _Session(number)
    with session as rc:
        if rc != Drv.DRV_NO_ERROR:
            return rc
        rc, _ = session.send(bytes([MODE_DOWNLOAD]) + area[:ROOT_BYTES] + record, Ext.FIRST)
        if rc != Drv.DRV_NO_ERROR:
            return rc
        for offset in range(0, len(area), CHUNK):
            last = offset + CHUNK >= len(area)
            rc, _ = session.send(area[offset : offset + CHUNK], Ext.LAST if last else Ext.CONT)
            if rc != Drv.DRV_NO_ERROR:
                return rc
            if progress is not None:
                progress(min(offset + CHUNK, len(area)), len(area))
    return Drv.DRV_NO_ERROR


def upload_database(number: int, progress: Progress | None = None) -> tuple[int, bytes]:
    """The stored data area (mode 2); 1200 when the card has none."""
    session = _Session(number)
    with session as rc:
        if rc != Drv.DRV_NO_ERROR:
            return rc, b""
        data = bytearray()
        e = Ext.FIRST
        while len(data) <= MAX_DATA_AREA:
            rc, answer = session.send(bytes([MODE_UPLOAD]), e)
            if rc != Drv.DRV_NO_ERROR or answer is None:
                return rc, b""
            data += answer.data
            if progress is not None:
                progress(len(data), _expected_length(data))
            if answer.e & Ext.SEQ_MASK == Ext.LAST:
                return Drv.DRV_NO_ERROR, bytes(data)
            e = Ext.CONT
    return Drv.DRV_DEV_FUNCTION_FAILED, b""  # the card never said "last"


def _expected_length(data: bytearray) -> int:
    """The data area's length from root word w5, once the first piece is in."""
    return 2 * struct.unpack_from("<H", data, 10)[0] if len(data) >= 12 else len(data)


def delete_database(number: int) -> int:
    """Erase the stored database (mode 4, start segment 8); effective at the next start."""
    session = _Session(number)
    with session as rc:
        if rc != Drv.DRV_NO_ERROR:
            return rc
        rc, _ = session.send(bytes([MODE_DELETE, SEGMENT]), Ext.NORM)
        return rc


def flash_directory(number: int) -> tuple[int, list[FlashEntry]]:
    """What the card's flash holds (mode 5)."""
    session = _Session(number)
    with session as rc:
        if rc != Drv.DRV_NO_ERROR:
            return rc, []
        rc, answer = session.send(bytes([MODE_DIRECTORY]), Ext.NORM)
        if rc != Drv.DRV_NO_ERROR or answer is None:
            return rc, []
    entries = []
    count = answer.data[1] if len(answer.data) > 1 else 0
    for index in range(count):
        at = 2 + index * DIRECTORY_ENTRY.size
        if at + DIRECTORY_ENTRY.size > len(answer.data):
            break
        segment, name, length, checksum, stored = DIRECTORY_ENTRY.unpack_from(answer.data, at)
        entries.append(FlashEntry(segment, name.rstrip(b"\0").decode("latin-1"), length,
                                  checksum, stored))
    return Drv.DRV_NO_ERROR, entries

