"""CPU per 1,000 frames/s: the card's cost as its bus traffic grows (issue 22, item 4).

One card with ``NODES`` generic nodes in ``cifemu sim`` on a fresh ``shm`` channel,
uncontrolled handshake, configured on line. The host writes a new value into every
node's outputs once per period (one DevExchangeIO, open loop: it does not wait for the
echo); the card sends each node's RPDO, the node answers with its TPDO, and the card
writes that into the inputs: 2 x ``NODES`` PDO frames per period, plus the nodes'
heartbeats. The periods in ``PERIODS_MS`` give about 500, 2,000 and 8,000 frames/s;
one window without writes, measured after them, gives the idle figure (the card with
its nodes operational and a host attached), the fit's starting point.

Per window: the frames written on the channel by every station (the shm counters,
``firmware.shm.bus.frames_written``: read without joining the bus, so counting costs
the card nothing) and the CPU time of the firmware process (with its SYNC timer
process) and of ``cifemu sim`` from /proc (utime + stime, ``bench.cpu.Usage``). A
least-squares line through the windows gives per cent of one core per 1,000 frames/s
for each process, and its value at 0 frames/s.
"""

from __future__ import annotations

import itertools
import time
import uuid
from typing import Any

import numpy as np

from bench.can.card import (
    TIMEOUT_MS,
    SeparateBus,
    io_offsets,
    network_toml,
    simulated_card,
    start_uncontrolled,
)
from bench.can.pdo_loop import image_values
from bench.common import progress
from bench.cpu import Usage
from dbm_tools.network import parse_network
from firmware.shm.bus import frames_written
from host_api.driver import DevExchangeIO

NODES = 16
PERIODS_MS = (64.0, 16.0, 4.0)
"""2 x 16 PDO frames per period: 500, 2,000 and 8,000 frames/s."""
SECONDS = 6.0
QUICK_SECONDS = 2.0
SETTLE_S = 1.0
"""Before each window: the frames of the window before have ended, start-up work is done."""


def _window(board: int, out_offset: int, channel: str, pids: dict[str, int],
            period_s: float | None, seconds: float) -> dict[str, Any]:
    """One window: writes every ``period_s`` (none when None); frames and CPU shares."""
    values = itertools.cycle(image_values(NODES))
    time.sleep(SETTLE_S)  # the traffic of the window before drains; not a wait on a condition
    frames_before = frames_written(channel)
    before = Usage.take(pids)
    start = time.perf_counter()
    end = start + seconds
    writes = 0
    if period_s is None:
        time.sleep(seconds)  # the idle window itself
    else:
        due = start
        while due < end:
            DevExchangeIO(board, out_offset, next(values), 0, 0, TIMEOUT_MS)
            writes += 1
            due += period_s
            time.sleep(max(0.0, due - time.perf_counter()))
    used = Usage.take(pids).pct_since(before)
    elapsed = time.perf_counter() - start
    frames = frames_written(channel) - frames_before
    return {
        "period_ms": None if period_s is None else period_s * 1000,
        "host_writes": writes,
        "frames": frames,
        "frames_per_s": round(frames / elapsed, 1),
        "firmware_pct": used["firmware"],
        "sim_pct": used["sim"],
        "seconds": round(elapsed, 2),
    }


def _fit(windows: list[dict[str, Any]], role: str) -> dict[str, Any]:
    """Least squares: per cent of a core = at_0 + per_1000 x frames/s / 1,000."""
    rates = np.array([w["frames_per_s"] for w in windows]) / 1000.0
    shares = np.array([w[f"{role}_pct"] for w in windows])
    slope, intercept = np.polyfit(rates, shares, 1)
    return {"pct_per_1000_frames_per_s": round(float(slope), 3),
            "pct_at_0_frames_per_s": round(float(intercept), 3)}


def frame_cost(quick: bool = False) -> dict[str, Any]:
    """The section's document: the windows, idle first, and the fitted lines."""
    seconds = QUICK_SECONDS if quick else SECONDS
    description = network_toml(range(1, NODES + 1))
    network = parse_network(description)
    out_offset, _ = io_offsets(network)
    channel = f"bench-{uuid.uuid4().hex[:12]}"
    with simulated_card(description, separate=True, bus=SeparateBus("shm", channel)) as card:
        progress(f"frame cost: on-line configuration of {NODES} nodes")
        board, _, _ = start_uncontrolled(card, network)
        assert card.sim is not None, "separate=True starts cifemu sim"
        pids = {"firmware": card.pid, "sim": card.sim.pid}
        windows = []
        # The idle window is measured last (and listed first): measured first, it took in
        # the tail of the on-line configuration (the boot-ups' last answers, numpy imported
        # in a thread of the card's own), seconds of wall time on a loaded machine: idle
        # 21 % of a core against 15 % at 8,000 frames/s in a run at a load of 12.
        for period_ms in (*PERIODS_MS, None):
            what = "idle" if period_ms is None else f"outputs every {period_ms:g} ms"
            progress(f"frame cost: {what}, {seconds} s")
            windows.append(_window(board.number, out_offset, channel, pids,
                                   None if period_ms is None else period_ms / 1000, seconds))
        windows.insert(0, windows.pop())
        firmware_log = card.log()
    idle = windows[0]
    for window in windows[1:]:
        added = window["frames_per_s"] - idle["frames_per_s"]
        window["above_idle_pct_per_1000_frames_per_s"] = {
            role: round(1000.0 * (window[f"{role}_pct"] - idle[f"{role}_pct"]) / added, 3)
            if added > 0 else None for role in ("firmware", "sim")}
    return {
        "description": f"one card, {NODES} generic nodes in cifemu sim on shm, uncontrolled "
                       "handshake; the host writes every node's outputs once per period (open "
                       f"loop): 2 x {NODES} PDO frames per period and the nodes' heartbeats; "
                       "frames: every frame on the channel (the shm counters); CPU: /proc "
                       "utime + stime over the window, per cent of one core; the first window "
                       "is the idle card (nodes operational, host attached, no writes)",
        "nodes": NODES,
        "seconds": seconds,
        "windows": windows,
        "idle": {"firmware_pct": idle["firmware_pct"], "sim_pct": idle["sim_pct"],
                 "frames_per_s": idle["frames_per_s"]},
        "firmware": _fit(windows, "firmware"),
        "sim": _fit(windows, "sim"),
        "firmware_log": firmware_log,
    }
