"""The tables of ``cifemu top`` as Rich renderables, for the live view and for ``--once``."""

from __future__ import annotations

from rich.console import Console, Group
from rich.measure import Measurement
from rich.table import Table
from rich.text import Text

from host_api.top.model import CHANGE_HIGHLIGHT_S, BusFigures, CardModel, NodeRow, PdoRow

NODE_COLUMNS = ("node", "name", "NMT state", "Nd_cfg", "Nd_state", "Nd_diag", "supervision",
                "seen", "last error", "last EMCY")


def _flag(value: bool) -> str:
    return "x" if value else "-"


def node_cells(row: NodeRow, now: float) -> tuple[str, ...]:
    """One node's row as text cells (the live view's DataTable takes the same)."""
    age = f"{now - row.last_seen:.1f} s ago" if row.last_seen is not None else "-"
    error = f"{row.last_error[0]} {row.last_error[1]}" if row.last_error else "-"
    emcy = f"{row.last_emcy[0]:04X}h {row.last_emcy[1]}" if row.last_emcy else "-"
    return (str(row.node), row.name, row.nmt_state, _flag(row.configured), _flag(row.running),
            _flag(row.diagnostic), row.control or "-", age, error, emcy)


def nodes_table(model: CardModel, now: float) -> Table:
    table = Table(title="nodes", expand=True)
    for column in NODE_COLUMNS:
        table.add_column(column)
    for row in model.node_rows():
        table.add_row(*node_cells(row, now))
    return table


def pdo_cells(row: PdoRow, now: float) -> tuple[Text, ...]:
    slot = row.slot
    changed = row.changed_at is not None and now - row.changed_at < CHANGE_HIGHLIGHT_S
    style = "bold yellow" if changed else ""
    values = slot.values(row.data)
    decimal = (", ".join(f"{name}={value}" for name, value in values) if values
               else " ".join(str(b) for b in row.data))
    place = "in" if slot.direction == "input" else "out"
    return (Text(f"{slot.node}"), Text(slot.label), Text(f"{slot.cob_id:03X}h"),
            Text(f"{place}[{slot.offset}..{slot.offset + slot.length - 1}]"),
            Text(row.data.hex(" "), style=style), Text(decimal, style=style))


def process_table(model: CardModel, now: float) -> Table:
    table = Table(title="process image", expand=True)
    for column in ("node", "PDO", "COB-ID", "bytes", "hex", "decimal"):
        table.add_column(column)
    for row in model.pdo_rows():
        table.add_row(*pdo_cells(row, now))
    return table


STALE_NOTE = ("stale: no firmware serves this image; every value below is the last one it "
              "wrote, not the card's now")
"""[ours] What ``--once`` prints above the values of a card whose firmware is gone."""


def bus_text(figures: BusFigures, stale: bool = False) -> str:
    load = (f"{figures.load_percent:.1f} % of {figures.bitrate} bit/s"
            if figures.load_percent is not None else "bit rate unknown")
    counters = "  ".join(f"{name} {value}" for name, value in figures.counters.items())
    state = f"{figures.can_state} (stale)" if stale else figures.can_state
    lost = (f"  {figures.tap_lost} frames lost (tap reader too slow)" if figures.tap_lost
            else "")
    return (f"CAN_state {state}  {figures.frames_per_s:.0f} frames/s ({load})  "
            f"{counters}{lost}")


def snapshot(model: CardModel, now: float, title: str, stale: bool = False) -> Group:
    """Everything at once, for ``--once``; ``stale``: the firmware is gone, and what the
    image shows is its last word (marked as such, never as the card's state)."""
    figures = model.bus(now)
    events = Table(title="events", show_header=False, expand=True)
    events.add_column()
    for line in list(model.events)[-10:]:
        events.add_row(line)
    head = [Text(title, style="bold")] + ([Text(STALE_NOTE, style="yellow")] if stale else [])
    return Group(*head, Text(bus_text(figures, stale)), nodes_table(model, now),
                 process_table(model, now), events)


def natural_width(renderable: Group, limit: int = 1000) -> int:
    """The columns ``renderable`` needs to show every cell whole (tables that expand
    measured at their content), for output that goes to no terminal [ours]."""
    console = Console(width=limit)
    widths = [Measurement.get(console, console.options, part).maximum
              for part in renderable.renderables]
    return max([80, *widths])
