"""Phase 2, ``pdo_throughput``: 126 generic nodes, one value in flight per node.

126 generic nodes, uncontrolled. For each node the host
keeps one value in flight: once a node's input shows the value written, the
host writes the next one, so every value is one RPDO and one TPDO and none is
merged with the next by the card. A value still missing 2 s after the
window is lost (its node stalls, so a single loss shows). The figure is 2 x
the input updates the host verified. The frames on the bus are counted as a
cross-check from outside the card: on ``shm`` a ``BusWatch`` in this process copies
the channel's rings, which the card does not notice (its candump trace, used before,
took 12.6 % of its samples, about 2 us of CPU per frame each way, that the baseline
does not pay); on SocketCAN the card's trace still counts them. Each window also gives
the card's CPU time per verified value, which a loaded machine moves less than the rate.
Baseline: the same closed loop driven by
a canopen network in this process, event-driven from its receive thread.
"""

from __future__ import annotations

import threading
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Any

import canopen
import numpy as np

from bench.can.baseline import in_process, start_all
from bench.can.card import (
    SeparateBus,
    io_offsets,
    network_toml,
    simulated_card,
    start_uncontrolled,
)
from bench.can.echo import DRAIN_S, U64, EchoWindow, echo_window
from bench.can.profile import PROFILE_SECONDS, profile_window
from bench.can.trace import BusWatch, Trace, count_frames, read_trace
from bench.common import (
    progress,
    ratio,
)
from dbm_tools.network import parse_network
from dpm.cia301 import RPDO_BASES, TPDO_BASES
from dpm.start_progress import stat_cpu_ns

THROUGHPUT_NODES = 126
THROUGHPUT_ACTIVE = (16, 126)
"""Nodes whose loop the host drives, one timed window each; the others idle."""
THROUGHPUT_SECONDS = 4.0

def trace_counts(window: EchoWindow, trace: Trace) -> dict[str, Any]:
    """What the bus carried during a window (watch or trace); nodes 1..active."""
    rpdo = (RPDO_BASES[0] + 1, RPDO_BASES[0] + window.active + 1)
    tpdo = (TPDO_BASES[0] + 1, TPDO_BASES[0] + window.active + 1)
    timed = (window.wall_start, window.wall_end)
    whole = (window.wall_start, window.wall_drained)
    rpdo_timed = count_frames(trace, *rpdo, *timed)
    tpdo_timed = count_frames(trace, *tpdo, *timed)
    rpdo_all = count_frames(trace, *rpdo, *whole)
    tpdo_all = count_frames(trace, *tpdo, *whole)
    seconds = window.wall_end - window.wall_start
    return {
        "rpdo_frames_sent": rpdo_timed,
        "tpdo_frames_received": tpdo_timed,
        "pdo_frames_per_s": round((rpdo_timed + tpdo_timed) / seconds, 1) if seconds else None,
        "including_drain": {
            "rpdo_frames_sent": rpdo_all,
            "tpdo_frames_received": tpdo_all,
            "input_updates_verified_by_host": window.verified_total,
            "tpdo_frames_minus_verified_updates": tpdo_all - window.verified_total,
            "rpdo_frames_minus_tpdo_frames": rpdo_all - tpdo_all,
        },
    }


def active_windows(nodes: int) -> tuple[int, ...]:
    """``THROUGHPUT_ACTIVE`` for a network of ``nodes`` (a smaller one than 126 drives all
    of them in its last window)."""
    return tuple(sorted({min(active, nodes) for active in THROUGHPUT_ACTIVE}))


def card_pdo_throughput(profile: bool, count: int, bus: SeparateBus | None) -> dict[str, Any]:
    nodes = list(range(1, count + 1))
    text = network_toml(nodes)
    network = parse_network(text)
    out_offset, in_offset = io_offsets(network)
    windows: list[EchoWindow] = []
    card_cpu_ns: list[int] = []
    profiled: dict[str, Any] | None = None
    watched = bus is None or bus.interface == "shm"
    with simulated_card(text, trace=not watched, separate=True, bus=bus) as card:
        progress(f"pdo throughput (card): on-line configuration of {len(nodes)} nodes")
        board, bus_download, operating = start_uncontrolled(card, network)
        online_boot_s = operating - bus_download
        values: U64 = np.arange(1, len(nodes) + 1, dtype=np.uint64) << np.uint64(40)
        with ExitStack() as stack:
            watch = stack.enter_context(BusWatch(card.channel)) if watched else None
            for active in active_windows(count):
                progress(f"pdo throughput (card): {active} nodes for {THROUGHPUT_SECONDS} s")
                cpu_before = stat_cpu_ns(card.pid)
                windows.append(echo_window(board.number, values, active, THROUGHPUT_SECONDS,
                                           out_offset, in_offset))
                card_cpu_ns.append(stat_cpu_ns(card.pid) - cpu_before)
        if profile:
            progress(f"pdo throughput (card): profiling {len(nodes)} nodes for "
                     f"{PROFILE_SECONDS} s with py-spy")
            profiled = profile_window(card, values, len(nodes), out_offset, in_offset)
        diagnostics = board.diagnostics()
        card.stop()
        if watch is not None:
            trace = watch.trace()
            counted: dict[str, Any] = {
                "bus_watch": {**watch.summary(), "note": (
                    "frames copied from the shm channel's rings by a thread of the benchmark "
                    "process, no station opened: the card pays nothing for the count; "
                    "frames_missed > 0 makes the counts a lower bound")}}
            watch.close()
        elif card.trace is None:
            raise RuntimeError("the card ran without a trace")
        else:
            trace = read_trace(card.trace)
            counted = {"trace_damage": {
                "lines": trace.lines,
                "damaged_lines": trace.damaged_lines,
                "duplicate_records": trace.duplicates,
                "note": "the card's trace is written unsynchronised from several threads; "
                        "records written over each other are recovered where readable, so "
                        "the trace counts are a cross-check (a lower bound), not the figure",
            }}
        firmware_log = card.log()
    for window in windows:
        window.trace = trace_counts(window, trace)
    best = max(windows, key=lambda w: w.echoes_per_s)
    result: dict[str, Any] = {
        "pdo_frames_per_s": round(2 * best.echoes_per_s, 1),
        "input_frames_per_s": round(best.echoes_per_s, 1),
        "active_nodes": best.active,
        "lost_total": sum(w.lost for w in windows),
        "figure_note": "pdo_frames_per_s = 2 x the input updates the host verified (each is one "
                       "RPDO sent and one TPDO received and stored); best window",
        "windows": [{**w.summary(), "card_cpu_us_per_echo": round(
            cpu / 1000 / w.verified_total, 2) if w.verified_total else None}
            for w, cpu in zip(windows, card_cpu_ns, strict=True)],
        **counted,
        "task2state_counters": {
            "usMsg_Time_Out": diagnostics.usMsg_Time_Out,
            "usRx_Overflow": diagnostics.usRx_Overflow,
            "usBus_Error_Cnt": diagnostics.usBus_Error_Cnt,
        },
        "online_boot_nodes": len(nodes),
        "online_boot_s": round(online_boot_s, 3),
        "firmware_log": firmware_log,
    }
    if profiled is not None:
        result["profile"] = profiled
    return result


@dataclass(slots=True)
class _Echoes:
    """The baseline's closed loop, served from the canopen network's receive thread."""

    client: canopen.Network
    values: list[int]
    running: bool = True
    verified: int = 0
    pending: set[int] = field(default_factory=set)
    drained: threading.Event = field(default_factory=threading.Event)

    def send(self, index: int) -> None:
        self.client.send_message(RPDO_BASES[0] + 1 + index,
                                 self.values[index].to_bytes(8, "little"))

    def on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        del timestamp
        index = can_id - TPDO_BASES[0] - 1
        if index not in self.pending or int.from_bytes(data, "little") != self.values[index]:
            return
        self.verified += 1
        if self.running:
            self.values[index] += 1
            self.send(index)
        else:
            self.pending.discard(index)
            if not self.pending:
                self.drained.set()


def baseline_pdo_throughput(count: int) -> dict[str, Any]:
    nodes = list(range(1, count + 1))
    network = parse_network(network_toml(nodes))
    with in_process(network) as (sim, client):
        start_all(sim, client)
        time.sleep(0.05)  # the TPDOs of entering OPERATIONAL
        loop = _Echoes(client, [(node << 40) + 1 for node in nodes], pending=set(range(len(nodes))))
        for node in nodes:
            client.subscribe(TPDO_BASES[0] + node, loop.on_tpdo)
        progress(f"pdo throughput (baseline): {len(nodes)} nodes for {THROUGHPUT_SECONDS} s")
        start = time.perf_counter()
        for index in range(len(nodes)):
            loop.send(index)
        time.sleep(THROUGHPUT_SECONDS)
        loop.running = False
        timed = loop.verified
        elapsed = time.perf_counter() - start
        loop.drained.wait(DRAIN_S)
        lost = len(loop.pending)
        for node in nodes:
            client.unsubscribe(TPDO_BASES[0] + node, loop.on_tpdo)
    echoes = timed / elapsed
    return {
        "name": "canopen network in this process drives the same closed loop on the same "
                f"{len(nodes)} simulated generic nodes, event-driven (the next RPDO is sent "
                "from the TPDO's receive callback)",
        "active_nodes": len(nodes),
        "verified_echoes_per_s": round(echoes, 1),
        "pdo_frames_per_s": round(2 * echoes, 1),
        "lost": lost,
    }


def pdo_throughput(profile: bool, nodes: int = THROUGHPUT_NODES,
                   bus: SeparateBus | None = None) -> dict[str, Any]:
    baseline = baseline_pdo_throughput(nodes)
    card = card_pdo_throughput(profile, nodes, bus)
    return {
        "description": "closed loop, one value in flight per node: the host writes a node's "
                       "next output value once its input shows the previous one; every value "
                       "is one RPDO the card sends and one TPDO it receives and stores; frames "
                       "counted on the bus from outside the card (shm: its rings, copied by "
                       "the benchmark; SocketCAN: the card's trace), input updates verified "
                       "by the host",
        "cif": card,
        "baseline": baseline,
        "ratio_to_baseline": {
            "definition": "cif pdo_frames_per_s / baseline pdo_frames_per_s",
            "pdo_frames_per_s": ratio(card["pdo_frames_per_s"], baseline["pdo_frames_per_s"]),
        },
    }

