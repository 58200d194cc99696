"""`cifemu top`: the snapshot and the live view driven headless by Textual's pilot (real card)."""

from __future__ import annotations

import asyncio
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from textual.widgets import DataTable, RichLog, Static

from cifemu.commands.top import build_model
from dpm.tap import TapSubscriber, decode_frame
from host_api.board import Board
from host_api.status import read_image, snapshot
from host_api.top.app import TopApp
from host_api.top.feed import CardFeed
from host_api.top.render import pdo_cells
from tests import commands
from tests.conftest import ROOT, LoadDeadline, start_card, wait_until

DEMO = ROOT / "cifemu" / "examples" / "demo.toml"


def test_once_prints_nodes_with_names_states_and_the_mapped_process_image(
        tmp_path: Path) -> None:
    card = start_card(tmp_path, 0, "--simulate", str(DEMO), "--configure")
    try:
        out = commands.run([sys.executable, "-m", "cifemu", "top", "--once", "--dpm-dir",
                            str(tmp_path), "--sample", "2.5"], capture_output=True, text=True,
                           timeout=60, cwd=ROOT, env={**os.environ, "COLUMNS": "200"})
    finally:
        card.stop()
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    row = next(line for line in lines if "valve block" in line)  # the remembered network file
    assert "OPERATIONAL" in row and "guarding 200 ms x3" in row and "s ago" in row
    assert any("digital I/O 1" in line and "heartbeat 1000 ms" in line for line in lines)
    assert any("TPDO1" in line and "184h" in line and "in[24..31]" in line for line in lines)
    assert "frames/s" in out.stdout and "% of 500000 bit/s" in out.stdout


def test_once_without_a_card_is_one_line(tmp_path: Path) -> None:
    out = commands.run([sys.executable, "-m", "cifemu", "top", "--once", "--dpm-dir",
                        str(tmp_path)], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 1 and out.stderr.startswith("cifemu top: no image")
    assert out.stderr.count("\n") == 1


def emcy_counter(tap: TapSubscriber, node: int) -> Callable[[], int]:
    """Counts the EMCYs of ``node`` the card's tap shows from now on (replays left out);
    each call reads what arrived."""
    seen = 0

    def count() -> int:
        nonlocal seen
        while (batch := tap.recv(0.001)) is not None:
            for datagram in batch.frames:
                frame, replay = decode_frame(datagram)
                seen += frame.arbitration_id == 0x80 + node and not replay
        return seen

    return count


def snapshot_of(directory: Path) -> dict[str, Any]:
    image = read_image(0, str(directory))
    assert image is not None
    return snapshot(image)


def _text(app: TopApp, selector: str) -> str:
    return str(app.query_one(selector, Static).content)


def _log_lines(app: TopApp) -> list[str]:
    return [strip.text for strip in app.query_one("#events", RichLog).lines]


async def _until(pilot: object, condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = LoadDeadline(timeout)
    while not condition():
        assert deadline.left() > 0, f"timed out waiting for {what}"
        await asyncio.sleep(0.05)


def test_live_view_keys_act_on_the_selected_node(tmp_path: Path) -> None:
    card = start_card(tmp_path, 0, "--simulate", str(DEMO), "--configure")
    model = build_model(DEMO)
    feed = CardFeed(model, 0, tmp_path)
    feed.start()

    def row_of(node: int) -> dict[str, str]:
        table = app.query_one("#nodes", DataTable)
        cells = table.get_row(str(node))
        return {str(key): str(cell) for key, cell in zip(
            [c.key.value for c in table.ordered_columns], cells, strict=True)}

    async def scenario() -> None:
        async with app.run_test(size=(160, 50)) as pilot:
            await _until(pilot, lambda: len(app.query_one("#nodes", DataTable).rows) >= 4
                         and row_of(2)["Nd_state"] == "x", 15, "node 2 in data exchange")
            assert row_of(3)["name"] == "valve block"
            await pilot.press("down")  # node 2
            await pilot.press("t")
            await _until(pilot, lambda: any("NMT stop node 2: done" in line
                                            for line in _log_lines(app)), 10, "the stop's answer")
            await _until(pilot, lambda: row_of(2)["Nd_state"] == "-"
                         and row_of(2)["NMT state"] == "STOPPED", 10, "node 2 stopped")
            await pilot.press("s")
            await _until(pilot, lambda: row_of(2)["NMT state"] == "OPERATIONAL", 10,
                         "node 2 started again")
            await pilot.press("o")
            for key in "1000 0":
                await pilot.press("space" if key == " " else key)
            await pilot.press("enter")
            await _until(pilot, lambda: any("SDO read node 2 1000h/00h = 91 01 0f 00" in line
                                            for line in _log_lines(app)), 10, "the SDO answer")
            await pilot.press("o")
            for key in "zz":
                await pilot.press(key)
            await pilot.press("enter")
            await _until(pilot, lambda: any("is no object address" in line
                                            for line in _log_lines(app)), 5, "the typing error")
            # the process image: an output change is highlighted in hex and decimal
            with Board(0, tmp_path) as board:
                board.exchange_io(bytes([7]) * 8)
            await _until(pilot, lambda: model.pdo_rows()[0].data == bytes([7]) * 8, 10,
                         "new outputs")
            cells = pdo_cells(model.pdo_rows()[0], time.time())
            assert str(cells[4]) == "07 07 07 07 07 07 07 07" and cells[4].style == "bold yellow"
            assert "history of RPDO1 node 1" in _text(app, "#spark-label")
            await pilot.press("v")
            await _until(pilot, lambda: "history of TPDO1 node 1" in _text(app, "#spark-label"),
                         5, "the next value followed")
            # node 4's EMCY burst (5 s after the simulation started), with its CiA 301 meaning
            await _until(pilot, lambda: "4210h Temperature: device temperature" in
                         row_of(4)["last EMCY"], 20, "node 4's EMCY")
            assert "frames/s" in _text(app, "#bus")

    app = TopApp(model, feed, 0, tmp_path, interval=0.1)
    try:
        asyncio.run(scenario())
    finally:
        feed.stop()
        card.stop()


def test_a_view_started_after_an_emcy_still_shows_it_and_a_trace_does_not(
        tmp_path: Path) -> None:
    """The demo's network with node 4's burst 1 s after it is started, not 5: the tap below
    subscribes as soon as the card is READY, before the card has started any node."""
    network = tmp_path / "demo.toml"
    network.write_text(DEMO.read_text().replace("after_s = 5.0", "after_s = 1.0"))
    assert network.read_text() != DEMO.read_text()
    card = start_card(tmp_path, 0, "--simulate", str(network), "--configure")
    tap = TapSubscriber(card.path)
    try:
        emcys = emcy_counter(tap, 4)
        wait_until(lambda: emcys() == 3, 20, "node 4's EMCY burst (3 EMCYs) on the tap")
        assert 4 in snapshot_of(tmp_path)["task2state"]["nd_diag"]
        out = commands.run([sys.executable, "-m", "cifemu", "top", "--once", "--dpm-dir",
                            str(tmp_path), "--sample", "0.5"], capture_output=True, text=True,
                           timeout=60, cwd=ROOT, env={**os.environ, "COLUMNS": "220"})
        trace = commands.run([sys.executable, "-m", "cifemu", "monitor", "--dpm-dir",
                              str(tmp_path), "--type", "emcy", "--duration", "1.5"],
                             capture_output=True, text=True, timeout=60, cwd=ROOT)
    finally:
        tap.close()
        card.stop()
    row = next(line for line in out.stdout.splitlines() if "sensor box" in line)
    assert "4210h Temperature: device temperature" in row
    assert trace.returncode == 0 and trace.stdout == ""
