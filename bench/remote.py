"""``python -m bench remote``: the card on a bridged bus (python-can-remote) beside shm.

Each bridge gets a rig of its own: ``cifemu sim`` with one generic node on a fresh
``shm`` channel, and the card either on that channel (``shm``, the reference) or
across python-can-remote's websocket server on 127.0.0.1 serving it (``remote``).
Per rig, in one run so the figures share the machine's load (reported beside them):

- ``pdo_loop``: DevExchangeIO output -> RPDO -> node -> TPDO -> input, timed by
  ``bench.common.measure`` (uncontrolled handshake, as ``bench.can``'s phase 1);
- ``sdo``: SDO uploads of 1000h through the mailbox, for ``SDO_SECONDS``;
- ``frames``: the transport alone, no card: a burst of ``BURST`` numbered frames
  from a client of the bridge to an ``shm`` reader; lost, reordered, frames/s;
- ``nodes_lost``: the nodes' process killed and started again: what the host reads in
  Task2State, how long the card takes to notice (Nd_state empty) and to recover;
- ``link_lost`` (remote only): the server killed and started again on its port.

Needs python-can-remote (``pip install -e '.[remote]'``); without it, the remote rig
reports why it did not run.
"""

from __future__ import annotations

import contextlib
import importlib.util
import itertools
import os
import queue
import re
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from bench.can.card import (
    BOARD,
    DEVICE_TYPE_BYTES,
    TIMEOUT_MS,
    SimCard,
    board_of,
    io_offsets,
    network_toml,
    start_uncontrolled,
)
from bench.common import (
    STARTUP_TIMEOUT,
    STOP_TIMEOUT,
    latency_stats,
    machine_info,
    measure,
    progress,
    scratch_root,
    sized_main,
    source_fingerprint,
    stop_process,
    timed,
    wait_ready,
)
from dbm_tools.network import parse_network
from dpm.commands import COM_SDO_UP_DOWNLOAD
from dpm.message import Message, Task
from dpm.task2 import ComDiagnostics
from firmware.shm.bus import channel_path
from host_api.board import Board, CifError
from host_api.driver import DevExchangeIO, DevGetTaskState

NAME = "remote"
DEFAULTS = (200, 20)
"""``--count`` and ``--warmup`` of the PDO loop."""
BRIDGES = ("shm", "remote")
SDO_SECONDS = 3.0
BURST = 2000
"""Frames in the transport burst: more than a websocket's and a socket's buffers hold."""
QUIET_S = 2.0
"""The burst is over when the reader saw none of its frames for this long."""
ECHO_TIMEOUT_S = 1.0
RECOVER_TIMEOUT_S = 30.0
LISTENING = re.compile(rb"Connect using channel '(ws://[^']+)'")
SERVER_START_S = 20.0
BURST_ID = 0x7E0
"""Identifier of the burst frames: no CANopen service of the node or the card uses it."""


@dataclass
class Server:
    """python-can-remote's server serving one shm channel on 127.0.0.1."""

    proc: subprocess.Popen[bytes]
    url: str
    port: int


def start_server(channel: str, port: int = 0) -> Server:
    """``python -m can_remote`` on ``port`` (0: the kernel picks; the URL is read from its
    log, so no port is guessed)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "can_remote", "-i", "shm", "-c", channel, "-H", "127.0.0.1",
         "-p", str(port)], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE)
    lines: queue.Queue[bytes] = queue.Queue()

    def pump() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.put(line)

    threading.Thread(target=pump, daemon=True).start()
    deadline = time.monotonic() + SERVER_START_S
    while time.monotonic() < deadline and proc.poll() is None:
        with contextlib.suppress(queue.Empty):
            found = LISTENING.search(lines.get(timeout=0.1))
            if found:
                url = found.group(1).decode().replace("localhost", "127.0.0.1")
                return Server(proc, url, int(url.rstrip("/").rsplit(":", 1)[1]))
    stop_process(proc)
    raise RuntimeError("python -m can_remote did not say where it listens")


def stop_server(server: Server) -> None:
    """SIGINT, the server's only clean end (KeyboardInterrupt): after SIGTERM its side of the
    shm channel would stay in /dev/shm. SIGTERM and SIGKILL follow if it does not end."""
    if server.proc.poll() is None:
        server.proc.send_signal(signal.SIGINT)
        with contextlib.suppress(subprocess.TimeoutExpired):
            server.proc.wait(STOP_TIMEOUT)
    stop_process(server.proc)


def start_sim(toml: Path, channel: str) -> subprocess.Popen[bytes]:
    sim = subprocess.Popen([sys.executable, "-m", "cifemu", "sim", str(toml), "--interface",
                            "shm", "--channel", channel, "--log-level", "WARNING"],
                           stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)
    assert sim.stdout is not None
    if not sim.stdout.readline().startswith(b"simulating"):
        stop_process(sim)
        raise RuntimeError("cifemu sim did not start")
    threading.Thread(target=sim.stdout.read, daemon=True).start()  # the pipe must not fill
    return sim


@dataclass
class Rig:
    bridge: str
    card: SimCard
    channel: str
    toml: Path
    server: Server | None

    @property
    def card_channel(self) -> tuple[str, str]:
        """The interface and channel a client of this bridge opens."""
        return ("remote", self.server.url) if self.server else ("shm", self.channel)


@contextmanager
def rig(bridge: str) -> Iterator[Rig]:
    """The node in ``cifemu sim`` on a fresh shm channel, the card on ``bridge`` to it."""
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-remote-", dir=scratch_root()) as tmp:
        directory = Path(tmp)
        toml = directory / "network.toml"
        toml.write_text(network_toml([1]))
        channel = f"bench-remote-{uuid.uuid4().hex[:12]}"
        server = start_server(channel) if bridge == "remote" else None
        made: Rig | None = None
        try:
            sim = start_sim(toml, channel)
            interface, card_channel = ("remote", server.url) if server else ("shm", channel)
            stderr_path = directory / "firmware.stderr"
            with stderr_path.open("wb") as stderr:
                proc = subprocess.Popen(
                    [sys.executable, "-m", "cifemu", "firmware", "--board", str(BOARD),
                     "--dpm-dir", tmp, "--log-level", "WARNING", "--interface", interface,
                     "--channel", card_channel, "--flash", str(directory / "flash")],
                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=stderr)
            card = SimCard(directory, proc, None, stderr_path, sim=sim)
            made = Rig(bridge, card, channel, toml, server)
            wait_ready(proc, directory / f"board{BOARD}.dpm", STARTUP_TIMEOUT)
            card.board = Board(BOARD, directory, timeout=5000).open()
            yield made
        finally:
            if made is not None:
                made.card.stop()
                server = made.server
            if server is not None:
                stop_server(server)
            # Hygiene: the server's threads may end before its side of the channel closes.
            channel_path(channel).unlink(missing_ok=True)


def diagnostics(board: int) -> ComDiagnostics:
    rc, raw = DevGetTaskState(board, 2, 64)
    if rc != 0:
        raise RuntimeError(f"DevGetTaskState returned {rc}")
    return ComDiagnostics.decode(raw)


def pdo_loop(rig: Rig, count: int, warmup: int) -> dict[str, Any]:
    network = parse_network(rig.toml.read_text())
    board = board_of(rig.card)
    out_offset, in_offset = io_offsets(network)
    number, clock = board.number, time.perf_counter_ns
    values = itertools.cycle([bytes([v]) * 8 for v in range(1, 256)])
    give_up_ns = int(ECHO_TIMEOUT_S * 1e9)

    def round_trip() -> int:
        value = next(values)
        start = clock()
        DevExchangeIO(number, out_offset, value, 0, 0, TIMEOUT_MS)
        while DevExchangeIO(number, 0, b"", in_offset, 8, TIMEOUT_MS)[1] != value:
            if clock() - start > give_up_ns:
                return 1
        return 0

    progress(f"{rig.bridge}: pdo loop, {warmup} warm-up + 2 x {count} round trips")
    measured = measure(round_trip, count, warmup, frozenset({0}))
    return {"latency_us": latency_stats(measured.latencies_ns),
            "round_trips_per_s": round(measured.per_second, 1),
            "lost_round_trips": measured.failures}


def sdo(rig: Rig) -> dict[str, Any]:
    board = board_of(rig.card)
    head = struct.pack("<BBHBBBB", 1, 0, 0x1000, 0, 0, 0, 1)

    def upload() -> bool:
        try:
            answer = board.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_SDO_UP_DOWNLOAD,
                                            data=head))
        except CifError:
            return False
        return answer.f == 0 and bytes(answer.data[8:12]) == DEVICE_TYPE_BYTES

    progress(f"{rig.bridge}: SDO uploads for {SDO_SECONDS} s")
    rate = timed(upload, 5, SDO_SECONDS, 4)
    return {"uploads_per_s": round(rate.per_s(), 1), "uploads": rate.transfers,
            "failures": rate.failures}


def frames(rig: Rig) -> dict[str, Any]:
    """A burst through the transport alone; every frame numbered, so loss and reordering
    show. Reported, never hidden: a bridge that drops frames says how many."""
    interface, channel = rig.card_channel
    progress(f"{rig.bridge}: a burst of {BURST} frames through the transport")
    reader = can.Bus(interface="shm", channel=rig.channel)
    sender = can.Bus(interface=interface, channel=channel)
    seen: list[int] = []
    last = [0.0]

    def read() -> None:  # beside the sender, so a slow transport overflows no reader
        quiet_from = time.perf_counter()
        while len(seen) < BURST and time.perf_counter() - quiet_from < QUIET_S:
            msg = reader.recv(0.1)  # the node's heartbeats come too: not a quiet bus
            if msg is not None and msg.arbitration_id == BURST_ID:
                seen.append(int.from_bytes(msg.data, "little"))
                last[0] = quiet_from = time.perf_counter()

    thread = threading.Thread(target=read, daemon=True)
    try:
        thread.start()
        start = time.perf_counter()
        for n in range(BURST):
            sender.send(can.Message(arbitration_id=BURST_ID, is_extended_id=False,
                                    data=n.to_bytes(4, "little")))
        sent_s = time.perf_counter() - start
        thread.join()
    finally:
        sender.shutdown()
        reader.shutdown()
    elapsed = last[0] - start
    reordered = sum(1 for a, b in itertools.pairwise(seen) if b < a)
    return {"sent": BURST, "received": len(seen), "lost": BURST - len(set(seen)),
            "reordered": reordered, "send_s": round(sent_s, 3),
            "frames_per_s": round(len(seen) / elapsed, 1) if elapsed > 0 else None}


def _lost_and_back(rig: Rig, kill: str) -> dict[str, Any]:
    """Kill the nodes' process (``sim``) or the bridge's server (``server``), read what
    the host sees, start it again and time the recovery."""
    board = board_of(rig.card).number
    before = diagnostics(board)
    start = time.perf_counter()
    port = 0
    if kill == "sim":
        assert rig.card.sim is not None
        rig.card.sim.send_signal(signal.SIGKILL)
        rig.card.sim.wait()
    else:
        assert rig.server is not None
        port = rig.server.port
        rig.server.proc.send_signal(signal.SIGKILL)
        rig.server.proc.wait()
    noticed = _until(lambda: not diagnostics(board).operating(), RECOVER_TIMEOUT_S)
    lost = diagnostics(board)
    if kill == "sim":
        rig.card.sim = start_sim(rig.toml, rig.channel)
    else:
        rig.server = start_server(rig.channel, port)
    back_start = time.perf_counter()
    back = _until(lambda: diagnostics(board).operating() == [1], RECOVER_TIMEOUT_S)
    after = diagnostics(board)
    return {
        "noticed_s": None if noticed is None else round(noticed - start, 3),
        "err_event": lost.bErr_event, "err_node": lost.bErr_rem_adr,
        "can_state": lost.bCAN_State,
        "bus_off_cnt": lost.usBus_Off_Cnt - before.usBus_Off_Cnt,
        "bus_error_cnt": lost.usBus_Error_Cnt - before.usBus_Error_Cnt,
        "msg_time_out": lost.usMsg_Time_Out - before.usMsg_Time_Out,
        "recovered_s": None if back is None else round(back - back_start, 3),
        "err_event_after": after.bErr_event,
        "recover_timeout_s": RECOVER_TIMEOUT_S,
    }


def _until(condition: Any, timeout: float) -> float | None:
    deadline = time.perf_counter() + timeout
    while time.perf_counter() < deadline:
        if condition():
            return time.perf_counter()
        time.sleep(0.01)
    return None


def bridge(name: str, count: int, warmup: int) -> dict[str, Any]:
    if name == "remote" and importlib.util.find_spec("can_remote") is None:
        return {"skipped": "python-can-remote is not installed: pip install -e '.[remote]'"}
    result: dict[str, Any] = {"loadavg_before": list(os.getloadavg())}
    with rig(name) as made:
        start_uncontrolled(made.card, parse_network(made.toml.read_text()))
        result["pdo_loop"] = pdo_loop(made, count, warmup)
        result["sdo"] = sdo(made)
        result["frames"] = frames(made)
        progress(f"{name}: the nodes' process killed and started again")
        result["nodes_lost"] = _lost_and_back(made, "sim")
        if made.server is not None:
            progress(f"{name}: the server killed and started again")
            result["link_lost"] = _lost_and_back(made, "server")
        result["firmware_log"] = made.card.log()
    result["loadavg_after"] = list(os.getloadavg())
    return result


def run(count: int | None, warmup: int | None) -> dict[str, Any]:
    count = count or DEFAULTS[0]
    warmup = DEFAULTS[1] if warmup is None else warmup
    return {
        "name": NAME,
        "description": "the card on a bridged bus beside shm, same run: PDO loop latency, "
                       "SDO rate, a frame burst through the transport alone (loss, order), "
                       "and what the host reads when the nodes or the link go and come back",
        "machine": machine_info(),
        "source": source_fingerprint(),
        "bridges": {name: bridge(name, count, warmup) for name in BRIDGES},
    }


def main(argv: list[str] | None = None) -> int:
    return sized_main("python -m bench.remote", __doc__, run, DEFAULTS, argv)


if __name__ == "__main__":
    raise SystemExit(main())
