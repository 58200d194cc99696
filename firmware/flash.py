"""The card's flash: the stored database, the RCS load function (msg.b 6), start-up from flash.

The flash is a directory, one per board (default
``platformdirs.user_data_dir("cifemu")/flash/board<N>``, or
``$CIFEMU_FLASH_DIR/board<N>``, or ``cifemu firmware --flash DIR``). It holds
one file, ``database.bin``: the DBM data area exactly as the host sent it (no
44-byte file header; ``cifemu dbm show`` reads it as it is). A new database is
written to a temporary file, fsync'ed and renamed over the old one, so a card
killed at any moment keeps either the old database or the new one, whole. The
directory is the firmware's alone (docs/security.md): created mode 0750, refused
when another user owns it or any other user can write to it; the temporary file
has an unpredictable name and is made with O_EXCL, so nothing planted is followed.

The load function (docs/dbm.md section 3; answers rx/tx swapped, a = 6, same nr),
selected by d[0] of a message whose msg.e has no continuation bits:

- 3 download: first message e = 4, ln = 51: d[1..16] the data area's root
  words w0..w7, d[17..50] the GLOBAL record. Then the data area from byte 0,
  240 bytes per message, e = 8, the last one e = 0x0C with the rest.
  Each message is answered [ours]: f = 0, or an error that ends the download:
  20 segment name not "CANopen ", or a data area that is no readable DBM
  [ours]; 22 msg.nr not one more than the previous message's (mod 256) [ours:
  counting starts at the first message's nr]; 23 ln not 51 / 240 / the rest,
  root words w5 != w6 or a length outside 416..65534, or root words in the
  data that differ from the first message's; 24 a continuation with no
  download (or upload) going on, or a download command without e = 4;
  25 w0 of the first message is not the sum of the received words.
  The answer to the last message comes after the database is stored; it takes
  effect at the next start.
- 2 upload [ours]: the host sends e = 4, d[0] = 2; the card answers with the
  first 240 bytes of the stored data area, e = 4 (first), then answers each
  further request (e = 8, d[0] = 2, nr + 1) with the next piece, e = 8; the
  last piece has e = 0x0C (also when it is the first). f 200 (DEVICE is not
  configured) when nothing is stored.
- 4 delete: d[1] = start segment, 8 (seed 5.2.2); the answer has ln = 1,
  d[0] = 4 [ours: the seed gives ln = 1 without naming the byte]. Deleting
  an empty flash is no error. Without a database the card comes up READY
  without RUN at its next start.
- 5 flash directory [ours]: answer d[0] = 5, d[1] = number of entries (0 or
  1), then per entry 18 bytes: bSegment u8 (8), szSegmentName[9] (GLOBAL's,
  NUL padded; zeros if the data cannot be read), usLength u16 (data-area
  bytes), usChecksum u16 (w0), ulStored u32 (Unix time of the store).
- Any other mode, or a message too short for its mode: f 21 (parameter fault
  in request) [ours]. A new command abandons an unfinished transfer [ours].

At every start (``StoredDatabase.load``, then ``configure``) the database
runs through ``check_dbm``; a database that fails, or whose data sets the CAN
task refuses, leaves the card READY without RUN with the CTRL bit and
Err_Event 56 (unknown baud rate) or 60 (double node address) at Err_Node_adr
255, else 212 at 255 or at the node whose record failed. Else
BUS_CAN_EXT, every NODES record and BUS_CAN go to the CAN task in that
order, and the BUS_CAN download starts the network. [ours] A start that finds the
same bytes in flash as the start before takes that start's verdict and decoded data
sets instead of checking and decoding them again (issue 22: 127 node sets cost a cold
start 30-50 ms of CPU before READY, each time).
"""

from __future__ import annotations

import logging
import os
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import platformdirs

from dbm_tools.container import FIRST_TABLE, MAX_DATA_AREA, ROOT_WORDS, DbmFile, read_data_area
from dbm_tools.errors import DbmError
from dbm_tools.parameters import NodeParameterSet
from dbm_tools.tables import (
    BUS_CAN,
    BUS_CAN_EXT,
    DESCRIPT,
    GLOBAL,
    NODES,
    PLC_PARAM,
    SEGMENT_NAME_CANOPEN,
    GlobalSet,
    PlcParam,
)
from dbm_tools.validate import check_dbm
from dpm.commands import (
    DIRECTORY_ENTRY,
    LOAD_CHUNK,
    LOAD_FIRST_LENGTH,
    LOAD_ROOT_BYTES,
    LOAD_SEGMENT,
    MODE_DELETE,
    MODE_DIRECTORY,
    MODE_DOWNLOAD,
    MODE_UPLOAD,
)
from dpm.errors import ERR_EVENT_OF_DATA_CHECK, ERR_NODE_DEVICE, DeviceEvent, RcsF
from dpm.image import CardDirectory
from dpm.message import Ext, Message
from dpm.task2 import ComPlcParameter, GlobalBits

if TYPE_CHECKING:
    from firmware.card import Card

log = logging.getLogger(__name__)

FLASH_ENV = "CIFEMU_FLASH_DIR"
DATABASE_FILE = "database.bin"
DATABASE_MODE = 0o640


def default_flash_dir(board: int) -> Path:
    """``$CIFEMU_FLASH_DIR/board<N>``, else the user's data directory (platformdirs)."""
    root = os.environ.get(FLASH_ENV)
    base = Path(root) if root else Path(platformdirs.user_data_dir("cifemu")) / "flash"
    return base / f"board{board}"


class FlashStore:
    """One board's flash directory: read, replace atomically, erase.

    ``UnsafePathError`` when the directory or the stored database is not the
    firmware user's own (docs/security.md)."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self._files = CardDirectory(directory, create=True, private=True)
        try:
            for name in self._files.names():
                if name.startswith(f".{DATABASE_FILE}.") and name.endswith(".tmp"):
                    self._files.unlink(name)  # a store interrupted by a kill: never renamed
            self.read()  # a database that is no regular file of ours is refused at the start
        except BaseException:
            self._files.close()
            raise

    def close(self) -> None:
        self._files.close()

    @property
    def path(self) -> Path:
        return self.directory / DATABASE_FILE

    def read(self) -> bytes | None:
        return self._files.read(DATABASE_FILE)

    def stored_at(self) -> float | None:
        try:
            return os.stat(DATABASE_FILE, dir_fd=self._files.fd, follow_symlinks=False).st_mtime
        except FileNotFoundError:
            return None

    def store(self, area: bytes) -> None:
        """Replace the database: the old one stays whole until the new one is on disk."""
        self._files.replace(DATABASE_FILE, area, DATABASE_MODE, durable=True)

    def erase(self) -> None:
        self._files.unlink(DATABASE_FILE)
        self._files.sync()


def _segment_name(area: bytes) -> str | None:
    """GLOBAL's szSegmentName, or None when the data area is no readable DBM."""
    try:
        dbm = read_data_area(area)
    except DbmError:
        return None
    table = dbm.table(GLOBAL)
    if table is None or dbm.table_number(GLOBAL) != FIRST_TABLE or len(table.records) != 1:
        return None
    try:
        return GlobalSet.decode(table.records[0]).szSegmentName
    except DbmError:
        return None


# --- the load function ---------------------------------------------------------------------


@dataclass
class _Download:
    length: int
    root: bytes
    next_nr: int
    data: bytearray = field(default_factory=bytearray)


@dataclass
class _Upload:
    data: bytes
    next_nr: int
    position: int = 0


class LoadFunction:
    """msg.b 6 of the RCS task: download, upload, delete and list the stored database."""

    def __init__(self, store: FlashStore, on_delete: Callable[[], None]) -> None:
        self.store = store
        self._on_delete = on_delete
        """Called after a delete: the card withdraws RUN (``RcsTask``)."""
        self._download: _Download | None = None
        self._upload: _Upload | None = None

    def abort(self) -> None:
        """Forget an unfinished transfer (a start, or a new command)."""
        self._download = None
        self._upload = None

    def handle(self, msg: Message) -> Message:
        sequence = msg.e & Ext.SEQ_MASK
        if sequence in (Ext.CONT, Ext.LAST):
            if self._download is not None:
                return self._continue_download(msg, sequence == Ext.LAST)
            if self._upload is not None:
                return self._continue_upload(msg)
            return msg.answer(f=RcsF.WRONG_SEQUENCE)
        self.abort()
        if not msg.data:
            return msg.answer(f=RcsF.PARAMETER_FAULT)
        mode = msg.data[0]
        if mode in (MODE_DOWNLOAD, MODE_UPLOAD) and sequence != Ext.FIRST:
            return msg.answer(f=RcsF.WRONG_SEQUENCE)
        if mode == MODE_DOWNLOAD:
            return self._first_download(msg)
        if mode == MODE_UPLOAD:
            return self._first_upload(msg)
        if mode == MODE_DELETE:
            return self._delete(msg)
        if mode == MODE_DIRECTORY:
            return self._directory(msg)
        return msg.answer(f=RcsF.PARAMETER_FAULT)

    # download

    def _first_download(self, msg: Message) -> Message:
        if msg.ln != LOAD_FIRST_LENGTH:
            return msg.answer(f=RcsF.WRONG_SIZE)
        root = msg.data[1 : 1 + LOAD_ROOT_BYTES]
        try:
            name = GlobalSet.decode(msg.data[1 + LOAD_ROOT_BYTES :]).szSegmentName
        except DbmError:
            name = None
        if name != SEGMENT_NAME_CANOPEN:
            log.info("download refused: segment name %r is not %r", name, SEGMENT_NAME_CANOPEN)
            return msg.answer(f=RcsF.DB_NOT_VALID)
        words = struct.unpack("<8H", root)
        length = 2 * words[5]
        if words[5] != words[6] or not 2 * ROOT_WORDS <= length <= MAX_DATA_AREA:
            return msg.answer(f=RcsF.WRONG_SIZE)
        self._download = _Download(length, root, (msg.nr + 1) & 0xFF)
        return msg.answer()

    def _continue_download(self, msg: Message, last: bool) -> Message:
        download = self._download
        assert download is not None
        if msg.nr != download.next_nr:
            self.abort()
            return msg.answer(f=RcsF.WRONG_MESSAGE_NUMBER)
        remaining = download.length - len(download.data)
        fits = msg.ln == remaining if last else msg.ln == LOAD_CHUNK and remaining > LOAD_CHUNK
        if not fits:
            self.abort()
            return msg.answer(f=RcsF.WRONG_SIZE)
        download.data += msg.data
        download.next_nr = (msg.nr + 1) & 0xFF
        if not last:
            return msg.answer()
        self.abort()
        area = bytes(download.data)
        words = struct.unpack(f"<{len(area) // 2}H", area)
        (first_w0,) = struct.unpack_from("<H", download.root)
        if words[0] != first_w0 or sum(words[1:]) & 0xFFFF != first_w0:
            return msg.answer(f=RcsF.CHECKSUM)
        if area[2:LOAD_ROOT_BYTES] != download.root[2:]:
            return msg.answer(f=RcsF.WRONG_SIZE)
        if _segment_name(area) != SEGMENT_NAME_CANOPEN:
            return msg.answer(f=RcsF.DB_NOT_VALID)
        try:
            self.store.store(area)
        except OSError as exc:
            log.error("database not stored in %s: %s", self.store.directory, exc.strerror)
            return msg.answer(f=RcsF.FLASH_FULL)
        log.info("database of %d bytes stored in %s", len(area), self.store.path)
        return msg.answer()

    # upload

    def _first_upload(self, msg: Message) -> Message:
        data = self.store.read()
        if data is None:
            return msg.answer(f=RcsF.NO_DATABASE)
        self._upload = _Upload(data, msg.nr)
        return self._next_piece(msg, first=True)

    def _continue_upload(self, msg: Message) -> Message:
        upload = self._upload
        assert upload is not None
        if msg.nr != upload.next_nr:
            self.abort()
            return msg.answer(f=RcsF.WRONG_MESSAGE_NUMBER)
        return self._next_piece(msg, first=False)

    def _next_piece(self, msg: Message, first: bool) -> Message:
        upload = self._upload
        assert upload is not None
        piece = upload.data[upload.position : upload.position + LOAD_CHUNK]
        upload.position += len(piece)
        upload.next_nr = (msg.nr + 1) & 0xFF
        if upload.position >= len(upload.data):
            self.abort()
            return msg.answer(data=piece, e=Ext.LAST)
        return msg.answer(data=piece, e=Ext.FIRST if first else Ext.CONT)

    # delete, directory

    def _delete(self, msg: Message) -> Message:
        if msg.ln < 2 or msg.data[1] != LOAD_SEGMENT:
            return msg.answer(f=RcsF.PARAMETER_FAULT)
        self.store.erase()
        log.info("database deleted from %s", self.store.path)
        self._on_delete()
        return msg.answer(data=bytes([MODE_DELETE]))

    def _directory(self, msg: Message) -> Message:
        data = self.store.read()
        stored = self.store.stored_at()
        if data is None or stored is None:
            return msg.answer(data=bytes([MODE_DIRECTORY, 0]))
        name = (_segment_name(data) or "").encode("latin-1")
        (w0,) = struct.unpack_from("<H", data) if len(data) >= 2 else (0,)
        entry = DIRECTORY_ENTRY.pack(LOAD_SEGMENT, name, len(data) & 0xFFFF, w0, int(stored))
        return msg.answer(data=bytes([MODE_DIRECTORY, 1]) + entry)


# --- start-up from flash -------------------------------------------------------------------


@dataclass
class StoredDatabase:
    """The database found in flash at a start, with the checks' verdict.

    ``faults`` holds the Err_Node_adr and Err_Event each failed check reports (255 with 56
    or 60 for a bad baud rate or a double address, else 212 at 255 or at the node of a NODES
    record) with what failed; a faulty database is not used.
    """

    dbm: DbmFile | None
    faults: list[tuple[int, int, str]]
    raw: bytes = b""
    """The flash's bytes as read: a later start that reads the same takes this reading."""
    _node_sets: list[tuple[int, bytes, NodeParameterSet]] | None = field(
        default=None, repr=False, compare=False)

    @classmethod
    def load(cls, store: FlashStore, previous: StoredDatabase | None = None
             ) -> StoredDatabase | None:
        """None when the flash is empty; ``previous`` (the last start's reading) when the
        flash holds the same bytes: nothing is checked or decoded twice (its data sets are
        never changed by the card, ``node_sets``)."""
        raw = store.read()
        if raw is None:
            return None
        if previous is not None and previous.raw == raw:
            return previous
        try:
            dbm = read_data_area(raw)
        except DbmError as exc:
            return cls(None, [(ERR_NODE_DEVICE, DeviceEvent.FAULTY_DATABASE,
                               f"unreadable: {exc}")], raw)
        nodes = dbm.table(NODES)
        faults: list[tuple[int, int, str]] = []
        for finding in check_dbm(dbm, warnings=False):
            if finding.severity != "error":
                continue
            node = ERR_NODE_DEVICE
            event = ERR_EVENT_OF_DATA_CHECK.get(finding.number)
            if event is None:
                event = DeviceEvent.FAULTY_DATABASE
                if finding.table == NODES and nodes is not None and finding.record is not None:
                    node = nodes.records[finding.record - 1][0]
            faults.append((node, event, f"{finding.number} {finding.text}: {finding.table} record "
                                 f"{finding.record} {finding.field}: {finding.detail}"))
        return cls(dbm, faults, raw)

    def node_sets(self) -> list[tuple[int, bytes, NodeParameterSet]]:
        """NODES as (address, data set, decoded), decoded at the first start that uses them
        (``check_dbm`` checked them at ``load``). The decoded sets go to the node handlers of
        every start that reads these bytes: the card only reads them."""
        if self._node_sets is None:
            nodes = self.dbm.table(NODES) if self.dbm is not None else None
            self._node_sets = [(record[0], record[1:], NodeParameterSet.decode(record[1:]))
                               for record in (nodes.records if nodes is not None else [])]
        return self._node_sets

    def _record(self, name: str) -> bytes | None:
        table = self.dbm.table(name) if self.dbm is not None else None
        return table.records[0] if table is not None and table.records else None

    def _global(self) -> GlobalSet:
        record = self._record(GLOBAL)
        assert record is not None  # check_dbm insists on it
        return GlobalSet.decode(record)

    @property
    def usable(self) -> bool:
        return self.dbm is not None and not self.faults

    @property
    def waits_for_host(self) -> bool:
        """GLOBAL bSystemStart != 0: the bus starts when the host clears NOTREADY."""
        return self.usable and self._global().bSystemStart != 0

    def protocol_parameters(self) -> ComPlcParameter:
        """A cold start's protocol parameters: PLC_PARAM's bMode, GLOBAL's supervision time.

        [ours] usHostWatchdogValue overrides PLC_PARAM's usWatchDogTime (seed
        6.2.1 calls it the supervision time); a faulty database gives the
        firmware defaults.
        """
        parameter = ComPlcParameter()
        if not self.usable:
            return parameter
        plc = self._record(PLC_PARAM)
        if plc is not None:
            parameter.bMode = PlcParam.decode(plc).bMode
        parameter.usWatchDogTime = self._global().usHostWatchdogValue
        return parameter

    def descript_records(self) -> dict[int, bytes] | None:
        """DESCRIPT records by station address, for GET_CONFIGURATION; None: no table."""
        table = self.dbm.table(DESCRIPT) if self.usable and self.dbm is not None else None
        if table is None:
            return None
        return {record[0]: record for record in table.records if record}

    def configure(self, device: Card) -> None:
        """Hand the data sets to the CAN task, or report why the database is not used."""
        for node, event, what in self.faults:
            log.warning("stored database not used: %s", what)
            device.report_error(node, event, GlobalBits.CTRL)
        if not self.usable:
            return
        can = device.can
        ext = self._record(BUS_CAN_EXT)
        if ext is not None and self._refused(device, ERR_NODE_DEVICE, BUS_CAN_EXT,
                                             can.download_extended(ext)):
            return
        for address, data, params in self.node_sets():
            if self._refused(device, address, NODES, can.take_node(address, data, params)):
                return
        bus = self._record(BUS_CAN)
        assert bus is not None  # check_dbm insists on it
        if not self._refused(device, ERR_NODE_DEVICE, BUS_CAN, can.download_bus(bus)):
            can.from_flash = True  # flash ranks above the on-line download (seed 5.2.2)

    @staticmethod
    def _refused(device: Card, node: int, table: str, f: int) -> bool:
        if f == 0:
            return False
        log.warning("stored database not used: the CAN task refused %s (node %d) with f %d",
                    table, node, f)
        device.report_error(node, DeviceEvent.FAULTY_DATABASE, GlobalBits.CTRL)
        return True

