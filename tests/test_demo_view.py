"""The demo shows the network first: top's nodes, and its lines in a file (issue 24 item 6)."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

from tests import commands
from tests.conftest import ROOT, wait_until


def test_the_demo_piped_to_a_file_prints_the_node_table_and_the_emcy(tmp_path: Path) -> None:
    out = tmp_path / "demo.txt"
    with out.open("w") as file:
        demo = subprocess.Popen([sys.executable, "-m", "cifemu", "demo", "--dpm-dir",
                                 str(tmp_path / "cif")], cwd=ROOT, stdout=file,
                                stderr=subprocess.PIPE, text=True)
        try:
            # A demo that ended (its firmware did not start) fails now, with its stderr,
            # not at pytest-timeout's 120 s (a run at load 24 did).
            wait_until(lambda: "EMCY node 4 4210h" in out.read_text() or demo.poll() is not None,
                       60, "node 4's EMCY in the demo's file")
            assert demo.poll() is None, demo.stderr.read() if demo.stderr else ""
        finally:
            demo.send_signal(signal.SIGINT)
            code = commands.wait(demo, 30)
    text = out.read_text()
    assert code == 0, demo.stderr.read() if demo.stderr else ""
    assert "Ctrl-C ends the demo. In another terminal:" in text
    table = text[text.index("nodes of demo.toml"):]
    for name in ("digital I/O 1", "digital I/O 2", "valve block", "sensor box"):
        row = next(line for line in table.splitlines() if name in line)
        assert "OPERATIONAL" in row and "…" not in row, row
    assert "Temperature: device temperature" in text  # the EMCY code's CiA 301 meaning


def test_the_live_view_shows_the_card_bits_one_key_away(tmp_path: Path) -> None:
    """top's view with a card view: c shows the card's flags, c again hides them."""
    import asyncio

    from rich.text import Text
    from textual.widgets import Static

    from host_api.top.app import TopApp
    from host_api.top.feed import CardFeed
    from host_api.top.model import CardModel

    model = CardModel()
    feed = CardFeed(model, 0, tmp_path)  # no card: the view says so, the key still works
    app = TopApp(model, feed, 0, tmp_path, card_view=lambda: Text("HostFlags READY RUN"))

    async def press() -> tuple[bool, bool, str, bool]:
        async with app.run_test() as pilot:
            card = app.query_one("#card", Static)
            before = card.has_class("visible")
            await pilot.press("c")
            shown = card.has_class("visible"), str(card.content)
            await pilot.press("c")
            return before, *shown, card.has_class("visible")

    assert asyncio.run(press()) == (False, True, "HostFlags READY RUN", False)
