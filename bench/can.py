"""CANopen benchmarks: PDO loop, PDO throughput, SDO, boot-up and SYNC, against simulated nodes.

Every card figure comes from a firmware process started as ``cifemu firmware
--simulate NETWORK.toml --interface virtual``: the card and the simulated nodes
(``firmware.sim``) share one python-can virtual bus inside that process; phases
2, 4 and 5 instead run the nodes as ``cifemu sim`` in a process of their own, on
a fresh ``shm`` channel, so that what is measured is the card and not the
simulator sharing its interpreter lock (phase 4 measured 1.7 s with the 127
nodes inside the card's process, 1.0 s with them outside). This
process is the host and reaches the card only through the driver API. Every
baseline runs here, in this process, in the same run: python ``canopen`` (or
python-can) talking straight to the same simulated nodes on a virtual bus, with
no card between them.

1. ``pdo_loop_latency``: one generic node, card in the uncontrolled handshake
   (bMode 2 by DevPutTaskParameter + WARMSTART, then the on-line configuration).
   The host writes a new output value with DevExchangeIO and polls the input
   until it reads the same value back: output -> RPDO -> node -> TPDO -> input.
   Baseline: a canopen ``RemoteNode`` sends RPDO1 and waits for TPDO1.
2. ``pdo_throughput``: 126 generic nodes, uncontrolled. For each node the host
   keeps one value in flight: once a node's input shows the value written, the
   host writes the next one, so every value is one RPDO and one TPDO and none is
   merged by the card's 1 ms output scan. A value still missing 2 s after the
   window is lost (its node stalls, so a single loss shows). The figure is 2 x
   the input updates the host verified; the card's candump trace counts the
   frames on the bus as a cross-check. Baseline: the same closed loop driven by
   a canopen network in this process, event-driven from its receive thread.
3. ``sdo``: COM_SDO_Up_Download (msg.b 74) of expedited uploads of 1000h, and
   download + upload of a 247-byte DOMAIN (the mailbox's largest SDO payload;
   segmented, 36 segments each way). The generic node has no DOMAIN, so the
   benchmark writes an EDS of the generic node plus DOMAIN 2000h and both sides
   simulate that. Baseline: canopen's ``SdoClient`` straight to the node.
4. ``boot``: 127 generic nodes from a stored database (DevDownload, then a cold
   start): the time from DevReset until all 127 are in Nd_state. Node 127 cannot
   be configured on line: area code 127 of COM_Download is the bus parameter
   set, so the on-line figure (taken from phase 2) has 126 nodes, timed from the
   bus parameter download. Baseline: canopen runs the card's boot sequence
   (NMT reset node, boot-up, upload 1000h, download 1017h, 1005h, 1014h, NMT
   start) for the same 127 simulated nodes, 32 nodes in parallel as the card.
5. ``sync_jitter``: ``[bus] sync_period_ms = 1``, 16 generic nodes: the periods
   between the SYNC frames (0x080) in the card's candump trace, idle and while
   the host drives the PDO loop of phase 2 on all 16 nodes. Baseline: python-can
   ``send_periodic`` at 1 ms on a virtual bus, logged and measured the same way;
   and the machine's own floor: a process that does nothing but sleep until each
   millisecond and note the time (no CAN, no threads), once as a normal process
   and once under SCHED_FIFO as the card's SYNC timer process runs on ``shm``
   (where the machine allows it); the SCHED_FIFO loop also runs beside the card
   in both of its windows, since this VM's wake-up latency changes by the minute.

``--profile`` attaches py-spy (``--gil``: only the thread holding the GIL is
sampled) to the firmware for an extra window of phase 2 and adds where the
firmware process spends its time, by thread role, to the document.

    python -m bench.can [--count N] [--warmup N] [--only NAME ...] [--profile]
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np
import numpy.typing as npt
from canopen import objectdictionary as od
from canopen.objectdictionary import ObjectDictionary, ODVariable
from canopen.sdo.client import SdoClient
from canopen.sdo.exceptions import SdoError

from bench.common import (
    STARTUP_TIMEOUT,
    _scratch_root,
    _stop,
    _wait_ready,
    add_size_arguments,
    emit,
    latency_stats,
    machine_info,
    percentile,
    progress,
    ratio,
    source_fingerprint,
)
from dbm_tools.builder import build_dbm
from dbm_tools.container import write_dbm
from dbm_tools.network import Network, parse_network
from dbm_tools.parameters import NodeParameterSet
from dbm_tools.tables import NODES
from dpm.image import image_path
from dpm.message import Message
from dpm.task2 import ComDiagnostics, ComPlcParameter
from firmware.can.shm_cyclic import REALTIME_PRIORITY
from firmware.sim import SimulatedNetwork
from firmware.sim.generic import generic_object_dictionary
from firmware.sim.nmt import INITIALISING, OPERATIONAL
from host_api.board import Board, CifError
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload
from host_api.driver import (
    COLDSTART,
    GET_IO_INFO,
    DevExchangeIO,
    DevGetInfo,
    DevGetTaskState,
    DevReset,
)
from host_api.online import configure_online

NAME = "can"
PHASES = ("latency", "throughput", "sdo", "boot", "sync")

DEFAULT_COUNT = 2_000
"""PDO loop round trips timed (card and baseline each)."""
DEFAULT_WARMUP = 200

BOARD = 0
CHANNEL = "cifemu-bench"
TIMEOUT_MS = 1000
RESET_TIMEOUT_MS = 10_000
BOOT_TIMEOUT_S = 20.0
ECHO_TIMEOUT_S = 1.0
"""A PDO loop round trip not back within this is a failure."""

UNCONTROLLED_BMODE = 2
"""Task2Parameter bMode that selects exchange mode 3 (uncontrolled) at a warm start."""
UNCONTROLLED_EXCHANGE_MODE = 3

THROUGHPUT_NODES = 126
THROUGHPUT_ACTIVE = (16, 126)
"""Nodes whose loop the host drives, one timed window each; the others idle."""
THROUGHPUT_SECONDS = 4.0
HOST_IDLE_S = 0.0002
"""The host's pause after a poll that found no echo: a polling host must not take a
core from the card and the nodes (the machine has two)."""
STALL_S = 0.5
"""Echoes slower than this are counted apart (late, not lost)."""
DRAIN_S = 2.0
"""After a window, how long the values in flight may take before they count as lost."""
PROFILE_SECONDS = 4.0
PROFILE_RATE = 100

SDO_SECONDS = 2.0
"""Per kind of transfer and side, in SDO_ROUNDS alternating slices."""
SDO_ROUNDS = 4
SDO_WARMUP = 50
DOMAIN_INDEX = 0x2000
DOMAIN_BYTES = 247
"""The largest SDO payload one mailbox message carries (8-byte header + 247 = 255)."""
COM_SDO_UP_DOWNLOAD = 74
COM_NODE_DIAG = 66
MAILBOX_SECONDS = 1.0
CAN_TASK, USER = 3, 16
SDO_READ, SDO_WRITE = 1, 2
DEVICE_TYPE = 0x000F0191

BOOT_NODES = 127
BOOT_REPEATS = 3
BOOT_WORKERS = 32
"""The card's node-boot thread pool (firmware.can.master.Master.executor)."""
BOOTUP_TIMEOUT_S = 3.0

SYNC_NODES = 16
SYNC_PERIOD_MS = 1
SYNC_SECONDS = 3.0
SYNC_COB_ID = 0x080
SYNC_SETTLE_S = 1.0
"""After the nodes are up, before the idle window: on ``shm`` the card's SYNC timer process
(the spare started with the card) may still be starting its interpreter, competing with the
card and ``cifemu sim`` starting theirs."""

TARGET_FRAMES_PER_S = 18_000.0
TARGET_SDO_RATIO = 0.5
TARGET_BOOT_S = 2.0
TARGET_SYNC_P99_US = 200.0

RPDO1, TPDO1, NMT_ID = 0x200, 0x180, 0x000
NMT_START, NMT_RESET_NODE = 0x01, 0x81

U64 = npt.NDArray[np.uint64]
SDO_TIMEOUT_TEXT = "0x05040000"
"""canopen's SDO client logs its timeout abort with this code."""


# --- the card under test --------------------------------------------------------------------


@dataclass(slots=True)
class SimCard:
    """A firmware process with its simulated network, and the host's board on it."""

    directory: Path
    proc: subprocess.Popen[bytes]
    trace: Path | None
    stderr: Path
    board: Board | None = None
    sim: subprocess.Popen[bytes] | None = None
    """``cifemu sim`` when the nodes run in a process of their own."""

    @property
    def pid(self) -> int:
        return self.proc.pid

    def log(self) -> dict[str, Any]:
        """What the firmware logged so far (WARNING and above): lines, SDO timeouts, examples."""
        try:
            lines = self.stderr.read_text(errors="replace").splitlines()
        except FileNotFoundError:
            lines = []
        return {"lines": len(lines),
                "sdo_timeouts": sum(SDO_TIMEOUT_TEXT in line for line in lines),
                "first_lines": [line[:200] for line in lines[:3]]}

    def stop(self) -> None:
        """End the firmware (idempotent): the trace is complete afterwards."""
        if self.board is not None:
            self.board.close()
            self.board = None
        _stop(self.proc)
        if self.sim is not None:
            _stop(self.sim)


@contextmanager
def simulated_card(description: str, *, trace: bool = False,
                   separate: bool = False) -> Iterator[SimCard]:
    """``cifemu firmware --simulate`` on a fresh image directory and flash; board opened.

    ``separate`` runs the nodes as ``cifemu sim`` in a process of their own, the
    two meeting on a fresh ``shm`` channel, so the card's threads do not share
    an interpreter lock with the simulator (as on a real bus, where the nodes
    are other machines).
    """
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-can-", dir=_scratch_root()) as tmp:
        directory = Path(tmp)
        toml = directory / "network.toml"
        toml.write_text(description)
        trace_path = directory / "trace.log" if trace else None
        stderr_path = directory / "firmware.stderr"
        interface, channel = ("shm", f"bench-{uuid.uuid4().hex[:12]}") if separate else (
            "virtual", CHANNEL)
        command = [sys.executable, "-m", "firmware", "--board", str(BOARD), "--dpm-dir", tmp,
                   "--log-level", "WARNING", "--interface", interface, "--channel", channel,
                   "--flash", str(directory / "flash")]
        if not separate:
            command += ["--simulate", str(toml)]
        if trace_path is not None:
            command += ["--trace", str(trace_path)]
        sim = None
        if separate:
            sim = subprocess.Popen(
                [sys.executable, "-m", "firmware.sim", str(toml), "--interface", interface,
                 "--channel", channel, "--log-level", "WARNING"],
                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)
            assert sim.stdout is not None
            if not sim.stdout.readline().startswith(b"simulating"):  # its nodes are on the bus
                _stop(sim)
                raise RuntimeError("cifemu sim did not start")
            # The node lines are read by nobody further on: the pipe must not fill.
            threading.Thread(target=sim.stdout.read, daemon=True).start()
        with stderr_path.open("wb") as stderr:
            proc = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                    stderr=stderr)
        card = SimCard(directory, proc, trace_path, stderr_path, sim=sim)
        try:
            _wait_ready(proc, image_path(directory, BOARD), STARTUP_TIMEOUT)
            card.board = Board(BOARD, directory, timeout=5000).open()
            yield card
        finally:
            card.stop()
            logged = card.log()
            if logged["lines"]:
                progress(f"the firmware logged {logged['lines']} line(s), e.g. "
                         f"{logged['first_lines'][0]}")


def _board(card: SimCard) -> Board:
    if card.board is None:
        raise RuntimeError("the card's board is closed")
    return card.board


def network_toml(nodes: Sequence[int], *, sync_period_ms: int = 0, eds: Path | None = None,
                 handshake: str = "uncontrolled") -> str:
    """A network description of generic nodes (or nodes of ``eds``)."""
    lines = ["[bus]", f"sync_period_ms = {sync_period_ms}", "host_watchdog_ms = 0",
             f'handshake = "{handshake}"']
    for node in nodes:
        lines += ["[[node]]", f"id = {node}"]
        if eds is not None:
            lines.append(f'eds = "{eds}"')
    return "\n".join(lines) + "\n"


def select_uncontrolled(board: Board) -> None:
    """bMode 2 by DevPutTaskParameter + WARMSTART; check the card reports exchange mode 3."""
    board.warm_start(ComPlcParameter(bMode=UNCONTROLLED_BMODE))
    rc, io_info = DevGetInfo(board.number, GET_IO_INFO, 6)
    if rc != 0 or len(io_info) < 2 or io_info[1] != UNCONTROLLED_EXCHANGE_MODE:
        raise RuntimeError(f"card not in the uncontrolled mode (rc {rc}, io info {io_info.hex()})")


def operating_count(board: int) -> int:
    rc, raw = DevGetTaskState(board, 2, 64)
    if rc != 0:
        raise RuntimeError(f"DevGetTaskState returned {rc}")
    return len(ComDiagnostics.decode(raw).operating())


def wait_operating(board: int, nodes: int, timeout: float = BOOT_TIMEOUT_S) -> float:
    """perf_counter() when ``nodes`` nodes are in Nd_state (polled every 0.5 ms)."""
    deadline = time.perf_counter() + timeout
    while True:
        if operating_count(board) >= nodes:
            return time.perf_counter()
        if time.perf_counter() > deadline:
            raise RuntimeError(f"only {operating_count(board)} of {nodes} nodes operating "
                               f"after {timeout} s")
        time.sleep(0.0005)


def configure(card: SimCard, network: Network) -> float:
    """The on-line configuration; returns perf_counter() just before the bus parameter download."""
    marks: list[float] = []

    def mark(text: str) -> None:
        if text.startswith("bus parameters"):
            marks.append(time.perf_counter())

    configure_online(_board(card), network, progress=mark)
    if not marks:
        raise RuntimeError("configure_online never reached the bus parameters")
    return marks[-1]


def io_offsets(network: Network) -> tuple[int, int]:
    """Output and input offset of the first node; the nodes' 8 bytes must follow each other."""
    dbm = build_dbm(network)
    table = dbm.table(NODES)
    if table is None:
        raise RuntimeError("the network has no nodes")
    sets = [NodeParameterSet.decode(record[1:]) for record in table.records]
    outputs = [s.ausOutputOffsets[0] for s in sets]
    inputs = [s.ausInputOffsets[0] for s in sets]
    contiguous = all(b - a == 8 for a, b in itertools.pairwise(outputs)) and all(
        b - a == 8 for a, b in itertools.pairwise(inputs))
    if not contiguous:
        raise RuntimeError("the nodes' process data is not contiguous")
    return outputs[0], inputs[0]


# --- the baseline side: simulated nodes and a canopen network in this process --------------------


@contextmanager
def in_process(network: Network) -> Iterator[tuple[SimulatedNetwork, canopen.Network]]:
    """``network``'s simulated nodes and a canopen network on a private virtual channel."""
    channel = f"cifemu-bench-baseline-{uuid.uuid4().hex}"
    sim_bus = can.Bus(interface="virtual", channel=channel)
    sim = SimulatedNetwork(network, sim_bus)
    sim.start()
    client = canopen.Network(can.Bus(interface="virtual", channel=channel))
    client.connect()
    try:
        yield sim, client
    finally:
        client.disconnect()
        sim.stop()
        sim_bus.shutdown()


def sdo_client(client: canopen.Network, node: int) -> SdoClient:
    sdo = SdoClient(0x600 + node, 0x580 + node,  # type: ignore[no-untyped-call]
                    ObjectDictionary())  # type: ignore[no-untyped-call]
    sdo.network = client
    client.subscribe(0x580 + node, sdo.on_response)
    return sdo


def start_all(sim: SimulatedNetwork, client: canopen.Network, timeout: float = 5.0) -> None:
    """Once every node has booted, NMT start to all; wait until all of them are OPERATIONAL."""
    deadline = time.monotonic() + timeout
    while any(node.nmt.code == INITIALISING for node in sim.nodes.values()):
        if time.monotonic() > deadline:
            raise RuntimeError("simulated nodes did not boot")
        time.sleep(0.001)
    client.send_message(NMT_ID, bytes([NMT_START, 0]))
    while any(node.nmt.code != OPERATIONAL for node in sim.nodes.values()):
        if time.monotonic() > deadline:
            raise RuntimeError("simulated nodes did not reach OPERATIONAL")
        time.sleep(0.001)


# --- 1. PDO loop latency --------------------------------------------------------------------------


@dataclass(slots=True)
class Loop:
    latencies_ns: list[int] = field(default_factory=list)
    failures: int = 0
    elapsed_s: float = 0.0
    firmware_log: dict[str, Any] | None = None

    def summary(self) -> dict[str, Any]:
        result: dict[str, Any] = {
            "latency_us": latency_stats(self.latencies_ns),
            "round_trips": len(self.latencies_ns),
            "round_trips_per_s": round(len(self.latencies_ns) / self.elapsed_s, 1)
            if self.elapsed_s else None,
            "failures": self.failures,
        }
        if self.firmware_log is not None:
            result["firmware_log"] = self.firmware_log
        return result


VALUES = [bytes([v]) * 8 for v in range(1, 256)]
"""Successive outputs: each differs from the one before, none is the inputs' initial 0."""


def card_pdo_latency(count: int, warmup: int) -> Loop:
    network = parse_network(network_toml([1]))
    with simulated_card(network_toml([1])) as card:
        board = _board(card)
        select_uncontrolled(board)
        configure(card, network)
        wait_operating(board.number, 1)
        out_offset, in_offset = io_offsets(network)
        number, exchange, clock = board.number, DevExchangeIO, time.perf_counter_ns
        loop = Loop()
        progress(f"pdo latency (card): {warmup} warm-up + {count} round trips")
        began = clock()
        for i in range(warmup + count):
            value = VALUES[i % len(VALUES)]
            start = clock()
            exchange(number, out_offset, value, 0, 0, TIMEOUT_MS)
            deadline = start + int(ECHO_TIMEOUT_S * 1e9)
            ok = True
            while exchange(number, 0, b"", in_offset, 8, TIMEOUT_MS)[1] != value:
                if clock() > deadline:
                    ok = False
                    break
            if i == warmup - 1:
                began = clock()
            if i < warmup:
                continue
            if ok:
                loop.latencies_ns.append(clock() - start)
            else:
                loop.failures += 1
        loop.elapsed_s = (clock() - began) / 1e9
        loop.firmware_log = card.log()
        return loop


def baseline_pdo_latency(count: int, warmup: int) -> Loop:
    network = parse_network(network_toml([1]))
    with in_process(network) as (sim, client):
        node = canopen.RemoteNode(1, generic_object_dictionary(network.nodes[0]))
        client.add_node(node)
        node.rpdo.read(from_od=True)  # type: ignore[no-untyped-call]
        node.tpdo.read(from_od=True)  # type: ignore[no-untyped-call]
        start_all(sim, client)
        rpdo, tpdo = node.rpdo[1], node.tpdo[1]
        condition = tpdo.receive_condition
        clock = time.perf_counter_ns
        loop = Loop()
        progress(f"pdo latency (baseline): {warmup} warm-up + {count} round trips")
        began = clock()
        for i in range(warmup + count):
            value = VALUES[i % len(VALUES)]
            start = clock()
            ok = True
            with condition:  # taken before the send: the TPDO cannot slip past the wait
                rpdo.data = bytearray(value)
                rpdo.transmit()
                while bytes(tpdo.data) != value:
                    if not condition.wait(ECHO_TIMEOUT_S):
                        ok = False
                        break
            if i == warmup - 1:
                began = clock()
            if i < warmup:
                continue
            if ok:
                loop.latencies_ns.append(clock() - start)
            else:
                loop.failures += 1
        loop.elapsed_s = (clock() - began) / 1e9
        return loop


def pdo_latency(count: int, warmup: int) -> dict[str, Any]:
    baseline = baseline_pdo_latency(count, warmup).summary()
    card = card_pdo_latency(count, warmup).summary()
    return {
        "description": "DevExchangeIO writes a new 8-byte output, the host polls the input "
                       "until it shows the value: output -> RPDO1 -> generic node -> TPDO1 -> "
                       "input; card in the uncontrolled handshake (exchange mode 3), 1 node",
        "cif": card,
        "baseline": {"name": "canopen RemoteNode: RPDO1 transmit, wait for TPDO1 with the value "
                             "(same simulated node, virtual bus, this process)", **baseline},
        "ratio_to_baseline": {
            "definition": "cif / baseline",
            "p50": ratio(card["latency_us"].get("p50", 0.0),
                         baseline["latency_us"].get("p50", 0.0)),
            "p99": ratio(card["latency_us"].get("p99", 0.0),
                         baseline["latency_us"].get("p99", 0.0)),
        },
    }


# --- 2. PDO throughput ----------------------------------------------------------------------------


@dataclass(slots=True)
class EchoWindow:
    """One closed-loop window: every value written is verified back at the input."""

    active: int
    seconds: float
    verified_timed: int = 0
    """Values verified before the window's end."""
    verified_total: int = 0
    """... and while the values in flight at the end drained."""
    lost: int = 0
    """Values never seen at the input, DRAIN_S after the window's end."""
    exchange_errors: int = 0
    host_loops: int = 0
    wall_start: float = 0.0
    wall_end: float = 0.0
    wall_drained: float = 0.0
    elapsed_s: float = 0.0
    echo_s: list[npt.NDArray[np.float64]] = field(default_factory=list)
    """Seconds from writing each value to seeing it at the input."""
    trace: dict[str, Any] = field(default_factory=dict)

    @property
    def echoes_per_s(self) -> float:
        return self.verified_timed / self.elapsed_s if self.elapsed_s else 0.0

    def summary(self) -> dict[str, Any]:
        echo = np.concatenate(self.echo_s) if self.echo_s else np.zeros(0)
        result: dict[str, Any] = {
            "active_nodes": self.active,
            "seconds": round(self.elapsed_s, 3),
            "verified_echoes": self.verified_timed,
            "verified_echoes_per_s": round(self.echoes_per_s, 1),
            "pdo_frames_per_s": round(2 * self.echoes_per_s, 1),
            "lost": self.lost,
            f"echoes_slower_than_{STALL_S}_s": int(np.count_nonzero(echo > STALL_S)),
            "echo_latency_us": latency_stats([int(x) for x in echo * 1e9]),
            "exchange_errors": self.exchange_errors,
            "host_polls": self.host_loops,
        }
        if self.trace:
            result["trace"] = self.trace
        return result


def echo_window(board: int, values: U64, active: int, seconds: float, out_offset: int,
                in_offset: int,
                record: Callable[[npt.NDArray[np.float64]], object] | None = None) -> EchoWindow:
    """Drive ``active`` nodes' loops for ``seconds``, then let the values in flight drain.

    ``values`` holds every node's current output value (u64, little endian) and is
    advanced in place, so the next window starts from values the nodes have not seen.
    A value never comes back twice and is never replaced before it came back, so a
    value still missing ``DRAIN_S`` after the window is lost (and its node stalled).
    ``record`` takes the loop times instead of ``EchoWindow.echo_s`` (the soak's
    histogram, which does not grow).
    """
    window = EchoWindow(active, seconds)
    size = 8 * active
    out = values[:active]
    out += np.uint64(1)
    pending = np.ones(active, dtype=bool)
    exchange, clock = DevExchangeIO, time.perf_counter
    out_bytes = out.tobytes()
    window.wall_start = time.time()
    start = clock()
    sent_at = np.full(active, start)
    end = start + seconds
    running = True
    drain_deadline = 0.0
    while True:
        rc, raw = exchange(board, out_offset, out_bytes, in_offset, size, TIMEOUT_MS)
        now = clock()
        window.host_loops += 1
        if rc != 0 or len(raw) != size:
            window.exchange_errors += 1
            continue
        done = (np.frombuffer(raw, dtype="<u8") == out) & pending
        echoed = int(np.count_nonzero(done))
        if not echoed:
            time.sleep(HOST_IDLE_S)
        else:
            window.verified_total += echoed
            (record or window.echo_s.append)(now - sent_at[done])
            if running:
                out[done] += np.uint64(1)
                sent_at[done] = now
                out_bytes = out.tobytes()
            else:
                pending &= ~done
        if running:
            if now >= end:
                running = False
                window.elapsed_s = now - start
                window.wall_end = time.time()
                window.verified_timed = window.verified_total
                drain_deadline = now + DRAIN_S
        elif not pending.any() or now > drain_deadline:
            window.lost = int(np.count_nonzero(pending))
            window.wall_drained = time.time()
            return window


TRACE_RECORD = re.compile(rb"\((\d+\.\d{6})\) \S+ ([0-9A-F]{3,8})#")
"""One candump record's time stamp and identifier, wherever it starts in a line."""
TRACE_LINE = re.compile(rb"\(\d+\.\d{6}\) \S+ [0-9A-F]{3,8}#[0-9A-FR]*( [RT])?")


@dataclass(slots=True)
class Trace:
    """The frames of a candump-format trace, sorted by time."""

    stamps: npt.NDArray[np.float64]
    idents: npt.NDArray[np.int64]
    lines: int
    damaged_lines: int
    """Lines that are not exactly one record (records written over each other)."""
    duplicates: int
    """Records found twice in the damage (same time stamp and identifier), counted once."""


def read_trace(path: Path) -> Trace:
    """Every record of a trace, also those inside damaged lines; exact duplicates once.

    The card writes its trace from several threads (the receive thread, and each
    thread that sends); records can land inside one another, so records are
    searched anywhere in a line rather than one per line.
    """
    raw = path.read_bytes()
    lines = raw.splitlines()
    damaged = sum(1 for line in lines if not TRACE_LINE.fullmatch(line))
    seen: set[tuple[bytes, bytes]] = set()
    records: list[tuple[float, int]] = []
    duplicates = 0
    for match in TRACE_RECORD.finditer(raw):
        key = (match.group(1), match.group(2))
        if key in seen:
            duplicates += 1
            continue
        seen.add(key)
        records.append((float(match.group(1)), int(match.group(2), 16)))
    records.sort()
    stamps = np.array([r[0] for r in records], dtype=np.float64)
    idents = np.array([r[1] for r in records], dtype=np.int64)
    return Trace(stamps, idents, len(lines), damaged, duplicates)


def count_frames(trace: Trace, low: int, high: int, since: float, until: float) -> int:
    """Frames with ``low <= identifier < high`` stamped within ``[since, until]``."""
    idents, stamps = trace.idents, trace.stamps
    mask = (idents >= low) & (idents < high) & (stamps >= since) & (stamps <= until)
    return int(np.count_nonzero(mask))


def trace_counts(window: EchoWindow, trace: Trace) -> dict[str, Any]:
    """What the card's own trace saw during a window; nodes 1..active."""
    rpdo = (RPDO1 + 1, RPDO1 + window.active + 1)
    tpdo = (TPDO1 + 1, TPDO1 + window.active + 1)
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


def card_pdo_throughput(profile: bool) -> dict[str, Any]:
    nodes = list(range(1, THROUGHPUT_NODES + 1))
    text = network_toml(nodes)
    network = parse_network(text)
    out_offset, in_offset = io_offsets(network)
    windows: list[EchoWindow] = []
    profiled: dict[str, Any] | None = None
    with simulated_card(text, trace=True, separate=True) as card:
        board = _board(card)
        select_uncontrolled(board)
        progress(f"pdo throughput (card): on-line configuration of {len(nodes)} nodes")
        bus_download = configure(card, network)
        operating = wait_operating(board.number, len(nodes))
        online_boot_s = operating - bus_download
        values: U64 = np.arange(1, len(nodes) + 1, dtype=np.uint64) << np.uint64(40)
        for active in THROUGHPUT_ACTIVE:
            progress(f"pdo throughput (card): {active} nodes for {THROUGHPUT_SECONDS} s")
            windows.append(echo_window(board.number, values, active, THROUGHPUT_SECONDS,
                                       out_offset, in_offset))
        if profile:
            progress(f"pdo throughput (card): profiling {len(nodes)} nodes for "
                     f"{PROFILE_SECONDS} s with py-spy")
            profiled = profile_window(card, values, len(nodes), out_offset, in_offset)
        diagnostics = board.diagnostics()
        card.stop()
        if card.trace is None:
            raise RuntimeError("the card ran without a trace")
        trace = read_trace(card.trace)
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
        "windows": [w.summary() for w in windows],
        "trace_damage": {
            "lines": trace.lines,
            "damaged_lines": trace.damaged_lines,
            "duplicate_records": trace.duplicates,
            "note": "the card's trace is written unsynchronised from several threads; records "
                    "written over each other are recovered where readable, so the trace "
                    "counts are a cross-check (a lower bound), not the figure",
        },
        "task2state_counters": {
            "usMsg_Time_Out": diagnostics.usMsg_Time_Out,
            "usRx_Overflow": diagnostics.usRx_Overflow,
            "usBus_Error_Cnt": diagnostics.usBus_Error_Cnt,
        },
        "online_boot_126_nodes_s": round(online_boot_s, 3),
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
        self.client.send_message(RPDO1 + 1 + index, self.values[index].to_bytes(8, "little"))

    def on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        del timestamp
        index = can_id - TPDO1 - 1
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


def baseline_pdo_throughput() -> dict[str, Any]:
    nodes = list(range(1, THROUGHPUT_NODES + 1))
    network = parse_network(network_toml(nodes))
    with in_process(network) as (sim, client):
        start_all(sim, client)
        time.sleep(0.05)  # the TPDOs of entering OPERATIONAL
        loop = _Echoes(client, [(node << 40) + 1 for node in nodes], pending=set(range(len(nodes))))
        for node in nodes:
            client.subscribe(TPDO1 + node, loop.on_tpdo)
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
            client.unsubscribe(TPDO1 + node, loop.on_tpdo)
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


def pdo_throughput(profile: bool) -> dict[str, Any]:
    baseline = baseline_pdo_throughput()
    card = card_pdo_throughput(profile)
    return {
        "description": "closed loop, one value in flight per node: the host writes a node's "
                       "next output value once its input shows the previous one; every value "
                       "is one RPDO the card sends and one TPDO it receives and stores; frames "
                       "counted in the card's candump trace, input updates verified by the host",
        "cif": card,
        "baseline": baseline,
        "ratio_to_baseline": {
            "definition": "cif pdo_frames_per_s / baseline pdo_frames_per_s",
            "pdo_frames_per_s": ratio(card["pdo_frames_per_s"], baseline["pdo_frames_per_s"]),
        },
    }


# --- profiling the firmware (optional) ------------------------------------------------------------


ROLES = {
    "card: CAN tick (output scan, RPDO send, supervision)": ("can-tick",),
    "card: SYNC producer": ("can-sync",),
    "card: node boot / SDO workers": ("node-boot",),
    "card: device loop (mailboxes, handshakes)": ("MainThread",),
    "simulator: timers": ("sim scheduler",),
    "simulator: heartbeat producers (python-can cyclic tasks)": ("Cyclic send task",),
}
CARD_RX = "card: controller receive (input PDOs -> image)"
SIM_RX = "simulator: receive (RPDO apply, echo, TPDO send, SDO server)"


def _py_spy() -> str | None:
    beside = Path(sys.executable).parent / "py-spy"
    return str(beside) if beside.exists() else shutil.which("py-spy")


def profile_window(card: SimCard, values: U64, active: int, out_offset: int,
                   in_offset: int) -> dict[str, Any]:
    """One more throughput window with py-spy sampling the firmware's GIL holder."""
    spy = _py_spy()
    if spy is None:
        return {"error": "py-spy not found"}
    output = card.directory / "profile.txt"
    command = [spy, "record", "--pid", str(card.pid), "--duration", str(int(PROFILE_SECONDS)),
               "--rate", str(PROFILE_RATE), "--format", "raw", "--output", str(output),
               "--threads", "--gil", "--nonblocking"]
    recorder = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    time.sleep(0.3)  # py-spy attaches
    window = echo_window(_board(card).number, values, active, PROFILE_SECONDS, out_offset,
                         in_offset)
    try:
        _, errors = recorder.communicate(timeout=PROFILE_SECONDS + 30)
    except subprocess.TimeoutExpired:
        recorder.kill()
        _, errors = recorder.communicate()
    if recorder.returncode != 0 or not output.exists():
        return {"error": f"py-spy failed ({recorder.returncode}): "
                         f"{errors.decode(errors='replace').strip()[-300:]}"}
    summary = summarise_profile(output.read_text(), PROFILE_SECONDS * PROFILE_RATE)
    frames = 2 * window.echoes_per_s
    card_busy = summary["card_share"] * summary["gil_busy_fraction"]
    return {
        "tool": f"py-spy record --gil --rate {PROFILE_RATE} --duration {int(PROFILE_SECONDS)}",
        "active_nodes": active,
        "verified_echoes_per_s_while_profiled": round(window.echoes_per_s, 1),
        "lost_while_profiled": window.lost,
        **summary,
        "estimated_card_only_pdo_frames_per_s": round(frames / card_busy, 1)
        if card_busy else None,
        "estimate_note": "frames/s divided by the fraction of wall time the card's own threads "
                         "held the GIL: roughly the rate if the simulated nodes cost nothing "
                         "(rough: the CAN tick's cost grows with ticks and nodes, not frames)",
    }


def summarise_profile(raw: str, expected_samples: float) -> dict[str, Any]:
    """Shares of GIL samples by thread role and by function (py-spy raw, ``--threads``)."""
    by_thread: Counter[str] = Counter()
    thread_kind: dict[str, Counter[str]] = {}
    thread_name: dict[str, str] = {}
    inclusive: Counter[str] = Counter()
    total = 0
    for line in raw.splitlines():
        stack, _, count_text = line.rpartition(" ")
        try:
            count = int(count_text)
        except ValueError:
            continue
        frames = stack.split(";")
        head = frames[0]
        tid = head.partition(")")[0]
        thread_name[tid] = head.partition(": ")[2]
        by_thread[tid] += count
        total += count
        kinds = thread_kind.setdefault(tid, Counter())
        if "firmware/can/bus.py" in stack:
            kinds["card"] += count
        elif "firmware/sim/" in stack or "canopen/network.py" in stack:
            kinds["sim"] += count
        seen: set[str] = set()
        for frame in frames[1:]:
            name = frame.split(":")[0] + ")" if ":" in frame else frame
            if name not in seen:
                seen.add(name)
                inclusive[name] += count
    shares: Counter[str] = Counter()
    for tid, count in by_thread.items():
        name = thread_name[tid]
        role = next((r for r, prefixes in ROLES.items() if name.startswith(prefixes)), None)
        if role is None and name.startswith("Notifier"):
            kinds = thread_kind.get(tid, Counter())
            role = CARD_RX if kinds["card"] >= kinds["sim"] else SIM_RX
        shares[role or f"other: {name}"] += count

    def share(value: int) -> float:
        return round(value / total, 3) if total else 0.0

    card = sum(v for k, v in shares.items() if k.startswith("card"))
    sim = sum(v for k, v in shares.items() if k.startswith("simulator"))
    skip = ("Thread._bootstrap", "Thread.run ", "Thread._bootstrap_inner")
    top = [{"function": name, "share": share(value)} for name, value in inclusive.most_common(60)
           if not name.startswith(skip)][:25]
    return {
        "gil_samples": total,
        "gil_busy_fraction": round(min(1.0, total / expected_samples), 3)
        if expected_samples else None,
        "share_by_role": {k: share(v) for k, v in shares.most_common()},
        "card_share": share(card),
        "simulator_share": share(sim),
        "top_functions_inclusive": top,
    }


# --- 3. SDO through the mailbox -------------------------------------------------------------------


def write_bench_eds(directory: Path) -> Path:
    """The generic node's object dictionary plus a read-write DOMAIN 2000h, as an EDS."""
    node = parse_network(network_toml([1])).nodes[0]
    dictionary = generic_object_dictionary(node)
    domain = ODVariable("Benchmark domain", DOMAIN_INDEX, 0)
    domain.data_type = od.DOMAIN
    domain.access_type = "rw"
    dictionary.add_object(domain)
    path = directory / "bench.eds"
    canopen.export_od(dictionary, str(path), doc_type="eds")
    return path


@dataclass(slots=True)
class Rate:
    transfers: int = 0
    failures: int = 0
    elapsed_s: float = 0.0
    payload_bytes: int = 0

    def per_s(self) -> float:
        return self.transfers / self.elapsed_s if self.elapsed_s else 0.0

    def kib_per_s(self) -> float:
        return self.payload_bytes / 1024 / self.elapsed_s if self.elapsed_s else 0.0


def timed(step: Callable[[], bool], warmup: int, seconds: float, payload: int) -> Rate:
    """Run ``step`` (True = success) ``warmup`` times, then for ``seconds``."""
    for _ in range(warmup):
        step()
    rate = Rate()
    clock = time.perf_counter
    start = clock()
    end = start + seconds
    while True:
        if step():
            rate.transfers += 1
            rate.payload_bytes += payload
        else:
            rate.failures += 1
        now = clock()
        if now >= end:
            rate.elapsed_s = now - start
            return rate


def sdo_message(node: int, index: int, sub: int, data: bytes | None = None) -> Message:
    """COM_SDO_Up_Download: device_adr, 0, index, sub, data_cnt, 0, function 1 read / 2 write."""
    payload = data or b""
    head = struct.pack("<BBHBBBB", node, 0, index, sub, len(payload), 0,
                       SDO_WRITE if data is not None else SDO_READ)
    return Message(rx=CAN_TASK, tx=USER, b=COM_SDO_UP_DOWNLOAD, data=head + payload)


DEVICE_TYPE_BYTES = DEVICE_TYPE.to_bytes(4, "little")
DOMAIN_PAYLOAD = bytes(range(DOMAIN_BYTES))


@dataclass(frozen=True, slots=True)
class SdoSteps:
    """One side's transfers, each returning True on success."""

    expedited: Callable[[], bool]
    segmented: Callable[[], bool]


@contextmanager
def card_sdo_steps(eds: Path) -> Iterator[tuple[SdoSteps, Callable[[], bool], SimCard]]:
    """The card's SDO transfers by COM_SDO_Up_Download, and a COM_Node_Diag round trip."""
    text = network_toml([1], eds=eds)
    with simulated_card(text) as card:
        board = _board(card)
        configure(card, parse_network(text))
        wait_operating(board.number, 1)

        def transact(msg: Message) -> Message | None:
            try:
                return board.transact(msg)
            except CifError:
                return None

        def expedited() -> bool:
            answer = transact(sdo_message(1, 0x1000, 0))
            return answer is not None and answer.f == 0 and answer.data[8:12] == DEVICE_TYPE_BYTES

        def domain() -> bool:
            written = transact(sdo_message(1, DOMAIN_INDEX, 0, DOMAIN_PAYLOAD))
            if written is None or written.f != 0:
                return False
            read = transact(sdo_message(1, DOMAIN_INDEX, 0))
            return read is not None and read.f == 0 and read.data[8:] == DOMAIN_PAYLOAD

        def node_diag() -> bool:
            answer = transact(Message(rx=CAN_TASK, tx=USER, b=COM_NODE_DIAG,
                                      data=bytes([1, 0, 0, 0, 0, 0, 5, 1])))
            return answer is not None and answer.f == 0

        yield SdoSteps(expedited, domain), node_diag, card


@contextmanager
def baseline_sdo_steps(eds: Path) -> Iterator[SdoSteps]:
    """canopen's SdoClient straight to the same simulated node, in this process."""
    network = parse_network(network_toml([1], eds=eds))
    with in_process(network) as (_, client):
        sdo = sdo_client(client, 1)

        def expedited() -> bool:
            try:
                return bytes(sdo.upload(0x1000, 0)) == DEVICE_TYPE_BYTES
            except SdoError:
                return False

        def domain() -> bool:
            try:
                sdo.download(DOMAIN_INDEX, 0, DOMAIN_PAYLOAD)
                return bytes(sdo.upload(DOMAIN_INDEX, 0)) == DOMAIN_PAYLOAD
            except SdoError:
                return False

        yield SdoSteps(expedited, domain)


def interleaved(card: Callable[[], bool], baseline: Callable[[], bool], warmup: int,
                payload: int) -> tuple[Rate, Rate]:
    """Card and baseline in alternating slices, so a change of the machine's load hits both."""
    slice_s = SDO_SECONDS / SDO_ROUNDS
    totals = (Rate(), Rate())
    for step in (card, baseline):
        for _ in range(warmup):
            step()
    for _ in range(SDO_ROUNDS):
        for total, step in zip(totals, (card, baseline), strict=True):
            part = timed(step, 0, slice_s, payload)
            total.transfers += part.transfers
            total.failures += part.failures
            total.elapsed_s += part.elapsed_s
            total.payload_bytes += part.payload_bytes
    return totals


def sdo() -> dict[str, Any]:
    with (tempfile.TemporaryDirectory(prefix="cifemu-bench-eds-") as tmp,
          card_sdo_steps(write_bench_eds(Path(tmp))) as (card_steps, node_diag, sim_card),
          baseline_sdo_steps(Path(tmp) / "bench.eds") as base_steps):
        progress(f"sdo: expedited uploads, card and baseline alternating, {SDO_ROUNDS} x "
                 f"{SDO_SECONDS / SDO_ROUNDS} s each")
        card_fast, base_fast = interleaved(card_steps.expedited, base_steps.expedited,
                                           SDO_WARMUP, 4)
        progress(f"sdo: {DOMAIN_BYTES}-byte DOMAIN download + upload, alternating")
        card_seg, base_seg = interleaved(card_steps.segmented, base_steps.segmented,
                                         SDO_WARMUP // 5, 2 * DOMAIN_BYTES)
        progress("sdo: COM_Node_Diag mailbox round trips (reference)")
        mailbox = timed(node_diag, SDO_WARMUP, MAILBOX_SECONDS, 0)
        firmware_log = sim_card.log()

    def side(fast: Rate, segmented: Rate) -> dict[str, Any]:
        return {
            "expedited_uploads_per_s": round(fast.per_s(), 1),
            "expedited_failures": fast.failures,
            "segmented_transfers_per_s": round(segmented.per_s(), 1),
            "segmented_kib_per_s": round(segmented.kib_per_s(), 2),
            "segmented_failures": segmented.failures,
        }

    card, baseline = side(card_fast, card_seg), side(base_fast, base_seg)
    card["firmware_log"] = firmware_log
    mailbox_us = 1e6 / mailbox.per_s() if mailbox.per_s() else None
    card["mailbox_reference"] = {
        "name": "COM_Node_Diag (msg.b 66) to the CAN task: the same mailbox round trip, "
                "answered at once by the device loop, no bus traffic",
        "round_trips_per_s": round(mailbox.per_s(), 1),
        "failures": mailbox.failures,
        "us_per_round_trip": round(mailbox_us, 1) if mailbox_us else None,
    }
    if mailbox_us and card_fast.per_s() and base_fast.per_s():
        card["expedited_us_split"] = {
            "total": round(1e6 / card_fast.per_s(), 1),
            "mailbox_round_trip": round(mailbox_us, 1),
            "inside_the_card": round(1e6 / card_fast.per_s() - mailbox_us, 1),
            "baseline_total": round(1e6 / base_fast.per_s(), 1),
        }
    return {
        "description": "expedited: upload of 1000h (4 bytes); segmented: download then upload "
                       f"of a {DOMAIN_BYTES}-byte DOMAIN {DOMAIN_INDEX:04X}h (KiB/s counts "
                       "the payload both ways); card: COM_SDO_Up_Download (msg.b 74) by "
                       "Board.transact, one transfer at a time; card and baseline run in "
                       f"{SDO_ROUNDS} alternating slices each",
        "cif": card,
        "baseline": {"name": "canopen SdoClient straight to the same simulated node "
                             "(virtual bus, this process)", **baseline},
        "ratio_to_baseline": {
            "definition": "cif / baseline",
            "expedited": ratio(card["expedited_uploads_per_s"],
                               baseline["expedited_uploads_per_s"]),
            "segmented": ratio(card["segmented_kib_per_s"], baseline["segmented_kib_per_s"]),
        },
    }


# --- 4. boot-up --------------------------------------------------------------------------------


def card_boot() -> dict[str, Any]:
    nodes = list(range(1, BOOT_NODES + 1))
    text = network_toml(nodes)
    database = write_dbm(build_dbm(parse_network(text)))
    runs: list[dict[str, float]] = []
    with simulated_card(text, separate=True) as card:
        board = _board(card)
        rc = DevDownload(board.number, CONFIGURATION_DOWNLOAD, database)
        if rc != 0:
            raise RuntimeError(f"DevDownload returned {rc}")
        for attempt in range(BOOT_REPEATS):
            progress(f"boot (card): cold start {attempt + 1}/{BOOT_REPEATS} with {len(nodes)} "
                     "nodes in the stored database")
            start = time.perf_counter()
            rc = DevReset(board.number, COLDSTART, RESET_TIMEOUT_MS)
            if rc != 0:
                raise RuntimeError(f"DevReset(COLDSTART) returned {rc}")
            ready = time.perf_counter()
            operating = wait_operating(board.number, len(nodes))
            runs.append({"all_operating_s": round(operating - start, 3),
                         "ready_s": round(ready - start, 3)})
        firmware_log = card.log()
    return {"nodes": len(nodes), "runs": runs,
            "median_s": round(_median([r["all_operating_s"] for r in runs]), 3),
            "firmware_log": firmware_log}


def _median(values: list[float]) -> float:
    return percentile(sorted(values), 50)


def baseline_boot() -> dict[str, Any]:
    nodes = list(range(1, BOOT_NODES + 1))
    network = parse_network(network_toml(nodes))
    runs: list[float] = []
    with in_process(network) as (_, client):
        bootups = {node: threading.Event() for node in nodes}

        def on_error_control(can_id: int, data: bytearray, timestamp: float) -> None:
            del timestamp
            if data and data[0] == 0:
                bootups[can_id - 0x700].set()

        for node in nodes:
            client.subscribe(0x700 + node, on_error_control)
        clients = {node: sdo_client(client, node) for node in nodes}

        def boot_node(node: int) -> None:
            """The card's boot steps (firmware.can.node.NodeHandler._boot_steps)."""
            sdo = clients[node]
            bootups[node].clear()
            client.send_message(NMT_ID, bytes([NMT_RESET_NODE, node]))
            if not bootups[node].wait(BOOTUP_TIMEOUT_S):
                raise RuntimeError(f"node {node}: no boot-up")
            if bytes(sdo.upload(0x1000, 0)) != DEVICE_TYPE_BYTES:
                raise RuntimeError(f"node {node}: wrong device type")
            sdo.download(0x1017, 0, struct.pack("<H", 500))
            sdo.download(0x1005, 0, struct.pack("<I", SYNC_COB_ID))
            sdo.download(0x1014, 0, struct.pack("<I", 0x80 + node))
            client.send_message(NMT_ID, bytes([NMT_START, node]))

        time.sleep(0.1)  # the nodes' power-on boot-ups
        with ThreadPoolExecutor(max_workers=BOOT_WORKERS) as pool:
            for attempt in range(BOOT_REPEATS):
                progress(f"boot (baseline): run {attempt + 1}/{BOOT_REPEATS}, {len(nodes)} nodes")
                start = time.perf_counter()
                list(pool.map(boot_node, nodes))
                runs.append(time.perf_counter() - start)
    return {
        "name": f"canopen runs the card's boot sequence for the same {len(nodes)} simulated "
                "nodes in this process: NMT reset node, wait for the boot-up, upload 1000h, "
                "download 1017h, 1005h, 1014h, NMT start; "
                f"{BOOT_WORKERS} nodes in parallel (the card's boot pool)",
        "nodes": len(nodes),
        "runs_s": [round(r, 3) for r in runs],
        "median_s": round(_median(runs), 3),
    }


def boot(online_126_s: float | None) -> dict[str, Any]:
    baseline = baseline_boot()
    card = card_boot()
    if online_126_s is not None:
        card["online_126_nodes_s"] = online_126_s
        card["online_note"] = ("on-line configuration (configure_online), 126 nodes, timed from "
                               "the bus parameter download; node 127 cannot be configured on "
                               "line because area code 127 of COM_Download is the bus "
                               "parameter set (taken from the pdo_throughput phase)")
    return {
        "description": f"{BOOT_NODES} generic nodes stored in the card's flash (DevDownload), "
                       "then DevReset(COLDSTART): seconds from the reset call until all "
                       "nodes are in Nd_state (the start downloads nodes, then the bus "
                       "parameters, which start the network)",
        "cif": card,
        "baseline": baseline,
        "ratio_to_baseline": {"definition": "cif median / baseline median",
                              "median": ratio(card["median_s"], baseline["median_s"])},
    }


# --- 5. SYNC jitter ----------------------------------------------------------------------------


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


def card_sync() -> dict[str, Any]:
    nodes = list(range(1, SYNC_NODES + 1))
    text = network_toml(nodes, sync_period_ms=SYNC_PERIOD_MS)
    network = parse_network(text)
    out_offset, in_offset = io_offsets(network)
    with simulated_card(text, trace=True, separate=True) as card:
        board = _board(card)
        select_uncontrolled(board)
        configure(card, network)
        wait_operating(board.number, len(nodes))
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
    syncs = trace.stamps[trace.idents == SYNC_COB_ID]
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
                can.Message(arbitration_id=SYNC_COB_ID, is_extended_id=False, data=b""),
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
    syncs = stamps[(trace.idents == SYNC_COB_ID) & (stamps >= since) & (stamps <= until)]
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


def sync_jitter() -> dict[str, Any]:
    floor = machine_floor_sync()
    floor_realtime = machine_floor_sync(realtime=True)
    baseline = baseline_sync()
    card = card_sync()
    card_p99 = card["idle"].get("jitter_us", {}).get("p99")
    base_p99 = baseline.get("jitter_us", {}).get("p99")
    return {
        "description": f"[bus] sync_period_ms = {SYNC_PERIOD_MS}: jitter = |period - "
                       f"{SYNC_PERIOD_MS} ms| between successive SYNC frames (0x080) by the "
                       "time stamps of the card's candump trace (the sender's time of the send; on "
                       "shm the SYNC comes from the card's SCHED_FIFO timer process)",
        "cif": card,
        "baseline": baseline,
        "machine_floor": floor,
        "machine_floor_realtime": floor_realtime,
        "ratio_to_baseline": {"definition": "cif idle jitter p99 / baseline jitter p99",
                              "jitter_p99": ratio(card_p99 or 0.0, base_p99 or 0.0)},
        "card_over_machine_floor_us": {
            "definition": "cif jitter p99 - the SCHED_FIFO sleep loop's p99 in the same window: "
                          "what the card adds to what this machine allows at that moment",
            "idle": _excess(card["idle"]),
            "with_pdo_loop": _excess(card["with_pdo_loop"]),
        },
    }


def _excess(window: dict[str, Any]) -> float | None:
    card = window.get("jitter_us", {}).get("p99")
    floor = window["machine_floor_realtime_same_window"].get("jitter_us", {}).get("p99")
    return None if card is None or floor is None else round(card - floor, 1)


# --- the document -------------------------------------------------------------------------------


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


if __name__ == "__main__":
    raise SystemExit(main())
