"""The CAN benchmark's JSON document and command line: the phases in order.

CANopen services of the card against simulated nodes, each next to python canopen or
python-can talking straight to the same simulated nodes in this process:

  latency     PDO loop round trip, 1 node (bench.can.pdo_loop)
  throughput  PDO frames/s, 126 nodes, one value in flight each (bench.can.throughput)
  sdo         COM_SDO_Up_Download, expedited and a 247-byte DOMAIN (bench.can.sdo)
  boot        127 nodes from a stored database to Nd_state (bench.can.boot)
  sync        jitter of a 1 ms SYNC, idle and under PDO load (bench.can.sync)

--profile adds a py-spy profile of the firmware during an extra throughput window.
--nodes N caps every phase's network at N nodes. Where os.cpu_count() is 1 (inside
tools/vcan-vm, say) the phases default to 16 nodes (SMALL_NODES): the full configuration's 126
booting nodes saturate one CPU there, and the card's time-outs then fail nodes that did
answer (docs/benchmarks.md "SocketCAN under User-Mode Linux"). --interface socketcan --channel vcan0
runs the phases whose nodes are a process of their own (throughput, boot, sync) on that
link instead of a fresh shm channel. The JSON's params say which configuration ran.

    python -m bench.can [--count N] [--warmup N] [--only NAME ...] [--profile]
                        [--nodes N] [--interface shm|socketcan] [--channel NAME]
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from collections.abc import Sequence
from typing import Any

from bench.can.boot import BOOT_NODES, BOOT_REPEATS, boot
from bench.can.card import OPERATING_POLL_S, SeparateBus
from bench.can.echo import STALL_S
from bench.can.pdo_loop import pdo_latency
from bench.can.sdo import DOMAIN_BYTES, SDO_SECONDS, sdo
from bench.can.sync import SYNC_NODES, SYNC_PERIOD_MS, SYNC_SECONDS, sync_jitter
from bench.can.throughput import (
    THROUGHPUT_NODES,
    THROUGHPUT_SECONDS,
    active_windows,
    pdo_throughput,
)
from bench.common import (
    add_size_arguments,
    emit,
    machine_info,
    source_fingerprint,
)

NAME = "can"
PHASES = ("latency", "throughput", "sdo", "boot", "sync")

DEFAULT_COUNT = 2_000
"""PDO loop round trips timed (card and baseline each)."""
DEFAULT_WARMUP = 200


TARGET_FRAMES_PER_S = 18_000.0
TARGET_SDO_RATIO = 0.5
TARGET_BOOT_S = 2.0
TARGET_SYNC_P99_US = 200.0

SMALL_NODES = 16
"""[ours] The phases' node cap where this machine has one CPU (os.cpu_count() == 1)."""
INTERFACES = ("shm", "socketcan")


def default_nodes() -> tuple[int | None, str]:
    """The node cap when the caller gives none, and why."""
    if os.cpu_count() == 1:
        return SMALL_NODES, ("os.cpu_count() is 1: the full configuration's 126 booting nodes "
                             "saturate one CPU, and the card then fails nodes that answered")
    return None, "the full configuration"


def run(count: int | None = None, warmup: int | None = None, *,
        only: Sequence[str] | None = None, profile: bool = False, nodes: int | None = None,
        bus: SeparateBus | None = None) -> dict[str, Any]:
    """The CAN benchmark's JSON document; ``only`` picks phases of ``PHASES``.

    ``nodes`` caps every phase's network (``default_nodes`` when None); ``bus`` is where
    the throughput, boot and sync phases meet their separate nodes (fresh ``shm``).
    """
    why = "given by the caller (--nodes)"
    if nodes is None:
        nodes, why = default_nodes()
    cap = nodes or BOOT_NODES
    throughput_nodes = min(cap, THROUGHPUT_NODES)
    boot_nodes = min(cap, BOOT_NODES)
    sync_nodes = min(cap, SYNC_NODES)
    full = (throughput_nodes, boot_nodes) == (THROUGHPUT_NODES, BOOT_NODES)
    bus = bus or SeparateBus()
    count = DEFAULT_COUNT if count is None else count
    warmup = DEFAULT_WARMUP if warmup is None else warmup
    phases = list(only) if only else list(PHASES)
    logging.getLogger("canopen").setLevel(logging.WARNING)
    machine = machine_info()
    source = source_fingerprint()
    started = time.perf_counter()
    document: dict[str, Any] = {
        "benchmark": NAME,
        "description": "CANopen services of the card against simulated nodes "
                       "(cifemu firmware --simulate, python-can virtual bus, one process), "
                       "each next to python canopen / python-can talking straight to the "
                       "same simulated nodes in this process",
        "machine": machine,
        "source": source,
        "params": {
            "count": count, "warmup": warmup, "phases": phases,
            "node_cap": nodes, "node_cap_reason": why, "full_configuration": full,
            "separate_nodes_bus": bus.describe(),
            "throughput_nodes": throughput_nodes,
            "throughput_active": list(active_windows(throughput_nodes)),
            "throughput_seconds": THROUGHPUT_SECONDS, "stall_s": STALL_S,
            "sdo_seconds": SDO_SECONDS, "domain_bytes": DOMAIN_BYTES,
            "boot_nodes": boot_nodes, "boot_repeats": BOOT_REPEATS,
            "operating_poll_s": OPERATING_POLL_S,
            "sync_period_ms": SYNC_PERIOD_MS, "sync_seconds": SYNC_SECONDS,
            "sync_nodes": sync_nodes,
        },
        "targets": {
            "pdo_loop_latency": None,
            "pdo_frames_per_s_min": TARGET_FRAMES_PER_S, "pdo_frames_lost": 0,
            "sdo_ratio_to_baseline_min": TARGET_SDO_RATIO,
            "boot_127_nodes_s_max": TARGET_BOOT_S,
            "sync_jitter_p99_us_max": TARGET_SYNC_P99_US,
        },
        "meets_target": {},
    }
    meets: dict[str, bool | None] = document["meets_target"]
    online_boot: tuple[int, float] | None = None
    if "latency" in phases:
        document["pdo_loop_latency"] = pdo_latency(count, warmup)
        meets["pdo_loop_latency"] = None  # no target set
    if "throughput" in phases:
        result = pdo_throughput(profile, throughput_nodes, bus)
        document["pdo_throughput"] = result
        # The targets are the full configuration's (126 and 127 nodes): none for another.
        meets["pdo_throughput"] = (result["cif"]["pdo_frames_per_s"] >= TARGET_FRAMES_PER_S
                                   and result["cif"]["lost_total"] == 0) if full else None
        online_boot = (result["cif"]["online_boot_nodes"], result["cif"]["online_boot_s"])
    if "sdo" in phases:
        result = sdo()
        document["sdo"] = result
        ratios = result["ratio_to_baseline"]
        meets["sdo_expedited"] = (ratios["expedited"] or 0.0) >= TARGET_SDO_RATIO
        meets["sdo_segmented"] = (ratios["segmented"] or 0.0) >= TARGET_SDO_RATIO
    if "boot" in phases:
        result = boot(online_boot, boot_nodes, bus)
        document["boot"] = result
        meets["boot_127_nodes"] = result["cif"]["median_s"] <= TARGET_BOOT_S if full else None
    if "sync" in phases:
        result = sync_jitter(sync_nodes, bus)
        document["sync_jitter"] = result
        p99 = result["cif"].get("idle", {}).get("jitter_us", {}).get("p99")
        meets["sync_jitter"] = p99 is not None and p99 <= TARGET_SYNC_P99_US
    document["run_seconds"] = round(time.perf_counter() - started, 1)
    return document


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.can", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_size_arguments(parser, f"PDO loop round trips, default {DEFAULT_COUNT}",
                       f"default {DEFAULT_WARMUP}")
    parser.add_argument("--only", nargs="+", choices=PHASES, metavar="NAME",
                        help=f"run only these phases: {', '.join(PHASES)}")
    parser.add_argument("--profile", action="store_true",
                        help="profile the firmware with py-spy during an extra throughput window")
    parser.add_argument("--nodes", type=_nodes, default=None, metavar="N",
                        help=f"cap every phase's network at N nodes (default: the full "
                             f"configuration, {SMALL_NODES} where os.cpu_count() is 1)")
    parser.add_argument("--interface", choices=INTERFACES, default="shm",
                        help="where the throughput, boot and sync phases meet their separate "
                             "nodes (default shm, a fresh channel per card)")
    parser.add_argument("--channel", default=None,
                        help="the link for --interface socketcan (default vcan0)")
    args = parser.parse_args(argv)
    if args.channel is not None and args.interface != "socketcan":
        parser.error("--channel goes with --interface socketcan")
    bus = SeparateBus("socketcan", args.channel or "vcan0") if (
        args.interface == "socketcan") else SeparateBus()
    emit(run(args.count, args.warmup, only=args.only, profile=args.profile, nodes=args.nodes,
             bus=bus))
    return 0


def _nodes(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if not 1 <= value <= BOOT_NODES:
        raise argparse.ArgumentTypeError(f"a node count from 1 to {BOOT_NODES}, not {text!r}")
    return value
