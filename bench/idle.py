"""``python -m bench idle``: what a card costs while nobody uses it (issue 22).

The CPU time of the firmware process over a window (``--seconds``, 20 by default)
from /proc (``bench.cpu``): with no network and no host, on the same ``shm`` bus as
the nodes but with none, and with N configured simulated nodes (``--nodes``, 1 and 16
by default) that run as ``cifemu sim`` in a process of their own and are all
operational before the window starts; the host that configured them stays open and
does nothing. What a node adds is counted against the card on the same bus: the
``shm`` reader's own bounded sleep is the bus's cost, not the nodes'. Each figure is split into the
device loop (the firmware's main thread) and its other threads (the CAN master, the
controller's receive thread). Baseline, same run: a Python process
blocked on a Unix datagram socket, as a card asleep on its doorbell would be.

CPU time, not wall time: the figures hold on a loaded machine. The card on the bus runs
beside each card with nodes, and the two are measured over one window: what a node adds is
a difference of a few hundredths of a per cent, and the same idle card's CPU moves more
than that from one window to the next (2026-12-03, load 2-9: its device loop, at the same 4
wake-ups a second, took 0.056-0.102 % in 20 s windows one after the other), with whatever
else the machine does meanwhile. Side by side, that weighs on both alike. Each card's
thread wake-ups a second, which hardly move, are in ``per_thread``, and what each node adds
to them in ``added_wakeups_per_node_per_s``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from bench.can.card import SeparateBus, network_toml, simulated_card, start_uncontrolled
from bench.common import help_text, machine_info, progress, running_card, source_fingerprint
from bench.cpu import CpuSample, blocked_process, share
from dbm_tools.network import parse_network

NAME = "idle"
WINDOW_S = 20.0
NODE_COUNTS = (1, 16)
FIRST_NODE = 1
SETTLE_S = 1.0
"""Seconds between READY (or every node operating) and the window: start-up work ends."""


def window(pid: int, seconds: float) -> dict[str, Any]:
    """CPU shares of ``pid`` over ``seconds`` of wall time."""
    return windows([pid], seconds)[0]


def windows(pids: list[int], seconds: float) -> list[dict[str, Any]]:
    """CPU shares of each of ``pids`` over the same ``seconds`` of wall time."""
    before = [CpuSample.take(pid) for pid in pids]
    time.sleep(seconds)  # the measurement window itself, not a wait on a condition
    return [share(first, CpuSample.take(pid), pid) for pid, first in zip(pids, before, strict=True)]


def _card_without_network(seconds: float) -> dict[str, Any]:
    with running_card() as card:
        time.sleep(SETTLE_S)
        return window(card.pid, seconds)


@contextmanager
def _card_on_bus_without_nodes() -> Iterator[int]:
    """The card on a fresh channel of the nodes' bus (``shm``), nobody else on it; its pid."""
    interface, channel = SeparateBus().for_card()
    with running_card(extra=("--interface", interface, "--channel", channel)) as card:
        yield card.pid


@contextmanager
def _card_with_nodes(nodes: int) -> Iterator[int]:
    """A card with ``nodes`` operational nodes on a channel of its own; its pid."""
    addresses = list(range(FIRST_NODE, FIRST_NODE + nodes))
    description = network_toml(addresses)
    with simulated_card(description, separate=True) as card:
        start_uncontrolled(card, parse_network(description))
        yield card.pid


def _wakeups_per_s(figures: dict[str, Any]) -> float:
    return float(sum(thread["wakeups_per_s"] for thread in figures["per_thread"]))


def measure_idle(seconds: float, node_counts: tuple[int, ...]) -> dict[str, Any]:
    """The document: baseline, the bare card, the card on the bus, and beside it in the same
    window, the card with each node count in turn."""
    progress(f"{NAME}: baseline, a process blocked on a socket, {seconds} s")
    with blocked_process() as pid:
        baseline = window(pid, seconds)
    progress(f"{NAME}: card, no network, no host, {seconds} s")
    bare = _card_without_network(seconds)
    on_bus: list[dict[str, Any]] = []
    with_nodes: list[dict[str, Any]] = []
    with _card_on_bus_without_nodes() as on_bus_pid:
        for nodes in node_counts:
            # One at a time: a process's driver opens one image directory (DevOpenDriver).
            with _card_with_nodes(nodes) as pid:
                time.sleep(SETTLE_S)
                progress(f"{NAME}: the card on the nodes' bus (shm) with no nodes and, beside "
                         f"it, a card with {nodes} operational node(s), no host using them, "
                         f"{seconds} s")
                alone, entry = windows([on_bus_pid, pid], seconds)
            entry["nodes"] = nodes
            on_bus.append(alone)
            with_nodes.append(entry)
    per_node = [round((entry["process_pct"] - alone["process_pct"]) / entry["nodes"], 4)
                for entry, alone in zip(with_nodes, on_bus, strict=True)]
    per_node_wakeups = [
        round((_wakeups_per_s(entry) - _wakeups_per_s(alone)) / entry["nodes"], 2)
        for entry, alone in zip(with_nodes, on_bus, strict=True)
    ]
    return {
        "benchmark": NAME,
        "unit": "per cent of one core, CPU time over wall time",
        "window_s": seconds,
        "baseline_blocked_process": baseline,
        "card_no_network": bare,
        "card_on_shm_no_nodes": on_bus[0] if on_bus else None,
        "card_on_shm_no_nodes_beside_each": on_bus,
        "card_with_nodes": with_nodes,
        "added_per_node_pct": per_node,
        "added_per_node_note": "each card_with_nodes entry less the card on shm with no nodes "
                               "measured beside it over the same window "
                               "(card_on_shm_no_nodes_beside_each), divided by its node count",
        "added_wakeups_per_node_per_s": per_node_wakeups,
        "targets": {"card_pct_max": 0.5, "per_node_pct_max": 0.05},
        "machine": machine_info(),
        "source": source_fingerprint(),
    }


def run(count: int | None = None, warmup: int | None = None) -> dict[str, Any]:
    """``python -m bench idle``: ``count``, when given, is the window in seconds."""
    del warmup
    return measure_idle(float(count) if count else WINDOW_S, NODE_COUNTS)


def main(argv: list[str] | None = None) -> int:
    from bench.common import emit

    parser = argparse.ArgumentParser(prog="python -m bench.idle", description=help_text(__doc__))
    parser.add_argument("--seconds", type=float, default=WINDOW_S, help="window (default 20)")
    parser.add_argument("--nodes", type=int, nargs="*", default=list(NODE_COUNTS),
                        help="node counts to measure (default 1 16)")
    args = parser.parse_args(argv)
    emit(measure_idle(args.seconds, tuple(args.nodes)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
