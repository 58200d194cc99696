"""Phase 5, ``sync_jitter``: the card's 1 ms SYNC against python-can and the machine.

``[bus] sync_period_ms = 1``, 16 generic nodes: the periods
between the SYNC frames (0x080) in the card's candump trace, idle and while
the host drives the PDO loop of phase 2 on all 16 nodes. Baseline: python-can
``send_periodic`` at 1 ms on a virtual bus, logged and measured the same way;
and the machine's own floor: a process that does nothing but sleep until each
millisecond and note the time (no CAN, no threads), once as a normal process
and once under SCHED_FIFO as the card's SYNC timer process runs on ``shm``
(where the machine allows it); the SCHED_FIFO loop also runs beside the card
in both of its windows, since this VM's wake-up latency changes by the minute.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import can
import numpy as np
import numpy.typing as npt

from bench.can.card import (
    SeparateBus,
    io_offsets,
    network_toml,
    simulated_card,
    start_uncontrolled,
)
from bench.can.echo import U64, echo_window
from bench.can.trace import read_trace
from bench.common import (
    percentile,
    progress,
    ratio,
)
from dbm_tools.network import parse_network
from dpm.cia301 import COB_ID_SYNC
from firmware.shm.cyclic import REALTIME_PRIORITY
from host_api.errors import HostApiError

SYNC_NODES = 16
SYNC_PERIOD_MS = 1
SYNC_SECONDS = 3.0
SYNC_SETTLE_S = 1.0
"""After the nodes are up, before the idle window: on ``shm`` the card's SYNC timer process
(the spare started with the card) may still be starting its interpreter, competing with the
card and ``cifemu sim`` starting theirs."""


def sync_stats(stamps: npt.NDArray[np.float64], period_s: float,
               seconds: float) -> dict[str, Any]:
    """Period and jitter (|period - nominal|) statistics of successive SYNC time stamps."""
    expected = round(seconds / period_s)
    if len(stamps) < 2:
        return {"syncs": len(stamps), "expected_syncs": expected}
    periods_us = np.diff(np.sort(stamps)) * 1e6
    nominal = period_s * 1e6
    jitter = sorted(float(x) for x in np.abs(periods_us - nominal))
    ordered = sorted(float(x) for x in periods_us)

    def us(value: float) -> float:
        return round(value, 1)

    return {
        "syncs": len(stamps),
        "expected_syncs": expected,
        "period_us": {"mean": us(float(np.mean(periods_us))), "p50": us(percentile(ordered, 50)),
                      "min": us(ordered[0]), "max": us(ordered[-1])},
        "jitter_us": {"p50": us(percentile(jitter, 50)), "p90": us(percentile(jitter, 90)),
                      "p99": us(percentile(jitter, 99)), "p99_9": us(percentile(jitter, 99.9)),
                      "max": us(jitter[-1])},
        "periods_over_1_5x_nominal": int(np.count_nonzero(periods_us > 1.5 * nominal)),
    }


def card_sync(count: int, bus: SeparateBus | None) -> dict[str, Any]:
    nodes = list(range(1, count + 1))
    text = network_toml(nodes, sync_period_ms=SYNC_PERIOD_MS)
    network = parse_network(text)
    out_offset, in_offset = io_offsets(network)
    with simulated_card(text, trace=True, separate=True, bus=bus) as card:
        try:
            board, _, _ = start_uncontrolled(card, network)
        except (RuntimeError, HostApiError) as exc:
            # A machine too slow for 1,000 SYNC frames/s (one CPU under User-Mode Linux):
            # the nodes do not come up. That is the result, with what the card logged.
            progress(f"sync (card): {exc}")
            return {"nodes": len(nodes), "failed": str(exc), "firmware_log": card.log()}
        time.sleep(SYNC_SETTLE_S)
        progress(f"sync (card): {SYNC_SECONDS} s idle, then {SYNC_SECONDS} s with the PDO loop")
        # The machine's floor in the same windows: this VM's wake-up latency changes
        # from one minute to the next, and a separate measurement may miss that.
        floor_loop = start_floor_loop(realtime=True)
        idle = (time.time(), time.time() + SYNC_SECONDS)
        time.sleep(SYNC_SECONDS)
        idle_floor = floor_result(floor_loop, realtime=True)
        values: U64 = np.arange(1, len(nodes) + 1, dtype=np.uint64) << np.uint64(40)
        floor_loop = start_floor_loop(realtime=True)
        window = echo_window(board.number, values, len(nodes), SYNC_SECONDS, out_offset,
                             in_offset)
        loaded_floor = floor_result(floor_loop, realtime=True)
        card.stop()
        if card.trace is None:
            raise RuntimeError("the card ran without a trace")
        trace = read_trace(card.trace)
        firmware_log = card.log()
    syncs = trace.stamps[trace.idents == COB_ID_SYNC]
    loaded = (window.wall_start, window.wall_end)
    return {
        "nodes": len(nodes),
        "trace_damage": {"lines": trace.lines, "damaged_lines": trace.damaged_lines,
                         "duplicate_records": trace.duplicates},
        "firmware_log": firmware_log,
        "idle": {
            **sync_stats(syncs[(syncs >= idle[0]) & (syncs <= idle[1])], SYNC_PERIOD_MS / 1e3,
                         idle[1] - idle[0]),
            "machine_floor_realtime_same_window": idle_floor,
        },
        "with_pdo_loop": {
            "verified_echoes_per_s": round(window.echoes_per_s, 1),
            **sync_stats(syncs[(syncs >= loaded[0]) & (syncs <= loaded[1])],
                         SYNC_PERIOD_MS / 1e3, loaded[1] - loaded[0]),
            "machine_floor_realtime_same_window": loaded_floor,
        },
    }


def baseline_sync() -> dict[str, Any]:
    channel = f"cifemu-bench-sync-{uuid.uuid4().hex}"
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-sync-") as tmp:
        path = Path(tmp) / "sync.log"
        sender = can.Bus(interface="virtual", channel=channel)
        receiver = can.Bus(interface="virtual", channel=channel)
        logger = can.Logger(str(path))
        notifier = can.Notifier(receiver, [logger], timeout=0.1)
        try:
            progress(f"sync (baseline): python-can send_periodic for {SYNC_SECONDS} s")
            task = sender.send_periodic(
                can.Message(arbitration_id=COB_ID_SYNC, is_extended_id=False, data=b""),
                SYNC_PERIOD_MS / 1e3)
            time.sleep(SYNC_SETTLE_S)
            since = time.time()
            time.sleep(SYNC_SECONDS)
            until = time.time()
            task.stop()
        finally:
            notifier.stop()
            logger.stop()
            receiver.shutdown()
            sender.shutdown()
        trace = read_trace(path)
    stamps = trace.stamps
    syncs = stamps[(trace.idents == COB_ID_SYNC) & (stamps >= since) & (stamps <= until)]
    return {"name": "python-can send_periodic(0x080, 1 ms) on a virtual bus, logged to a candump "
                    "trace by a can.Logger on a second bus object (this process)",
            **sync_stats(syncs, SYNC_PERIOD_MS / 1e3, until - since)}


MACHINE_FLOOR_LOOP = """
import json, os, sys, time
period, count, realtime = float(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "1"
if realtime:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(REALTIME_PRIORITY))
print("started", flush=True)
stamps, due = [], time.perf_counter()
for _ in range(count):
    due += period
    left = due - time.perf_counter()
    if left > 0:
        time.sleep(left)
    stamps.append(time.perf_counter())
print(json.dumps(stamps))
"""


def start_floor_loop(realtime: bool) -> subprocess.Popen[bytes]:
    """A bare 1 ms sleep loop for ``SYNC_SECONDS`` in a process of its own, returned once
    its interpreter has started (so that start-up falls outside the window it measures)."""
    count = round(SYNC_SECONDS / (SYNC_PERIOD_MS / 1e3))
    script = MACHINE_FLOOR_LOOP.replace("REALTIME_PRIORITY", str(REALTIME_PRIORITY))
    loop = subprocess.Popen([sys.executable, "-c", script, str(SYNC_PERIOD_MS / 1e3), str(count),
                             "1" if realtime else "0"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    assert loop.stdout is not None
    loop.stdout.readline()  # "started", or "" when it failed (floor_result reports that)
    return loop


def floor_result(loop: subprocess.Popen[bytes], realtime: bool) -> dict[str, Any]:
    """The statistics of a ``start_floor_loop`` process (skipped where SCHED_FIFO is denied)."""
    out, err = loop.communicate()
    kind = "SCHED_FIFO " if realtime else ""
    if loop.returncode:
        return {"name": f"a {kind}sleep loop", "skipped": err.decode().strip()[-200:]}
    stamps = np.array(json.loads(out), dtype=np.float64)
    return {"name": f"a {kind}process that only sleeps until each 1 ms deadline and notes "
                    "the time",
            **sync_stats(stamps, SYNC_PERIOD_MS / 1e3, SYNC_SECONDS)}


def machine_floor_sync(realtime: bool = False) -> dict[str, Any]:
    """The best a sleeping Python process gets on this machine now: no CAN, no threads.

    ``realtime``: under SCHED_FIFO, as the card's SYNC timer process on ``shm``.
    """
    kind = "SCHED_FIFO " if realtime else ""
    progress(f"sync (machine floor): a bare {kind}1 ms sleep loop for {SYNC_SECONDS} s")
    return floor_result(start_floor_loop(realtime), realtime)


def sync_jitter(nodes: int = SYNC_NODES, bus: SeparateBus | None = None) -> dict[str, Any]:
    floor = machine_floor_sync()
    floor_realtime = machine_floor_sync(realtime=True)
    baseline = baseline_sync()
    card = card_sync(nodes, bus)
    failed = "failed" in card
    card_p99 = None if failed else card["idle"].get("jitter_us", {}).get("p99")
    base_p99 = baseline.get("jitter_us", {}).get("p99")
    return {
        "description": f"[bus] sync_period_ms = {SYNC_PERIOD_MS}: jitter = |period - "
                       f"{SYNC_PERIOD_MS} ms| between successive SYNC frames (0x080) by the "
                       "time stamps of the card's candump trace (on shm the sender's time of the "
                       "send, the SYNC coming from the card's SCHED_FIFO timer process; on "
                       "socketcan the kernel's receive time, the SYNC coming from its broadcast "
                       "manager)",
        "cif": card,
        "baseline": baseline,
        "machine_floor": floor,
        "machine_floor_realtime": floor_realtime,
        "ratio_to_baseline": {"definition": "cif idle jitter p99 / baseline jitter p99",
                              "jitter_p99": ratio(card_p99 or 0.0, base_p99 or 0.0)},
        "card_over_machine_floor_us": {
            "definition": "cif jitter p99 - the SCHED_FIFO sleep loop's p99 in the same window: "
                          "what the card adds to what this machine allows at that moment",
            "idle": None if failed else _excess(card["idle"]),
            "with_pdo_loop": None if failed else _excess(card["with_pdo_loop"]),
        },
    }


def _excess(window: dict[str, Any]) -> float | None:
    card = window.get("jitter_us", {}).get("p99")
    floor = window["machine_floor_realtime_same_window"].get("jitter_us", {}).get("p99")
    return None if card is None or floor is None else round(card - floor, 1)

