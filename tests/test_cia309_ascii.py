"""The CiA 309-3 codec: data type byte vectors, request lines of both dialects, answers.

Vectors follow what CANopenNode's gateway (``309/CO_gateway_ascii.c``, ``301/CO_fifo.c``) and
Lely's (``src/co/gw_txt.c``, ``src/co/val.c``) read and print. Pure functions only: no socket.
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Callable
from datetime import datetime

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dpm.cia301 import ABORT_TYPE_LENGTH_MISMATCH
from dpm.cia305 import LssAddress
from host_api.cia309.datatypes import (
    INTEGER_RANGES,
    DataTypeError,
    Dialect,
    format_value,
    parse_data_type,
    parse_integer,
    parse_value,
)
from host_api.cia309.formatters import (
    SDO_ABORT_TEXTS,
    abort_text,
    error_text,
    format_abort,
    format_empty,
    format_error,
    format_event,
    format_help,
    format_lss_address,
    format_lss_node_id,
    format_lss_number,
    format_ok,
    format_pdo_read,
    format_plain_upload,
    format_upload,
    format_value_response,
    format_version,
)
from host_api.cia309.framing import DEFAULT_MAX_LINE, LineFramer, OverlongLine
from host_api.cia309.model import (
    BootUpEvent,
    DataType,
    EmergencyEvent,
    ErrorCode,
    ErrorControlEvent,
    Event,
    NmtState,
    PdoMapping,
    RpdoEvent,
    SdoProgressEvent,
    VersionInfo,
)
from host_api.cia309.parser import (
    _parse_stripped,
    _plain_read,
    _plain_write,
    parse_request,
    plain_read_line,
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

CO = Dialect.CANOPENNODE
LELY = Dialect.LELY
DIALECTS = [CO, LELY]
EXAMPLES = int(os.environ.get("CIFEMU_FUZZ_EXAMPLES", "300"))
FIXED = [dtype for dtype in DataType if dtype.size is not None]
INTEGERS = [
    dtype
    for dtype in FIXED
    if dtype.value[0] in "iux" and dtype not in (DataType.BOOLEAN,)
]


# --------------------------------------------------------------------------- data types

# mnemonic, text written, bytes on the bus, CANopenNode prints, Lely prints
VECTORS = [
    ("b", "0", "00", "0", "0"),
    ("b", "1", "01", "1", "1"),
    ("i8", "-128", "80", "-128", "-128"),
    ("i8", "127", "7f", "127", "127"),
    ("i8", "-0x1", "ff", "-1", "-1"),
    ("i16", "-32768", "0080", "-32768", "-32768"),
    ("i16", "0x7FFF", "ff7f", "32767", "32767"),
    ("i24", "-8388608", "000080", "-8388608", "-8388608"),
    ("i24", "8388607", "ffff7f", "8388607", "8388607"),
    ("i32", "-2147483648", "00000080", "-2147483648", "-2147483648"),
    ("i40", "-1", "ffffffffff", "-1", "-1"),
    ("i48", "0x7FFFFFFFFFFF", "ffffffffff7f", "140737488355327", "140737488355327"),
    ("i56", "-36028797018963968", "00000000000080", "-36028797018963968", "-36028797018963968"),
    ("i64", "-9223372036854775808", "0000000000000080", "-9223372036854775808",
     "-9223372036854775808"),
    ("i64", "9223372036854775807", "ffffffffffffff7f", "9223372036854775807",
     "9223372036854775807"),
    ("u8", "255", "ff", "255", "0xff"),
    ("u8", "010", "08", "8", "0x08"),
    ("u16", "1000", "e803", "1000", "0x03e8"),
    ("u16", "0xFFFF", "ffff", "65535", "0xffff"),
    ("u24", "0xABCDEF", "efcdab", "11259375", "0xabcdef"),
    ("u32", "4294967295", "ffffffff", "4294967295", "0xffffffff"),
    ("u40", "0x0102030405", "0504030201", "4328719365", "0x0102030405"),
    ("u48", "1", "010000000000", "1", "0x000000000001"),
    ("u56", "0xFFFFFFFFFFFFFF", "ffffffffffffff", "72057594037927935", "0xffffffffffffff"),
    ("u64", "18446744073709551615", "ffffffffffffffff", "18446744073709551615",
     "0xffffffffffffffff"),
    ("x8", "0x1a", "1a", "0x1A", "0x1a"),
    ("x16", "4119", "1710", "0x1017", "0x1017"),
    ("x32", "0x60000108", "08010060", "0x60000108", "0x60000108"),
    ("x64", "1", "0100000000000000", "0x0000000000000001", "0x0000000000000001"),
    ("r32", "1.5", "0000c03f", "1.5", "1.5"),
    ("r32", "-0.1", "cdccccbd", "-0.1", "-0.1"),
    ("r32", "0x1.8p1", "00004040", "3", "3"),
    ("r32", "inf", "0000807f", "inf", "inf"),
    ("r32", "-INF", "000080ff", "-inf", "-inf"),
    ("r32", "1e-5", "acc52737", "1e-05", "1e-05"),
    ("r64", "0.1", "9a9999999999b93f", "0.1", "0.1"),
    ("r64", "1e20", "408cb5781daf1544", "1e+20", "1e+20"),
    ("r64", "123456789", "00000054346f9d41", "123456789", "123456789"),
    ("r64", "-0", "0000000000000080", "-0", "-0"),
    ("t", "1 2", "020000000100", "1 2", "1 2"),
    ("t", "0xFFFF 268435455", "ffffff0fffff", "65535 268435455", "65535 268435455"),
    ("td", "0 86399999", "ff5b2605" + "0000", "0 86399999", "0 86399999"),
    ("vs", "save", "73617665", '"save"', '"save"'),
    ("vs", '"a ""quoted"" word"', "61202271756f7465642220776f7264",
     '"a ""quoted"" word"', '"a ""quoted"" word"'),
    ("vs", '""', "", '""', '""'),
    ("os", "AQID", "010203", "AQID", "AQID"),
    ("os", "AQ", "01", "AQ==", "AQ=="),
    ("os", "AQ==", "01", "AQ==", "AQ=="),
    ("us", "QQBCAA==", "41004200", "QQBCAA==", "QQBCAA=="),
    ("d", "3q2+7w", "deadbeef", "3q2+7w==", "3q2+7w=="),
    ("hex", "01 0203 4", "01020304", "01 02 03 04", "01 02 03 04"),
    ("hex", "ab", "ab", "AB", "AB"),
]


@pytest.mark.parametrize(("mnemonic", "text", "wire", "co_text", "lely_text"), VECTORS)
def test_value_vectors(mnemonic: str, text: str, wire: str, co_text: str, lely_text: str) -> None:
    dtype = parse_data_type(mnemonic)
    for dialect in DIALECTS:
        assert parse_value(dtype, text, dialect) == bytes.fromhex(wire)
    assert format_value(dtype, bytes.fromhex(wire), CO) == co_text
    assert format_value(dtype, bytes.fromhex(wire), LELY) == lely_text


@pytest.mark.parametrize(
    ("mnemonic", "text"),
    [
        ("u8", "256"),
        ("u8", "-1"),
        ("u32", "4294967296"),
        ("u64", "18446744073709551616"),
        ("i8", "128"),
        ("i8", "-129"),
        ("i16", "32768"),
        ("i24", "8388608"),
        ("i64", "-9223372036854775809"),
        ("b", "2"),
        ("u16", "08"),
        ("u16", "0x"),
        ("u16", "1.0"),
        ("u16", "12abc"),
        ("u16", "1 2"),
        ("u16", "+"),
        ("u16", "--1"),
        ("u16", "1_000"),
        ("u16", "9" * 500),
        ("i32", "\u0661"),
        ("r32", "1e39"),
        ("r32", "0x1p200"),
        ("r64", "1e400"),
        ("r64", "1.5f"),
        ("r64", "1_0.0"),
        ("r64", "0x1p99999"),
        ("r64", "nan(1)"),
        ("t", "1"),
        ("t", "1 2 3"),
        ("t", "65536 0"),
        ("td", "0 268435456"),
        ("vs", '"open'),
        ("vs", 'a"b'),
        ("vs", '"a"b"'),
        ("vs", "two words"),
        ("vs", '"\u20ac"'),
        ("os", "A"),
        ("os", "AQID="),
        ("os", "AQ*D"),
        ("os", "===="),
        ("os", "AQ ID"),
        ("us", "QQ=="),
        ("d", "!"),
        ("hex", "0g"),
        ("hex", "0x01"),
        ("u8", "   "),
    ],
)
def test_malformed_and_out_of_range_values(mnemonic: str, text: str) -> None:
    with pytest.raises(DataTypeError) as caught:
        parse_value(parse_data_type(mnemonic), text, CO)
    assert caught.value.abort_code is None  # a syntax error: 309-3 error 101


def test_c_integer_syntax() -> None:
    """strtol base 0, as both gateways read numbers; negative never wraps."""
    assert parse_integer("0x1017", 0, 0xFFFF) == 0x1017
    assert parse_integer("0X1a", 0, 0xFF) == 0x1A
    assert parse_integer("017", 0, 0xFF) == 15
    assert parse_integer("0", 0, 0) == 0
    assert parse_integer("+7", 0, 9) == 7
    assert parse_integer("-0x10", -16, 0) == -16
    for bad in ("08", "0x", "x10", "", "1e3", " 1", "0b1"):
        with pytest.raises(DataTypeError):
            parse_integer(bad, -100, 100)


def test_visible_string_dialects() -> None:
    vs = DataType.VISIBLE_STRING
    # CANopenNode reads backslashes literally and wants quotes around several words.
    assert parse_value(vs, r'"C:\dir\n"', CO) == b"C:\\dir\\n"
    # Lely reads C escapes (invalid ones stay a backslash) and takes unquoted text to the end.
    assert parse_value(vs, r'"a\n\t\"\\\101\x42\q"', LELY) == b'a\n\t"\\AB\\q'
    assert parse_value(vs, "two words", LELY) == b"two words"
    assert parse_value(vs, '"trailing backslash\\"', CO) == b"trailing backslash\\"
    with pytest.raises(DataTypeError):
        parse_value(vs, r'"\777"', LELY)  # 511 is no byte
    # Answers: CANopenNode drops NUL and CR, Lely stops at NUL and escapes the rest.
    data = b'say "hi"\r\n\x01\\\'\x7f\xe9\0tail'
    assert format_value(vs, data, CO) == '"say ""hi""\n\x01\\\'\x7f\xe9tail"'
    assert format_value(vs, data, LELY) == '"say ""hi""\\r\\n\\001\\\\\\\'\\177\\351"'


def test_length_mismatch_carries_the_abort_code() -> None:
    with pytest.raises(DataTypeError) as caught:
        format_value(DataType.UNSIGNED32, b"\x01\x02", CO)
    assert caught.value.abort_code == ABORT_TYPE_LENGTH_MISMATCH == 0x06070010


def test_reserved_time_bits_are_not_shown() -> None:
    assert format_value(DataType.TIME_OF_DAY, bytes.fromhex("01000010" "0200"), LELY) == "2 1"


def test_data_type_table() -> None:
    assert parse_data_type("U16") is DataType.UNSIGNED16
    with pytest.raises(DataTypeError):
        parse_data_type("u12")
    assert DataType.UNSIGNED24.size == 3
    assert DataType.VISIBLE_STRING.size is None
    assert DataType.INTEGER24.cia301_index == 0x10
    assert DataType.HEX16.cia301_index == DataType.UNSIGNED16.cia301_index == 0x06
    assert DataType.HEX.cia301_index is None
    assert DataType.REAL64.pdo_mappable
    assert not DataType.DOMAIN.pdo_mappable
    assert CO.line_end == "\r\n"
    assert LELY.line_end == "\n"


@settings(max_examples=EXAMPLES, deadline=None)
@given(st.sampled_from(INTEGERS), st.data())
def test_integer_text_round_trip(dtype: DataType, data: st.DataObject) -> None:
    size = dtype.size
    assert size is not None
    signed = dtype.value.startswith("i")
    low, high = ((-(1 << (8 * size - 1)), (1 << (8 * size - 1)) - 1) if signed
                 else (0, (1 << (8 * size)) - 1))
    value = data.draw(st.integers(low, high))
    text = data.draw(st.sampled_from([str(value), hex(value), oct(value).replace("o", "")]))
    wire = parse_value(dtype, text)
    assert wire == value.to_bytes(size, "little", signed=signed)
    for dialect in DIALECTS:
        assert parse_value(dtype, format_value(dtype, wire, dialect), dialect) == wire


@settings(max_examples=EXAMPLES, deadline=None)
@given(st.sampled_from(FIXED), st.sampled_from(DIALECTS), st.data())
def test_fixed_size_bytes_round_trip(
    dtype: DataType, dialect: Dialect, data: st.DataObject
) -> None:
    """Any bus value reads back from its own text, except NaN payloads and reserved bits."""
    size = dtype.size
    assert size is not None
    wire = data.draw(st.binary(min_size=size, max_size=size))
    if dtype in (DataType.REAL32, DataType.REAL64):
        value = struct.unpack("<f" if size == 4 else "<d", wire)[0]
        if math.isnan(value):
            return
    if dtype in (DataType.TIME_OF_DAY, DataType.TIME_DIFFERENCE):
        wire = bytes([*wire[:3], wire[3] & 0x0F, *wire[4:]])
    if dtype is DataType.BOOLEAN:
        wire = bytes([wire[0] & 1])
    assert parse_value(dtype, format_value(dtype, wire, dialect), dialect) == wire


@settings(max_examples=EXAMPLES, deadline=None)
@given(st.floats(allow_nan=False), st.floats(allow_nan=False, width=32))
def test_real_round_trip(double: float, single: float) -> None:
    wire = struct.pack("<d", double)
    assert parse_value(DataType.REAL64, format_value(DataType.REAL64, wire)) == wire
    wire = struct.pack("<f", single)
    assert parse_value(DataType.REAL32, format_value(DataType.REAL32, wire)) == wire


@settings(max_examples=EXAMPLES, deadline=None)
@given(st.binary(max_size=64), st.sampled_from(DIALECTS))
def test_string_types_round_trip(wire: bytes, dialect: Dialect) -> None:
    visible = wire.replace(b"\0", b"")
    if dialect is CO:
        visible = visible.replace(b"\r", b"")
    vs = DataType.VISIBLE_STRING
    assert parse_value(vs, format_value(vs, visible, dialect), dialect) == visible
    if wire:
        for dtype in (DataType.OCTET_STRING, DataType.DOMAIN, DataType.HEX):
            assert parse_value(dtype, format_value(dtype, wire, dialect), dialect) == wire
        even = wire[: len(wire) // 2 * 2]
        if even:
            us = DataType.UNICODE_STRING
            assert parse_value(us, format_value(us, even, dialect), dialect) == even


# --------------------------------------------------------------------------- framing


def test_framer_splits_on_cr_lf_and_crlf() -> None:
    framer = LineFramer()
    assert framer.feed(b"[1] start\n[2] stop\r\n[3] preop\r[4] x") == [
        "[1] start",
        "[2] stop",
        "[3] preop",
    ]
    assert framer.pending == 5
    assert framer.feed(b"\r") == ["[4] x"]
    assert framer.feed(b"\n\n") == [""]  # the LF completes CR LF, the next one is empty
    assert framer.feed(b"\xe9\r\n") == ["\xe9"]  # one character per byte, never an error


def test_framer_reports_an_overlong_line_once_and_resyncs() -> None:
    framer = LineFramer(max_line=12)
    assert framer.feed(b"[1] 12345678\n") == ["[1] 12345678"]  # exactly the limit
    events = framer.feed(b"[7] w 0x2000 0 d AAAA")
    assert events == [OverlongLine("[7] w 0x2000 ")]  # the first max_line + 1 bytes
    overlong = events[0]
    assert isinstance(overlong, OverlongLine)
    assert overlong.sequence == 7
    assert framer.feed(b"AAAAAAAAAAAAAAAAAAAAAAAAA") == []
    assert framer.pending == 0
    assert framer.feed(b"AA\r\n[8] start\n") == ["[8] start"]
    error = overlong.error()
    assert (error.error, error.sequence) == (ErrorCode.OUT_OF_MEMORY, 7)
    assert OverlongLine("AAAA").sequence is None
    assert OverlongLine("[12").sequence is None
    assert OverlongLine("[x] a").sequence is None
    assert DEFAULT_MAX_LINE >= 2000  # CANopenLinux's command buffer


@settings(max_examples=EXAMPLES, deadline=None)
@given(st.binary(max_size=200), st.lists(st.integers(0, 200), max_size=6))
def test_framer_does_not_depend_on_chunking(stream: bytes, cuts: list[int]) -> None:
    whole = LineFramer(max_line=20).feed(stream)
    framer = LineFramer(max_line=20)
    pieces: list[str | OverlongLine] = []
    start = 0
    for cut in sorted(cuts):
        pieces += framer.feed(stream[start:cut])
        start = max(start, cut)
    pieces += framer.feed(stream[start:])
    assert pieces == whole
    assert all(isinstance(item, OverlongLine) or len(item) <= 20 for item in whole)


# --------------------------------------------------------------------------- requests

# Lines as the two dialects' clients write them, and the request each must give.
REQUESTS: list[tuple[str, Request]] = [
    # CANopenNode (CO_GTWA_helpString, cocomm.md)
    ("[1] 4 read 0x1017 0 u16",
     SdoUpload(sequence=1, node=4, index=0x1017, subindex=0, dtype=DataType.UNSIGNED16)),
    ("[1] r 0x1017 0", SdoUpload(sequence=1, index=0x1017, subindex=0)),
    ("[2] 1 w 0x1017 0 u16 1000",
     SdoDownload(sequence=2, node=1, index=0x1017, subindex=0, dtype=DataType.UNSIGNED16,
                 data=b"\xe8\x03")),
    ("[3] 1 w 0x1010 1 vs save",
     SdoDownload(sequence=3, node=1, index=0x1010, subindex=1, dtype=DataType.VISIBLE_STRING,
                 data=b"save")),
    ('[4] w 0x2000 0 vs "a # b"  # comment',
     SdoDownload(sequence=4, index=0x2000, subindex=0, dtype=DataType.VISIBLE_STRING,
                 data=b"a # b")),
    ("[5] w 0x2001 0 hex 01 02 0A", SdoDownload(sequence=5, index=0x2001, subindex=0,
                                               dtype=DataType.HEX, data=b"\x01\x02\x0a")),
    ("[6] w 0x2002 0 d AQID", SdoDownload(sequence=6, index=0x2002, subindex=0,
                                         dtype=DataType.DOMAIN, data=b"\x01\x02\x03")),
    ("[2] 1 4 start", StartNode(sequence=2, net=1, node=4)),
    ("[7] 0 start", StartNode(sequence=7, node=0)),
    ("[8] stop", StopNode(sequence=8)),
    ("[9] 5 preop", EnterPreoperational(sequence=9, node=5)),
    ("[9] 5 preoperational", EnterPreoperational(sequence=9, node=5)),
    ("[10] 5 reset node", ResetNode(sequence=10, node=5)),
    ("[11] reset comm", ResetCommunication(sequence=11)),
    ("[11] reset communication", ResetCommunication(sequence=11)),
    ("[3] set network 1", SetDefaultNetwork(sequence=3, network=1)),
    ("[12] set node 4", SetDefaultNode(sequence=12, node_id=4)),
    ("[13] set sdo_timeout 1000", SetSdoTimeout(sequence=13, timeout_ms=1000)),
    ("[14] set sdo_block 1", SetSdoBlock(sequence=14, enabled=True)),
    ("[15] help", Help(sequence=15)),
    ("[15] help datatype", Help(sequence=15, topic="datatype")),
    ("[15] help LSS", Help(sequence=15, topic="lss")),
    ("[16] log", Log(sequence=16)),
    ("[17] lss_switch_glob 1", LssSwitchGlobal(sequence=17, configuration=True)),
    ("[17] lss_switch_sel 0x360 2 3 0x4",
     LssSwitchSelective(sequence=17, address=LssAddress(0x360, 2, 3, 4))),
    ("[18] lss_set_node 5", LssConfigureNodeId(sequence=18, node_id=5)),
    ("[18] lss_set_node 255", LssConfigureNodeId(sequence=18, node_id=255)),
    ("[19] lss_conf_bitrate 0 4", LssConfigureBitRate(sequence=19, table_selector=0,
                                                     table_index=4)),
    ("[20] lss_activate_bitrate 1000", LssActivateBitRate(sequence=20, switch_delay_ms=1000)),
    ("[21] lss_store", LssStore(sequence=21)),
    ("[22] lss_inquire_addr", LssInquireAddress(sequence=22)),
    ("[22] lss_inquire_addr 3", LssInquireAddress(sequence=22, lss_sub=3)),
    ("[23] lss_get_node", LssInquireNodeId(sequence=23)),
    ("[24] _lss_fastscan", LssIdentifyFastscan(sequence=24)),
    ("[24] _lss_fastscan 50", LssIdentifyFastscan(sequence=24, timeout_ms=50)),
    ("[25] lss_allnodes", LssCompleteConfiguration(sequence=25)),
    ("[25] lss_allnodes 100", LssCompleteConfiguration(sequence=25, timeout_ms=100)),
    ("[25] lss_allnodes 100 10 0", LssCompleteConfiguration(
        sequence=25, timeout_ms=100, first_node_id=10, store=False)),
    ("[25] lss_allnodes 100 10 1 2 0x360 1 0 0 0 0 0",
     LssCompleteConfiguration(sequence=25, timeout_ms=100, first_node_id=10, store=True,
                              criteria=(LssScanCriterion(2, 0x360), LssScanCriterion(1, 0),
                                        LssScanCriterion(0, 0), LssScanCriterion(0, 0)))),
    # Lely (doc/coctl.md, co_gw_txt_lex_*)
    ("[5] r 0x1018 0x01 u32",
     SdoUpload(sequence=5, index=0x1018, subindex=1, dtype=DataType.UNSIGNED32)),
    ("[ 5 ] 1 2 READ 0x1018 1 U32",
     SdoUpload(sequence=5, net=1, node=2, index=0x1018, subindex=1, dtype=DataType.UNSIGNED32)),
    ("[6] 2 w 0x2000 0 t 1 2", SdoDownload(sequence=6, node=2, index=0x2000, subindex=0,
                                          dtype=DataType.TIME_OF_DAY,
                                          data=bytes.fromhex("020000000100"))),
    ("[2] set id 1", SetNodeId(sequence=2, node_id=1)),
    ("[3] init 0", InitGateway(sequence=3, bit_rate_index=0)),
    ("[3] 2 init 9", InitGateway(sequence=3, net=2, bit_rate_index=9)),
    ("[4] set heartbeat 500", SetHeartbeatProducer(sequence=4, producer_time=500)),
    ("[4] 1 set heartbeat 0", SetHeartbeatProducer(sequence=4, net=1, producer_time=0)),
    ("[5] set command_timeout 2000", SetCommandTimeout(sequence=5, timeout_ms=2000)),
    ("[5] set command_size 4096", SetCommandSize(sequence=5, size=4096)),
    ("[6] boot_up_indication Disable", SetBootUpForwarding(sequence=6, enabled=False)),
    ("[6] 1 boot_up_indication enable", SetBootUpForwarding(sequence=6, net=1, enabled=True)),
    ("[7] info version", GetVersion(sequence=7)),
    ("[7] 1 info version", GetVersion(sequence=7, net=1)),
    ("[8] 1 2 enable guarding 100 3",
     EnableGuarding(sequence=8, net=1, node=2, guard_time=100, lifetime_factor=3)),
    ("[8] 2 disable guarding", DisableGuarding(sequence=8, node=2)),
    ("[9] 2 enable heartbeat 1500", EnableHeartbeat(sequence=9, node=2, consumer_time=1500)),
    ("[9] 2 disable heartbeat", DisableHeartbeat(sequence=9, node=2)),
    ("[10] set rpdo 1 0x201 event 2 0x6200 1 u8 0x6411 1 i16",
     ConfigureRpdo(sequence=10, number=1, cob_id=0x201, transmission_type=0xFF,
                   mappings=(PdoMapping(0x6200, 1, DataType.UNSIGNED8),
                             PdoMapping(0x6411, 1, DataType.INTEGER16)))),
    ("[10] 1 set rpdo 2 0x301 sync10 2 u8 0x6000 1",
     ConfigureRpdo(sequence=10, net=1, number=2, cob_id=0x301, transmission_type=10,
                   mappings=(PdoMapping(None, None, DataType.UNSIGNED8),
                             PdoMapping(0x6000, 1, None)))),
    ("[11] set tpdo 1 0x181 rtr 0",
     ConfigureTpdo(sequence=11, number=1, cob_id=0x181, transmission_type=0xFD, mappings=())),
    ("[11] set tpdox 1 0x181 event100 500 1 0x6000 1 u8",
     ConfigureTpdo(sequence=11, number=1, cob_id=0x181, transmission_type=0xFF,
                   inhibit_time=100, event_timer=500,
                   mappings=(PdoMapping(0x6000, 1, DataType.UNSIGNED8),))),
    ("[11] set tpdox 2 0x182 rtr 250 0",
     ConfigureTpdo(sequence=11, number=2, cob_id=0x182, transmission_type=0xFD,
                   event_timer=250, mappings=())),
    ("[11] set tpdox 3 0x183 sync1 4 1 r32",
     ConfigureTpdo(sequence=11, number=3, cob_id=0x183, transmission_type=1, sync_start=4,
                   mappings=(PdoMapping(None, None, DataType.REAL32),))),
    ("[12] r p 1", ReadPdo(sequence=12, number=1)),
    ("[12] 2 read pdo 512", ReadPdo(sequence=12, net=2, number=512)),
    ("[13] w p 1 2 0x1 -1", WritePdo(sequence=13, number=1, values=(1, -1))),
    ("[13] write PDO 3 0", WritePdo(sequence=13, number=3, values=())),
    ("[14] lss_inquire_addr 0x5A", LssInquireAddress(sequence=14, lss_sub=0)),
    ("[14] lss_inquire_addr 0x5D", LssInquireAddress(sequence=14, lss_sub=3)),
    ("[15] lss_identity 0x360 1 0 5 0 0xFFFFFFFF",
     LssIdentifyRemoteSlave(sequence=15,
                            selection=LssAddressRange(0x360, 1, 0, 5, 0, 0xFFFFFFFF))),
    ("[16] lss_ident_nonconf", LssIdentifyNonConfigured(sequence=16)),
    ("[17] _lss_slowscan 0x360 1 0 5 0 100",
     LssSlowscan(sequence=17, selection=LssAddressRange(0x360, 1, 0, 5, 0, 100))),
    ("[18] 1 _lss_fastscan 0x360 0xFFFFFFFF 0 0 0 0 7 0xF",
     LssIdentifyFastscan(sequence=18, net=1, known=LssAddress(0x360, 0, 0, 7),
                         mask=LssAddress(0xFFFFFFFF, 0, 0, 0xF))),
    # 309-1 services with our spelling
    ("[19] store", StoreConfiguration(sequence=19)),
    ("[19] 2 store 1", StoreConfiguration(sequence=19, net=2, specifier=1)),
    ("[20] restore 3", RestoreConfiguration(sequence=20, specifier=3)),
    ("[21] lss_fastscan 0x12345678 31 0 1",
     LssFastscan(sequence=21, id_number=0x12345678, bit_checked=31, lss_sub=0, lss_next=1)),
    ("[21] lss_fastscan 0 128 0 0",
     LssFastscan(sequence=21, id_number=0, bit_checked=128, lss_sub=0, lss_next=0)),
    ("[22] lss_assign 0x360 2 3 4 9",
     LssAssignNodeId(sequence=22, address=LssAddress(0x360, 2, 3, 4), node_id=9)),
    # sequence numbers and spacing
    ("[0]start", StartNode(sequence=0)),
    ("  [4294967295]   Start   ", StartNode(sequence=0xFFFFFFFF)),
    ("[0x10] stop", StopNode(sequence=16)),
    ("[1] 1 reset node # reboot", ResetNode(sequence=1, node=1)),
]


@pytest.mark.parametrize(("line", "request_"), REQUESTS, ids=[line for line, _ in REQUESTS])
def test_request_lines(line: str, request_: Request) -> None:
    for dialect in DIALECTS:
        assert parse_request(line, dialect) == request_


@pytest.mark.parametrize("line", ["", "   ", "# comment", "  # [1] start", "\t"])
def test_empty_and_comment_lines(line: str) -> None:
    assert parse_request(line) is None
    assert format_empty(CO) == "\r\n"
    assert format_empty(LELY) is None


def test_visible_string_values_follow_the_dialect() -> None:
    line = r'[1] w 0x2000 0 vs "tab\there"'
    assert _data(parse_request(line, CO)) == b"tab\\there"
    assert _data(parse_request(line, LELY)) == b"tab\there"
    assert _data(parse_request("[1] w 0x2000 0 vs two words", LELY)) == b"two words"
    assert _data(parse_request(r'[1] w 0x2000 0 vs "say \"hi\""', LELY)) == b'say "hi"'
    with pytest.raises(ParseError):
        parse_request(r'[1] w 0x2000 0 vs "say \"hi\""', CO)  # CANopenNode: a quote ends it


def _data(request: Request | None) -> bytes:
    assert isinstance(request, SdoDownload)
    return request.data


# line, 309-3 error, sequence echoed
ERRORS = [
    ("[1] foo", ErrorCode.REQUEST_NOT_SUPPORTED, 1),
    ("[1] 4 led", ErrorCode.REQUEST_NOT_SUPPORTED, 1),
    ("[2] set foo 1", ErrorCode.REQUEST_NOT_SUPPORTED, 2),
    ("[2] reset all", ErrorCode.REQUEST_NOT_SUPPORTED, 2),
    ("[2] enable sync", ErrorCode.REQUEST_NOT_SUPPORTED, 2),
    ("[2] disable sync", ErrorCode.REQUEST_NOT_SUPPORTED, 2),
    ("[2] info date", ErrorCode.REQUEST_NOT_SUPPORTED, 2),
    ("start", ErrorCode.SYNTAX_ERROR, None),
    ("1 start", ErrorCode.SYNTAX_ERROR, None),
    ("[x] start", ErrorCode.SYNTAX_ERROR, None),
    ("[-1] start", ErrorCode.SYNTAX_ERROR, None),
    ("[4294967296] start", ErrorCode.SYNTAX_ERROR, None),
    ("[1 start", ErrorCode.SYNTAX_ERROR, None),
    ("[3]", ErrorCode.SYNTAX_ERROR, 3),
    ("[3] 4", ErrorCode.SYNTAX_ERROR, 3),
    ("[3] 1 2 3 start", ErrorCode.SYNTAX_ERROR, 3),
    ("[3] 4x start", ErrorCode.SYNTAX_ERROR, 3),
    ("[3] 4 start now", ErrorCode.SYNTAX_ERROR, 3),
    ("[4] read", ErrorCode.SYNTAX_ERROR, 4),
    ("[4] read 0x10000 0", ErrorCode.SYNTAX_ERROR, 4),
    ("[4] read 0x1000 256", ErrorCode.SYNTAX_ERROR, 4),
    ("[4] read 0x1000 0 u12", ErrorCode.SYNTAX_ERROR, 4),
    ("[4] read 0x1000 0 u8 extra", ErrorCode.SYNTAX_ERROR, 4),
    ("[5] write 0x1000 0 u8", ErrorCode.SYNTAX_ERROR, 5),
    ("[5] write 0x1000 0 u8 256", ErrorCode.SYNTAX_ERROR, 5),
    ("[5] write 0x1000 0 u8 1 2", ErrorCode.SYNTAX_ERROR, 5),
    ('[5] write 0x1000 0 vs "open', ErrorCode.SYNTAX_ERROR, 5),
    ('[5] write 0x1000 0 vs "a"b', ErrorCode.SYNTAX_ERROR, 5),
    ("[5] write 0x1000 0 d !!", ErrorCode.SYNTAX_ERROR, 5),
    ("[6] reset", ErrorCode.SYNTAX_ERROR, 6),
    ("[6] set", ErrorCode.SYNTAX_ERROR, 6),
    ("[6] set sdo_timeout 0", ErrorCode.SYNTAX_ERROR, 6),
    ("[6] set sdo_block 2", ErrorCode.SYNTAX_ERROR, 6),
    ("[6] 1 set network 2", ErrorCode.SYNTAX_ERROR, 6),
    ("[6] 1 2 set node 3", ErrorCode.SYNTAX_ERROR, 6),
    ("[6] 1 help", ErrorCode.SYNTAX_ERROR, 6),
    ("[6] help me", ErrorCode.SYNTAX_ERROR, 6),
    ("[6] log now", ErrorCode.SYNTAX_ERROR, 6),
    ("[7] init 10", ErrorCode.SYNTAX_ERROR, 7),
    ("[7] boot_up_indication maybe", ErrorCode.SYNTAX_ERROR, 7),
    ("[7] set rpdo 0 0x201 event 0", ErrorCode.SYNTAX_ERROR, 7),
    ("[7] set rpdo 513 0x201 event 0", ErrorCode.SYNTAX_ERROR, 7),
    ("[7] set rpdo 1 0x201 sync241 0", ErrorCode.SYNTAX_ERROR, 7),
    ("[7] set rpdo 1 0x201 cyclic 0", ErrorCode.SYNTAX_ERROR, 7),
    ("[7] set rpdo 1 0x201 event100 0", ErrorCode.SYNTAX_ERROR, 7),
    ("[7] set rpdo 1 0x201 event 65 u8", ErrorCode.SYNTAX_ERROR, 7),
    ("[7] set rpdo 1 0x201 event 2 u8", ErrorCode.SYNTAX_ERROR, 7),
    ("[7] set rpdo 1 0x201 event 1 vs", ErrorCode.SYNTAX_ERROR, 7),
    ("[7] set rpdo 1 0x201 event 1 0x6000", ErrorCode.SYNTAX_ERROR, 7),
    ("[7] set tpdox 1 0x181 event 500 0", ErrorCode.SYNTAX_ERROR, 7),
    ("[8] w p 1 2 5", ErrorCode.SYNTAX_ERROR, 8),
    ("[8] w p 1 1 5 6", ErrorCode.SYNTAX_ERROR, 8),
    ("[8] r p", ErrorCode.SYNTAX_ERROR, 8),
    ("[8] 1 2 r p 1", ErrorCode.SYNTAX_ERROR, 8),
    ("[9] lss_switch_glob 2", ErrorCode.SYNTAX_ERROR, 9),
    ("[9] lss_switch_sel 1 2 3", ErrorCode.SYNTAX_ERROR, 9),
    ("[9] lss_switch_sel 1 2 3 0x100000000", ErrorCode.SYNTAX_ERROR, 9),
    ("[9] lss_inquire_addr 4", ErrorCode.SYNTAX_ERROR, 9),
    ("[9] lss_inquire_addr 0x5E", ErrorCode.SYNTAX_ERROR, 9),
    ("[9] lss_fastscan 0 32 0 0", ErrorCode.SYNTAX_ERROR, 9),
    ("[9] lss_fastscan 0 0 4 0", ErrorCode.SYNTAX_ERROR, 9),
    ("[9] _lss_fastscan 1 2", ErrorCode.SYNTAX_ERROR, 9),
    ("[9] lss_allnodes 100 2", ErrorCode.SYNTAX_ERROR, 9),
    ("[9] lss_allnodes 100 2 1 3 0 0 0 0 0 0 0", ErrorCode.SYNTAX_ERROR, 9),
    ("[9] lss_store now", ErrorCode.SYNTAX_ERROR, 9),
    ("[10] 0 1 start", ErrorCode.UNSUPPORTED_NET, 10),
    ("[10] 65536 1 start", ErrorCode.UNSUPPORTED_NET, 10),
    ("[10] 0 store", ErrorCode.UNSUPPORTED_NET, 10),
    ("[10] set network 0", ErrorCode.UNSUPPORTED_NET, 10),
    ("[10] set network 65536", ErrorCode.UNSUPPORTED_NET, 10),
    ("[11] 128 start", ErrorCode.UNSUPPORTED_NODE, 11),
    ("[11] 1 200 read 0x1000 0", ErrorCode.UNSUPPORTED_NODE, 11),
    ("[11] 0 read 0x1000 0", ErrorCode.UNSUPPORTED_NODE, 11),
    ("[11] 0 enable heartbeat 100", ErrorCode.UNSUPPORTED_NODE, 11),
    ("[11] set node 0", ErrorCode.UNSUPPORTED_NODE, 11),
    ("[11] set node 128", ErrorCode.UNSUPPORTED_NODE, 11),
    ("[11] set id 128", ErrorCode.UNSUPPORTED_NODE, 11),
    ("[11] lss_set_node 200", ErrorCode.UNSUPPORTED_NODE, 11),
    ("[11] lss_assign 1 2 3 4 255", ErrorCode.UNSUPPORTED_NODE, 11),
    ("[11] lss_allnodes 100 128 1", ErrorCode.UNSUPPORTED_NODE, 11),
    ("[11] set node x", ErrorCode.SYNTAX_ERROR, 11),
]


@pytest.mark.parametrize(("line", "error", "sequence"), ERRORS, ids=[e[0] for e in ERRORS])
def test_parse_errors(line: str, error: ErrorCode, sequence: int | None) -> None:
    for dialect in DIALECTS:
        with pytest.raises(ParseError) as caught:
            parse_request(line, dialect)
        assert (caught.value.error, caught.value.sequence) == (error, sequence)


@settings(max_examples=EXAMPLES * 5, deadline=None)
@given(st.text(max_size=80), st.sampled_from(DIALECTS))
def test_parser_raises_only_parse_error_on_any_text(line: str, dialect: Dialect) -> None:
    try:
        parse_request(line, dialect)
    except ParseError as error:
        assert error.error in (100, 101, 106, 107)


WORDS = [
    "[1]", "[", "]", "0", "1", "128", "0x1017", "-1", "r", "w", "p", "set", "tpdox", "rpdo",
    "event5", "sync3", "rtr", "u8", "vs", "d", "t", "hex", '"a b"', '"', "#", "lss_allnodes",
    "_lss_fastscan", "reset", "node", "enable", "heartbeat", "info", "version", "AQ==",
    "\\x41", "\u0663", "lss_inquire_addr", "0x5C", "store",
]


@settings(max_examples=EXAMPLES * 5, deadline=None)
@given(st.lists(st.sampled_from(WORDS), max_size=12), st.sampled_from(DIALECTS))
def test_parser_on_near_miss_requests(words: list[str], dialect: Dialect) -> None:
    """Plausible words in any order reach deep into the grammar; still only ParseError."""
    try:
        request = parse_request("[1] " + " ".join(words), dialect)
    except ParseError as error:
        assert error.sequence == 1
    else:
        assert request is None or request.sequence == 1


READ_NUMBERS = ["0", "1", "4", "9", "01", "010", "08", "127", "128", "255", "256", "4119",
                "65535", "65536", "99999", "0x0", "0x1", "0X1", "0x1017", "0xFFFF", "0xffff",
                "0x10000", "0x00001", "-1", "+1", "999999999", "4294967295", "4294967296"]
READ_WORDS = ["r", "read", "R", "Read", "rd", "u32", "U32", "x8", "hex", "i16", "vs", "r64",
              "u", "p", "#", '"a"']


def assert_as_the_general_parser(line: str, dialect: Dialect,
                                 shortcut: Callable[[str], Request | None]) -> None:
    """``shortcut`` (a plain form's parser) gives None for ``line`` or exactly the request
    the general parser gives; ``parse_request`` gives the general parser's request, or its
    error (number, sequence and text)."""
    try:
        general: Request | ParseError | None = _parse_stripped(line.strip(), dialect)
    except ParseError as error:
        general = error
    plain = shortcut(line.strip())
    if plain is not None:
        assert plain == general
    try:
        assert parse_request(line, dialect) == general
    except ParseError as error:
        assert isinstance(general, ParseError)
        assert (error.error, error.sequence, str(error)) == (
            general.error, general.sequence, str(general))


@settings(max_examples=EXAMPLES * 10, deadline=None)
@given(st.lists(st.sampled_from(READ_NUMBERS), min_size=1, max_size=3),
       st.lists(st.sampled_from(READ_NUMBERS + READ_WORDS), max_size=4),
       st.sampled_from(READ_NUMBERS), st.sampled_from(["r", "read", "R", "w"]),
       st.sampled_from([" ", "  ", "\t", ""]), st.sampled_from(DIALECTS))
def test_plain_reads_parse_as_the_general_parser_parses_them(
        head: list[str], tail: list[str], sequence: str, command: str, space: str,
        dialect: Dialect) -> None:
    """Issue 22: the server's shortcut for the plain read (``_plain_read``) makes exactly
    the request the general parser makes of the same line, or leaves the line to it; lines
    near the plain form (other spellings of numbers, ranges, case, spaces, extra words)."""
    words = [f"[{sequence}]", *head[:-1], head[-1], command, *tail]
    line = space.join(words) if space else " ".join(words).replace(" ", "", 1)
    assert_as_the_general_parser(line, dialect, _plain_read)


def test_plain_reads_take_the_shortcut() -> None:
    """The reads 309-3 clients send take the shortcut, and come out as the general parser
    reads them."""
    for line in ("[1] 4 read 0x1000 0 u32", "[23] 2 5 r 0x1017 0 u16", "[0] 127 r 0 255",
                 "[999999999] 1 read 65535 0x1 hex"):
        plain = _plain_read(line)
        assert plain is not None
        assert plain == _parse_stripped(line, Dialect.CANOPENNODE)


LINE_ENDS_SENT = [b"\n", b"\r\n", b"", b"\r", b"\n\n", b"\r\n\n", b" \n"]
"""How a client may end what it sends: one line end (LF, CR LF), none, another line after."""


def assert_as_the_plain_read(line: str, end: bytes, max_line: int) -> None:
    """``plain_read_line`` (C) of ``line`` sent with ``end`` gives ``_plain_read``'s request
    (the general parser's) or None, and gives it whenever the line is one whole line in the
    plain form with no white space around it."""
    data = line.encode("latin-1") + end
    fast = plain_read_line(data, max_line)
    whole = end in (b"\n", b"\r\n") and len(line.encode("latin-1")) <= max_line
    if fast is not None:
        assert whole
        assert fast == _plain_read(line.strip())
        assert fast == parse_request(line)
    if whole and line == line.strip() and "\r" not in line and "\n" not in line:
        assert fast == _plain_read(line)


@settings(max_examples=EXAMPLES * 10, deadline=None)
@given(st.lists(st.sampled_from(READ_NUMBERS), min_size=1, max_size=3),
       st.lists(st.sampled_from(READ_NUMBERS + READ_WORDS), max_size=4),
       st.sampled_from(READ_NUMBERS), st.sampled_from(["r", "read", "R", "w"]),
       st.sampled_from([" ", "  ", "\t", ""]), st.sampled_from(["", " ", "\t"]),
       st.sampled_from(LINE_ENDS_SENT), st.sampled_from([DEFAULT_MAX_LINE, 30, 20, 0]))
def test_the_plain_read_in_c_is_the_plain_read(
        head: list[str], tail: list[str], sequence: str, command: str, space: str,
        around: str, end: bytes, max_line: int) -> None:
    """Issue 22: the server's plain read in C (``plain_read_line``, the line's end and the
    command size included) makes exactly ``_plain_read``'s request of a line, or leaves
    the line to the Python path; lines near the plain form, as ``_plain_read``'s test's."""
    words = [f"[{sequence}]", *head[:-1], head[-1], command, *tail]
    line = space.join(words) if space else " ".join(words).replace(" ", "", 1)
    assert_as_the_plain_read(around + line + around, end, max_line)


@settings(max_examples=EXAMPLES * 5, deadline=None)
@given(st.text(alphabet=st.characters(max_codepoint=0xFF), max_size=60),
       st.sampled_from(LINE_ENDS_SENT))
def test_the_plain_read_in_c_on_any_text(line: str, end: bytes) -> None:
    """Any Latin-1 text: the plain read in C gives None or the parser's request."""
    assert_as_the_plain_read(line, end, DEFAULT_MAX_LINE)
    assert_as_the_plain_read("[1] 1 r " + line, end, DEFAULT_MAX_LINE)


def test_the_reads_clients_send_take_the_plain_read_in_c() -> None:
    """The reads 309-3 clients send are parsed in C, as the parser reads them; with white
    space around them or over the command size, they are left to the Python path."""
    for line in ("[1] 4 read 0x1000 0 u32", "[23] 2 5 r 0x1017 0 u16", "[0] 127 r 0 255",
                 "[999999999] 1 read 65535 0x1 hex", "[7] 65535 1 r 0xFFFF 0xff x64"):
        for end in (b"\n", b"\r\n"):
            fast = plain_read_line(line.encode() + end, DEFAULT_MAX_LINE)
            assert fast is not None
            assert fast == _parse_stripped(line, Dialect.CANOPENNODE)
        assert plain_read_line(f" {line}\n".encode(), DEFAULT_MAX_LINE) is None
        assert plain_read_line(f"{line}\n".encode(), len(line) - 1) is None
    for line in ("[1] 128 r 0 0", "[1] 0 r 0 0", "[1] 65536 1 r 0 0", "[1] 1 r 0x10000 0",
                 "[1] 1 r 65536 0", "[1] 1 r 0 256", "[1] 1 r 0 0x100", "[1000000000] 1 r 0 0",
                 "[1] 1 r 0 0 u128", "[1] 1 r 0 0 U32", "[1] 1 r 010 0", "[1] 1 r 0X1 0"):
        assert _plain_read(line) is None
        assert plain_read_line(f"{line}\n".encode(), DEFAULT_MAX_LINE) is None, line


@settings(max_examples=EXAMPLES * 5, deadline=None)
@given(st.sampled_from([None, *DataType]), st.sampled_from(DIALECTS),
       st.integers(0, (1 << 64) + 1), st.data())
def test_the_upload_answer_in_c_is_format_upload(
        dtype: DataType | None, dialect: Dialect, sequence: int, data: st.DataObject) -> None:
    """Issue 22: the upload's answer in C (``format_plain_upload``) is ``format_upload``'s
    text, or None; never None for no type, HEX, or an integer type of the data's size."""
    size = None if dtype is None else dtype.size
    value = data.draw(st.binary(min_size=size or 0, max_size=size or 0) if size is not None
                      and data.draw(st.booleans()) else st.binary(max_size=12))
    fast = format_plain_upload(dialect is LELY, dialect.line_end, sequence, dtype, value)
    if fast is not None:
        assert fast == format_upload(sequence, dtype, value, dialect)
    integer = dtype in INTEGER_RANGES and len(value) == size
    if sequence < 1 << 64 and (dtype in (None, DataType.HEX) or integer):
        assert fast is not None


def one_of_words(*words: str) -> st.SearchStrategy[list[str]]:
    return st.sampled_from(words).map(lambda word: [word])


WRITE_PARTS: dict[str, tuple[st.SearchStrategy[list[str]], st.SearchStrategy[list[str]]]] = {
    # each part of a write line: spellings of the plain form (in range or just out), then
    # near misses
    "sequence": (one_of_words("[0]", "[1]", "[23]", "[999999999]"),
                 one_of_words("[01]", "[-1]", "[+1]", "[0x1]", "[1000000000]", "[4294967295]",
                              "[4294967296]", "[ 1]", "[1 ]", "[x]", "[]")),
    "address": (st.lists(st.sampled_from(["1", "2", "9", "127", "128", "65535", "65536"]),
                         min_size=1, max_size=2),
                st.lists(st.sampled_from(["0", "1", "01", "0x1", "127", "65535", "99999", "-1",
                                          "+1"]), max_size=3)),
    "command": (one_of_words("w", "write"),
                one_of_words("W", "Write", "wr", "writ", "r", "read", "p")),
    "index": (one_of_words("0", "1", "4119", "0x1017", "0x6200", "65535", "65536", "99999",
                           "0xffff", "0xFFFF"),
              one_of_words("0x10000", "0x00001", "0X1", "010", "08", "-1", "+1", "4294967296")),
    "subindex": (one_of_words("0", "1", "255", "256", "999", "0x1", "0xff", "0xFF"),
                 one_of_words("0x100", "0x001", "0X1", "00", "01", "-1", "+1", "4294967296")),
    "type": (one_of_words(*(dtype.value for dtype in INTEGER_RANGES)),
             one_of_words("U16", "I8", "B", "r32", "r64", "t", "td", "vs", "os", "us", "d",
                          "hex", "u", "u128", "x24")),
    "value": (one_of_words(
        "0", "1", "2", "-0", "-1", "7", "127", "128", "-128", "-129", "255", "256", "32767",
        "-32768", "32768", "65535", "65536", "8388607", "-8388608", "16777215", "16777216",
        "2147483647", "-2147483648", "2147483648", "4294967295", "4294967296",
        "1099511627775", "1099511627776", "9223372036854775807", "-9223372036854775808",
        "9223372036854775808", "-9223372036854775809", "18446744073709551615",
        "18446744073709551616", "99999999999999999999", "-99999999999999999999", "0x0", "0x1",
        "0X1", "0x7f", "0X7F", "0x80", "0xff", "0x100", "0xFFFF", "0x10000", "0xFFFFFF",
        "0xFFFFFFFF", "0x100000000", "0xFFFFFFFFFFFFFFFF", "0x10000000000000000"),
              one_of_words("+1", "01", "-01", "010", "08", "00", "-0x1", "0x",
                           "0x00000000000000001", "1.5", "1e3", "inf", "1_000", "\u0663", "AQ==",
                           '"1"', "0b1", "0o7", "#", "1#", "0 0")),
    "ending": (st.just([]), one_of_words("1", "u8", "#", "# a comment", '"x"', "\\x41")),
}
"""``test_plain_writes_parse_as_the_general_parser_parses_them``'s lines, part by part."""


@st.composite
def write_lines(draw: st.DrawFn) -> str:
    """A write line in the plain form with up to two of its parts, or its spacing, near
    misses (drawn part by part: a line of words drawn all at random is almost never
    plain), a word missing or not, white space around it."""
    broken = draw(st.sets(st.sampled_from([*WRITE_PARTS, "spacing", "missing"]), max_size=2))
    words = [word for name, (plain, near) in WRITE_PARTS.items()
             for word in draw(near if name in broken else plain)]
    if "missing" in broken:
        del words[draw(st.integers(0, len(words) - 1))]
    space = draw(st.sampled_from(["  ", "\t", "", "\r"])) if "spacing" in broken else " "
    line = space.join(words) if space else " ".join(words).replace(" ", "", 1)
    margin = draw(st.sampled_from(["", " ", "\t", "\r"]))
    return margin + line + margin


@settings(max_examples=EXAMPLES * 10, deadline=None)
@given(write_lines(), st.sampled_from(DIALECTS))
def test_plain_writes_parse_as_the_general_parser_parses_them(
        line: str, dialect: Dialect) -> None:
    """Issue 22: the server's shortcut for the plain write of an integer (``_plain_write``)
    makes exactly the request, value bytes included, that the general parser makes of the
    same line, or leaves the line to it; and lines near the plain form: every integer
    type's limits and one past them, negative values of unsigned types, other spellings
    of numbers (leading zeros, ``0X``, signs, octal), other types, case, spaces, a word
    missing or one too many, in either dialect. ``parse_request`` gives the general
    parser's request, or its error (number, sequence and text)."""
    assert_as_the_general_parser(line, dialect, _plain_write)


def test_plain_writes_take_the_shortcut() -> None:
    """The integer writes 309-3 clients send take the shortcut, and come out as the general
    parser reads them in both dialects, value bytes included."""
    for line, data in (("[1] 4 write 0x6200 1 u8 0", b"\0"),
                       ("[23] 1 2 w 0x2006 0 u16 0x1234", b"\x34\x12"),
                       ("[0] 127 w 0 255 i8 -128", b"\x80"),
                       ("[7] 2 w 0x1017 0 u16 1000", b"\xe8\x03"),
                       ("[8] 2 w 0x2001 0 b 1", b"\x01"),
                       ("[9] 2 w 0x2003 0 i32 -2", b"\xfe\xff\xff\xff"),
                       ("[10] 2 w 0x2010 0 x64 0xFFFFFFFFFFFFFFFF", b"\xff" * 8),
                       ("[999999999] 65535 1 write 65535 0x1 u24 16777215", b"\xff" * 3)):
        plain = _plain_write(line)
        assert plain is not None and plain.data == data
        for dialect in DIALECTS:
            assert plain == _parse_stripped(line, dialect)


# --------------------------------------------------------------------------- answers


def test_ok_value_and_error_answers() -> None:
    assert format_ok(1) == "[1] OK\r\n"
    assert format_ok(1, LELY) == "[1] OK\n"
    assert format_value_response(2, "1000") == "[2] 1000\r\n"
    assert format_error(3, 101) == "[3] ERROR:101 #Syntax error.\r\n"
    assert format_error(3, 101, describe=False) == "[3] ERROR:101\r\n"
    assert format_error(3, 101, LELY) == "[3] ERROR: 101 (Syntax error)\n"
    assert format_error(3, 101, LELY, describe=False) == "[3] ERROR: 101\n"
    assert format_error(3, 101, detail="index missing") == (
        "[3] ERROR:101 #Syntax error: index missing.\r\n")
    assert format_error(3, 101, LELY, detail="index missing") == (
        "[3] ERROR: 101 (Syntax error: index missing)\n")
    explained = format_error(3, 100, detail="unknown command '\r\n" + "x" * 500 + "'")
    assert explained.count("\r\n") == 1 and len(explained) < 200  # one line, bounded
    assert format_error(4, 999, LELY) == "[4] ERROR: 999 (Unknown error code)\n"
    assert format_abort(5, 0x06020000) == (
        "[5] ERROR:0x06020000 #Object does not exist in the object dictionary.\r\n"
    )
    assert format_abort(5, 0x06020000, describe=False) == "[5] ERROR:0x06020000\r\n"
    assert format_abort(5, 0x06020000, LELY) == (
        "[5] ERROR: 06020000 (Object does not exist in the object dictionary)\n"
    )
    assert format_abort(6, 0x12345678, LELY, describe=False) == "[6] ERROR: 12345678\n"
    assert abort_text(0x12345678) == "Unknown abort code"


def test_cocomm_recognises_the_answers() -> None:
    """cocomm.c's printReply: "] ERROR:" and "\\r\\n" mean failure, "] OK\\r\\n" success."""
    assert "] ERROR:" in format_error(1, 103) and format_error(1, 103).endswith("\r\n")
    assert "] ERROR:" in format_abort(1, 0x05040000)
    assert "] OK\r\n" in format_ok(1)
    value = format_upload(1, DataType.UNSIGNED16, b"\xe8\x03")
    assert value.index("] ") < 15 and value.endswith("\r\n")


def test_upload_answers() -> None:
    u16 = DataType.UNSIGNED16
    assert format_upload(1, u16, b"\xe8\x03") == "[1] 1000\r\n"
    assert format_upload(1, u16, b"\xe8\x03", LELY) == "[1] 0x03e8\n"
    assert format_upload(1, None, b"\xe8\x03") == "[1] E8 03\r\n"
    assert format_upload(1, u16, b"\xe8") == "[1] E8\r\n"  # CANopenNode falls back to hex
    assert format_upload(1, u16, b"\xe8", LELY) == (
        "[1] ERROR: 06070010 (Data type does not match, length of service parameter does not "
        "match)\n"
    )
    assert format_upload(2, DataType.VISIBLE_STRING, b"abc") == '[2] "abc"\r\n'


def test_version_lss_and_pdo_answers() -> None:
    info = VersionInfo(vendor_id=0x44, product_code=7, revision=0x00010002, serial=1234)
    assert format_version(1, info, LELY) == "[1] 68 7 1.2 1234 3 2.0 1.0\n"
    assert format_version(1, info) == "[1] 68 7 1.2 1234 3 2.0 1.0\r\n"
    assert format_lss_number(2, 0x360) == "[2] 0x00000360\r\n"
    assert format_lss_number(2, 0xABC, LELY) == "[2] 0x00000abc\n"
    address = LssAddress(0x360, 0xAB, 3, 4)
    assert format_lss_address(3, address) == "[3] 0x00000360 0x000000AB 0x00000003 0x00000004\r\n"
    assert format_lss_address(3, address, LELY) == (
        "[3] 0x00000360 0x000000ab 0x00000003 0x00000004\n"
    )
    assert format_lss_node_id(4, 10) == "[4] 0x0A\r\n"
    assert format_lss_node_id(4, 10, LELY) == "[4] 10\n"
    assert format_pdo_read(5, 1, 2, (1, 0xFF)) == "[5] 1 pdo 2 2 0x1 0xff\r\n"


def test_help_is_one_answer() -> None:
    for topic in (None, "datatype", "lss"):
        text = format_help(topic)
        assert text.endswith("\r\n") and text.count("\r\n") == 1
    assert format_help(None, LELY).endswith("\n")
    assert "lss_allnodes" in format_help("lss")


def test_error_tables() -> None:
    """Every number of docs/cia309.md has its text; the Lely gateway words two of them shorter."""
    numbers = [100, 101, 102, 103, 104, 105, 106, 107, 200, 201, 202, 203, 204, 205,
               300, 301, 303, 304, 305, 400, 401, 501, 502, 503, 504, 505, 600]
    assert sorted(int(code) for code in ErrorCode) == numbers
    assert all(ErrorCode(number).text for number in numbers)
    assert error_text(305) == "CAN active (at init or start-up)"
    assert error_text(305, LELY) == "CAN active"
    assert error_text(501, LELY) == "LSS error"
    assert error_text(203, LELY) == error_text(203) == "Heartbeat lost"
    assert len(SDO_ABORT_TEXTS) == 31
    assert abort_text(0x05040000) == "SDO protocol timed out"
    assert abort_text(0x08000024) == "No data available"


EVENTS: list[tuple[Event, str, str | None]] = [
    (BootUpEvent(1, 5), "1 5 BOOT_UP\n",
     'CANopen Remote node ID = 0x05: NMT state changed to: "initializing" (0)\r\n'),
    (ErrorControlEvent(1, 5, NmtState.OPERATIONAL), "1 5 ERRORx OPER\n",
     'CANopen Remote node ID = 0x05: NMT state changed to: "operational" (5)\r\n'),
    (ErrorControlEvent(2, 6, NmtState.PRE_OPERATIONAL, ErrorCode.HEARTBEAT_STARTED),
     "2 6 ERRORx PREO 202 (Heartbeat started)\n",
     'CANopen Remote node ID = 0x06: NMT state changed to: "pre-operational" (127)\r\n'),
    (ErrorControlEvent(1, 5, error=ErrorCode.HEARTBEAT_LOST), "1 5 ERROR 203 (Heartbeat lost)\n",
     'CANopen Remote node ID = 0x05: NMT state changed to: "unknown" (-1)\r\n'),
    (ErrorControlEvent(1, 7, NmtState.INITIALIZING), "1 7 ERROR\n",
     'CANopen Remote node ID = 0x07: NMT state changed to: "initializing" (0)\r\n'),
    (ErrorControlEvent(1, 7, NmtState.STOPPED), "1 7 ERRORx STOP\n",
     'CANopen Remote node ID = 0x07: NMT state changed to: "stopped" (4)\r\n'),
    (EmergencyEvent(1, 5, 0x8130, 0x11, bytes([1, 2, 3, 4, 5])),
     "1 5 EMCY 8130 11 1 2 3 4 5\n",
     "CANopen Emergency message from node 0x05: errorCode=0x8130, errorRegister=0x11, "
     "errorBit=0x01, infoCode=0x05040302\r\n"),
    (EmergencyEvent(1, 0x7F, 0x1000, 0x01), "1 127 EMCY 1000 01 0 0 0 0 0\n",
     "CANopen Emergency message from node 0x7F: errorCode=0x1000, errorRegister=0x01, "
     "errorBit=0x00, infoCode=0x00000000\r\n"),
    (RpdoEvent(1, 3, (0x10, 0)), "1 pdo 3 2 0x10 0x0\n", None),
    (SdoProgressEvent(1, 5, True, 889), "1 5 SDOr 889\n", None),
    (SdoProgressEvent(1, 5, False, 7), "1 5 SDOw 7\n", None),
]


@pytest.mark.parametrize(("event", "lely", "canopennode"), EVENTS)
def test_event_lines(event: Event, lely: str, canopennode: str | None) -> None:
    assert format_event(event, LELY) == lely
    assert format_event(event, CO) == canopennode


def test_canopennode_log_lines_carry_the_time() -> None:
    line = format_event(BootUpEvent(1, 2), CO, stamp=datetime(2024, 5, 6, 7, 8, 9))
    assert line == (
        '2024-05-06 07:08:09: CANopen Remote node ID = 0x02: NMT state changed to: '
        '"initializing" (0)\r\n'
    )
