"""The DBM container against SyCon's real file and against files we build."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from dbm_tools.container import (
    FILE_HEADER_SIZE,
    MAX_DATA_AREA,
    MAX_TABLES,
    TOOL_DATE,
    DbmFile,
    DbmTable,
    data_area,
    load_dbm,
    read_data_area,
    read_dbm,
    save_dbm,
    write_dbm,
)
from dbm_tools.errors import DbmError
from tests.fixtures import REAL_DBM, real_dbm_bytes

REAL_TABLES = [
    "GLOBAL",
    "BUS_DP",
    "SL_DP",
    "PLC_PARAM",
    "PROJEKT",
    "KBL_HEADER",
    "KBL",
    "ALI-SETUP",
    "OBJ-DEF",
    "ALI_CLIENT",
    "ALI_SERVER",
    "ST_OV_0",
    "DESCRIPT",
]


def words(area: bytes) -> list[int]:
    return list(struct.unpack(f"<{len(area) // 2}H", area))


def reseal(area: bytes) -> bytes:
    """Recompute w0 so that a deliberately broken data area fails later than the checksum."""
    return struct.pack("<H", sum(words(area)[1:]) & 0xFFFF) + area[2:]


@pytest.fixture(scope="module")
def real() -> bytes:
    return real_dbm_bytes()


def sample_file() -> DbmFile:
    return DbmFile(
        [
            DbmTable("GLOBAL", [b"CANopen \0" + bytes(25)]),
            DbmTable("ODD", [b"abc", b"", b"hello"], pad_bytes={2: 0x54}),
            DbmTable("EMPTY"),
            DbmTable("NODES", [bytes([9, 1, 2]), bytes([3, 4]), bytes([200])], key_length=1),
            DbmTable("WIDE", [b"\x02\x01x", b"\x01\x02y", b"\x01\x01z"], key_length=2),
        ]
    )


# --- the real SyCon file -------------------------------------------------------------------


def test_real_file_reads_completely(real: bytes) -> None:
    dbm = read_dbm(real)
    assert [t.name for t in dbm.tables] == REAL_TABLES
    assert len(dbm.tables) == 13
    assert dbm.date == "Mar  9 2000"
    assert dbm.header_unknown_34 == 0x0B58
    assert dbm.root_unknown_w4 == 0x7EF4
    glob = dbm.table("GLOBAL")
    assert glob is not None
    assert glob.records[0].startswith(b"PB_COMBI\0")
    assert glob.records[0][32:34] == (1000).to_bytes(2, "little")


def test_real_file_checksum_w0(real: bytes) -> None:
    area = real[FILE_HEADER_SIZE:]
    assert words(area)[0] == sum(words(area)[1:]) & 0xFFFF == 0x207C


def test_real_file_table_shapes(real: bytes) -> None:
    dbm = read_dbm(real)
    numbers = {t.name: dbm.table_number(t.name) for t in dbm.tables}
    assert numbers["GLOBAL"] == 8
    assert numbers["DESCRIPT"] == 32
    keyed = {t.name: t.key_length for t in dbm.tables if t.keyed}
    assert keyed == {"KBL": 4, "OBJ-DEF": 2, "ALI_CLIENT": 1, "ALI_SERVER": 1, "ST_OV_0": 2}
    counts = {t.name: len(t.records) for t in dbm.tables}
    assert counts["ST_OV_0"] == 9
    assert counts["KBL"] == counts["OBJ-DEF"] == 0
    sizes = {t.name: [len(r) for r in t.records] for t in dbm.tables}
    assert sizes["GLOBAL"] == [34]
    assert sizes["PLC_PARAM"] == [4]
    assert sizes["PROJEKT"] == [234]
    assert sizes["DESCRIPT"] == [129]
    # SyCon leaves garbage in some pad bytes; we keep it to write the file back unchanged
    bus_dp = dbm.table("BUS_DP")
    assert bus_dp is not None
    assert bus_dp.pad_bytes == {0: 0x54}


def test_real_file_rewrites_identically(real: bytes) -> None:
    assert write_dbm(read_dbm(real)) == real


def test_real_data_area(real: bytes) -> None:
    dbm = read_dbm(real)
    assert data_area(dbm) == real[FILE_HEADER_SIZE:]
    bare = read_data_area(real[FILE_HEADER_SIZE:])
    assert bare.tables == dbm.tables
    assert bare.root_unknown_w4 == dbm.root_unknown_w4
    assert bare.date == TOOL_DATE
    assert bare.header_unknown_34 == 0


def test_real_file_checksum_mismatch(real: bytes) -> None:
    broken = bytearray(real)
    broken[-1] ^= 0x01
    with pytest.raises(DbmError, match="checksum"):
        read_dbm(bytes(broken))


def test_load_and_save(tmp_path: Path, real: bytes) -> None:
    dbm = load_dbm(REAL_DBM)
    target = tmp_path / "copy.dbm"
    save_dbm(target, dbm)
    assert target.read_bytes() == real


# --- files we build ------------------------------------------------------------------------


def test_new_file_round_trip() -> None:
    dbm = sample_file()
    raw = write_dbm(dbm)
    again = read_dbm(raw)
    assert again == dbm
    assert write_dbm(again) == raw


def test_new_file_layout() -> None:
    raw = write_dbm(sample_file())
    assert raw[:10] == b"DBMFILE  \0"
    assert raw[10:22] == TOOL_DATE.encode() + b"\0"
    size, one, unknown, length, start = struct.unpack_from("<HHIHI", raw, 30)
    assert (size, one, unknown, length, start) == (44, 1, 0, len(raw) - 44, 44)
    root = words(raw[44:])
    assert root[0] == sum(root[1:]) & 0xFFFF
    assert root[1:8] == [0, 12, 5, 0, length // 2, length // 2, 1]
    # NODES is table 14: a key index, then the directory right after it
    assert root[14] and root[15] and root[15] < root[14]
    assert root[9] == root[11] == root[13] == 0
    assert not any(root[8 + 2 * 5 : 208])


def test_key_index_in_key_order() -> None:
    raw = write_dbm(sample_file())
    area = raw[44:]
    root = words(area)
    index_block = words(area[2 * root[15] : 2 * root[14]])
    assert index_block[:6] == [2, 0, 0, 15, 0, 74]
    assert index_block[6:10] == [2, 1, 3, 0]  # keys 3, 9, 200
    wide = words(area[2 * root[17] : 2 * root[16]])
    # keys compare as little-endian numbers 0x0102, 0x0201, 0x0101, not byte-wise
    assert wide[6:10] == [3, 1, 2, 0]


def test_odd_record_pads_and_block_header() -> None:
    raw = write_dbm(sample_file())
    area = raw[44:]
    root = words(area)
    directory = words(area[2 * root[10] : 2 * root[10] + 74])
    assert directory[:6] == [1, 0, 0, 10, 0, 74]
    first = 2 * directory[7]
    assert words(area[first : first + 12]) == [0, 0, 10, 7, 1, 16]
    assert area[first + 12 : first + 16] == b"abc\0"
    third = 2 * directory[9]
    assert words(area[third : third + 12]) == [0, 0, 10, 9, 1, 18]
    assert area[third + 12 : third + 18] == b"hello\x54"


def test_empty_database() -> None:
    dbm = DbmFile([])
    raw = write_dbm(dbm)
    assert len(raw) == 44 + 416
    assert read_dbm(raw) == dbm


def test_more_than_30_records_round_trip() -> None:
    records = [bytes([address]) + bytes(range(address % 7)) for address in range(127, 0, -1)]
    dbm = DbmFile([DbmTable("GLOBAL", [bytes(34)]), DbmTable("NODES", records, key_length=1)])
    raw = write_dbm(dbm)
    again = read_dbm(raw)
    assert again == dbm
    assert write_dbm(again) == raw
    area = raw[44:]
    root = words(area)
    directory = words(area[2 * root[10] : 2 * root[10] + 12 + 2 * 128])
    assert directory[5] == 12 + 2 * 128
    descriptor = words(area[2 * directory[6] : 2 * directory[6] + 26])
    assert descriptor[6:13] == [0x11, 127, 0xFFFF, 127, 0, 127, 127]
    key_index = words(area[2 * root[11] : 2 * root[11] + 12 + 2 * 128])
    assert key_index[6:] == [*range(127, 0, -1), 0]


def test_table_number_lookup() -> None:
    dbm = sample_file()
    assert dbm.table_number("NODES") == 14
    assert dbm.table("nope") is None
    with pytest.raises(DbmError):
        dbm.table_number("nope")


# --- writer refusals -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "tables",
    [
        [DbmTable("")],
        [DbmTable("A"), DbmTable("A")],
        [DbmTable("X" * 18)],
        [DbmTable("NAME\0")],
        [DbmTable("\u20ac")],
        [DbmTable("K", [b"\x01"], key_length=16)],
        [DbmTable("K", [b"\x01"], key_length=2)],
        [DbmTable("P", [b"\x01"], pad_bytes={0: 256})],
        [DbmTable(f"T{i}") for i in range(MAX_TABLES + 1)],
        [DbmTable("BIG", [bytes(MAX_DATA_AREA)])],
    ],
)
def test_writer_refuses(tables: list[DbmTable]) -> None:
    with pytest.raises(DbmError):
        write_dbm(DbmFile(tables))


def test_writer_refuses_long_date() -> None:
    with pytest.raises(DbmError):
        write_dbm(DbmFile([], date="Mar  9 2000 12:00"))


def test_most_tables() -> None:
    dbm = DbmFile([DbmTable(f"T{i}", [b"x"], key_length=1) for i in range(MAX_TABLES)])
    assert read_dbm(write_dbm(dbm)) == dbm


# --- reader refusals -----------------------------------------------------------------------


def patched(raw: bytes, offset: int, value: bytes) -> bytes:
    """Overwrite data-area bytes at `offset` and reseal w0, so the later checks are reached."""
    area = bytearray(raw[44:])
    area[offset : offset + len(value)] = value
    return raw[:44] + reseal(bytes(area))


@pytest.mark.parametrize(
    ("offset", "value", "reason"),
    [
        (2, b"\x01\x00", "root words"),  # w1
        (6, b"\x0e\x00", "root slots"),  # w3: one table too many
        (8 + 2 * 200, b"\x01\x00", "root slots"),  # a pointer in an unused root slot
        (16, b"\xd1\x00", "directory at word"),  # slot 8 points one word late
        (2 * 208, b"\x02\x00", "block at word"),  # GLOBAL's directory typed as key index
        (2 * 208 + 8, b"\x01\x00", "pad count"),  # pad on a directory
        (2 * 208 + 10, b"\x4c\x00", "descriptor not at word"),  # directory one word longer
        (2 * 208 + 12, b"\xf6\x00", "descriptor not at word"),
        (2 * 208 + 16, b"\x01\x00", "unused directory slot"),
        (2 * 245 + 12, b"\x11\x00", "descriptor f0"),  # GLOBAL claims a key
        (2 * 245 + 16, b"\x00\x00", "descriptor words"),  # f2
        (2 * 245 + 24, b"\x1f\x00", "descriptor words"),  # f6
        (2 * 245 + 26, b"G" * 18, "NUL terminated"),
        (2 * 245 + 26, b"\0" * 18, "empty table name"),
        (2 * 245 + 26, b"GLOBAL\0X", "not NUL padded"),
        # f1 = f3 = f5 = f6 = 31 records, but a 30-slot directory
        (2 * 245 + 14, b"\x1f\x00\xff\xff\x1f\x00\x00\x00\x1f\x00\x1f\x00", "directory size"),
        (2 * 267 + 10, b"\x30\x00", "expected"),  # a longer record hides the next directory
        (2 * 267 + 10, b"\x2f\x00", "bad length"),  # odd block length
        (2 * 267 + 10, b"\x0a\x00", "bad length"),  # shorter than its header
        (2 * 795 + 12, b"\x01\x00", "key index"),  # KBL's empty key index lists slot 1
        (2 * 1287 + 12, b"\x02\x00\x01\x00", "key index"),  # ST_OV_0 slots 1 and 2 swapped
        # key index names neither its table (30, docs/dbm.md) nor its root slot (31, the file)
        (2 * 1287 + 6, b"\x20\x00", "block at word"),
    ],
)
def test_reader_refuses_damaged_fixture(
    real: bytes, offset: int, value: bytes, reason: str
) -> None:
    with pytest.raises(DbmError, match=reason):
        read_dbm(patched(real, offset, value))


def test_reader_refuses_key_shorter_than_record() -> None:
    raw = write_dbm(DbmFile([DbmTable("K", [b"ab"], key_length=2)]))
    root = words(raw[44:])
    descriptor = words(raw[44 + 2 * root[8] : 44 + 2 * root[8] + 14])[6]
    damaged = patched(raw, 2 * descriptor + 12, b"\x13\x00")  # key length 3 > record length 2
    with pytest.raises(DbmError, match="shorter than its key"):
        read_dbm(damaged)


def test_reader_refuses_duplicate_names() -> None:
    raw = write_dbm(DbmFile([DbmTable("A"), DbmTable("B")]))
    root = words(raw[44:])
    second_directory = 2 * root[10]
    descriptor = words(raw[44 + second_directory : 44 + second_directory + 14])[6]
    with pytest.raises(DbmError, match="duplicate"):
        read_dbm(patched(raw, 2 * descriptor + 26, b"A\0"))


@pytest.mark.parametrize(
    ("offset", "value", "reason"),
    [
        (0, b"DBMFILE! \0", "magic"),
        (21, b"X", "date"),
        (22, b"\x01", "22..29"),
        (30, b"\x2d\x00", "file header words"),
        (32, b"\x02\x00", "file header words"),
        (40, b"\x2e\x00\x00\x00", "file header words"),
        (38, b"\x84\x0d", "header says"),
    ],
)
def test_reader_refuses_damaged_header(real: bytes, offset: int, value: bytes, reason: str) -> None:
    damaged = real[:offset] + value + real[offset + len(value) :]
    with pytest.raises(DbmError, match=reason):
        read_dbm(damaged)


@pytest.mark.parametrize("size", [0, 10, 43, 44, 44 + 414, 3501])
def test_reader_refuses_truncated(real: bytes, size: int) -> None:
    with pytest.raises(DbmError):
        read_dbm(real[:size])


def test_reader_refuses_trailing_bytes(real: bytes) -> None:
    area = real[44:] + b"\0\0"
    length = len(area) // 2
    area = area[:10] + struct.pack("<HH", length, length) + area[14:]
    with pytest.raises(DbmError, match="after the last block"):
        read_data_area(reseal(area))


@pytest.mark.parametrize("size", [0, 415, 417, MAX_DATA_AREA + 2])
def test_data_area_sizes(size: int) -> None:
    with pytest.raises(DbmError, match="impossible"):
        read_data_area(bytes(size))
