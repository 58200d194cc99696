"""SocketCAN benchmarks on vcan0: the kernel's path, its broadcast manager, the card on it.

Runs where SocketCAN and vcan0 exist: on a Linux with vcan, or inside
``tools/vcan-vm`` (``make bench-vcan``), where every figure is one of User-Mode
Linux, whose every system call goes through ptrace on the host. Every figure
has its baseline from the same run, on the same (virtual) machine.

1. ``round_trip``: python-can on vcan0, two bus objects in this process; one
   sends, the other receives and answers, the first receives the answer.
   Baseline: the same on ``shm`` (two stations in this process).
2. ``burst``: frames sent back to back to a receiver that reads them after the
   burst: how many arrive (the socket buffer is what holds them). Baseline: ``shm``.
3. ``bcm_sync``: python-can ``send_periodic`` at 1 ms, which on socketcan is the
   kernel's broadcast manager, received with the kernel's time stamps: the floor
   of the card's SYNC on socketcan. Beside it the ``shm`` counterpart: the timer
   process the card's SYNC comes from on ``shm`` (SCHED_FIFO where allowed),
   time stamped by that process as it writes each frame.
4. ``card_sync``: ``[bus] sync_period_ms`` = 10 and 1 (``CARD_SYNC_MS``), 16 generic
   nodes in ``cifemu sim`` (a process of its own), the card on vcan0 (its controller
   hands SYNC to the broadcast manager): the periods between SYNC frames as this
   process receives them, idle and while the host drives the PDO loop on all 16 nodes.
   A period whose nodes do not all boot is reported as such, with the card's log.
5. ``cia309_vs_canopennode``: 309-3 reads of a CANopenNode device's 1000h through
   ``cifemu 309 serve`` and the card, against CANopenNode's own gateway, one client for
   both (``bench.canopennode``); where CANopenNode is not built beside the project, the
   phase says so and how to build it.
6. ``can``: the CAN benchmark (``python -m bench.can``) but its sync phase, its
   separate nodes on vcan0, at its configuration for one CPU
   (``bench.can.document.default_nodes``).

    python -m bench.vcan [--count N] [--card-sync-ms MS ...] [--no-can] [--only PHASE ...]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

from bench import canopennode
from bench.can import document
from bench.can.card import (
    SeparateBus,
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
)
from dbm_tools.network import parse_network
from dpm.cia301 import COB_ID_SYNC
from host_api.board import Board
from host_api.errors import HostApiError
from host_api.ready import wait_ready

CHANNEL = "vcan0"
BOARD = 0
ROUND_TRIPS = 2000
BURST = 5000
PERIOD_S = 0.001
CARD_SYNC_MS = (10, 1)
"""The card's SYNC periods tried: inside User-Mode Linux on a loaded 2-core host, 1 ms has
failed (the card's receive thread fell behind 1,000 SYNC frames/s and boot SDOs timed out)."""
SHM_CHANNEL = "cifemu-bench-vcan"
HOST_LOADAVG = "CIFEMU_HOST_LOADAVG"
"""The host's load average (1, 5, 15 min) as ``make bench-vcan`` starts the guest: inside
User-Mode Linux, ``machine.loadavg`` is the guest's own."""
CAN_PHASES = ("latency", "throughput", "sdo", "boot")
"""The CAN benchmark's phases run here; its sync phase (the card's SYNC at 1 ms, 16 nodes) is
``card_sync`` above, on vcan0 too."""
FIRST_SYNC_TIMEOUT_S = 10.0
"""How long the first frame of a periodic task may take: the ``shm`` timer process is an
interpreter start away (about 1 s inside User-Mode Linux)."""


def bus(interface: str = "socketcan") -> can.BusABC:
    if interface == "shm":
        return can.Bus(interface="shm", channel=SHM_CHANNEL)
    return can.Bus(interface="socketcan", channel=CHANNEL)


def round_trip(count: int, interface: str = "socketcan") -> dict[str, Any]:
    progress(f"{interface} round trip: {count} frames")
    a, b = bus(interface), bus(interface)
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


def burst(count: int, interface: str = "socketcan") -> dict[str, Any]:
    progress(f"{interface} burst: {count} frames back to back")
    a, b = bus(interface), bus(interface)
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
        if (msg is not None and msg.arbitration_id == COB_ID_SYNC and not msg.is_extended_id
                and start <= msg.timestamp <= end):
            stamps.append(msg.timestamp)
    return np.array(stamps, dtype=np.float64)


def periodic_sync(interface: str) -> dict[str, Any]:
    """``send_periodic`` at 1 ms: the kernel's broadcast manager on socketcan, the card's
    timer process on ``shm`` (``timer_process``, as the card's controller opens it). One that
    does not start or send is a result too (on a host at load 30 the timer process's start
    took longer than its time-out), and the phases after it still run."""
    what = "broadcast manager" if interface == "socketcan" else "shm timer process"
    try:
        return periodic_sync_run(interface, what)
    except (RuntimeError, can.CanError) as exc:
        progress(f"{what}: {exc}")
        return {"source": what, "failed": str(exc)}


def periodic_sync_run(interface: str, what: str) -> dict[str, Any]:
    progress(f"{what}: send_periodic at 1 ms for {SYNC_SECONDS} s")
    if interface == "shm":
        sender = can.Bus(interface="shm", channel=SHM_CHANNEL, timer_process=True)
    else:
        sender = bus()
    receiver = bus(interface)
    try:
        task = sender.send_periodic(
            can.Message(arbitration_id=COB_ID_SYNC, data=b"", is_extended_id=False), PERIOD_S)
        deadline = time.monotonic() + FIRST_SYNC_TIMEOUT_S
        while (msg := receiver.recv(0.1)) is None or msg.arbitration_id != COB_ID_SYNC:
            if time.monotonic() > deadline:
                raise RuntimeError(f"no SYNC from the {what}")
        time.sleep(0.2)
        stamps = record_syncs(receiver, SYNC_SECONDS)
        task.stop()
        result = {"source": what, **sync_stats(stamps, PERIOD_S, SYNC_SECONDS)}
        realtime = getattr(task, "realtime", None)
        if realtime is not None:
            result["sched_fifo"] = realtime
        return result
    finally:
        sender.shutdown()
        receiver.shutdown()


def card_sync(period_ms: int) -> dict[str, Any]:
    """The card's SYNC at ``period_ms``; a network that does not come up is a result too."""
    try:
        return card_sync_run(period_ms)
    except (RuntimeError, HostApiError) as exc:
        progress(f"card SYNC at {period_ms} ms: {exc}")
        return {"nodes": SYNC_NODES, "sync_period_ms": period_ms, "failed": str(exc)}


def card_sync_run(period_ms: int) -> dict[str, Any]:
    nodes = list(range(1, SYNC_NODES + 1))
    text = network_toml(nodes, sync_period_ms=period_ms)
    network = parse_network(text)
    out_offset, in_offset = io_offsets(network)
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-vcan-", dir=scratch_root()) as tmp:
        directory = Path(tmp)
        toml = directory / "network.toml"
        toml.write_text(text)
        sim = subprocess.Popen([sys.executable, "-m", "cifemu", "sim", str(toml), "--interface",
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
                [sys.executable, "-m", "cifemu", "firmware", "--board", str(BOARD),
                 "--dpm-dir", tmp, "--log-level", "WARNING", "--interface", "socketcan",
                 "--channel", CHANNEL, "--flash", str(directory / "flash")],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=stderr)
        card = SimCard(directory, proc, None, stderr_path, sim=sim)
        receiver = bus()
        try:
            wait_ready(proc, directory, BOARD, STARTUP_TIMEOUT)
            card.board = Board(BOARD, directory, timeout=5000).open()
            select_uncontrolled(card.board)
            configure(card, network)
            try:
                wait_operating(BOARD, len(nodes))
            except RuntimeError as exc:
                raise RuntimeError(f"{exc}; the firmware log: {card.log()}") from None
            time.sleep(SYNC_SETTLE_S)
            progress(f"card SYNC at {period_ms} ms on vcan0: {SYNC_SECONDS} s idle, then with "
                     "the PDO loop")
            idle = record_syncs(receiver, SYNC_SECONDS)
            values = np.arange(1, len(nodes) + 1, dtype=np.uint64) << np.uint64(40)
            recorded: list[np.ndarray[Any, np.dtype[np.float64]]] = []
            recorder = threading.Thread(
                target=lambda: recorded.append(record_syncs(receiver, SYNC_SECONDS)))
            recorder.start()
            window = echo_window(BOARD, values, len(nodes), SYNC_SECONDS, out_offset,
                                 in_offset)
            recorder.join()
            period_s = period_ms / 1e3
            return {"nodes": len(nodes), "sync_period_ms": period_ms,
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


PHASES = ("round_trip", "burst", "sync_1ms", "card_sync", "cia309_vs_canopennode", "can")


def run(count: int | None = None, card_sync_ms: tuple[int, ...] = CARD_SYNC_MS,
        with_can: bool = True, only: tuple[str, ...] = PHASES) -> dict[str, Any]:
    count = count or ROUND_TRIPS
    document_: dict[str, Any] = {
        "benchmark": "vcan",
        "description": __doc__.split("\n\n")[0] if __doc__ else "",
        "machine": machine_info(),
        "host_loadavg_at_start": os.environ.get(HOST_LOADAVG),
    }
    if "round_trip" in only:
        document_["round_trip"] = {"socketcan": round_trip(count),
                                   "baseline_shm": round_trip(count, "shm")}
    if "burst" in only:
        document_["burst"] = {"socketcan": burst(BURST), "baseline_shm": burst(BURST, "shm")}
    if "sync_1ms" in only:
        document_["sync_1ms"] = {"bcm": periodic_sync("socketcan"),
                                 "shm_timer": periodic_sync("shm")}
    if "card_sync" in only:
        document_["card_sync"] = [card_sync(period) for period in card_sync_ms]
    if "cia309_vs_canopennode" in only:
        document_["cia309_vs_canopennode"] = canopennode.run()
    if with_can and "can" in only:
        progress("the CAN benchmark, its separate nodes on vcan0")
        document_["can"] = document.run(only=CAN_PHASES, bus=SeparateBus("socketcan", CHANNEL))
    return document_


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.vcan", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=None,
                        help=f"round trips (default {ROUND_TRIPS})")
    parser.add_argument("--card-sync-ms", type=int, nargs="+", default=list(CARD_SYNC_MS),
                        metavar="MS", help="the card's SYNC periods to measure "
                                           f"(default {' '.join(map(str, CARD_SYNC_MS))})")
    parser.add_argument("--no-can", action="store_true",
                        help="leave out the CAN benchmark's phases (python -m bench.can)")
    parser.add_argument("--only", nargs="+", choices=PHASES, default=list(PHASES),
                        metavar="PHASE", help=f"run these phases only ({', '.join(PHASES)})")
    args = parser.parse_args(argv)
    emit(run(args.count, tuple(args.card_sync_ms), with_can=not args.no_can,
             only=tuple(args.only)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
