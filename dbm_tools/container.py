"""The DBM container: file header, root block, and the per-table blocks (docs/dbm.md section 1).

The writer derives every pointer, length, pad, count, key index and the root
checksum w0 from the tables, so a from-scratch `DbmFile([...])` and a file read
from disk go through the same code. Only values whose meaning is unknown and
which differ from our own choice in real files are kept in the model (the u32
at file offset 34, root word w4, the garbage in pad bytes); with them,
re-writing SyCon's file reproduces it byte for byte.

The reader is strict: it accepts exactly the layout the writer produces (both
the SyCon form with 30 record slots and our form for more than 30 records),
and any other byte sequence raises DbmError. Words the sample shows as
constants (w1 0, w2 12, w7 1, header words 44 and 1, descriptor f2 0xFFFF and
f4 0) are checked, not stored.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

from dbm_tools._binary import decode_text, encode_text, pack, unpack
from dbm_tools.errors import DbmError

FILE_MAGIC = b"DBMFILE  \0"
FILE_HEADER_SIZE = 44
DATE_SIZE = 12
ROOT_WORDS = 208
BLOCK_HEADER_SIZE = 12
TABLE_NAME_SIZE = 18
RECORD_SLOTS = 30
"""Record slots of a SyCon directory; tables with more records get one slot per record [ours]."""
FIRST_TABLE = 8
"""Root slot of the first table: GLOBAL, where drivers look for it."""
MAX_TABLES = (ROOT_WORDS - FIRST_TABLE) // 2
MAX_DATA_AREA = 0xFFFE
"""The file header stores the data-area length in a u16 (offset 38), word aligned."""
MAX_KEY_LENGTH = 0x0F

TOOL_DATE = "Nov 22 2026"
"""Written into new file headers, like the C __DATE__ of the SyCon dbm32.dll build."""

BLOCK_RECORD = 0
BLOCK_DIRECTORY = 1
BLOCK_KEY_INDEX = 2
BLOCK_DESCRIPTOR = 4

_DESCRIPTOR_KEYED = 0x10
_DESCRIPTOR_F2 = 0xFFFF
_DESCRIPTOR_SIZE = 14 + TABLE_NAME_SIZE
_DESCRIPTOR_SLOT_POSITION = 6
"""A block's position field is the word of its pointer in the parent: 6 header words + slot."""
_ROOT_W2 = 12
_ROOT_W7 = 1
_HEADER_W32 = 1


@dataclass
class DbmTable:
    """One table: its name and records, in slot order.

    `key_length` is 0 for a plain table; for a keyed table the first
    `key_length` bytes of each record are its key (NODES: the node address).
    `pad_bytes` maps a record's list index to the byte SyCon left in the pad
    of an odd-length record (it is not always 0); absent entries write 0.
    """

    name: str
    records: list[bytes] = field(default_factory=list)
    key_length: int = 0
    pad_bytes: dict[int, int] = field(default_factory=dict)

    @property
    def keyed(self) -> bool:
        """Keyed tables carry a key-index block and descriptor f0 0x10 | key length."""
        return self.key_length > 0

    @property
    def slot_count(self) -> int:
        """Descriptor f6: 30 as SyCon writes, or one slot per record beyond that [ours]."""
        return max(RECORD_SLOTS, len(self.records))

    def key_order(self) -> list[int]:
        """1-based record slots sorted by key, as the key-index block lists them.

        Keys compare as little-endian unsigned numbers (they are u8/u16 fields
        in all known tables); equal keys keep slot order.
        """
        return [
            slot + 1
            for slot in sorted(
                range(len(self.records)),
                key=lambda i: int.from_bytes(self.records[i][: self.key_length], "little"),
            )
        ]


@dataclass
class DbmFile:
    """A whole DBM file; `DbmFile([tables...])` is also how a new file is built.

    Tables are in creation order, which fixes their numbers (8, 10, 12, ...).
    `header_unknown_34` (file offset 34) and `root_unknown_w4` are kept from
    files read from disk and are 0 in new files [ours]; `date` is the tool
    date string of the file header, which a bare data area does not have.
    """

    tables: list[DbmTable]
    date: str = TOOL_DATE
    header_unknown_34: int = 0
    root_unknown_w4: int = 0

    def table(self, name: str) -> DbmTable | None:
        """Tables are found by name, as dbm_get_num does on the card."""
        return next((t for t in self.tables if t.name == name), None)

    def table_number(self, name: str) -> int:
        """The root slot of the table's directory; GLOBAL must be 8."""
        for index, table in enumerate(self.tables):
            if table.name == name:
                return FIRST_TABLE + 2 * index
        raise DbmError("no such table", table=name)


# --- writing ---------------------------------------------------------------------------------


def _block(kind: int, parent: int, position: int, payload: bytes, pad_byte: int = 0) -> bytes:
    pad = len(payload) % 2
    length = BLOCK_HEADER_SIZE + len(payload) + pad
    header = pack("6H", kind, 0, parent, position, pad, length, what="block header")
    return header + payload + (pack("B", pad_byte, what="pad byte") if pad else b"")


def _words(values: list[int], what: str) -> bytes:
    return pack(f"{len(values)}H", *values, what=what)


def _check_table(table: DbmTable, names: set[str]) -> None:
    if not table.name:
        raise DbmError("empty table name")
    if table.name in names:
        raise DbmError("duplicate table name", table=table.name)
    if not 0 <= table.key_length <= MAX_KEY_LENGTH:
        raise DbmError(
            f"key length must be 0..{MAX_KEY_LENGTH}", table=table.name, field="key_length"
        )
    for index, record in enumerate(table.records):
        if len(record) < table.key_length:
            raise DbmError("record shorter than its key", table=table.name, record=index + 1)
    for index, value in table.pad_bytes.items():
        if not 0 <= value <= 0xFF:
            raise DbmError("pad byte out of range", table=table.name, record=index + 1)


def data_area(dbm: DbmFile) -> bytes:
    """The bytes a card stores and receives: root block and table blocks, no file header.

    Raises DbmError for tables the container cannot hold (names, keys, sizes).
    """
    if len(dbm.tables) > MAX_TABLES:
        raise DbmError(f"more than {MAX_TABLES} tables")
    names: set[str] = set()
    root = [0] * ROOT_WORDS
    blocks: list[bytes] = []
    position = ROOT_WORDS

    def add(block: bytes) -> int:
        nonlocal position
        start = position
        blocks.append(block)
        position += len(block) // 2
        return start

    for index, table in enumerate(dbm.tables):
        _check_table(table, names)
        names.add(table.name)
        number = FIRST_TABLE + 2 * index
        slots = table.slot_count
        count = len(table.records)
        if table.keyed:
            index_words = table.key_order() + [0] * (slots + 1 - count)
            root[number + 1] = add(
                _block(BLOCK_KEY_INDEX, 0, number + 1, _words(index_words, "key index"))
            )
        directory_size = (BLOCK_HEADER_SIZE + 2 * (slots + 1)) // 2
        descriptor_at = position + directory_size
        record_at = descriptor_at + (BLOCK_HEADER_SIZE + _DESCRIPTOR_SIZE) // 2
        directory = [descriptor_at]
        record_blocks = []
        for slot, record in enumerate(table.records, start=1):
            block = _block(
                BLOCK_RECORD,
                number,
                _DESCRIPTOR_SLOT_POSITION + slot,
                record,
                table.pad_bytes.get(slot - 1, 0),
            )
            directory.append(record_at)
            record_at += len(block) // 2
            record_blocks.append(block)
        directory += [0] * (slots + 1 - len(directory))
        root[number] = add(_block(BLOCK_DIRECTORY, 0, number, _words(directory, "directory")))
        f0 = _DESCRIPTOR_KEYED | table.key_length if table.keyed else 0
        descriptor = _words(
            [f0, count, _DESCRIPTOR_F2, count, 0, count, slots], "descriptor"
        ) + encode_text(table.name, TABLE_NAME_SIZE - 1, "table name").ljust(TABLE_NAME_SIZE, b"\0")
        add(_block(BLOCK_DESCRIPTOR, number, _DESCRIPTOR_SLOT_POSITION, descriptor))
        for block in record_blocks:
            add(block)

    if 2 * position > MAX_DATA_AREA:
        raise DbmError(f"data area of {2 * position} bytes exceeds {MAX_DATA_AREA}")
    root[1:8] = [0, _ROOT_W2, len(dbm.tables), dbm.root_unknown_w4, position, position, _ROOT_W7]
    body = _words(root[1:], "root block") + b"".join(blocks)
    checksum = sum(struct.unpack(f"<{len(body) // 2}H", body)) & 0xFFFF
    return pack("H", checksum, what="w0") + body


def write_dbm(dbm: DbmFile) -> bytes:
    """A complete DBM file: the 44-byte file header followed by the data area (DbmError as
    ``data_area``)."""
    area = data_area(dbm)
    header = (
        FILE_MAGIC
        + encode_text(dbm.date, DATE_SIZE - 1, "date").ljust(DATE_SIZE, b"\0")
        + bytes(8)
        + pack(
            "HHIHI",
            FILE_HEADER_SIZE,
            _HEADER_W32,
            dbm.header_unknown_34,
            len(area),
            FILE_HEADER_SIZE,
            what="file header",
        )
    )
    return header + area


def save_dbm(path: Path, dbm: DbmFile) -> None:
    """Write a DBM file to disk; DbmError as ``write_dbm``, OSError from the file."""
    path.write_bytes(write_dbm(dbm))


# --- reading ---------------------------------------------------------------------------------


@dataclass
class _Block:
    payload: bytes
    pad_byte: int
    words: int


def _read_block(data: bytes, at: int, kind: int, parent: int, position: int, table: str,
                also: int | None = None) -> _Block:
    offset = 2 * at
    btype, zero, bparent, bposition, pad, length = unpack("6H", data, offset, "block header")
    expected = (kind, 0, parent, position)
    if bposition == also:
        bposition = position
    if (btype, zero, bparent, bposition) != expected:
        raise DbmError(
            f"block at word {at}: header {(btype, zero, bparent, bposition)} != {expected}",
            table=table,
        )
    if pad > (1 if kind == BLOCK_RECORD else 0):
        raise DbmError(f"block at word {at}: pad count {pad}", table=table)
    if length % 2 or length < BLOCK_HEADER_SIZE + pad or offset + length > len(data):
        raise DbmError(f"block at word {at}: bad length {length}", table=table)
    end = offset + length - pad
    return _Block(data[offset + BLOCK_HEADER_SIZE : end], data[end] if pad else 0, length // 2)


def _as_words(payload: bytes) -> list[int]:
    return list(struct.unpack(f"<{len(payload) // 2}H", payload))


def _read_table(data: bytes, number: int, keyed: bool, at: int) -> tuple[DbmTable, int]:
    """Read one table's blocks, which must start at word `at`; return it and the next word."""
    where = f"#{number}"
    index_words: list[int] = []
    if keyed:
        if unpack("H", data, 2 * (number + 1), "root slot")[0] != at:
            raise DbmError(f"key index not at word {at}", table=where)
        # The real file names the key index's own root slot (number + 1); a file written
        # by hand may name the table number, which docs/dbm.md allows: both load.
        block = _read_block(data, at, BLOCK_KEY_INDEX, 0, number + 1, where, also=number)
        index_words = _as_words(block.payload)
        at += block.words
    root_pointer = unpack("H", data, 2 * number, "root slot")[0]
    if root_pointer != at:
        raise DbmError(f"directory at word {root_pointer}, expected {at}", table=where)
    block = _read_block(data, at, BLOCK_DIRECTORY, 0, number, where)
    directory = _as_words(block.payload)
    at += block.words
    if not directory or directory[0] != at:
        raise DbmError(f"descriptor not at word {at}", table=where)
    block = _read_block(data, at, BLOCK_DESCRIPTOR, number, _DESCRIPTOR_SLOT_POSITION, where)
    at += block.words
    if len(block.payload) != _DESCRIPTOR_SIZE:
        raise DbmError("descriptor block size", table=where)
    f0, f1, f2, f3, f4, f5, f6 = unpack("7H", block.payload, 0, "descriptor")
    raw_name = block.payload[14:]
    if b"\0" not in raw_name:
        raise DbmError("table name not NUL terminated", table=where)
    name = decode_text(raw_name, "table name")
    if not name:
        raise DbmError("empty table name", table=where)
    count = f1
    key_length = f0 - _DESCRIPTOR_KEYED if keyed else 0
    if not (1 <= key_length <= MAX_KEY_LENGTH if keyed else f0 == 0):
        raise DbmError(f"descriptor f0 {f0:#x} does not match the root slots", table=name)
    if (f2, f3, f4, f5, f6) != (_DESCRIPTOR_F2, count, 0, count, max(RECORD_SLOTS, count)):
        raise DbmError(f"descriptor words {(f0, f1, f2, f3, f4, f5, f6)}", table=name)
    if len(directory) != f6 + 1 or (keyed and len(index_words) != f6 + 1):
        raise DbmError(f"directory size does not match {f6} slots", table=name)
    if any(directory[count + 1 :]):
        raise DbmError("pointer in an unused directory slot", table=name)
    table = DbmTable(name, key_length=key_length)
    for slot in range(1, count + 1):
        if directory[slot] != at:
            raise DbmError(f"record not at word {at}", table=name, record=slot)
        block = _read_block(data, at, BLOCK_RECORD, number, _DESCRIPTOR_SLOT_POSITION + slot, name)
        at += block.words
        if len(block.payload) < key_length:
            raise DbmError("record shorter than its key", table=name, record=slot)
        table.records.append(block.payload)
        if block.pad_byte:
            table.pad_bytes[slot - 1] = block.pad_byte
    if keyed and index_words != table.key_order() + [0] * (f6 + 1 - count):
        raise DbmError("key index not in key order", table=name)
    return table, at


def read_data_area(data: bytes) -> DbmFile:
    """Read a bare data area, as a card stores it and answers an upload with.

    The result has the default file-header fields, since the data area does
    not carry them. Raises DbmError for anything that is no data area.
    """
    data = bytes(data)
    if len(data) < 2 * ROOT_WORDS or len(data) % 2 or len(data) > MAX_DATA_AREA:
        raise DbmError(f"data area length {len(data)} impossible")
    words = _as_words(data)
    if sum(words[1:]) & 0xFFFF != words[0]:
        raise DbmError(f"checksum w0 {words[0]:#06x} does not match the data area", field="w0")
    _, w1, w2, count, w4, w5, w6, w7 = words[:8]
    if (w1, w2, w7) != (0, _ROOT_W2, _ROOT_W7) or w5 != w6 or 2 * w5 != len(data):
        raise DbmError(f"root words {words[:8]} do not describe this data area")
    if count > MAX_TABLES:
        raise DbmError(f"{count} tables")
    slots = words[FIRST_TABLE:ROOT_WORDS]
    if any(slots[2 * count :]) or not all(slots[0 : 2 * count : 2]):
        raise DbmError(f"root slots do not hold {count} tables")
    dbm = DbmFile([], root_unknown_w4=w4)
    at = ROOT_WORDS
    for index in range(count):
        number = FIRST_TABLE + 2 * index
        table, at = _read_table(data, number, words[number + 1] != 0, at)
        if dbm.table(table.name) is not None:
            raise DbmError("duplicate table name", table=table.name)
        dbm.tables.append(table)
    if 2 * at != len(data):
        raise DbmError(f"{len(data) - 2 * at} bytes after the last block")
    return dbm


def read_dbm(file: bytes) -> DbmFile:
    """Read a complete DBM file (file header + data area); DbmError for anything else."""
    file = bytes(file)
    if len(file) < FILE_HEADER_SIZE or not file.startswith(FILE_MAGIC):
        raise DbmError("not a DBM file (magic)")
    raw_date = file[len(FILE_MAGIC) : len(FILE_MAGIC) + DATE_SIZE]
    if b"\0" not in raw_date:
        raise DbmError("date not NUL terminated", field="date")
    date = decode_text(raw_date, "date")
    if any(file[22:30]):
        raise DbmError("file header bytes 22..29 not zero")
    size, w32, unknown_34, length, start = unpack("HHIHI", file, 30, "file header")
    if (size, w32, start) != (FILE_HEADER_SIZE, _HEADER_W32, FILE_HEADER_SIZE):
        raise DbmError(f"file header words {(size, w32, start)}")
    if len(file) != FILE_HEADER_SIZE + length:
        raise DbmError(f"file is {len(file)} bytes, header says {FILE_HEADER_SIZE + length}")
    dbm = read_data_area(file[FILE_HEADER_SIZE:])
    dbm.date = date
    dbm.header_unknown_34 = unknown_34
    return dbm


def load_dbm(path: Path) -> DbmFile:
    """Read a DBM file from disk; DbmError as ``read_dbm``, OSError from the file."""
    return read_dbm(path.read_bytes())
