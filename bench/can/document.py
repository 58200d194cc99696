"""The CAN benchmark's JSON document and command line: the phases in order.

CANopen services of the card against simulated nodes, each next to python canopen or
python-can talking straight to the same simulated nodes in this process:

  latency     PDO loop round trip, 1 node (bench.can.pdo_loop)
  throughput  PDO frames/s, 126 nodes, one value in flight each (bench.can.throughput)
  sdo         COM_SDO_Up_Download, expedited and a 247-byte DOMAIN (bench.can.sdo)
  boot        127 nodes from a stored database to Nd_state (bench.can.boot)
  sync        jitter of a 1 ms SYNC, idle and under PDO load (bench.can.sync)

--profile adds a py-spy profile of the firmware during an extra throughput window.

    python -m bench.can [--count N] [--warmup N] [--only NAME ...] [--profile]
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Sequence
from typing import Any

from bench.can.boot import BOOT_NODES, BOOT_REPEATS, boot
from bench.can.echo import STALL_S
from bench.can.pdo_loop import pdo_latency
from bench.can.sdo import DOMAIN_BYTES, SDO_SECONDS, sdo
from bench.can.sync import SYNC_NODES, SYNC_PERIOD_MS, SYNC_SECONDS, sync_jitter
from bench.can.throughput import (
    THROUGHPUT_ACTIVE,
    THROUGHPUT_NODES,
    THROUGHPUT_SECONDS,
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


def run(count: int | None = None, warmup: int | None = None, *,
        only: Sequence[str] | None = None, profile: bool = False) -> dict[str, Any]:
    """The CAN benchmark's JSON document; ``only`` picks phases of ``PHASES``."""
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
            "throughput_nodes": THROUGHPUT_NODES, "throughput_active": list(THROUGHPUT_ACTIVE),
            "throughput_seconds": THROUGHPUT_SECONDS, "stall_s": STALL_S,
            "sdo_seconds": SDO_SECONDS, "domain_bytes": DOMAIN_BYTES,
            "boot_nodes": BOOT_NODES, "boot_repeats": BOOT_REPEATS,
            "sync_period_ms": SYNC_PERIOD_MS, "sync_seconds": SYNC_SECONDS,
            "sync_nodes": SYNC_NODES,
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
    online_boot: float | None = None
    if "latency" in phases:
        document["pdo_loop_latency"] = pdo_latency(count, warmup)
        meets["pdo_loop_latency"] = None  # no target set
    if "throughput" in phases:
        result = pdo_throughput(profile)
        document["pdo_throughput"] = result
        meets["pdo_throughput"] = (result["cif"]["pdo_frames_per_s"] >= TARGET_FRAMES_PER_S
                                   and result["cif"]["lost_total"] == 0)
        online_boot = result["cif"]["online_boot_126_nodes_s"]
    if "sdo" in phases:
        result = sdo()
        document["sdo"] = result
        ratios = result["ratio_to_baseline"]
        meets["sdo_expedited"] = (ratios["expedited"] or 0.0) >= TARGET_SDO_RATIO
        meets["sdo_segmented"] = (ratios["segmented"] or 0.0) >= TARGET_SDO_RATIO
    if "boot" in phases:
        result = boot(online_boot)
        document["boot"] = result
        meets["boot_127_nodes"] = result["cif"]["median_s"] <= TARGET_BOOT_S
    if "sync" in phases:
        result = sync_jitter()
        document["sync_jitter"] = result
        p99 = result["cif"]["idle"].get("jitter_us", {}).get("p99")
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
    args = parser.parse_args(argv)
    emit(run(args.count, args.warmup, only=args.only, profile=args.profile))
    return 0


