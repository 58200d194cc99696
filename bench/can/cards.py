"""Scaling by cards: 1, 2 and 4 cards at once, each with its own network (issue 22, item 4).

Boards 0..K-1 in one image directory, as a driver sees several cards in one PC. Each
card is a firmware process of its own with ``NODES_PER_CARD`` generic nodes in a
``cifemu sim`` of its own on a fresh ``shm`` channel, in the uncontrolled handshake and
configured on line. Each card has a host process of its own (so the hosts share no
interpreter lock) that closes the PDO loop of all its nodes as ``bench.can.active_nodes``
does, paced at one round trip every ``LOOP_PERIOD_S``: a fixed control loop per card,
as on a test bench, so that adding a card adds a known amount of work and the figures
say what the cards cost each other. All hosts start their loops together; the window's
CPU time of every firmware process (with its SYNC timer process) and every ``cifemu
sim`` comes from /proc (``bench.cpu.Usage``).
"""

from __future__ import annotations

import multiprocessing
import tempfile
import time
from contextlib import ExitStack
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from bench.can.card import io_offsets, network_toml, simulated_card, start_uncontrolled
from bench.can.pdo_loop import image_round_trip
from bench.common import latency_stats, progress, scratch_root
from bench.cpu import Usage
from dbm_tools.network import parse_network
from host_api.board import Board

CARD_COUNTS = (1, 2, 4)
NODES_PER_CARD = 16
LOOP_PERIOD_S = 0.02
"""A round trip every 20 ms per card (50 Hz): 1,600 PDO frames/s per card of 16 nodes."""
SECONDS = 10.0
QUICK_SECONDS = 3.0
HOST_WARMUP = 20
HOST_START_S = 60.0
"""How long a host process may take to start and open its board (spawning an interpreter
beside busy cards on two cores)."""


def card_host(conn: Connection, directory: str, board: int, out_offset: int, in_offset: int,
              nodes: int, seconds: float) -> None:
    """One card's host, in a process of its own: warm up, say ``ready``, wait for ``go``,
    run the paced loop for ``seconds``, send back its figures (or ``{"error": ...}``)."""
    try:
        with Board(board, directory, timeout=5000):
            step = image_round_trip(board, out_offset, in_offset, nodes)
            for _ in range(HOST_WARMUP):
                step()
            conn.send("ready")
            conn.recv()
            clock = time.perf_counter_ns
            latencies: list[int] = []
            failures = 0
            start = time.perf_counter()
            due = start
            while due < start + seconds:
                began = clock()
                if step() != 0:
                    failures += 1
                latencies.append(clock() - began)
                due = max(due + LOOP_PERIOD_S, time.perf_counter())  # late: no catching up
                time.sleep(max(0.0, due - time.perf_counter()))
            conn.send({"board": board, "latency_us": latency_stats(latencies),
                       "round_trips": len(latencies), "failures": failures,
                       "seconds": round(time.perf_counter() - start, 2)})
    except Exception as exc:  # the parent reports it; a host must not hang the benchmark
        conn.send({"board": board, "error": f"{type(exc).__name__}: {exc}"})
    finally:
        conn.close()


def _end(process: multiprocessing.process.BaseProcess) -> None:
    process.join(10)
    if process.is_alive():
        process.terminate()
        process.join()


def _receive(conn: Connection, timeout: float, what: str) -> Any:
    if not conn.poll(timeout):
        raise RuntimeError(f"no {what} from a card's host within {timeout} s")
    return conn.recv()


def cards_at_once(count: int, seconds: float) -> dict[str, Any]:
    """``count`` cards with their nodes and hosts, their loops running together."""
    description = network_toml(range(1, NODES_PER_CARD + 1))
    network = parse_network(description)
    out_offset, in_offset = io_offsets(network)
    context = multiprocessing.get_context("spawn")
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-cards-", dir=scratch_root()) as tmp, \
            ExitStack() as stack:
        images = Path(tmp)
        cards = []
        for board in range(count):
            progress(f"cards: starting board {board} of {count} with {NODES_PER_CARD} nodes")
            card = stack.enter_context(simulated_card(description, separate=True, board=board,
                                                      dpm_dir=images))
            start_uncontrolled(card, network)
            cards.append(card)
        hosts = []
        for board in range(count):
            ours, theirs = context.Pipe()
            process = context.Process(target=card_host, daemon=True,
                                      args=(theirs, tmp, board, out_offset, in_offset,
                                            NODES_PER_CARD, seconds))
            process.start()
            stack.callback(_end, process)
            theirs.close()
            hosts.append(ours)
        for conn in hosts:
            if (ready := _receive(conn, HOST_START_S, "ready")) != "ready":
                raise RuntimeError(f"a card's host failed: {ready}")
        pids = {f"firmware {board}": card.pid for board, card in enumerate(cards)}
        pids |= {f"sim {board}": card.sim.pid for board, card in enumerate(cards)
                 if card.sim is not None}
        progress(f"cards: {count} card(s), each host's loop every {LOOP_PERIOD_S * 1000:.0f} ms "
                 f"for {seconds} s")
        before = Usage.take(pids)
        for conn in hosts:
            conn.send("go")
        results = [_receive(conn, seconds + HOST_START_S, "figures") for conn in hosts]
        used = Usage.take(pids).pct_since(before)
        logs = [card.log() for card in cards]
    per_card = [{**result, "firmware_pct": used[f"firmware {board}"],
                 "sim_pct": used.get(f"sim {board}"), "firmware_log": logs[board]}
                for board, result in enumerate(results)]
    firmware_total = round(sum(used[f"firmware {b}"] for b in range(count)), 3)
    return {
        "cards": count,
        "firmware_total_pct": firmware_total,
        "firmware_per_card_pct": round(firmware_total / count, 3),
        "sim_total_pct": round(sum(used.get(f"sim {b}", 0.0) for b in range(count)), 3),
        "per_card": per_card,
    }


def several_cards(counts: tuple[int, ...], quick: bool = False,
                  seconds: float | None = None) -> dict[str, Any]:
    """The section's document: one entry per card count; ``seconds`` overrides the hosts'
    window (``SECONDS``, ``QUICK_SECONDS``)."""
    seconds = seconds or (QUICK_SECONDS if quick else SECONDS)
    return {
        "description": f"boards 0..K-1 in one image directory, each a firmware process with "
                       f"{NODES_PER_CARD} generic nodes in its own cifemu sim on its own shm "
                       f"channel, uncontrolled handshake; each card's host (a process of its "
                       f"own) closes the loop of all {NODES_PER_CARD} nodes once every "
                       f"{LOOP_PERIOD_S * 1000:.0f} ms, the hosts together for {seconds} s; "
                       "CPU: /proc utime + stime of each firmware process (with its SYNC "
                       "timer process) and each cifemu sim over that window, per cent of one "
                       "core",
        "nodes_per_card": NODES_PER_CARD,
        "loop_period_ms": LOOP_PERIOD_S * 1000,
        "pdo_frames_per_s_per_card": round(2 * NODES_PER_CARD / LOOP_PERIOD_S),
        "seconds": seconds,
        "runs": [cards_at_once(count, seconds) for count in counts],
    }
