"""The card on a CAN bus across a network: python-can-remote's websocket bridge, loopback only.

Three real processes, as on a bench whose CAN network is on another machine: the
card (``--interface remote``, the server's URL as its channel), python-can-remote's
server (``python -m can_remote``) on an ``shm`` channel, and ``cifemu sim`` on that
same channel, the server's side. The host sees the nodes only through the image:
their boot-up in Nd_state, an SDO through the mailbox, a PDO loop through
DevExchangeIO, and a lost heartbeat as Err_Event 30 in Task2State.
"""

from __future__ import annotations

import importlib.util
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import pytest

from dbm_tools.network import GENERIC_DEVICE_TYPE, load_network
from dpm.commands import COM_SDO_UP_DOWNLOAD
from dpm.message import Message, Task
from dpm.task2 import CanState, GlobalBits
from firmware.can.bus import (
    KEEPALIVE_IDLE_S,
    KEEPALIVE_INTERVAL_S,
    KEEPALIVE_PROBES,
    LINK_DEAD_S,
    CanBus,
    stream_of,
)
from firmware.shm.station import channel_path
from host_api.board import Board
from host_api.online import configure_online
from tests import commands
from tests.conftest import Card, start_card, wait_until

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("can_remote") is None,
    reason="python-can-remote is not installed: pip install -e '.[remote]' (or '.[dev]')")

NODES = [1, 2]
NETWORK = "".join(f"[[node]]\nid = {n}\nheartbeat_ms = 600\n" for n in NODES)
"""Heartbeat consumers of 600 ms: lost quickly after a kill, not by a busy machine."""
UNSUPERVISED = '[[node]]\nid = 1\nerror_control = "none"\n'
"""A node without error control: nothing tells the card it was away, so nothing boots it
again and no boot-up sends its outputs; only the card's own resend can."""
RESENT_S = 5.0
"""The bound on the outputs' resend once the server listens again: the card tries to open
the link every second (``REOPEN_S``), then sends at its next tick; the rest is margin for a
loaded machine."""
SERVER_START_S = 20.0
"""How long the server may take to listen, and then to answer its first bus request, in the
time the test's processes could run (``wait_until``)."""
LISTENING = re.compile(rb"Connect using channel '(ws://[^']+)'")


@dataclass
class Remote:
    """python-can-remote's server on an shm channel: its process and the URL it serves."""

    proc: subprocess.Popen[bytes]
    url: str

    @property
    def port(self) -> int:
        return int(self.url.rstrip("/").rsplit(":", 1)[1])

    def answers_bus_requests(self) -> bool:
        """Whether the server opens its side of the bus for a client: a client of the
        test's own asks, as the card will.

        The server loads its interface (the project's shm bus, numpy with it: 0.31-0.41 s
        of CPU here) only when its first client asks for a bus, and python-can-remote's
        client waits 5 s of wall time for that answer (``RemoteClientProtocol``), then
        raises "No response from server". The card was that first client: at load 9 its
        open took 3.0-3.8 s of wall time (0.33-0.49 s idle), at load 18 it ran out and the
        card came up with FAT, answering the configuration with msg.f 200. A server that
        has answered once answers the card in milliseconds."""
        try:
            bus = can.Bus(interface="remote", channel=self.url)
        except (can.CanError, OSError):  # no answer in the client's 5 s: ask again
            return False
        bus.shutdown()
        return True

    def stop(self) -> None:
        """SIGINT: the server's only clean end (KeyboardInterrupt); SIGTERM would leave its
        side of the shm channel behind in /dev/shm."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        commands.wait(self.proc, 10)


def start_remote_server(channel: str, port: int = 0) -> Remote:
    """``python -m can_remote`` on 127.0.0.1 and ``port``, by default one the kernel picks
    (``-p 0``): the URL is read from its log, so no port is guessed and none is raced for.
    Returned once it answers a bus request (``Remote.answers_bus_requests``), not when it
    listens: a card that connects then gets its answer in time."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "can_remote", "-i", "shm", "-c", channel, "-H", "127.0.0.1",
         "-p", str(port)], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE)
    stderr = proc.stderr
    assert stderr is not None
    urls: list[str] = []

    def pump() -> None:  # also keeps the pipe from filling
        for line in stderr:
            found = LISTENING.search(line)
            if found and not urls:
                urls.append(found.group(1).decode().replace("localhost", "127.0.0.1"))

    threading.Thread(target=pump, daemon=True).start()
    try:
        wait_until(lambda: urls or proc.poll() is not None, SERVER_START_S,
                   "python -m can_remote to say where it listens")
        if not urls:
            pytest.fail(f"python -m can_remote ended with {proc.returncode} before it "
                        "said where it listens")
        remote = Remote(proc, urls[0])
        wait_until(remote.answers_bus_requests, SERVER_START_S,
                   f"python -m can_remote at {remote.url} to answer a bus request")
    except BaseException:
        proc.kill()
        commands.wait(proc, 10)
        raise
    return remote


def start_sim(network: Path, channel: str) -> subprocess.Popen[bytes]:
    """``cifemu sim`` on the server's side, returned once its nodes are on the bus."""
    sim = subprocess.Popen([sys.executable, "-m", "cifemu", "sim", str(network), "--interface",
                            "shm", "--channel", channel, "--log-level", "WARNING"],
                           stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)
    assert sim.stdout is not None
    first = sim.stdout.readline()
    if not first.startswith(b"simulating"):
        sim.kill()
        commands.wait(sim, 10)
        pytest.fail(f"cifemu sim did not start: {first!r}")
    threading.Thread(target=sim.stdout.read, daemon=True).start()  # the pipe must not fill
    return sim


@dataclass
class Bench:
    card: Card
    server: Remote
    sim: subprocess.Popen[bytes] | None
    board: Board
    network: Path
    channel: str

    def sdo_read(self, node: int, index: int, sub: int) -> int:
        head = struct.pack("<BBHBBBB", node, 0, index, sub, 0, 0, 1)
        answer = self.board.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_SDO_UP_DOWNLOAD,
                                             data=head))
        assert answer.f == 0, f"SDO read of node {node}: msg.f {answer.f}"
        return int.from_bytes(answer.data[8:], "little")

    def kill_sim(self) -> None:
        assert self.sim is not None
        self.sim.send_signal(signal.SIGKILL)
        commands.wait(self.sim, 10)
        self.sim = None


@pytest.fixture
def bench(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Bench]:
    """The three processes on ``NETWORK``, or on the description a test gives as the
    fixture's parameter (``indirect``). A card that came up with FAT (it could not open its
    link) fails here, saying so with the card's log, not later as a msg.f 200."""
    network = tmp_path / "network.toml"
    network.write_text(getattr(request, "param", NETWORK))
    channel = f"remote-{uuid.uuid4().hex}"
    server = start_remote_server(channel)
    made: Bench | None = None
    try:
        sim = start_sim(network, channel)
        try:
            card = start_card(tmp_path, 0, "--interface", "remote", "--channel", server.url)
        except BaseException:
            _stop(sim)
            raise
        try:
            board = Board(0, tmp_path, timeout=5000).open()
            fatal = board.diagnostics().bGlobalBits & GlobalBits.FAT
            if fatal:
                board.close()
        except BaseException:
            card.stop()
            _stop(sim)
            raise
        if fatal:
            card.stop()
            _stop(sim)
            pytest.fail(_fat(card, server.url))
        made = Bench(card, server, sim, board, network, channel)
        yield made
    finally:
        if made is not None:
            made.board.close()
            made.card.stop()
            if made.sim is not None:
                _stop(made.sim)
        (made.server if made is not None else server).stop()
        # Hygiene for /dev/shm only: the server's threads may end before its buses close.
        channel_path(channel).unlink(missing_ok=True)


def _fat(card: Card, url: str) -> str:
    """Why a stopped card came up with FAT, from its log: it could not open its link, and
    every CAN-task command would be answered msg.f 200 (``CanTask.fatal``)."""
    log = card.log()
    return (f"the card came up with FAT: it could not open its python-can-remote link to "
            f"{url}, so the CAN task would answer every command with msg.f 200; its log: "
            f"{log.strip()}")


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
    commands.wait(proc, 10)


def test_card_boots_the_nodes_across_the_bridge_and_serves_sdo_and_pdo(bench: Bench) -> None:
    """Boot-up (Nd_state), an SDO upload through the mailbox and a PDO loop
    (DevExchangeIO output -> node 1 -> its TPDO -> input), all over the websocket."""
    configure_online(bench.board, load_network(bench.network))
    wait_until(lambda: bench.board.diagnostics().operating() == NODES, 15,
               "the nodes in data exchange through python-can-remote")
    diag = bench.board.diagnostics()
    assert diag.bCAN_State == CanState.OPERATE and diag.bErr_event == 0
    assert bench.sdo_read(1, 0x1000, 0) == GENERIC_DEVICE_TYPE
    for value in (b"\x5a", b"\xa5"):
        wait_until(lambda v=value: bench.board.exchange_io(v, receive_size=1) == v, 3,  # type: ignore[misc]
                   f"node 1 to echo {value.hex()} through the bridge")


def test_heartbeat_loss_behind_the_bridge_is_err_event_30_and_recovers(bench: Bench) -> None:
    """The nodes' process killed behind the server: the card reports the seed's 30 with
    NEXC; the nodes back, data exchange resumes with no error left."""
    configure_online(bench.board, load_network(bench.network))
    wait_until(lambda: bench.board.diagnostics().operating() == NODES, 15,
               "the nodes in data exchange")
    bench.kill_sim()
    wait_until(lambda: bench.board.diagnostics().operating() == [], 5,
               "every node's heartbeat lost")
    diag = bench.board.diagnostics()
    assert (diag.bErr_rem_adr, diag.bErr_event) == (1, 30)
    assert diag.bGlobalBits & GlobalBits.NEXC
    bench.sim = start_sim(bench.network, bench.channel)
    wait_until(lambda: bench.board.diagnostics().operating() == NODES, 15,
               "the nodes back in data exchange")
    diag = bench.board.diagnostics()
    assert (diag.bErr_event, diag.bErr_rem_adr) == (0, 0)
    assert not diag.bGlobalBits & GlobalBits.NEXC
    wait_until(lambda: bench.board.exchange_io(b"\x33", receive_size=1) == b"\x33", 3,
               "node 1 to echo the outputs again")


def test_a_lost_link_is_a_bus_off_and_the_card_reconnects(bench: Bench) -> None:
    """The server killed: no error frame comes, but the controller's transport fails; the
    card counts a bus-off (Bus_Off_Cnt, EVE [ours]) and the nodes' heartbeats are lost
    (Err_Event 30). The server back on its port: the controller reopens the interface and the
    nodes return to data exchange without a host's reset."""
    configure_online(bench.board, load_network(bench.network))
    wait_until(lambda: bench.board.diagnostics().operating() == NODES, 15,
               "the nodes in data exchange")
    bus_off = bench.board.diagnostics().usBus_Off_Cnt
    port = bench.server.port
    bench.server.proc.send_signal(signal.SIGKILL)
    commands.wait(bench.server.proc, 10)
    wait_until(lambda: bench.board.diagnostics().operating() == [], 5,
               "every node's heartbeat lost with the link")
    diag = bench.board.diagnostics()
    assert diag.bErr_event == 30
    assert diag.usBus_Off_Cnt == bus_off + 1
    assert diag.bGlobalBits & GlobalBits.EVE
    bench.server = start_remote_server(bench.channel, port)
    wait_until(lambda: bench.board.diagnostics().operating() == NODES, 20,
               "the nodes back in data exchange over the reopened link")
    wait_until(lambda: bench.board.exchange_io(b"\x66", receive_size=1) == b"\x66", 3,
               "node 1 to echo the outputs over the reopened link")


@pytest.mark.parametrize("bench", [UNSUPERVISED], indirect=True)
def test_outputs_written_while_the_link_is_down_go_out_when_it_is_back(bench: Bench) -> None:
    """Issue 26: the host writes a new output while the server is away. The PDO cannot go
    (Msg_Time_Out), and event-driven PDOs go on change only, so before the fix the node
    kept its old outputs for good while the host believed its new ones went out. Once the
    link is back the card sends every running node's outputs again: node 1's echo shows the
    new value without the host writing anything more (it only reads its inputs)."""
    configure_online(bench.board, load_network(bench.network))
    wait_until(lambda: bench.board.diagnostics().operating() == [1], 15,
               "node 1 in data exchange")
    wait_until(lambda: bench.board.exchange_io(b"\x11", receive_size=1) == b"\x11", 3,
               "node 1 to echo the first output")
    before = bench.board.diagnostics()
    port = bench.server.port
    bench.server.proc.send_signal(signal.SIGKILL)
    commands.wait(bench.server.proc, 10)
    wait_until(lambda: bench.board.diagnostics().usBus_Off_Cnt == before.usBus_Off_Cnt + 1, 5,
               "the lost link counted as a bus-off")
    assert bench.board.exchange_io(b"\x77", receive_size=1) == b"\x11"
    wait_until(lambda: bench.board.diagnostics().usMsg_Time_Out > before.usMsg_Time_Out, 5,
               "the output PDO not sent while the link is down (Msg_Time_Out)")
    bench.server = start_remote_server(bench.channel, port)
    wait_until(lambda: bench.board.exchange_io(receive_size=1) == b"\x77", RESENT_S,
               "node 1 to echo the output written while the link was down, unwritten since")
    diag = bench.board.diagnostics()
    assert diag.operating() == [1] and diag.bErr_event == 0


def test_the_bridge_connection_is_probed_by_tcp_keep_alive(tmp_path: Path) -> None:
    """The card's controller sets TCP keep-alive and a user time-out on the websocket's
    connection (``keep_alive``), so that a peer gone without a word is a bus-off within
    ``LINK_DEAD_S``. What is checked is the options on the real connection (getsockopt), not
    a pulled cable: on loopback the kernel answers every probe itself for the peer, and
    silencing it (a packet filter, netem, a network namespace) needs what this machine's
    kernel or the suite lacks. In process, to reach the socket."""
    channel = f"remote-{uuid.uuid4().hex}"
    server = start_remote_server(channel)
    try:
        bus = CanBus("remote", server.url)
        try:
            stream = stream_of(bus.bus)
            assert stream is not None, "python-can-remote's connection not found"
            assert stream.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE) == 1
            assert stream.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE) == KEEPALIVE_IDLE_S
            assert (stream.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL)
                    == KEEPALIVE_INTERVAL_S)
            assert stream.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT) == KEEPALIVE_PROBES
            assert (stream.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT)
                    == LINK_DEAD_S * 1000)
            assert LINK_DEAD_S <= 5, "docs/remote-bus.md promises a dead peer within ~5 s"
        finally:
            bus.shutdown()
    finally:
        server.stop()
        channel_path(channel).unlink(missing_ok=True)
