"""`cifemu top`'s model on plain values: an image made by hand and frames as bytes."""

from __future__ import annotations

from pathlib import Path

from host_api.monitor.framebits import frame_bits
from tests.top_images import image, model


def test_nodes_come_from_the_file_and_the_card_bits(tmp_path: Path) -> None:
    card = model(tmp_path)
    card.update_image(image(nd_state=0x02), 100.0)
    rows = {row.node: row for row in card.node_rows()}
    assert rows[1].name == "pump" and rows[1].control == "heartbeat 1000 ms"
    assert rows[2].control == "guarding 100 ms x2"
    assert (rows[1].configured, rows[1].running) == (True, True)
    assert (rows[2].configured, rows[2].running) == (True, False)


def test_frames_give_nmt_state_age_emcy_and_events(tmp_path: Path) -> None:
    card = model(tmp_path)
    card.on_frame(0x701, b"\x00", timestamp=10.0)
    card.on_frame(0x701, b"\x05", timestamp=11.0)
    card.on_frame(0x702, b"\x84", timestamp=11.5)  # a guarding answer, toggle set
    card.on_frame(0x081, bytes.fromhex("1030010000000000"), timestamp=12.0)
    card.on_frame(0x000, b"\x02\x02", timestamp=13.0)
    rows = {row.node: row for row in card.node_rows()}
    assert rows[1].nmt_state == "OPERATIONAL" and rows[1].last_seen == 11.0
    assert rows[2].nmt_state == "STOPPED"
    assert rows[1].last_emcy == (0x3010, "Voltage")
    events = card.new_events(0)
    assert [e.split(" ", 1)[1] for e in events] == [
        "boot-up node 1", "EMCY node 1 3010h Voltage, error register 01h", "NMT stop: node 2"]
    assert card.new_events(2) == events[2:]


def test_err_event_is_logged_once_and_kept_as_the_nodes_last_error(tmp_path: Path) -> None:
    card = model(tmp_path)
    card.update_image(image(err=(2, 30)), 1.0)
    card.update_image(image(err=(2, 30)), 2.0)
    rows = {row.node: row for row in card.node_rows()}
    guarding = "guarding failed: no answer to node guarding within the life time"
    assert rows[2].last_error == (30, guarding)
    assert [e.split(" ", 1)[1] for e in card.new_events(0)] == [
        f"Err_Event 30 at node 2: {guarding}"]


def test_process_image_changes_history_and_bus_load(tmp_path: Path) -> None:
    card = model(tmp_path)
    card.update_image(image(inputs=bytes(8)), 1.0)
    card.update_image(image(inputs=bytes([9]) + bytes(7)), 2.0)
    rows = card.pdo_rows()
    tpdo1 = next(row for row in rows if row.slot.label == "TPDO1" and row.slot.node == 1)
    assert tpdo1.data == bytes([9]) + bytes(7) and tpdo1.changed_at == 2.0
    assert card.selected_slot() is not None
    card.select_next_value()  # RPDO1 node 1 -> TPDO1 node 1 ...
    for second in range(10):
        card.on_frame(0x181, bytes(8), timestamp=50.0 + second * 0.05)
    figures = card.bus(50.5)
    assert figures.frames_per_s == 10
    assert figures.load_percent is not None
    # TPDO1 of node 1 with eight zero bytes: 111 bits unstuffed, 15 stuff bits (framebits).
    assert abs(figures.load_percent - 100 * 10 * frame_bits(0x181, bytes(8)) / 125000) < 1e-9
    assert frame_bits(0x181, bytes(8)) > 47 + 64
    assert figures.can_state == "OPERATE"
