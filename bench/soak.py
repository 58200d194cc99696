"""``python -m bench soak --minutes N``: the card under full load for N minutes.

126 generic nodes run in ``cifemu sim`` on ``shm`` with every node's PDO loop closed (the
host writes a value, the node echoes it, the host verifies it at its input: the PDO loop of
``bench.can``'s throughput phase, one window per minute; the 1-minute form measures four
windows of 15 s). Beside it, in processes of their
own, a host does mailbox SDO transfers (COM_SDO_Up_Download, expedited reads of 1000h
round the nodes) and a CiA 309-3 client does SDO reads through the TCP server. The mailbox
host and the 309-3 server share one process, because a board's mailbox has one reader: the
gateway's, which passes the host's commands (``Gateway.transact``) [ours].

Reported (JSON on stdout): PDO frames exchanged and lost; resident memory (VmRSS) of the
firmware, the simulator and the hosts at the start and after every window, with the growth
after the first window; p50/p99 of the PDO loop and of both SDO round trips in the first
and the last window; SDO failures; the card's error counters, Err_Event and global bits;
and whether the issue's invariants held (``invariants``).

The minutes are wall-clock minutes of the PDO loop; set-up (126 boot-ups) comes before.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import socket
import statistics
import sys
import threading
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.synchronize import Event as EventType
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from bench.can.card import (
    configure,
    io_offsets,
    network_toml,
    select_uncontrolled,
    simulated_card,
    wait_operating,
)
from bench.can.echo import DRAIN_S, U64, echo_window
from bench.can.sdo import sdo_message
from bench.can.throughput import THROUGHPUT_NODES
from bench.common import (
    emit,
    help_text,
    machine_info,
    percentile,
    progress,
    source_fingerprint,
)
from dbm_tools.network import parse_network
from dpm.task2 import ComDiagnostics
from host_api.driver import DevGetTaskState

NAME = "soak"
DEFAULT_MINUTES = 1
MINUTE_S = 60.0
SHORT_WINDOW_S = 15.0
"""The 1-minute form measures four windows of 15 s, so that it checks the memory growth
after its first window and compares a first and a last window, as the long form does
with minutes."""
RSS_GROWTH_TARGET = 0.01
"""The issue's target: resident memory grows less than 1 % after the first minute (window)."""
SDO_NODES = 16
"""Nodes the two SDO clients go round (1000h of each), the first MAILBOX_NODES the
mailbox host's, the others the 309-3 client's: the card runs one SDO transfer per node at
a time and refuses a second with f 54 (the gateway's own turns do not see the host's)."""
MAILBOX_NODES = 8
SDO_PAUSE_S = 0.002
"""Between two SDO reads of one client: 'a host doing SDO transfers', not a flood that
would starve the PDO loop on a 2-core machine."""
CLIENT_DONE_WAIT_S = 30.0
"""How long the 309-3 server outlives its own SDO loop for the client's last request."""
DEVICE_TYPE = 0x000F0191
COUNTERS = ("usBus_Error_Cnt", "usBus_Off_Cnt", "usMsg_Time_Out", "usRx_Overflow")


# --- resident memory ------------------------------------------------------------------------


def rss_kib(pid: int) -> int | None:
    """VmRSS of ``pid`` in KiB (Linux /proc); None when the process is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


# --- round trips, kept per window without growing ---------------------------------------------


@dataclass
class Windows:
    """Round trips of the first and of the current window, and counts of every window.

    Only two windows of samples are kept, so a long soak does not grow the hosts' memory
    with its own measurements. A round trip that ends after the last window counts in it.
    """

    start: float
    width: float
    count: int
    first: list[float] = field(default_factory=list)
    last: list[float] = field(default_factory=list)
    last_index: int = 0
    counts: list[int] = field(default_factory=list)
    failures: int = 0
    failure_examples: list[str] = field(default_factory=list)

    def add(self, now: float, seconds: float) -> None:
        index = min(int((now - self.start) // self.width), self.count - 1)
        while len(self.counts) <= index:
            self.counts.append(0)
        self.counts[index] += 1
        if index == 0:
            self.first.append(seconds)
            return
        if index != self.last_index:
            self.last_index = index
            self.last = []
        self.last.append(seconds)

    def fail(self, what: str) -> None:
        self.failures += 1
        if len(self.failure_examples) < 3:
            self.failure_examples.append(what[:200])

    def summary(self) -> dict[str, Any]:
        last = self.last or self.first
        return {"round_trips": sum(self.counts), "per_window": self.counts,
                "failures": self.failures, "failure_examples": self.failure_examples,
                "first_window_us": _p50_p99(self.first),
                "last_window_us": _p50_p99(last)}


def _p50_p99(seconds: list[float]) -> dict[str, float | int]:
    ordered = sorted(seconds)
    if not ordered:
        return {"count": 0}
    return {"count": len(ordered), "p50": round(percentile(ordered, 50) * 1e6, 1),
            "p99": round(percentile(ordered, 99) * 1e6, 1)}


# --- the two SDO hosts (processes of their own) -----------------------------------------------


def _mailbox_and_server_host(directory: str, windows: Windows, conn: Connection,
                             client_done: EventType) -> None:
    """The 309-3 server (it owns the mailbox reader) and a host's mailbox SDO reads. The
    server stays until the 309-3 client is done: closed at the same deadline as the
    client's, it cut off the client's last request (an empty answer, counted a failure)."""
    from host_api.cia309.gateway import Gateway
    from host_api.cia309.server import BackgroundServer, ServerConfig

    until = windows.start + windows.width * windows.count
    with Gateway([0], directory) as gateway:
        server = BackgroundServer(gateway, ServerConfig(port=0))
        conn.send(server.port)
        try:
            node = 0
            while time.monotonic() < until:
                node = node % MAILBOX_NODES + 1
                began = time.monotonic()
                try:
                    answer = gateway.transact(sdo_message(node, 0x1000, 0))
                except Exception as exc:  # every failure is counted and shown, never hidden
                    windows.fail(f"{type(exc).__name__}: {exc}")
                else:
                    now = time.monotonic()
                    value = int.from_bytes(answer.data[8:12], "little")
                    if answer.f or value != DEVICE_TYPE:
                        windows.fail(f"node {node}: f {answer.f}, data {answer.data.hex()}")
                    else:
                        windows.add(now, now - began)
                time.sleep(SDO_PAUSE_S)
            client_done.wait(CLIENT_DONE_WAIT_S)
        finally:
            server.close()
    conn.send(windows.summary())


def _cia309_client(port: int, windows: Windows, conn: Connection,
                   done: EventType) -> None:
    """A 309-3 client reading 1000h round its nodes, one request at a time."""
    until = windows.start + windows.width * windows.count
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        reader = sock.makefile("rb")
        sequence, node = 0, 0
        while time.monotonic() < until:
            sequence = sequence % 1_000_000 + 1
            node = MAILBOX_NODES + node % (SDO_NODES - MAILBOX_NODES) + 1
            began = time.monotonic()
            sock.sendall(f"[{sequence}] {node} read 0x1000 0 u32\n".encode())
            line = reader.readline()
            now = time.monotonic()
            if line == f"[{sequence}] {DEVICE_TYPE}\r\n".encode():
                windows.add(now, now - began)
            else:
                windows.fail(f"node {node}: {line!r}")
                if not line:
                    break
            time.sleep(SDO_PAUSE_S)
    done.set()
    conn.send(windows.summary())


# --- the soak ---------------------------------------------------------------------------------


class LoopHistogram:
    """PDO loop times in 10 µs bins up to 2 s (the last bin takes the rest): a fixed
    amount of memory however long the soak, so the PDO host's RSS is the host's own."""

    BIN_S = 10e-6
    BINS = 200_000

    def __init__(self) -> None:
        self.counts = np.zeros(self.BINS, dtype=np.int64)

    def add(self, seconds: npt.NDArray[np.float64]) -> None:
        bins = np.minimum((seconds / self.BIN_S).astype(np.int64), self.BINS - 1)
        np.add.at(self.counts, bins, 1)

    def summary(self) -> dict[str, float | int]:
        total = int(self.counts.sum())
        if not total:
            return {"count": 0}
        cumulative = np.cumsum(self.counts)

        def at(q: float) -> float:
            index = int(np.searchsorted(cumulative, q * total, side="left"))
            return round((index + 0.5) * self.BIN_S * 1e6, 1)
        slow = int(self.counts[int(0.5 / self.BIN_S):].sum())
        return {"count": total, "p50": at(0.50), "p99": at(0.99), "max": at(1.0),
                "over_500_ms": slow}


def pdo_window(board: int, values: U64, seconds: float, out_offset: int,
               in_offset: int) -> dict[str, Any]:
    """Every node's PDO loop closed for ``seconds`` (``bench.can.echo_window``), the loop
    times kept in a ``LoopHistogram``."""
    histogram = LoopHistogram()
    window = echo_window(board, values, len(values), seconds, out_offset, in_offset,
                         record=histogram.add)
    return {"frames": 2 * window.verified_total, "lost": window.lost,
            "frames_per_s": round(2 * window.echoes_per_s, 1),
            "exchange_errors": window.exchange_errors, "loop_us": histogram.summary()}


class ErrorWatch:
    """Err_Event and Err_Node_adr as they change during the soak (Task2State every 0.1 s,
    the first 50 changes): a node lost for a moment shows here even when it is back by
    the end."""

    PERIOD_S = 0.1
    KEPT = 50

    def __init__(self, board: int, start: float) -> None:
        self.changes: list[dict[str, float | int]] = []
        self._board, self._start = board, start
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="soak-errors", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        shown = (0, 0)
        while not self._stop.wait(self.PERIOD_S):
            rc, raw = DevGetTaskState(self._board, 2, 64)
            if rc != 0:
                continue
            state = ComDiagnostics.decode(raw)
            now = (state.bErr_event, state.bErr_rem_adr)
            if now != shown and len(self.changes) < self.KEPT:
                self.changes.append({"s": round(time.monotonic() - self._start, 1),
                                     "err_event": now[0], "err_node_adr": now[1]})
            shown = now

    def stop(self) -> list[dict[str, float | int]]:
        self._stop.set()
        self._thread.join()
        return self.changes


def _growth(samples: list[dict[str, int | None]], role: str) -> float | None:
    """Relative growth of ``role``'s RSS from the first window's sample to the last."""
    values = [s[role] for s in samples]
    if len(values) < 3 or values[1] is None or values[-1] is None:
        return None
    return round((values[-1] - values[1]) / values[1], 4)


def soak(minutes: int) -> dict[str, Any]:
    nodes = list(range(1, THROUGHPUT_NODES + 1))
    text = network_toml(nodes)
    network = parse_network(text)
    out_offset, in_offset = io_offsets(network)
    context = multiprocessing.get_context("spawn")
    with simulated_card(text, separate=True) as card:
        board = card.board
        assert board is not None, "simulated_card opens the board"
        select_uncontrolled(board)
        progress(f"soak: on-line configuration of {len(nodes)} nodes")
        configure(card, network)
        wait_operating(board.number, len(nodes))
        # the hosts: everything before this line is set-up
        width = MINUTE_S if minutes > 1 else SHORT_WINDOW_S
        count = round(minutes * MINUTE_S / width)
        start = time.monotonic()
        windows = Windows(start, width, count)
        server_end, server_conn = context.Pipe(duplex=False)
        client_done = context.Event()
        server_host = context.Process(target=_mailbox_and_server_host,
                                      args=(str(card.directory), windows, server_conn,
                                            client_done))
        server_host.start()
        port = server_end.recv()
        client_end, client_conn = context.Pipe(duplex=False)
        client = context.Process(target=_cia309_client,
                                 args=(port, windows, client_conn, client_done))
        client.start()
        assert card.sim is not None
        pids = {"firmware": card.pid, "sim": card.sim.pid, "pdo_host": os.getpid(),
                "mailbox_and_309_server_host": server_host.pid or 0,
                "cia309_client": client.pid or 0}
        rss: list[dict[str, int | None]] = [{role: rss_kib(pid) for role, pid in pids.items()}]
        watch = ErrorWatch(board.number, start)
        values = np.arange(1, len(nodes) + 1, dtype=np.uint64) << np.uint64(40)
        pdo: list[dict[str, Any]] = []
        for index in range(count):
            progress(f"soak: window {index + 1} of {count} ({width:.0f} s)")
            # the window's values drain for up to DRAIN_S after it: inside the same width
            pdo.append(pdo_window(board.number, values, width - DRAIN_S - 0.5, out_offset,
                                  in_offset))
            _sleep_until(start + (index + 1) * width)
            rss.append({role: rss_kib(pid) for role, pid in pids.items()})
        mailbox_sdo = server_end.recv()
        cia309_sdo = client_end.recv()
        for process in (client, server_host):
            process.join(30)
        diagnostics = board.diagnostics()
        error_changes = watch.stop()
        counters = {name: int(getattr(diagnostics, name)) for name in COUNTERS}
        firmware_log = card.log()
    result = _report(minutes, width, pdo, rss, mailbox_sdo, cia309_sdo, counters, diagnostics)
    result["firmware_log"] = firmware_log
    result["err_event_changes"] = error_changes
    result["invariants"]["no_err_event_during_the_soak"] = not error_changes
    return result


def _sleep_until(deadline: float) -> None:
    remaining = deadline - time.monotonic()
    if remaining > 0:
        time.sleep(remaining)


def _report(minutes: int, width: float, pdo: list[dict[str, Any]],
            rss: list[dict[str, int | None]], mailbox_sdo: dict[str, Any],
            cia309_sdo: dict[str, Any], counters: dict[str, int],
            diagnostics: ComDiagnostics) -> dict[str, Any]:
    growth = {role: _growth(rss, role) for role in rss[0]}
    frames = sum(m["frames"] for m in pdo)
    lost = sum(m["lost"] for m in pdo)
    measured = [g for g in growth.values() if g is not None]
    invariants = {
        "no_frame_lost": lost == 0,
        "no_sdo_failure": mailbox_sdo["failures"] == 0 and cia309_sdo["failures"] == 0,
        "error_counters_zero": not any(counters.values()) and diagnostics.bErr_event == 0,
        "rss_growth_under_1_percent_after_the_first_window":
            all(g < RSS_GROWTH_TARGET for g in measured) if measured else None,
        "every_host_worked": bool(frames) and bool(mailbox_sdo["round_trips"])
            and bool(cia309_sdo["round_trips"]),
    }
    return {
        "benchmark": NAME,
        "minutes": minutes,
        "window_s": width,
        "nodes": THROUGHPUT_NODES,
        "pdo": {"frames_exchanged": frames, "frames_lost": lost,
                "frames_per_s_by_window": [m["frames_per_s"] for m in pdo],
                "exchange_errors": sum(m["exchange_errors"] for m in pdo),
                "first_window_loop_us": pdo[0]["loop_us"],
                "last_window_loop_us": pdo[-1]["loop_us"],
                "note": "frames = 2 x the echoes the host verified (one RPDO out, one TPDO in); "
                        "loop = host output written to the node's echo verified at the input"},
        "mailbox_sdo": mailbox_sdo,
        "cia309_sdo": cia309_sdo,
        "rss_kib": rss,
        "rss_growth_after_first_window": growth,
        "rss_note": "samples at the start of the load and after every window; growth from the "
                    "first window's sample to the last",
        "card_error_counters": counters,
        "err_event": diagnostics.bErr_event,
        "global_bits": diagnostics.bGlobalBits,
        "invariants": invariants,
        "machine": machine_info(),
        "source": source_fingerprint(),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "median_frames_per_s": statistics.median([m["frames_per_s"] for m in pdo]),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench soak", description=help_text(__doc__))
    parser.add_argument("--minutes", type=int, default=DEFAULT_MINUTES,
                        help=f"minutes of load (default {DEFAULT_MINUTES})")
    args = parser.parse_args(argv)
    if args.minutes < 1:
        parser.error("--minutes must be at least 1")
    emit(soak(args.minutes))
    return 0


def dispatch(argv: list[str] | None) -> int | None:
    """``python -m bench soak ...`` runs here (its own arguments, and not among the
    benchmarks ``python -m bench`` runs by default: it takes minutes); None otherwise."""
    arguments = sys.argv[1:] if argv is None else argv
    return main(arguments[1:]) if arguments[:1] == [NAME] else None

if __name__ == "__main__":
    raise SystemExit(main())
