"""The card under test: a firmware process with simulated nodes, and the host's board on it.

Shared by every phase: the card is started as ``cifemu firmware --simulate`` (or beside
``cifemu sim`` on a fresh ``shm`` channel), configured on line, and reached only through
the driver API.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from bench.common import (
    STARTUP_TIMEOUT,
    progress,
    scratch_root,
    stop_process,
)
from dbm_tools.builder import build_dbm
from dbm_tools.network import GENERIC_DEVICE_TYPE, Network
from dbm_tools.parameters import NodeParameterSet
from dbm_tools.tables import NODES
from dpm import flags as fl
from dpm.cia301 import ABORT_TIMEOUT, RPDO_BASES, TPDO_BASES
from dpm.layout import IO_AREA_SIZE
from dpm.task2 import BMODE_TO_EXCHANGE_MODE, ComDiagnostics, ComPlcParameter, PlcMode
from host_api.board import Board
from host_api.driver import (
    GET_IO_INFO,
    DevGetInfo,
    DevGetTaskState,
)
from host_api.online import configure_online
from host_api.ready import wait_ready
from host_api.registry import lookup

BOARD = 0
CHANNEL = "cifemu-bench"
TIMEOUT_MS = 1000
RESET_TIMEOUT_MS = 10_000
BOOT_TIMEOUT_S = 20.0
OPERATING_POLL_S = 0.01
"""How often ``wait_operating`` reads Nd_state when no ring came: the card rings this host
when Task2State changes (STATECOM, the state field's handshake), so the read follows each
change at once. It read Nd_state every 0.5 ms before: a busy poll that took CPU the booting
card needed, on two CPUs beside the boot benchmark's card and nodes (inside User-Mode Linux,
0 of 126 nodes up after 20 s against 37 with a 20 ms poll)."""

UNCONTROLLED_BMODE = PlcMode.UNCONTROLLED
"""Task2Parameter bMode that selects the uncontrolled handshake at a warm start."""
UNCONTROLLED_EXCHANGE_MODE = BMODE_TO_EXCHANGE_MODE[UNCONTROLLED_BMODE]

DEVICE_TYPE_BYTES = GENERIC_DEVICE_TYPE.to_bytes(4, "little")
"""Object 1000h of the generic node, as an SDO upload returns it."""

SDO_TIMEOUT_TEXT = f"0x{ABORT_TIMEOUT:08X}"
"""canopen's SDO client logs its timeout abort with this code."""


@dataclass(frozen=True, slots=True)
class SeparateBus:
    """Where the card meets nodes that run as ``cifemu sim`` in a process of their own.

    ``shm`` gets a fresh channel per card (the default); ``socketcan`` uses the named
    link (vcan0 inside ``tools/vcan-vm``), which the phases then share one after another.
    """

    interface: str = "shm"
    channel: str | None = None

    def for_card(self) -> tuple[str, str]:
        """The interface and channel of one card and its ``cifemu sim``."""
        if self.channel is not None:
            return self.interface, self.channel
        return self.interface, f"bench-{uuid.uuid4().hex[:12]}"

    def describe(self) -> str:
        return f"{self.interface} {self.channel}" if self.channel else f"fresh {self.interface}"


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
    interface: str = "virtual"
    channel: str = CHANNEL
    """Where the card and its nodes meet (a fresh ``shm`` channel for a separate ``sim``)."""

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
        stop_process(self.proc)
        if self.sim is not None:
            stop_process(self.sim)


@contextmanager
def simulated_card(description: str, *, trace: bool = False, separate: bool = False,
                   bus: SeparateBus | None = None, board: int = BOARD,
                   dpm_dir: Path | None = None, record: bool = False) -> Iterator[SimCard]:
    """``cifemu firmware --simulate`` on a fresh image directory and flash; board opened.

    ``separate`` runs the nodes as ``cifemu sim`` in a process of their own, the
    two meeting on ``bus`` (a fresh ``shm`` channel by default), so the card's
    threads do not share an interpreter lock with the simulator (as on a real bus,
    where the nodes are other machines). ``board`` and ``dpm_dir`` put the image
    beside other cards' (boards 0-3 in one directory, as a driver sees several cards);
    the flash, trace and log stay in the card's own temporary directory. ``record``: the
    card records a session there (``--record``), to measure what that costs.
    """
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-can-", dir=scratch_root()) as tmp:
        directory = Path(tmp)
        images = dpm_dir or directory
        toml = directory / "network.toml"
        toml.write_text(description)
        trace_path = directory / "trace.log" if trace else None
        stderr_path = directory / "firmware.stderr"
        interface, channel = (bus or SeparateBus()).for_card() if separate else (
            "virtual", CHANNEL)
        command = [sys.executable, "-m", "cifemu", "firmware", "--board", str(board),
                   "--dpm-dir", str(images), "--log-level", "WARNING", "--interface", interface,
                   "--channel", channel, "--flash", str(directory / "flash")]
        if not separate:
            command += ["--simulate", str(toml)]
        if trace_path is not None:
            command += ["--trace", str(trace_path)]
        if record:
            command += ["--record", str(directory / "session")]
        sim = start_sim(toml, interface, channel) if separate else None
        with stderr_path.open("wb") as stderr:
            proc = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                    stderr=stderr)
        card = SimCard(directory, proc, trace_path, stderr_path, sim=sim, interface=interface,
                       channel=channel)
        try:
            wait_ready(proc, images, board, STARTUP_TIMEOUT)
            card.board = Board(board, images, timeout=5000).open()
            yield card
        finally:
            card.stop()
            logged = card.log()
            if logged["lines"]:
                progress(f"the firmware logged {logged['lines']} line(s), e.g. "
                         f"{logged['first_lines'][0]}")


def start_sim(toml: Path, interface: str, channel: str) -> subprocess.Popen[bytes]:
    """``cifemu sim`` for the network description ``toml``, once its nodes are on the bus."""
    sim = subprocess.Popen(
        [sys.executable, "-m", "cifemu", "sim", str(toml), "--interface", interface,
         "--channel", channel, "--log-level", "WARNING"],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)
    assert sim.stdout is not None
    if not sim.stdout.readline().startswith(b"simulating"):  # its nodes are on the bus
        stop_process(sim)
        raise RuntimeError("cifemu sim did not start")
    # The node lines are read by nobody further on: the pipe must not fill.
    threading.Thread(target=sim.stdout.read, daemon=True).start()
    return sim


@contextmanager
def separate_nodes(description: str, bus: SeparateBus | None = None
                   ) -> Iterator[tuple[can.BusABC, subprocess.Popen[bytes]]]:
    """The nodes of ``description`` in ``cifemu sim``, as a card under test meets them
    (``simulated_card(separate=True)``), and a python-can bus of this process on their
    channel: for a baseline that must ask of the same nodes what the card asks. Yields the
    bus and the simulator's process."""
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-sim-", dir=scratch_root()) as tmp:
        toml = Path(tmp) / "network.toml"
        toml.write_text(description)
        interface, channel = (bus or SeparateBus()).for_card()
        sim = start_sim(toml, interface, channel)
        try:
            station = can.Bus(interface=interface, channel=channel)
            try:
                yield station, sim
            finally:
                station.shutdown()
        finally:
            stop_process(sim)


def board_of(card: SimCard) -> Board:
    if card.board is None:
        raise RuntimeError("the card's board is closed")
    return card.board


def network_toml(nodes: Sequence[int], *, sync_period_ms: int = 0, eds: Path | None = None,
                 handshake: str = "uncontrolled") -> str:
    """A network description of generic nodes (or nodes of ``eds``).

    With a SYNC period the first node also gets a synchronous RPDO of one byte (type 1, at
    the process image's last output byte, so no other node's offsets move): the card sends
    SYNC only while a node uses a SYNC-controlled PDO (seed 4.2), and the generic nodes'
    PDOs are event-driven. The node has no such RPDO and ignores the frame.
    """
    lines = ["[bus]", f"sync_period_ms = {sync_period_ms}", "host_watchdog_ms = 0",
             f'handshake = "{handshake}"']
    for number, node in enumerate(nodes):
        lines += ["[[node]]", f"id = {node}"]
        if eds is not None:
            lines.append(f'eds = "{eds}"')
        elif sync_period_ms and number == 0:
            lines += ["[[node.pdo]]", 'direction = "output"', f"cob_id = {RPDO_BASES[0] + node}",
                      "[[node.pdo]]", 'direction = "input"', f"cob_id = {TPDO_BASES[0] + node}",
                      "[[node.pdo]]", 'direction = "output"', f"cob_id = {RPDO_BASES[1] + node}",
                      "length = 1", "transmission = 1", f"offset = {IO_AREA_SIZE - 1}"]
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
    """perf_counter() when ``nodes`` nodes are in Nd_state: read when the card rings for a
    changed Task2State (the host acknowledges each change with STATEACK first, so that the
    card rings for the next), else every ``OPERATING_POLL_S``."""
    mapped = lookup(board)
    if isinstance(mapped, int):
        raise RuntimeError(f"board {board} is not initialised (rc {mapped})")
    deadline = time.perf_counter() + timeout
    while True:
        if fl.pending(mapped.host(), mapped.dev(), fl.STATE):
            mapped.change_dev_flags(toggle=fl.STATEACK)
        if operating_count(board) >= nodes:
            return time.perf_counter()
        if time.perf_counter() > deadline:
            raise RuntimeError(f"only {operating_count(board)} of {nodes} nodes operating "
                               f"after {timeout} s")
        mapped.bell.wait(OPERATING_POLL_S)


def configure(card: SimCard, network: Network) -> float:
    """The on-line configuration; returns perf_counter() just before the bus parameter download."""
    marks: list[float] = []

    def mark(text: str) -> None:
        if text.startswith("bus parameters"):
            marks.append(time.perf_counter())

    configure_online(board_of(card), network, progress=mark)
    if not marks:
        raise RuntimeError("configure_online never reached the bus parameters")
    return marks[-1]


def start_uncontrolled(card: SimCard, network: Network) -> tuple[Board, float, float]:
    """The PDO phases' card: uncontrolled handshake, configured on line, every node in
    Nd_state. Returns the board and the perf_counter() marks of the bus parameter download
    and of the last node entering Nd_state."""
    board = board_of(card)
    select_uncontrolled(board)
    bus_download = configure(card, network)
    operating = wait_operating(board.number, len(network.nodes))
    return board, bus_download, operating


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

