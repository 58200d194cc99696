"""The live view of ``cifemu top`` (Textual): nodes, process image, bus, events, keys.

Keys act on the node selected in the nodes table: s start, t stop,
p pre-operational, r reset node (NMT through the card's mailbox), o read an
object by SDO (type its index and subindex in hex), v follow the next PDO's
value in the sparkline, c the card's own state (flags, info areas, Task2State; where
the caller gives it, as ``cifemu demo`` does), q quit. Actions run in worker threads, so a node that
does not answer never freezes the screen; their outcome goes to the event log.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import ClassVar

from rich.console import RenderableType
from textual.app import App, ComposeResult
from textual.binding import Binding, BindingType
from textual.css.query import NoMatches
from textual.widgets import DataTable, Footer, Header, Input, RichLog, Sparkline, Static

from dpm.commands import Nmt
from host_api.top.actions import nmt, parse_sdo_address, sdo_read
from host_api.top.feed import CardFeed
from host_api.top.model import CardModel
from host_api.top.render import NODE_COLUMNS, bus_text, node_cells, process_table


class TopApp(App[None]):
    TITLE = "cifemu top"
    CSS = """
    #nodes { height: auto; max-height: 40%; }
    #pdos { height: auto; }
    #spark { height: 3; }
    #events { height: 1fr; min-height: 5; }
    #sdo { display: none; }
    #sdo.visible { display: block; }
    #card { display: none; height: auto; }
    #card.visible { display: block; }
    """
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("s", "nmt('start')", "start"),
        Binding("t", "nmt('stop')", "stop"),
        Binding("p", "nmt('preop')", "pre-op"),
        Binding("r", "nmt('reset')", "reset node"),
        Binding("o", "ask_sdo", "SDO read"),
        Binding("v", "next_value", "next value"),
        Binding("c", "card", "card bits"),
        Binding("q", "quit", "quit"),
    ]
    NMT_KEYS: ClassVar[dict[str, Nmt]] = {
        "start": Nmt.START, "stop": Nmt.STOP, "preop": Nmt.PREOPERATIONAL,
        "reset": Nmt.RESET_NODE,
    }

    def __init__(self, model: CardModel, feed: CardFeed, board: int, directory: Path,
                 interval: float = 0.25,
                 card_view: Callable[[], RenderableType | None] | None = None) -> None:
        super().__init__()
        self.card_view = card_view
        """What the c key shows: the card's flags and areas (None: the key says so)."""
        self.model = model
        self.feed = feed
        self.board = board
        self.directory = directory
        self.interval = interval
        self._events_seen = 0
        self._node_keys: list[int] = []

    def compose(self) -> ComposeResult:
        yield Header()
        yield Static(id="bus")
        yield Static(id="card")
        yield DataTable(id="nodes", cursor_type="row", zebra_stripes=True)
        yield Static(id="pdos")
        yield Static(id="spark-label")
        yield Sparkline([], id="spark")
        yield Input(placeholder="object to read: index subindex in hex, e.g. 1017 0", id="sdo")
        yield RichLog(id="events", max_lines=500)
        yield Footer()

    def on_mount(self) -> None:
        self.sub_title = f"board {self.board} in {self.directory}"
        table = self.query_one("#nodes", DataTable)
        for column in NODE_COLUMNS:
            table.add_column(column, key=column)
        self.refresh_view()
        self.set_interval(self.interval, self.refresh_view)

    # --- refreshing ------------------------------------------------------------------------

    def refresh_view(self) -> None:
        now = time.time()
        try:
            card = self.query_one("#card", Static)
        except NoMatches:
            return  # the interval fired while the app closes: its widgets are gone
        if card.has_class("visible") and self.card_view is not None:
            view = self.card_view()
            if view is not None:
                card.update(view)
        if not self.feed.poll_image():
            self.query_one("#bus", Static).update(f"board {self.board}: no image")
            return
        self.query_one("#bus", Static).update(bus_text(self.model.bus(now)))
        self._refresh_nodes(now)
        self.query_one("#pdos", Static).update(process_table(self.model, now))
        slot = self.model.selected_slot()
        label = f"history of {slot.label} node {slot.node} (v: next)" if slot else "no PDOs"
        self.query_one("#spark-label", Static).update(label)
        self.query_one("#spark", Sparkline).data = [float(v) for v in self.model.history]
        log = self.query_one("#events", RichLog)
        for line in self.model.new_events(self._events_seen):
            log.write(line)
            self._events_seen += 1

    def _refresh_nodes(self, now: float) -> None:
        table = self.query_one("#nodes", DataTable)
        rows = self.model.node_rows()
        keys = [row.node for row in rows]
        if keys != self._node_keys:
            cursor = table.cursor_row
            table.clear()
            for row in rows:
                table.add_row(*node_cells(row, now), key=str(row.node))
            self._node_keys = keys
            if rows:
                table.move_cursor(row=min(cursor, len(rows) - 1))
            return
        for row in rows:
            for column, cell in zip(NODE_COLUMNS, node_cells(row, now), strict=True):
                table.update_cell(str(row.node), column, cell)

    # --- actions ---------------------------------------------------------------------------

    def selected_node(self) -> int | None:
        table = self.query_one("#nodes", DataTable)
        if not self._node_keys or table.cursor_row < 0:
            return None
        return self._node_keys[min(table.cursor_row, len(self._node_keys) - 1)]

    def _in_background(self, job: Callable[[], str]) -> None:
        def work() -> None:
            text = job()
            self.call_from_thread(self.model.log, time.time(), text)

        self.run_worker(work, thread=True, exclusive=False)

    def action_nmt(self, which: str) -> None:
        node = self.selected_node()
        if node is None:
            self.model.log(time.time(), "no node selected")
            return
        command = self.NMT_KEYS[which]
        self.model.log(time.time(), f"host: NMT {which} node {node}")
        self._in_background(lambda: nmt(self.board, self.directory, node, command))

    def action_ask_sdo(self) -> None:
        box = self.query_one("#sdo", Input)
        box.add_class("visible")
        box.value = ""
        box.focus()

    def on_input_submitted(self, event: Input.Submitted) -> None:
        box = event.input
        box.remove_class("visible")
        self.query_one("#nodes", DataTable).focus()
        node = self.selected_node()
        try:
            index, subindex = parse_sdo_address(event.value)
        except ValueError as exc:
            self.model.log(time.time(), str(exc))
            return
        if node is None:
            self.model.log(time.time(), "no node selected")
            return
        self.model.log(time.time(), f"host: SDO read node {node} {index:04X}h/{subindex:02X}h")
        self._in_background(lambda: sdo_read(self.board, self.directory, node, index, subindex))

    def action_card(self) -> None:
        """Show or hide the card's own state above the nodes."""
        if self.card_view is None:
            self.model.log(time.time(), "c: `cifemu status` shows the card's flags and areas")
            return
        self.query_one("#card", Static).toggle_class("visible")
        self.refresh_view()

    def action_next_value(self) -> None:
        self.model.select_next_value()
