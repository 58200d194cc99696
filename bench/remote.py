"""``python -m bench remote``: the card across CAN bridges beside shm and vcan, in one run.

Each bridge gets a rig of its own: ``cifemu sim`` with one generic node on the nodes'
side, the card on the other side of the bridge:

- ``shm`` (reference): card and node on one fresh ``shm`` channel, no bridge;
- ``remote``: python-can-remote's websocket server on 127.0.0.1 serving that channel,
  the card its client;
- ``vcan`` (reference): card and node on vcan0, no bridge;
- ``socketcand``: the daemon serving vcan0 on 127.0.0.1, the node on vcan0, the card
  python-can's ``socketcand`` client (host and port as bus options);
- ``cannelloni``: two instances tunnelling vcan0 <-> vcan1 over UDP on 127.0.0.1, the
  card on vcan0, the node on vcan1.

Per rig, in one run so the figures share the machine's load (reported beside them):

- ``pdo_loop``: DevExchangeIO output -> RPDO -> node -> TPDO -> input, timed by
  ``bench.common.measure`` (uncontrolled handshake, as ``bench.can``'s phase 1);
- ``sdo``: SDO uploads of 1000h through the mailbox, for ``SDO_SECONDS``;
- ``frames``: the transport alone, no card: a burst of ``BURST`` numbered frames
  from a client on the card's side to a reader on the nodes' side; lost, reordered,
  frames/s (a bridge that drops frames says how many);
- ``nodes_lost``: the nodes' process killed, started again once the card noticed;
- ``link_lost`` (bridges only): the bridge killed (remote: its server; socketcand: the
  child that serves the card's connection, the daemon listens on; cannelloni: the card's
  end of the tunnel), started again once the card noticed.
  Both report what the host read in Task2State meanwhile (Err_Event, Bus_Off_Cnt,
  Msg_Time_Out), how long the card took to notice (a bus-off, or the node out of data
  exchange) and to recover (the node in data exchange and a PDO loop answering).

The SocketCAN rigs need vcan0 (and vcan1 for cannelloni): run inside ``tools/vcan-vm
--vcan 2``. socketcand and cannelloni are found as the vcan tests find them
(built outside this repository, docs/remote-bus.md); python-can-remote comes
with ``pip install -e '.[remote]'``.
A rig that cannot run says why instead of its figures.
"""

from __future__ import annotations

import contextlib
import importlib.util
import itertools
import os
import queue
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
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
from bench.can.pdo_loop import image_round_trip
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
)
from bench.vcan import HOST_LOADAVG
from dbm_tools.network import parse_network
from dpm.commands import COM_SDO_UP_DOWNLOAD
from dpm.message import Message, Task
from dpm.task2 import ComDiagnostics
from firmware.shm.station import channel_path
from host_api.board import Board, CifError
from host_api.driver import DevExchangeIO, DevGetTaskState
from host_api.ready import wait_ready

NAME = "remote"
DEFAULTS = (200, 20)
"""``--count`` and ``--warmup`` of the PDO loop."""
BRIDGES = ("shm", "remote", "vcan", "socketcand", "cannelloni")
NEAR, FAR = "vcan0", "vcan1"
"""The card's SocketCAN channel, and the far end of cannelloni's tunnel."""
BRIDGES_DIR = Path(os.environ.get("CIFEMU_BRIDGES",
                                  Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
                                  / "cifemu" / "bridges")) / "bin"
"""Where socketcand and cannelloni built outside this repository are looked for first
(``CIFEMU_BRIDGES``), before PATH."""
BUILD_HINT = ("build them as their own READMEs say and put them on PATH or in "
              "$CIFEMU_BRIDGES/bin (docs/remote-bus.md)")
SDO_SECONDS = 3.0
BURST = 2000
"""Frames in the transport burst: more than a websocket's and a socket's buffers hold."""
QUIET_S = 2.0
"""The burst is over when the reader saw none of its frames for this long."""
NOTICE_TIMEOUT_S = 15.0
RECOVER_TIMEOUT_S = 30.0
ECHO_WAIT_S = 0.3
"""How long one recovery probe waits for the node to echo its value."""
LISTENING = re.compile(rb"Connect using channel '(ws://[^']+)'")
SERVER_START_S = 20.0
BURST_ID = 0x7E0
"""Identifier of the burst frames: no CANopen service of the node or the card uses it."""
CANNELLONI_TIMEOUT_US = 1000
"""cannelloni's buffering before a UDP packet leaves (its default, 100 ms, is every
frame's delay)."""


def bridge_program(name: str) -> str | None:
    """socketcand or cannelloni: in ``BRIDGES_DIR``, else on PATH."""
    found = BRIDGES_DIR / name
    return str(found) if found.is_file() else shutil.which(name)


def socketcan_missing(*channels: str) -> str | None:
    """Why the SocketCAN rigs cannot run here, or None."""
    if not hasattr(socket, "AF_CAN"):
        return "no AF_CAN in this Python (Linux only)"
    for channel in channels:
        try:
            with socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW) as probe:
                probe.bind((channel,))
        except OSError as exc:
            return (f"no SocketCAN channel {channel} ({exc.strerror}): run inside "
                    "tools/vcan-vm --vcan 2")
    return None


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port free now on 127.0.0.1, for the daemons, which take no port 0."""
    with socket.socket(socket.AF_INET, kind) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def children_of(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (socketcand forks one per client)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue  # ended meanwhile
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def _spawn(command: list[str], session: bool = False) -> subprocess.Popen[bytes]:
    return subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=session)


# --- the bridges' own processes ------------------------------------------------------------


class Link:
    """A bridge's processes: what ``link_lost`` kills and starts again."""

    def kill(self) -> None:
        raise NotImplementedError

    def restart(self) -> None:
        """Start what ``kill`` ended; back when it serves again."""
        raise NotImplementedError

    def stop(self) -> None:
        raise NotImplementedError


@dataclass
class RemoteServer(Link):
    """python-can-remote's server serving one shm channel on 127.0.0.1."""

    channel: str
    proc: subprocess.Popen[bytes] | None = None
    url: str = ""
    port: int = 0

    def start(self) -> None:
        """``python -m can_remote`` on ``port`` (0: the kernel picks; the URL is read from
        its log, so no port is guessed)."""
        proc = subprocess.Popen(
            [sys.executable, "-m", "can_remote", "-i", "shm", "-c", self.channel, "-H",
             "127.0.0.1", "-p", str(self.port)], stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
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
                    self.proc = proc
                    self.url = found.group(1).decode().replace("localhost", "127.0.0.1")
                    self.port = int(self.url.rstrip("/").rsplit(":", 1)[1])
                    return
        stop_process(proc)
        raise RuntimeError("python -m can_remote did not say where it listens")

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def restart(self) -> None:
        self.start()  # on the same port, which the card dials again

    def stop(self) -> None:
        """SIGINT, the server's only clean end (KeyboardInterrupt): after SIGTERM its side
        of the shm channel would stay in /dev/shm. SIGTERM and SIGKILL follow if it does
        not end."""
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(STOP_TIMEOUT)
        stop_process(self.proc)


@dataclass
class Socketcand(Link):
    """The daemon serving vcan0 on 127.0.0.1 (no discovery beacon)."""

    program: str
    port: int = field(default_factory=free_port)
    proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.proc = _spawn([self.program, "-i", NEAR, "-l", "lo", "-p", str(self.port), "-n"],
                           session=True)
        deadline = time.monotonic() + SERVER_START_S
        while time.monotonic() < deadline and self.proc.poll() is None:
            with socket.socket() as probe:
                if probe.connect_ex(("127.0.0.1", self.port)) == 0:
                    return
            time.sleep(0.05)
        raise RuntimeError(f"socketcand did not listen on {self.port}")

    def kill(self) -> None:
        """The children that serve connections: the card's ends, the daemon listens on. A
        whole daemon restarted could not listen again on its port for a minute: it sets no
        SO_REUSEADDR, and the killed connection's end stays in TIME_WAIT."""
        assert self.proc is not None
        for child in children_of(self.proc.pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(child, signal.SIGKILL)

    def restart(self) -> None:
        """Nothing: the daemon still listens, the card connects again by itself."""

    def stop(self) -> None:
        if self.proc is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGTERM)
            stop_process(self.proc)


@dataclass
class Cannelloni(Link):
    """Two instances tunnelling vcan0 <-> vcan1 over UDP on 127.0.0.1."""

    program: str
    near_port: int = field(default_factory=lambda: free_port(socket.SOCK_DGRAM))
    far_port: int = field(default_factory=lambda: free_port(socket.SOCK_DGRAM))
    near: subprocess.Popen[bytes] | None = None
    far: subprocess.Popen[bytes] | None = None

    def _end(self, vcan: str, local: int, remote: int) -> subprocess.Popen[bytes]:
        return _spawn([self.program, "-I", vcan, "-R", "127.0.0.1", "-r", str(remote),
                       "-L", "127.0.0.1", "-l", str(local), "-t", str(CANNELLONI_TIMEOUT_US)])

    def start(self) -> None:
        self.far = self._end(FAR, self.far_port, self.near_port)
        self.restart()

    def kill(self) -> None:
        """The card's end of the tunnel."""
        assert self.near is not None
        self.near.send_signal(signal.SIGKILL)
        self.near.wait()

    def restart(self) -> None:
        self.near = self._end(NEAR, self.near_port, self.far_port)

    def stop(self) -> None:
        for end in (self.near, self.far):
            if end is not None:
                stop_process(end)


# --- the rigs ---------------------------------------------------------------------------


@dataclass
class Side:
    """A python-can bus: the nodes' or the card's side of a bridge."""

    interface: str
    channel: str
    options: dict[str, Any] = field(default_factory=dict)

    def open(self) -> can.BusABC:
        return can.Bus(interface=self.interface, channel=self.channel, **self.options)

    def flags(self) -> list[str]:
        """``cifemu firmware``/``sim`` flags that open this bus."""
        return ["--interface", self.interface, "--channel", self.channel, *itertools.chain(
            *(["--bus-option", f"{key}={value}"] for key, value in self.options.items()))]


@dataclass
class Rig:
    bridge: str
    card: SimCard
    toml: Path
    nodes: Side
    card_side: Side
    link: Link | None


def unavailable(bridge: str) -> str | None:
    """Why ``bridge``'s rig cannot run here, or None."""
    if bridge == "remote" and importlib.util.find_spec("can_remote") is None:
        return "python-can-remote is not installed: pip install -e '.[remote]'"
    if bridge in ("vcan", "socketcand"):
        return socketcan_missing(NEAR)
    if bridge == "cannelloni":
        return socketcan_missing(NEAR, FAR)
    return None


def _bridge_sides(bridge: str, channel: str) -> tuple[Side, Side, Link | None]:
    """The nodes' side, the card's side and the started bridge between them."""
    if bridge == "shm":
        return Side("shm", channel), Side("shm", channel), None
    if bridge == "vcan":
        return Side("socketcan", NEAR), Side("socketcan", NEAR), None
    if bridge == "remote":
        server = RemoteServer(channel)
        server.start()
        return Side("shm", channel), Side("remote", server.url), server
    program = bridge_program(bridge)
    if program is None:
        raise FileNotFoundError(f"{bridge} not found in {BRIDGES_DIR} or on PATH: build it "
                                f"with {BUILD_HINT}")
    if bridge == "socketcand":
        daemon = Socketcand(program)
        daemon.start()
        return (Side("socketcan", NEAR),
                Side("socketcand", NEAR, {"host": "127.0.0.1", "port": daemon.port}), daemon)
    tunnel = Cannelloni(program)
    tunnel.start()
    return Side("socketcan", FAR), Side("socketcan", NEAR), tunnel


def start_sim(toml: Path, side: Side) -> subprocess.Popen[bytes]:
    sim = subprocess.Popen([sys.executable, "-m", "cifemu", "sim", str(toml), *side.flags(),
                            "--log-level", "WARNING"],
                           stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)
    assert sim.stdout is not None
    if not sim.stdout.readline().startswith(b"simulating"):
        stop_process(sim)
        raise RuntimeError("cifemu sim did not start")
    threading.Thread(target=sim.stdout.read, daemon=True).start()  # the pipe must not fill
    return sim


@contextmanager
def rig(bridge: str) -> Iterator[Rig]:
    """The node in ``cifemu sim`` on its side, the card on the other side of ``bridge``."""
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-remote-", dir=scratch_root()) as tmp:
        directory = Path(tmp)
        toml = directory / "network.toml"
        toml.write_text(network_toml([1]))
        channel = f"bench-remote-{uuid.uuid4().hex[:12]}"
        link: Link | None = None
        card: SimCard | None = None
        try:
            nodes, card_side, link = _bridge_sides(bridge, channel)
            sim = start_sim(toml, nodes)
            stderr_path = directory / "firmware.stderr"
            with stderr_path.open("wb") as stderr:
                proc = subprocess.Popen(
                    [sys.executable, "-m", "cifemu", "firmware", "--board", str(BOARD),
                     "--dpm-dir", tmp, "--log-level", "WARNING", *card_side.flags(),
                     "--flash", str(directory / "flash")],
                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=stderr)
            card = SimCard(directory, proc, None, stderr_path, sim=sim)
            wait_ready(proc, directory, BOARD, STARTUP_TIMEOUT)
            card.board = Board(BOARD, directory, timeout=5000).open()
            yield Rig(bridge, card, toml, nodes, card_side, link)
        finally:
            if card is not None:
                card.stop()
            if link is not None:
                link.stop()
            # Hygiene: python-can-remote's threads may end before its side of the channel.
            channel_path(channel).unlink(missing_ok=True)


def diagnostics(board: int) -> ComDiagnostics:
    rc, raw = DevGetTaskState(board, 2, 64)
    if rc != 0:
        raise RuntimeError(f"DevGetTaskState returned {rc}")
    return ComDiagnostics.decode(raw)


# --- the measurements --------------------------------------------------------------------


def pdo_loop(rig: Rig, count: int, warmup: int) -> dict[str, Any]:
    network = parse_network(rig.toml.read_text())
    board = board_of(rig.card)
    out_offset, in_offset = io_offsets(network)
    round_trip = image_round_trip(board.number, out_offset, in_offset)

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
    progress(f"{rig.bridge}: a burst of {BURST} frames through the transport")
    reader = rig.nodes.open()
    sender = rig.card_side.open()
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


@dataclass
class Watch:
    """What the host reads in Task2State from a kill on: the first bus-off, the node's
    leaving data exchange, the first error the card reports."""

    board: int
    before: ComDiagnostics
    start: float = field(default_factory=time.perf_counter)
    bus_off_s: float | None = None
    nodes_out_s: float | None = None
    err: tuple[int, int] | None = None
    """(Err_Event, node) of the first error shown."""

    def sample(self) -> ComDiagnostics:
        diag = diagnostics(self.board)
        now = round(time.perf_counter() - self.start, 3)
        if self.bus_off_s is None and diag.usBus_Off_Cnt != self.before.usBus_Off_Cnt:
            self.bus_off_s = now
        if self.nodes_out_s is None and diag.operating() != [1]:
            self.nodes_out_s = now
        if self.err is None and diag.bErr_event:
            self.err = (diag.bErr_event, diag.bErr_rem_adr)
        return diag

    def noticed(self) -> bool:
        """Sample; True once the card showed the loss (a bus-off, or the node out)."""
        self.sample()
        return self.bus_off_s is not None or self.nodes_out_s is not None


def _until(condition: Callable[[], bool], timeout: float) -> float | None:
    deadline = time.perf_counter() + timeout
    while time.perf_counter() < deadline:
        if condition():
            return time.perf_counter()
        time.sleep(0.01)
    return None


def _settled(diag: ComDiagnostics) -> bool:
    """The node in data exchange and no error shown."""
    return diag.operating() == [1] and diag.bErr_event == 0


def _lost_and_back(rig: Rig, kill: str) -> dict[str, Any]:
    """Once the node is in data exchange with no error shown, kill the nodes' process
    (``sim``) or the bridge (``link``); once the card noticed, start it again and time the
    recovery: the node in data exchange and echoing a value the host had not written
    before."""
    board = board_of(rig.card).number
    out_offset, in_offset = io_offsets(parse_network(rig.toml.read_text()))
    # From a settled card: the burst before may have cost a slow machine a heartbeat.
    settled = _until(lambda: _settled(diagnostics(board)), RECOVER_TIMEOUT_S)
    watch = Watch(board, diagnostics(board))
    if kill == "sim":
        assert rig.card.sim is not None
        rig.card.sim.send_signal(signal.SIGKILL)
        rig.card.sim.wait()
    else:
        assert rig.link is not None
        rig.link.kill()
    noticed = _until(watch.noticed, NOTICE_TIMEOUT_S)
    if kill == "sim":
        rig.card.sim = start_sim(rig.toml, rig.nodes)
    else:
        assert rig.link is not None
        rig.link.restart()
    back_start = time.perf_counter()
    written = [DevExchangeIO(board, 0, b"", in_offset, 8, TIMEOUT_MS)[1][0]]

    def back() -> bool:
        """One probe: an output the node has not echoed yet (a new one each time, since the
        card sends an event-driven PDO only when its outputs change)."""
        written[0] = written[0] % 255 + 1
        value = bytes([written[0]]) * 8
        DevExchangeIO(board, out_offset, value, 0, 0, TIMEOUT_MS)

        def echoed() -> bool:
            operating = watch.sample().operating() == [1]  # every time: errors between show
            return operating and DevExchangeIO(board, 0, b"", in_offset, 8,
                                               TIMEOUT_MS)[1] == value

        return _until(echoed, ECHO_WAIT_S) is not None

    recovered = _until(back, RECOVER_TIMEOUT_S)
    after = diagnostics(board)
    return {
        "settled_before": settled is not None,
        "noticed_s": None if noticed is None else round(noticed - watch.start, 3),
        "bus_off_after_s": watch.bus_off_s,
        "nodes_out_after_s": watch.nodes_out_s,
        "err_event": None if watch.err is None else watch.err[0],
        "err_node": None if watch.err is None else watch.err[1],
        "bus_off_cnt": after.usBus_Off_Cnt - watch.before.usBus_Off_Cnt,
        "bus_error_cnt": after.usBus_Error_Cnt - watch.before.usBus_Error_Cnt,
        "msg_time_out": after.usMsg_Time_Out - watch.before.usMsg_Time_Out,
        "recovered_s": None if recovered is None else round(recovered - back_start, 3),
        "err_event_after": after.bErr_event,
        "notice_timeout_s": NOTICE_TIMEOUT_S,
        "recover_timeout_s": RECOVER_TIMEOUT_S,
    }


def bridge(name: str, count: int, warmup: int) -> dict[str, Any]:
    reason = unavailable(name)
    if reason is not None:
        return {"skipped": reason}
    result: dict[str, Any] = {"loadavg_before": list(os.getloadavg())}
    try:
        with rig(name) as made:
            start_uncontrolled(made.card, parse_network(made.toml.read_text()))
            result["pdo_loop"] = pdo_loop(made, count, warmup)
            result["sdo"] = sdo(made)
            result["frames"] = frames(made)
            progress(f"{name}: the nodes' process killed and started again")
            result["nodes_lost"] = _lost_and_back(made, "sim")
            if made.link is not None:
                progress(f"{name}: the link killed and started again")
                result["link_lost"] = _lost_and_back(made, "link")
            result["firmware_log"] = made.card.log()
    except FileNotFoundError as exc:  # a daemon not built here
        return {"skipped": str(exc)}
    result["loadavg_after"] = list(os.getloadavg())
    return result


def run(count: int | None, warmup: int | None) -> dict[str, Any]:
    count = count or DEFAULTS[0]
    warmup = DEFAULTS[1] if warmup is None else warmup
    return {
        "name": NAME,
        "description": "the card across CAN bridges beside shm and vcan, same run: PDO loop "
                       "latency, SDO rate, a frame burst through the transport alone (loss, "
                       "order), and what the host reads when the nodes or the link go and "
                       "come back",
        "machine": machine_info(),
        "host_loadavg_at_start": os.environ.get(HOST_LOADAVG),
        "source": source_fingerprint(),
        "bridges": {name: bridge(name, count, warmup) for name in BRIDGES},
    }


def main(argv: list[str] | None = None) -> int:
    return sized_main("python -m bench.remote", __doc__, run, DEFAULTS, argv)


if __name__ == "__main__":
    raise SystemExit(main())
