"""``python -m bench scaling``: what the card costs as its work grows (issue 22, item 4).

Three sections, each card figure beside its baseline from the same run:

  nodes  the PDO loop (p50/p99) and expedited SDO through the mailbox with 1, 16 and 126
         active nodes (bench.can.active_nodes); baseline: canopen RemoteNode / SdoClient
         on the same simulated nodes in this process
  cards  1, 2 and 4 cards (boards 0-3) at once, each with its own simulated network and
         its own host: per-card PDO loop p50/p99, CPU of the firmware processes
         (bench.can.cards); baseline: the one-card run
  cost   per cent of a core per 1,000 frames/s, fitted over windows of about 500, 2,000
         and 8,000 PDO frames/s, and the idle card (bench.can.frame_cost)

The nodes run as ``cifemu sim`` on a fresh ``shm`` channel per card. About 3 minutes
on an idle 2-core machine; --quick (shorter loops and windows) about 1. --count N sets
the PDO loop round trips of every node count, --warmup N the round trips before them,
--cards-seconds S the window in which the cards' hosts run their loops together (10 s;
--quick 3 s); tests/test_bench_scaling.py's tiny run gives 1.
``python -m bench --load scaling`` runs it beside two busy processes. The JSON gives the
load average at the start (machine.loadavg) and at the end (loadavg_at_end).

    python -m bench.scaling [--quick] [--only nodes|cards|cost ...] [--nodes N ...]
                            [--cards K ...] [--count N] [--warmup N] [--cards-seconds S]
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from collections.abc import Sequence
from typing import Any

from bench.can.active_nodes import COUNTS, NODE_COUNTS, WARMUP, active_nodes
from bench.can.cards import CARD_COUNTS, several_cards
from bench.can.frame_cost import frame_cost
from bench.common import add_size_arguments, emit, help_text, machine_info, source_fingerprint
from dpm.image import MAX_DEV_BOARDS

NAME = "scaling"
SECTIONS = ("nodes", "cards", "cost")
MAX_NODES = 126
"""The throughput phase's network: node 127 is left for a device of the user's own."""


def _load() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def summary(document: dict[str, Any]) -> dict[str, Any]:
    """The figures the README's table carries, and how they grow with the work."""
    result: dict[str, Any] = {}
    if runs := document.get("active_nodes"):
        result["active_nodes"] = [{
            "nodes": run["nodes"],
            "pdo_loop_us": {"p50": run["cif"]["pdo_loop"]["latency_us"].get("p50"),
                            "p99": run["cif"]["pdo_loop"]["latency_us"].get("p99")},
            "baseline_pdo_loop_us": {"p50": run["baseline"]["pdo_loop"]["latency_us"].get("p50"),
                                     "p99": run["baseline"]["pdo_loop"]["latency_us"].get("p99")},
            "sdo_per_s": run["cif"]["sdo"]["expedited_uploads_per_s"],
            "baseline_sdo_per_s": run["baseline"]["sdo"]["expedited_uploads_per_s"],
            "ratio_to_baseline": {k: v for k, v in run["ratio_to_baseline"].items()
                                  if k != "definition"},
        } for run in runs]
        first, last = runs[0], runs[-1]

        def growth(side: str) -> float | None:
            low = first[side]["pdo_loop"]["latency_us"].get("p50")
            high = last[side]["pdo_loop"]["latency_us"].get("p50")
            return round(high / low, 2) if low and high else None

        result["pdo_loop_p50_growth"] = {
            "definition": f"p50 with {last['nodes']} nodes / p50 with {first['nodes']}",
            "cif": growth("cif"), "baseline": growth("baseline")}
    if cards := document.get("cards"):
        result["cards"] = [{
            "cards": run["cards"],
            "pdo_loop_p50_us": [card.get("latency_us", {}).get("p50") for card in run["per_card"]],
            "pdo_loop_p99_us": [card.get("latency_us", {}).get("p99") for card in run["per_card"]],
            "pdo_loop_failures": [card.get("failures") for card in run["per_card"]],
            "firmware_sdo_timeouts": [card["firmware_log"]["sdo_timeouts"]
                                      for card in run["per_card"]],
            "firmware_total_pct": run["firmware_total_pct"],
            "firmware_per_card_pct": run["firmware_per_card_pct"],
            "sim_total_pct": run["sim_total_pct"],
        } for run in cards["runs"]]
    if cost := document.get("frame_cost"):
        result["cpu_per_1000_frames_per_s"] = {
            "firmware_pct": cost["firmware"]["pct_per_1000_frames_per_s"],
            "sim_pct": cost["sim"]["pct_per_1000_frames_per_s"],
            "idle_firmware_pct": cost["idle"]["firmware_pct"],
            "idle_sim_pct": cost["idle"]["sim_pct"],
        }
    return result


def scaling(*, quick: bool = False, sections: Sequence[str] = SECTIONS,
            node_counts: Sequence[int] = NODE_COUNTS, card_counts: Sequence[int] = CARD_COUNTS,
            count: int | None = None, warmup: int | None = None,
            cards_seconds: float | None = None) -> dict[str, Any]:
    """The benchmark's JSON document; ``cards_seconds`` overrides the cards' window."""
    logging.getLogger("canopen").setLevel(logging.WARNING)
    started = time.perf_counter()
    document: dict[str, Any] = {
        "benchmark": NAME,
        "description": "the card as its work grows: active nodes, cards at once, frames/s; "
                       "nodes in cifemu sim on shm, each card figure beside its baseline from "
                       "the same run",
        "machine": machine_info(),
        "source": source_fingerprint(),
        "params": {"quick": quick, "sections": list(sections), "node_counts": list(node_counts),
                   "card_counts": list(card_counts), "count": count, "warmup": warmup,
                   "cards_seconds": cards_seconds},
    }
    if "nodes" in sections:
        document["active_nodes"] = [active_nodes(nodes, quick, count, warmup)
                                    for nodes in node_counts]
    if "cards" in sections:
        document["cards"] = several_cards(tuple(card_counts), quick, cards_seconds)
    if "cost" in sections:
        document["frame_cost"] = frame_cost(quick)
    document["summary"] = summary(document)
    document["loadavg_at_end"] = _load()
    document["run_seconds"] = round(time.perf_counter() - started, 1)
    return document


def run(count: int | None = None, warmup: int | None = None) -> dict[str, Any]:
    """``python -m bench scaling``: every section, full length."""
    return scaling(count=count, warmup=warmup)


def run_quick(count: int | None = None, warmup: int | None = None) -> dict[str, Any]:
    """``python -m bench scaling --quick``: every section, short loops and windows."""
    return scaling(quick=True, count=count, warmup=warmup)


def _ranged(low: int, high: int, what: str) -> Any:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = 0
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{what} from {low} to {high}, not {text!r}")
        return value

    return parse


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = 0.0
    if not 0 < value <= 3600:
        raise argparse.ArgumentTypeError(f"a window from 0 to 3600 s, not {text!r}")
    return value


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.scaling", description=help_text(__doc__),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="short loops and windows: about a minute")
    parser.add_argument("--only", nargs="+", choices=SECTIONS, metavar="SECTION",
                        help=f"run only these sections: {', '.join(SECTIONS)}")
    parser.add_argument("--nodes", nargs="+", type=_ranged(1, MAX_NODES, "a node count"),
                        default=list(NODE_COUNTS), metavar="N",
                        help=f"active node counts (default {' '.join(map(str, NODE_COUNTS))})")
    parser.add_argument("--cards", nargs="+", type=_ranged(1, MAX_DEV_BOARDS, "a card count"),
                        default=list(CARD_COUNTS), metavar="K",
                        help=f"card counts (default {' '.join(map(str, CARD_COUNTS))})")
    add_size_arguments(parser, "PDO loop round trips per node count, default "
                       + ", ".join(f"{n}: {c}" for n, c in COUNTS.items()), f"default {WARMUP}")
    parser.add_argument("--cards-seconds", type=_seconds, default=None, metavar="S",
                        help="the window in which the cards' hosts run their loops "
                             "together, in seconds (default 10; --quick 3)")
    args = parser.parse_args(argv)
    emit(scaling(quick=args.quick, sections=args.only or SECTIONS, node_counts=args.nodes,
                 card_counts=args.cards, count=args.count, warmup=args.warmup,
                 cards_seconds=args.cards_seconds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
