"""LSS fastscan: 8 unconfigured slaves found through the card, against canopen on the bus.

The card figure: ``cifemu firmware --simulate NETWORK.toml`` with 8 unconfigured LSS slaves
(``id = 255``, one vendor, product and revision, serial numbers drawn from a fixed seed,
so every run scans the same 1-bits). This process is the host: ``host_api.cia309.lss``
finds one slave with a fastscan, gives it a node-ID (configure node-ID, switch state global
waiting: it starts up and leaves the scan), and again, until none is left. Each of the 8
fastscans is timed; so is the last one, which finds nobody. A second card repeats this with
vendor-ID, product code and revision given (CANopenNode's "match": one confirmation step
each, so only the serial number is scanned).

Baseline, same run, this process: canopen's ``LssMaster.fast_scan`` straight on a python-can
virtual bus against the same simulated slaves, no card between, with ``RESPONSE_TIMEOUT`` set
to the host master's fastscan step time-out, so an unanswered step (a 1-bit) costs both the
same; canopen as shipped also sleeps 10 ms after every step.

A fastscan's time is dominated by its unanswered steps (one per 1-bit of the address, each
a full time-out), so the figures depend on the addresses: ``params`` gives their 1-bits.
``--count`` is the number of rounds (each with fresh slaves); a fastscan has no steady state,
so ``--warmup`` is not used.

    python -m bench.lss [--count N]
"""

from __future__ import annotations

import argparse
import random
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import canopen

from bench.common import (
    STARTUP_TIMEOUT,
    BenchError,
    add_size_arguments,
    emit,
    help_text,
    load_text,
    machine_info,
    progress,
    ratio,
    scratch_root,
    source_fingerprint,
    stop_process,
)
from dbm_tools.network import parse_network
from dpm.cia305 import WAITING, LssAddress
from firmware.sim import SimulatedNetwork
from host_api.board import Board
from host_api.cia309.lss import (
    DEFAULT_SCAN_TIMEOUT_S,
    DEFAULT_TIMEOUT_S,
    SETTLE_S,
    LssError,
    LssMaster,
)
from host_api.ready import wait_ready

NAME = "lss"
NODES = 8
DEFAULT_ROUNDS = 1
VENDOR, PRODUCT, REVISION = 0x0000_0195, 0x0000_0401, 0x0001_0002
"""An LSS address as devices carry them: a small vendor-ID, product code and revision."""
SEED = 305
FIRST_NODE_ID = 2
BOARD = 0


def slave_addresses(round_number: int) -> list[LssAddress]:
    """The 8 slaves of a round: 24-bit serial numbers from a fixed seed."""
    rng = random.Random(SEED + round_number)
    return [LssAddress(VENDOR, PRODUCT, REVISION, serial)
            for serial in rng.sample(range(1, 1 << 24), NODES)]


def network_toml(addresses: list[LssAddress]) -> str:
    return "".join(f"[[node]]\nid = 255\nlss = {{ vendor = {a.vendor}, product = {a.product}, "
                   f"revision = {a.revision}, serial = {a.serial} }}\n" for a in addresses)


def one_bits(address: LssAddress) -> int:
    return sum(bin(number).count("1") for number in address)


@contextmanager
def simulated_card(description: str) -> Iterator[Board]:
    """``cifemu firmware --simulate`` on a fresh image directory; yields the opened board."""
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-lss-", dir=scratch_root()) as tmp:
        toml = Path(tmp) / "network.toml"
        toml.write_text(description)
        command = [sys.executable, "-m", "cifemu", "firmware", "--board", str(BOARD),
                   "--dpm-dir", tmp, "--log-level", "WARNING", "--simulate", str(toml),
                   "--flash", str(Path(tmp) / "flash")]
        proc = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
        try:
            wait_ready(proc, Path(tmp), BOARD, STARTUP_TIMEOUT)
            progress(f"firmware pid {proc.pid} READY with {NODES} unconfigured LSS slaves")
            board = Board(BOARD, tmp, timeout=5000).open()
            try:
                yield board
            finally:
                board.close()
        finally:
            stop_process(proc)


def scan_card(addresses: list[LssAddress], known: bool) -> dict[str, Any]:
    """Fastscan + assign through the card until nobody is left; the time of each fastscan."""
    match = {"vendor": VENDOR, "product": PRODUCT, "revision": REVISION} if known else {}
    seconds: list[float] = []
    found: list[LssAddress] = []
    with simulated_card(network_toml(addresses)) as board:
        lss = LssMaster(board)
        while True:
            try:
                start = time.perf_counter()
                address = lss.fastscan(**match)
                elapsed = time.perf_counter() - start
                if address is None:
                    if len(found) < len(addresses):
                        raise BenchError(not_found("the card's fastscan", found,
                                                   "no slave answered the next scan"))
                    return {"per_slave_s": seconds, "no_slave_left_s": elapsed, "found": found}
                seconds.append(elapsed)
                found.append(address)
                lss.configure_node_id(FIRST_NODE_ID + len(found) - 1)
                lss.switch_state_global(WAITING)
            except LssError as exc:
                raise BenchError(not_found("the card's fastscan", found, str(exc))) from exc


def scan_canopen(addresses: list[LssAddress]) -> dict[str, Any]:
    """The same with canopen's LSS master straight on a virtual bus (no card)."""
    channel = f"cifemu-bench-lss-{uuid.uuid4().hex}"
    sim_bus = can.Bus(interface="virtual", channel=channel)
    master = canopen.Network(can.Bus(interface="virtual", channel=channel))
    seconds: list[float] = []
    found: list[LssAddress] = []
    try:
        with SimulatedNetwork(parse_network(network_toml(addresses)), sim_bus):
            master.connect()
            lss = master.lss
            lss.RESPONSE_TIMEOUT = DEFAULT_SCAN_TIMEOUT_S
            while True:
                start = time.perf_counter()
                ok, numbers = lss.fast_scan()  # type: ignore[no-untyped-call]
                elapsed = time.perf_counter() - start
                if not ok:
                    if len(found) < len(addresses):
                        raise BenchError(not_found(
                            "canopen's fast_scan", found,
                            f"a step unanswered within RESPONSE_TIMEOUT "
                            f"({DEFAULT_SCAN_TIMEOUT_S * 1000:g} ms) reads as a 1-bit"))
                    return {"per_slave_s": seconds, "no_slave_left_s": elapsed, "found": found}
                seconds.append(elapsed)
                found.append(LssAddress(*numbers))
                try:
                    lss.configure_node_id(  # type: ignore[no-untyped-call]
                        FIRST_NODE_ID + len(found) - 1)
                except canopen.lss.LssError as exc:  # a wrong address selected nobody
                    raise BenchError(not_found("canopen's fast_scan", found[:-1],
                                               f"configure node-ID: {exc}")) from exc
                lss.send_switch_state_global(WAITING)  # type: ignore[no-untyped-call]
    finally:
        master.disconnect()
        sim_bus.shutdown()


def not_found(scanner: str, found: list[LssAddress], why: str) -> str:
    """The message of a scan that lost slaves: on a machine too loaded for the scan's
    time-outs, not a benchmark's result (a traceback from the statistics of no slave, before)."""
    return (f"{scanner} found {len(found)} of {NODES} slaves ({why}); its time-outs are too "
            f"short for this machine now ({load_text()}): run it on a quieter one")


def summary(runs: list[dict[str, Any]], rounds: list[list[LssAddress]]) -> dict[str, Any]:
    """Seconds per slave (all rounds), the 8-slave totals, and whether each found its 8."""
    per_slave = [s for run in runs for s in run["per_slave_s"]]
    totals = [sum(run["per_slave_s"]) for run in runs]
    return {
        "total_s_per_round": [round(t, 3) for t in totals],
        "total_s_p50": round(statistics.median(totals), 3),
        "per_slave_s": {"p50": round(statistics.median(per_slave), 3),
                        "min": round(min(per_slave), 3), "max": round(max(per_slave), 3)},
        "no_slave_left_s_p50": round(statistics.median(r["no_slave_left_s"] for r in runs), 3),
        "found_all": all(sorted(run["found"]) == sorted(addresses)
                         for run, addresses in zip(runs, rounds, strict=True)),
    }


def run(count: int | None = None, warmup: int | None = None) -> dict[str, Any]:
    """The LSS benchmark's JSON document (``warmup`` is not used, see the module)."""
    del warmup
    rounds = [slave_addresses(n) for n in range(DEFAULT_ROUNDS if count is None else count)]
    machine = machine_info()
    source = source_fingerprint()
    baseline, card, card_known = [], [], []
    for n, addresses in enumerate(rounds):
        progress(f"lss round {n + 1}/{len(rounds)}: canopen fast_scan baseline")
        baseline.append(scan_canopen(addresses))
        progress(f"lss round {n + 1}/{len(rounds)}: fastscan through the card")
        card.append(scan_card(addresses, known=False))
        progress(f"lss round {n + 1}/{len(rounds)}: fastscan through the card, numbers known")
        card_known.append(scan_card(addresses, known=True))
    card_result = summary(card, rounds)
    baseline_result = summary(baseline, rounds)
    bits = [one_bits(a) for addresses in rounds for a in addresses]
    return {
        "benchmark": NAME,
        "description": f"LSS fastscan of {NODES} unconfigured slaves through the card's "
                       "layer-2 access (COM_Tx_CAN_Layer2 / COM_Rx_CAN_Layer2), each then "
                       "given a node-ID",
        "machine": machine,
        "source": source,
        "params": {
            "slaves": NODES,
            "rounds": len(rounds),
            "scan_step_timeout_s": DEFAULT_SCAN_TIMEOUT_S,
            "confirmed_timeout_s": DEFAULT_TIMEOUT_S,
            "settle_s": SETTLE_S,
            "address_one_bits": {"mean": round(statistics.mean(bits), 1), "min": min(bits),
                                 "max": max(bits)},
        },
        "cifemu_fastscan": card_result,
        "cifemu_fastscan_vendor_product_revision_known": summary(card_known, rounds),
        "baseline": {"name": "canopen LssMaster.fast_scan on a python-can virtual bus, "
                             "RESPONSE_TIMEOUT = scan_step_timeout_s", **baseline_result},
        "ratio_to_baseline": {
            "definition": "cifemu_fastscan / baseline",
            "total_s_p50": ratio(card_result["total_s_p50"], baseline_result["total_s_p50"]),
        },
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.lss", description=help_text(__doc__),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_size_arguments(parser, f"rounds, default {DEFAULT_ROUNDS}", "not used")
    args = parser.parse_args(argv)
    try:
        emit(run(args.count, args.warmup))
    except BenchError as exc:
        print(f"python -m bench.lss: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
