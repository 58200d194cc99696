"""``python -m bench idle``: what a card costs while nobody uses it (issue 22).

The CPU time of the firmware process over a window (``--seconds``, 10 by default)
from /proc (``bench.cpu``): with no network and no host, on the same ``shm`` bus as
the nodes but with none, and with N configured simulated nodes (``--nodes``, 1 and 16
by default) that run as ``cifemu sim`` in a process of their own and are all
operational before the window starts; the host that configured them stays open and
does nothing. What a node adds is counted against the card on the same bus: the
``shm`` reader's own bounded sleep is the bus's cost, not the nodes'. Each figure is split into the
device loop (the firmware's main thread) and its other threads (the CAN master, the
controller's receive thread). Baseline, same run: a Python process
blocked on a Unix datagram socket, as a card asleep on its doorbell would be.

CPU time, not wall time: the figures hold on a loaded machine.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

from bench.can.card import SeparateBus, network_toml, simulated_card, start_uncontrolled
from bench.common import help_text, machine_info, progress, running_card, source_fingerprint
from bench.cpu import CpuSample, blocked_process, share
from dbm_tools.network import parse_network

NAME = "idle"
WINDOW_S = 10.0
NODE_COUNTS = (1, 16)
FIRST_NODE = 1
SETTLE_S = 1.0
"""Seconds between READY (or every node operating) and the window: start-up work ends."""


def window(pid: int, seconds: float) -> dict[str, Any]:
    """CPU shares of ``pid`` over ``seconds`` of wall time."""
    before = CpuSample.take(pid)
    time.sleep(seconds)  # the measurement window itself, not a wait on a condition
    return share(before, CpuSample.take(pid), pid)


def _card_without_network(seconds: float) -> dict[str, Any]:
    with running_card() as card:
        time.sleep(SETTLE_S)
        return window(card.pid, seconds)


def _card_on_bus_without_nodes(seconds: float) -> dict[str, Any]:
    """The card on a fresh channel of the nodes' bus (``shm``), nobody else on it."""
    interface, channel = SeparateBus().for_card()
    with running_card(extra=("--interface", interface, "--channel", channel)) as card:
        time.sleep(SETTLE_S)
        return window(card.pid, seconds)


def _card_with_nodes(nodes: int, seconds: float) -> dict[str, Any]:
    addresses = list(range(FIRST_NODE, FIRST_NODE + nodes))
    description = network_toml(addresses)
    with simulated_card(description, separate=True) as card:
        start_uncontrolled(card, parse_network(description))
        time.sleep(SETTLE_S)
        figures: dict[str, Any] = window(card.pid, seconds)
        figures["nodes"] = nodes
        return figures


def measure_idle(seconds: float, node_counts: tuple[int, ...]) -> dict[str, Any]:
    """The document: baseline, the bare card, the card with each node count."""
    progress(f"{NAME}: baseline, a process blocked on a socket, {seconds} s")
    with blocked_process() as pid:
        baseline = window(pid, seconds)
    progress(f"{NAME}: card, no network, no host, {seconds} s")
    bare = _card_without_network(seconds)
    progress(f"{NAME}: card on the nodes' bus (shm), no nodes, no host, {seconds} s")
    on_bus = _card_on_bus_without_nodes(seconds)
    with_nodes = []
    for nodes in node_counts:
        progress(f"{NAME}: card with {nodes} operational node(s), {seconds} s")
        with_nodes.append(_card_with_nodes(nodes, seconds))
    per_node = [
        round((entry["process_pct"] - on_bus["process_pct"]) / entry["nodes"], 4)
        for entry in with_nodes
    ]
    return {
        "benchmark": NAME,
        "unit": "per cent of one core, CPU time over wall time",
        "window_s": seconds,
        "baseline_blocked_process": baseline,
        "card_no_network": bare,
        "card_on_shm_no_nodes": on_bus,
        "card_with_nodes": with_nodes,
        "added_per_node_pct": per_node,
        "added_per_node_note": "each card_with_nodes entry less card_on_shm_no_nodes, divided "
                               "by its node count",
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
    parser.add_argument("--seconds", type=float, default=WINDOW_S, help="window (default 10)")
    parser.add_argument("--nodes", type=int, nargs="*", default=list(NODE_COUNTS),
                        help="node counts to measure (default 1 16)")
    args = parser.parse_args(argv)
    emit(measure_idle(args.seconds, tuple(args.nodes)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
