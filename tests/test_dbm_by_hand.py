"""A CANopen DBM written by hand from docs/dbm.md alone, as a user without SyCon would.

Nothing from dbm_tools builds it: only struct and the words of docs/dbm.md section 1
and the seed's data sets. The card must take the download and run from it.
"""

from __future__ import annotations

import struct
from pathlib import Path

from host_api import driver as d
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload
from tests.conftest import start_card, wait_until

ROOT_WORDS = 208


def block(kind: int, parent: int, position: int, payload: bytes) -> bytes:
    pad = len(payload) % 2
    body = payload + bytes(pad)
    return struct.pack("<6H", kind, 0, parent, position, pad, 12 + len(body)) + body


def table(number: int, name: str, records: list[bytes], at: int,
          key_length: int = 0) -> tuple[bytes, list[int]]:
    """The blocks of one table starting at word ``at``; also its root slot values."""
    out = b""
    slots = []
    if key_length:
        order = sorted(range(len(records)), key=lambda i: records[i][:key_length])
        index = struct.pack("<31H", *([i + 1 for i in order] + [0] * (31 - len(records))))
        # the table number, which docs/dbm.md says the reader accepts for a key index
        out += block(2, 0, number, index)
    directory_at = at + len(out) // 2
    descriptor_at = directory_at + (12 + 62) // 2
    descriptor = struct.pack("<7H", 0x10 | key_length if key_length else 0, len(records),
                             0xFFFF, len(records), 0, len(records), 30)
    descriptor += name.encode().ljust(18, b"\0")
    descriptor_block = block(4, number, 6, descriptor)
    pointers = [descriptor_at]
    record_blocks = b""
    word = descriptor_at + len(descriptor_block) // 2
    for slot, record in enumerate(records, 1):
        pointers.append(word)
        blk = block(0, number, 6 + slot, record)
        record_blocks += blk
        word += len(blk) // 2
    directory = block(1, 0, number, struct.pack("<31H", *(pointers + [0] * (31 - len(pointers)))))
    out += directory + descriptor_block + record_blocks
    slots = [directory_at] + ([at] if key_length else [])
    return out, slots


def hand_made_data_area() -> bytes:
    glob = b"CANopen \0" + bytes(10) + bytes([1]) + struct.pack("<hH", 1, 0) + bytes(4)
    glob += bytes([0]) + bytes(3) + struct.pack("<H", 0)
    assert len(glob) == 34
    bus = bytes([2]) + struct.pack("<HH", 0x80, 0) + bytes([0, 0])
    # Node 1: seed 5.2.5.1 — header, empty SDO list, RXPDO + TXPDO, ADD-tab.
    pdos = struct.pack("<BBHBH", 0, 8, 0x201, 255, 0) + struct.pack("<BBHBH", 1, 8, 0x181, 255, 0)
    body = struct.pack("<BHHHHHBBB", 0xC0, 0x000F, 0x0191, 0x81, 0x701, 1000, 0, 0, 0)
    body += struct.pack("<H", 2) + struct.pack("<H", 2 + len(pdos)) + pdos
    body += struct.pack("<HBBHH", 8, 1, 1, 0, 0)
    node = bytes([1]) + struct.pack("<H", 2 + len(body)) + body
    area = bytearray(2 * ROOT_WORDS)
    root = [0, 0, 12, 3, 0, 0, 0, 1] + [0] * (ROOT_WORDS - 8)
    at = ROOT_WORDS
    for number, name, records, key in ((8, "GLOBAL", [glob], 0), (10, "BUS_CAN", [bus], 0),
                                       (12, "NODES", [node], 1)):
        blocks, slots = table(number, name, records, at, key)
        root[number] = slots[0]
        if key:
            root[number + 1] = slots[1]
        area += blocks
        at += len(blocks) // 2
    root[5] = root[6] = len(area) // 2
    words = list(struct.unpack(f"<{ROOT_WORDS}H", struct.pack(f"<{ROOT_WORDS}H", *root)))
    tail = list(struct.unpack(f"<{(len(area) - 2 * ROOT_WORDS) // 2}H", area[2 * ROOT_WORDS :]))
    words[0] = sum(words[1:] + tail) & 0xFFFF
    area[: 2 * ROOT_WORDS] = struct.pack(f"<{ROOT_WORDS}H", *words)
    return bytes(area)


def test_a_dbm_written_from_dbm_md_runs_the_card(tmp_path: Path) -> None:
    network = tmp_path / "net.toml"
    network.write_text("[[node]]\nid = 1\n")
    header = b"DBMFILE  \0" + b"Nov 22 2026\0" + bytes(8) + struct.pack("<HHI", 44, 1, 0)
    area = hand_made_data_area()
    path = tmp_path / "hand.dbm"
    path.write_bytes(header + struct.pack("<HI", len(area), 44) + area)
    card = start_card(tmp_path, 0, "--simulate", str(network))
    try:
        assert d.DevOpenDriver(tmp_path) == 0 and d.DevInitBoard(0) == 0
        assert DevDownload(0, CONFIGURATION_DOWNLOAD, path) == 0
        assert d.DevReset(0, d.COLDSTART, 5000) == 0
        wait_until(lambda: d.DevGetTaskState(0, 2, 64)[1][32] == 0x02, 10, "node 1 in Nd_state")
        assert d.DevGetInfo(0, d.GET_IO_INFO, 1)[1] == b"\x01"  # COM
    finally:
        d.DevCloseDriver()
        card.stop()
