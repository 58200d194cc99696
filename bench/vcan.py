"""SocketCAN benchmarks on vcan0: the kernel's path, its broadcast manager, the card on it.

Runs where SocketCAN and vcan0 exist: on a Linux with vcan, or inside
``tools/vcan-vm`` (``make bench-vcan``), where every figure is one of User-Mode
Linux, whose every system call goes through ptrace on the host.

1. ``round_trip``: python-can on vcan0, two bus objects in this process; one
   sends, the other receives and answers, the first receives the answer.
2. ``burst``: frames sent back to back to a receiver that reads them after the
   burst: how many arrive (the socket buffer is what holds them).
3. ``bcm_sync``: python-can ``send_periodic`` at 1 ms, which on socketcan is the
   kernel's broadcast manager, received with the kernel's time stamps: the floor
   of the card's SYNC on socketcan.
4. ``card_sync``: ``[bus] sync_period_ms = 10`` (see ``CARD_SYNC_MS``), 16 generic
   nodes in ``cifemu sim`` (a process of its own), the card on vcan0 (its controller
   hands SYNC to the broadcast manager): the periods between SYNC frames as this
   process receives them, idle and while the host drives the PDO loop on all 16 nodes.

    python -m bench.vcan [--count N]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

from bench.can.card import (
    SYNC_COB_ID,
    SimCard,
    configure,
    io_offsets,
    network_toml,
    select_uncontrolled,
    wait_operating,
)
from bench.can.echo import echo_window
from bench.can.sync import SYNC_NODES, SYNC_SECONDS, SYNC_SETTLE_S, sync_stats
from bench.common import (
    STARTUP_TIMEOUT,
    emit,
    latency_stats,
    machine_info,
    progress,
    scratch_root,
    stop_process,
    wait_ready,
)
from dbm_tools.network import parse_network
from dpm.image import image_path
from host_api.board import Board

CHANNEL = "vcan0"
BOARD = 0
ROUND_TRIPS = 2000
BURST = 5000
PERIOD_S = 0.001
CARD_SYNC_MS = 10
"""The card's SYNC period here: at 1 ms, inside User-Mode Linux on a loaded 2-core host,
the receivers fell behind 1,000 SYNC frames/s and every boot SDO timed out."""


def bus() -> can.BusABC:
    return can.Bus(interface="socketcan", channel=CHANNEL)


def round_trip(count: int) -> dict[str, Any]:
    progress(f"vcan round trip: {count} frames")
    a, b = bus(), bus()
    try:
        request = can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False)
        answer = can.Message(arbitration_id=0x124, data=bytes(8), is_extended_id=False)
        samples = []
        for _ in range(count):
            start = time.perf_counter_ns()
            a.send(request)
            if b.recv(1.0) is None:
                raise RuntimeError("request lost")
            b.send(answer)
            if a.recv(1.0) is None:
                raise RuntimeError("answer lost")
            samples.append(time.perf_counter_ns() - start)
        total_s = sum(samples) / 1e9
        return {"round_trips": count, "per_s": round(count / total_s),
                "latency_us": latency_stats(samples)}
    finally:
        a.shutdown()
        b.shutdown()


def burst(count: int) -> dict[str, Any]:
    progress(f"vcan burst: {count} frames back to back")
    a, b = bus(), bus()
    try:
        start = time.perf_counter()
        for n in range(count):
            a.send(can.Message(arbitration_id=0x200, data=n.to_bytes(4, "little"),
                               is_extended_id=False))
        elapsed = time.perf_counter() - start
        received = 0
        while b.recv(0.2) is not None:
            received += 1
        return {"sent": count, "received": received, "sent_per_s": round(count / elapsed)}
    finally:
        a.shutdown()
        b.shutdown()


def record_syncs(receiver: can.BusABC, seconds: float) -> np.ndarray[Any, np.dtype[np.float64]]:
    """The kernel's receive time stamps of the SYNC frames during the next ``seconds``
    (what the socket still holds from before is read and passed over)."""
    stamps = []
    start = time.time()
    end = start + seconds
    while time.time() < end:
        msg = receiver.recv(0.1)
        if (msg is not None and msg.arbitration_id == SYNC_COB_ID and not msg.is_extended_id
                and start <= msg.timestamp <= end):
            stamps.append(msg.timestamp)
    return np.array(stamps, dtype=np.float64)


def bcm_sync() -> dict[str, Any]:
    progress(f"broadcast manager: send_periodic at 1 ms for {SYNC_SECONDS} s")
    sender, receiver = bus(), bus()
    try:
        task = sender.send_periodic(
            can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False), PERIOD_S)
        time.sleep(0.2)
        stamps = record_syncs(receiver, SYNC_SECONDS)
        task.stop()
        return sync_stats(stamps, PERIOD_S, SYNC_SECONDS)
    finally:
        sender.shutdown()
        receiver.shutdown()


def card_sync() -> dict[str, Any]:
    nodes = list(range(1, SYNC_NODES + 1))
    text = network_toml(nodes, sync_period_ms=CARD_SYNC_MS)
    network = parse_network(text)
    out_offset, in_offset = io_offsets(network)
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-vcan-", dir=scratch_root()) as tmp:
        directory = Path(tmp)
        toml = directory / "network.toml"
        toml.write_text(text)
        sim = subprocess.Popen([sys.executable, "-m", "firmware.sim", str(toml), "--interface",
                                "socketcan", "--channel", CHANNEL, "--log-level", "WARNING"],
                               stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)
        assert sim.stdout is not None
        if not sim.stdout.readline().startswith(b"simulating"):
            stop_process(sim)
            raise RuntimeError("cifemu sim did not start")
        threading.Thread(target=sim.stdout.read, daemon=True).start()
        stderr_path = directory / "firmware.stderr"
        with stderr_path.open("wb") as stderr:
            proc = subprocess.Popen(
                [sys.executable, "-m", "firmware", "--board", str(BOARD), "--dpm-dir", tmp,
                 "--log-level", "WARNING", "--interface", "socketcan", "--channel", CHANNEL,
                 "--flash", str(directory / "flash")],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=stderr)
        card = SimCard(directory, proc, None, stderr_path, sim=sim)
        receiver = bus()
        try:
            wait_ready(proc, image_path(directory, BOARD), STARTUP_TIMEOUT)
            card.board = Board(BOARD, directory, timeout=5000).open()
            select_uncontrolled(card.board)
            configure(card, network)
            wait_operating(BOARD, len(nodes))
            time.sleep(SYNC_SETTLE_S)
            progress(f"card SYNC on vcan0: {SYNC_SECONDS} s idle, then with the PDO loop")
            idle = record_syncs(receiver, SYNC_SECONDS)
            values = np.arange(1, len(nodes) + 1, dtype=np.uint64) << np.uint64(40)
            recorded: list[np.ndarray[Any, np.dtype[np.float64]]] = []
            recorder = threading.Thread(
                target=lambda: recorded.append(record_syncs(receiver, SYNC_SECONDS)))
            recorder.start()
            window = echo_window(BOARD, values, len(nodes), SYNC_SECONDS, out_offset,
                                 in_offset)
            recorder.join()
            period_s = CARD_SYNC_MS / 1e3
            return {"nodes": len(nodes), "sync_period_ms": CARD_SYNC_MS,
                    "idle": sync_stats(idle, period_s, SYNC_SECONDS),
                    "with_pdo_loop": {"verified_echoes_per_s": round(window.echoes_per_s, 1),
                                      **sync_stats(recorded[0], period_s, SYNC_SECONDS)},
                    "firmware_log": card.log()}
        finally:
            receiver.shutdown()
            card.stop()
            logged = card.log()
            if logged["lines"]:
                progress(f"the firmware logged {logged['lines']} line(s), e.g. "
                         f"{logged['first_lines']}")


def run(count: int | None = None) -> dict[str, Any]:
    return {
        "benchmark": "vcan",
        "description": __doc__.split("\n\n")[0] if __doc__ else "",
        "machine": machine_info(),
        "round_trip": round_trip(count or ROUND_TRIPS),
        "burst": burst(BURST),
        "bcm_sync": bcm_sync(),
        "card_sync": card_sync(),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.vcan", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=None,
                        help=f"round trips (default {ROUND_TRIPS})")
    args = parser.parse_args(argv)
    emit(run(args.count))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
