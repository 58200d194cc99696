"""The CAN task's message codecs (dpm.com) against byte vectors laid out as the seed's tables.

Each vector is written by hand from the ``msg.d[]`` table of its message in the seed manual
(chapter 5.2 and 5.3) or in docs/card-commands.md, not produced by the codec under test.
"""

from __future__ import annotations

from collections import deque

import pytest

from dbm_tools.parameters import BusParameterSet
from dpm.com import (
    END_SEQ_REQUEST,
    CanFrame,
    DownloadRequest,
    NmtRequest,
    NodeDiagnosis,
    NodeStatus,
    NodeSwitch,
    SdoTimeoutRequest,
    StartSeqRequest,
    UploadRequest,
    configuration_answer,
    configuration_request,
    decode_layer2_frames,
    decode_rx_filters,
    decode_start_seq_confirm,
    decode_transparent,
    decode_word,
    encode_bootup_indication,
    encode_layer2_frame,
    encode_rx_filters,
    encode_sdo_abort,
    encode_start_seq_confirm,
    encode_transparent_2a,
    encode_transparent_2b,
    encode_word,
    node_diag_answer,
    node_diag_request,
    sdo_abort_code,
    sdo_request,
)
from dpm.commands import NODE_DIAG_SIZE, Nmt
from dpm.message import MessageError, TelegramHeader

# --- COM_Start_Seq / COM_Download / COM_End_Seq / COM_Upload -----------------------------------


def test_start_seq_request_and_confirm() -> None:
    # Req_Adr 0, Area_Code 5, Timeout 1000 ms (word, Intel order); the confirm is Max_Len_Data_Unit
    raw = bytes([0x00, 0x05, 0xE8, 0x03])
    assert StartSeqRequest(5, 1000).encode() == raw
    assert StartSeqRequest.decode(raw) == StartSeqRequest(5, 1000)
    assert encode_start_seq_confirm(240) == bytes([240])
    assert decode_start_seq_confirm(bytes([240])) == 240
    with pytest.raises(MessageError):
        StartSeqRequest.decode(raw[:3])
    with pytest.raises(MessageError):
        decode_start_seq_confirm(b"")
    with pytest.raises(MessageError):
        decode_start_seq_confirm(b"\0")


def test_end_seq_request_is_req_adr() -> None:
    assert bytes([0x00]) == END_SEQ_REQUEST


def test_download_of_the_bus_parameters() -> None:
    """Seed 5.2.5.4.2: ln 11, Area_Code 127, Add_Offset 0, then the 7-byte bus parameter set."""
    raw = bytes([0x00, 0x7F, 0x00, 0x00,   # Req_Adr, Area_Code 127, Add_Offset 0
                 0x02,                     # Baud_rate 500 kBit/s
                 0x80, 0x00,               # CAN identifier for SYNC 0x80
                 0x0A, 0x00,               # SYNC reload timer 10 ms
                 0x01,                     # auto-clear ON
                 0x00])                    # INTEL
    request = DownloadRequest.decode(raw)
    assert (request.area, request.offset, len(request.data)) == (127, 0, 7)
    bus = BusParameterSet.decode(request.data)
    assert (bus.Baud_rate, bus.COB_ID_SYNC, bus.SYNC_Timer) == (2, 0x80, 10)
    assert DownloadRequest(127, request.data).encode() == raw


def test_sequenced_download_carries_its_offset() -> None:
    raw = bytes([0x00, 0x03, 0xF0, 0x00]) + bytes(range(10))
    assert DownloadRequest.decode(raw) == DownloadRequest(3, bytes(range(10)), 240)
    assert DownloadRequest(3, bytes(range(10)), 240).encode() == raw
    with pytest.raises(MessageError):
        DownloadRequest.decode(raw[:3])


def test_upload_request_is_five_bytes() -> None:
    raw = bytes([0x00, 0x7F, 0x02, 0x00, 0xF0])  # Area_Code 127, Add_Offset 2, Data_Len 240
    assert UploadRequest.decode(raw) == UploadRequest(127, 240, 2)
    assert UploadRequest(127, 240, 2).encode() == raw
    for wrong in (raw[:4], raw + b"\0"):
        with pytest.raises(MessageError):
            UploadRequest.decode(wrong)


# --- COM_Node_Diag -------------------------------------------------------------------------------


def test_node_diag_request_header() -> None:
    # device_adr 3, area 0, address 0, index 0, count 0, TASK_TDT_UINT8 (5), TASK_TFC_READ (1)
    assert node_diag_request(3) == bytes([0x03, 0x00, 0x00, 0x00, 0x00, 0x00, 0x05, 0x01])


def test_node_diag_answer() -> None:
    emcy = bytes([0x00, 0x10, 0x01, 0, 0, 0, 0, 0])
    diag = bytes([0x08,           # Nodestatus_1: Guard_Active
                  0x02, 0x00,     # Add_Info
                  0x91, 0x01,     # Profile_Number 401
                  0x05,           # Node_state operational
                  0x00,           # Actual_Error
                  0x01]) + emcy   # Emcy_Entries 1, then Emcy_Data
    diag = diag.ljust(NODE_DIAG_SIZE, b"\0")
    decoded = NodeDiagnosis.decode(diag)
    assert decoded == NodeDiagnosis(NodeStatus.GUARD_ACTIVE, 2, 401, 5, 0, deque([emcy], 5))
    assert decoded.encode() == diag
    answer = node_diag_answer(TelegramHeader.decode(node_diag_request(3)), diag)
    assert answer[:8] == bytes([0x03, 0x00, 0x00, 0x00, 0x00, 48, 0x05, 0x01])
    assert answer[8:] == diag
    with pytest.raises(MessageError):
        NodeDiagnosis.decode(diag[:47])
    with pytest.raises(MessageError):
        NodeDiagnosis.decode(diag[:7] + bytes([6]) + diag[8:])


def test_an_unconfigured_node_reads_deactivated() -> None:
    assert NodeDiagnosis(status=NodeStatus.DEACTIVATED).encode() == bytes([0x80]) + bytes(47)


def test_the_newest_five_emcy_messages_are_kept() -> None:
    diag = NodeDiagnosis()
    for n in range(7):
        diag.emcy.append(bytes([n]) * 8)
    raw = diag.encode()
    assert raw[7] == 5
    assert raw[8:48] == b"".join(bytes([n]) * 8 for n in range(2, 7))


# --- COM_SDO_Up_Download --------------------------------------------------------------------


def test_sdo_upload_and_download_requests() -> None:
    # node 2, data_area 0, Object Index 0x1000, Subindex 0, data_cnt 0, type 0, TASK_TFC_READ
    assert sdo_request(2, 0x1000, 0) == bytes([0x02, 0x00, 0x00, 0x10, 0x00, 0x00, 0x00, 0x01])
    # download: data_cnt 2, TASK_TFC_WRITE, then the data
    assert sdo_request(2, 0x1017, 0, b"\xe8\x03") == bytes(
        [0x02, 0x00, 0x17, 0x10, 0x00, 0x02, 0x00, 0x02, 0xE8, 0x03])


def test_sdo_abort_answer() -> None:
    """msg.f 3: the Abort Reason Code follows the header (ln 12)."""
    head = TelegramHeader.decode(sdo_request(2, 0x2000, 1))
    raw = encode_sdo_abort(head, 0x06020000)
    assert len(raw) == 12
    assert raw[8:] == bytes([0x00, 0x00, 0x02, 0x06])
    assert sdo_abort_code(raw) == 0x06020000
    with pytest.raises(MessageError):
        sdo_abort_code(raw[:11])


# --- COM_NMT_Module_Protocol ----------------------------------------------------------------


@pytest.mark.parametrize(("raw", "request_"), [
    (bytes([1, 5]), NmtRequest(Nmt.START, 5)),
    (bytes([2, 127]), NmtRequest(Nmt.STOP, 127)),
    (bytes([128, 0]), NmtRequest(Nmt.PREOPERATIONAL, 0)),
    (bytes([129, 1]), NmtRequest(Nmt.RESET_NODE, 1)),
    (bytes([130, 0]), NmtRequest(Nmt.RESET_COMMUNICATION, 0)),
])
def test_nmt_module_protocol(raw: bytes, request_: NmtRequest) -> None:
    assert request_.encode() == raw
    assert NmtRequest.decode(raw) == request_


def test_nmt_needs_two_bytes() -> None:
    with pytest.raises(MessageError):
        NmtRequest.decode(b"\x01")


# --- transparent CAN ------------------------------------------------------------------------


def test_transparent_2a() -> None:
    """5.2.10.1: ID.10..3 | ID.2..0 RTR DLC | 8 data bytes, ln 10."""
    raw = bytes([0x24, 0x62, 0xAA, 0xBB, 0, 0, 0, 0, 0, 0])  # ID 0x123, DLC 2
    frame = decode_transparent(raw)
    assert (frame.ident, frame.rtr, frame.length_code, frame.extended) == (0x123, False, 2, False)
    assert frame.payload == b"\xaa\xbb"
    assert encode_transparent_2a(CanFrame(0x123, b"\xaa\xbb")) == raw
    remote = decode_transparent(bytes([0x24, 0x72]) + bytes(8))
    assert (remote.rtr, remote.length_code, remote.payload) == (True, 2, b"")


def test_transparent_2b_standard_and_extended() -> None:
    """5.2.10.2: frame info (FF RTR 0 0 DLC), then 2 or 4 identifier bytes, 8 data."""
    standard = bytes([0x02, 0x24, 0x60, 0xAA, 0xBB, 0, 0, 0, 0, 0, 0])
    frame = decode_transparent(standard)
    assert (frame.ident, frame.extended, frame.payload) == (0x123, False, b"\xaa\xbb")
    assert encode_transparent_2b(CanFrame(0x123, b"\xaa\xbb")) == standard
    extended = bytes([0xC1, 0x91, 0xA2, 0xB3, 0xC0]) + bytes(8)  # RTR, DLC 1, ID 0x12345678
    frame = decode_transparent(extended)
    assert (frame.ident, frame.extended, frame.rtr, frame.length_code) == (0x12345678, True,
                                                                           True, 1)
    assert encode_transparent_2b(CanFrame(0x12345678, b"", True, 1, True)) == extended


@pytest.mark.parametrize("raw", [
    bytes([0x82]) + bytes(10),   # extended frame format in an 11-byte message
    bytes([0x02]) + bytes(12),   # standard frame format in a 13-byte message
    bytes(9), bytes(12), b"",
])
def test_transparent_rejects_a_wrong_length(raw: bytes) -> None:
    with pytest.raises(MessageError):
        decode_transparent(raw)


# --- layer 2 ------------------------------------------------------------------------------------


def test_layer2_frames() -> None:
    """5.3.1: each frame is ID.10..3, ID.2..0 RTR DLC, and DLC data bytes (none for RTR)."""
    raw = bytes([0x30, 0x22, 0x01, 0x02,   # ID 0x181, DLC 2, data 01 02
                 0xE0, 0x31])              # ID 0x701, RTR, DLC 1
    frames = decode_layer2_frames(raw)
    assert [(f.ident, f.rtr, f.length_code, f.payload) for f in frames] == [
        (0x181, False, 2, b"\x01\x02"), (0x701, True, 1, b"")]
    assert b"".join(encode_layer2_frame(f) for f in frames) == raw


@pytest.mark.parametrize("raw", [b"", b"\x30", bytes([0x30, 0x22, 0x01]), bytes([0x30, 0x29])])
def test_layer2_rejects_cut_or_oversized_frames(raw: bytes) -> None:
    with pytest.raises(MessageError):
        decode_layer2_frames(raw)


def test_rx_filters() -> None:
    """5.3.2.1: ID.7..0, then 0 0 0 0 0 ID.10..8."""
    raw = bytes([0x81, 0x01, 0xFF, 0x07])
    assert decode_rx_filters(raw) == [0x181, 0x7FF]
    assert encode_rx_filters([0x181, 0x7FF]) == raw
    for wrong in (b"", raw[:3]):
        with pytest.raises(MessageError):
            decode_rx_filters(wrong)


# --- GET_CONFIGURATION and our own commands ----------------------------------------------------


def test_get_configuration_answers_the_record_without_its_first_byte() -> None:
    head = TelegramHeader.decode(configuration_request(4))
    assert configuration_request(4) == bytes([4, 0, 0, 0, 0, 0, 0, 0])
    answer = configuration_answer(head, bytes([4]) + b"node four")
    assert answer == bytes([4, 0, 0, 0, 0, 9, 0, 0]) + b"node four"
    long_answer = configuration_answer(head, bytes(300))
    assert len(long_answer) == 255


def test_our_commands() -> None:
    """docs/card-commands.md, 110-117."""
    assert SdoTimeoutRequest(0, 500).encode() == bytes([0x00, 0xF4, 0x01])
    assert SdoTimeoutRequest.decode(bytes([0x05, 0xF4, 0x01])) == SdoTimeoutRequest(5, 500)
    guarding = bytes([0x03, 0x01, 0x64, 0x00, 0x03])  # node 3 on, 100 ms, factor 3
    assert NodeSwitch.decode(guarding, guarding=True) == NodeSwitch(3, True, 100, 3)
    assert NodeSwitch(3, True, 100, 3).encode() == guarding
    consumer = bytes([0x03, 0x00, 0xF4, 0x01])
    assert NodeSwitch.decode(consumer) == NodeSwitch(3, False, 500)
    assert NodeSwitch(3, False, 500).encode() == consumer
    assert encode_word(1000) == bytes([0xE8, 0x03]) and decode_word(b"\xe8\x03") == 1000
    assert encode_bootup_indication(7) == bytes([7])
    for wrong in (bytes([3, 2, 0, 0]), consumer[:3], guarding):
        with pytest.raises(MessageError):
            NodeSwitch.decode(wrong)
    with pytest.raises(MessageError):
        SdoTimeoutRequest.decode(b"\0\0")
    with pytest.raises(MessageError):
        decode_word(b"\0")
