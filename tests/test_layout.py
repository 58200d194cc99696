"""The image layout against docs/dpm.md's table, and the codecs against the seed's bytes."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

from dpm import layout
from dpm.message import Message, MessageError, TelegramHeader
from dpm.task2 import ComDiagnostics, ComPlcParameter

DPM_DOC = Path(__file__).resolve().parents[1] / "docs" / "dpm.md"


def documented_rows(heading: str) -> list[tuple[str, int, int]]:
    """(field, offset, size) of the table that follows ``heading`` in docs/dpm.md."""
    text = DPM_DOC.read_text(encoding="utf-8")
    section = text[text.index(heading) :]
    table = section[: section.index("\n\n", section.index("\n|"))]
    rows = re.findall(r"^\| `([\w.]+)` \| (0x[0-9A-F]{4}|\d+) \| (\d+) \|", table, re.M)
    return [(name, int(offset, 0), int(size)) for name, offset, size in rows]


def layout_fields(dtype: Any = layout.DPM_LAYOUT, prefix: str = "") -> list[str]:
    """Every named field of the image, sub-structures included (arrays of them excepted)."""
    names = []
    for name, (sub, *_) in dtype.fields.items():
        names.append(prefix + name)
        if sub.names is not None:
            names += layout_fields(sub, f"{prefix}{name}.")
    return names


IMAGE_ROWS = documented_rows("## 1. Layout")


@pytest.mark.parametrize(("name", "offset", "size"), IMAGE_ROWS)
def test_every_field_sits_where_the_docs_say(name: str, offset: int, size: int) -> None:
    assert layout.offset_of(name) == offset
    assert layout.size_of(name) == size


def test_the_docs_list_every_field_of_the_layout() -> None:
    assert [name for name, _, _ in IMAGE_ROWS] == layout_fields()


def test_the_regions_tile_the_whole_image() -> None:
    end = 0
    for name, offset, size in IMAGE_ROWS:
        if "." not in name:
            assert offset == end, name
            end = offset + size
    assert end == layout.DPM_SIZE == 8192


def test_taskinfo_entry_is_as_documented() -> None:
    rows = documented_rows("**TASKINFO entry**")
    fields: Any = layout.TASKINFO_ENTRY.fields
    assert [(name, at, sub.itemsize) for name, (sub, at, *_) in fields.items()] == rows
    assert layout.size_of("TaskInfo") == 7 * layout.TASKINFO_ENTRY.itemsize


def test_seed_addresses_of_the_canopen_fields() -> None:
    # Seed manual 2.2, 3.2 and 4.2 give these absolute addresses.
    assert layout.offset_of("Task2Parameter.bMode") == 0x1EC0
    assert layout.offset_of("Task2Parameter.usWatchDogTime") == 0x1EC1
    assert layout.offset_of("Task2Parameter.abConnStatus") == 0x1EF0
    for field, address in {
        "bGlobalBits": 0x1F40, "bCAN_State": 0x1F41, "bErr_rem_adr": 0x1F42,
        "bErr_event": 0x1F43, "usBus_Error_Cnt": 0x1F44, "usBus_Off_Cnt": 0x1F46,
        "usMsg_Time_Out": 0x1F48, "usRx_Overflow": 0x1F4A, "abNd_cfg": 0x1F50,
        "abNd_state": 0x1F60, "abNd_diag": 0x1F70,
    }.items():
        assert layout.offset_of(f"Task2State.{field}") == address
    # The raw-access offset of the connection bits (seed 3.1) is relative to the last KiB.
    assert layout.LAST_KB + 0x2F0 == layout.CONN_STATUS


def test_sub_structures_are_packed_as_dpm_md_lists_them() -> None:
    assert layout.MSG_STRUC.itemsize == 288
    assert layout.MSG_STRUC.fields is not None and layout.MSG_STRUC.fields["data"][1] == 8
    assert layout.VERSIONINFO.itemsize == 32
    assert layout.TASKINFO_ENTRY.itemsize == 16
    assert layout.offset_of("RcsInfo.bDriverType") == 0x1FF7
    assert layout.offset_of("DevInfo.abDevIdentifier") == 0x1FFB


def test_message_encodes_ln_plus_8_bytes() -> None:
    msg = Message(rx=2, tx=16, b=17, nr=5, data=bytes([0, 2, 4, 0, 0, 2, 5, 2, 0xAA, 0xBB]))
    raw = msg.encode()
    assert raw == bytes([2, 16, 10, 5, 0, 0, 17, 0, 0, 2, 4, 0, 0, 2, 5, 2, 0xAA, 0xBB])
    assert Message.decode(raw + b"stale tail") == msg


def test_message_decode_rejects_short_input() -> None:
    with pytest.raises(MessageError):
        Message.decode(b"\x02\x10\x05")
    with pytest.raises(MessageError):
        Message.decode(bytes([2, 16, 9, 0, 0, 0, 17, 0, 1, 2]))
    with pytest.raises(MessageError):
        Message(rx=2, tx=16, data=bytes(256)).encode()
    with pytest.raises(MessageError):
        Message(rx=300, tx=16).encode()


def test_message_decode_at_reads_in_place_as_decode_reads_a_copy() -> None:
    """The driver's get reads the host mailbox in the map with ``decode_at`` (issue 22)."""
    message = Message(rx=2, tx=16, b=17, data=bytes(range(9)), nr=5, a=3, f=1, e=4)
    image = bytearray(layout.PC_MBX) + message.encode() + b"\xee" * 40
    assert Message.decode_at(image, layout.PC_MBX) == message
    assert Message.decode_at(image, layout.PC_MBX) == Message.decode(image[layout.PC_MBX :])
    with pytest.raises(MessageError):
        Message.decode_at(image, len(image) - 4)  # shorter than a header
    with pytest.raises(MessageError):
        Message.decode_at(message.encode()[:12], 0)  # msg.ln says 9 data bytes, 4 follow


def test_answer_swaps_rx_tx_and_moves_b_to_a() -> None:
    answer = Message(rx=2, tx=16, b=17, nr=9).answer(f=163)
    assert (answer.rx, answer.tx, answer.a, answer.b, answer.nr, answer.f) == (16, 2, 17, 0, 9, 163)


def test_telegram_header_is_little_endian() -> None:
    head = TelegramHeader(device_adr=4, data_area=0, data_adr=0x1018, data_idx=1, data_cnt=4,
                          data_type=0, function=1, payload=b"\x01")
    assert head.encode() == bytes([4, 0, 0x18, 0x10, 1, 4, 0, 1, 1])
    assert TelegramHeader.decode(head.encode()) == head


def test_task2_views_decode_the_seed_structures() -> None:
    raw = bytes([0x21, 0xC0, 255, 220, 1, 0, 2, 0, 3, 0, 4, 0]) + bytes(4) + b"\x06" + bytes(15)
    raw += b"\x02" + bytes(15) + bytes(16)
    diag = ComDiagnostics.decode(raw)
    assert diag.can_state_name == "OPERATE"
    assert diag.err_text == "HOST-watchdog error"
    assert (diag.usBus_Error_Cnt, diag.usBus_Off_Cnt, diag.usMsg_Time_Out, diag.usRx_Overflow) == (
        1, 2, 3, 4)
    assert diag.configured() == [1, 2]
    assert diag.operating() == [1]
    assert [b.name for b in diag.global_bits] == ["CTRL", "NRDY"]
    param = ComPlcParameter(bMode=2, usWatchDogTime=500)
    encoded = param.encode()
    assert encoded[:3] == bytes([2, 0xF4, 0x01]) and len(encoded) == 64
    assert ComPlcParameter.decode(encoded) == param
