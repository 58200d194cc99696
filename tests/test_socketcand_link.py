"""A socketcand link lost while the card sends nothing: the host sees a bus-off within a
bound, and the card connects again once the server is back.

python-can's socketcand client returns no frame, and raises nothing, from a connection its
server closed; only its next ``send`` fails. An unconfigured card, or one whose nodes are
supervised by heartbeat consumers alone, sends nothing for as long as it likes, so the card
looks at the connection itself (``CanBus.check_link``).

The real daemon needs SocketCAN, which this machine's kernel may lack: with it, the same
loss is tested in tests/test_bridges_vcan.py inside tools/vcan-vm. Here a stand-in on
127.0.0.1 plays what the card's client sees of a socketcand: the greeting of its protocol
(``< hi >``, then ``< ok >`` to ``< open can0 >`` and to ``< rawmode >``), then it closes
the connection, as a daemon does that is stopped or dies. The stand-in is the only part
that is not real, and only because the daemon cannot run on every machine the suite does.
"""

from __future__ import annotations

import queue
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from dbm_tools.network import load_network
from dpm.task2 import ComDiagnostics, GlobalBits
from firmware.can.bus import (
    KEEPALIVE_IDLE_S,
    KEEPALIVE_INTERVAL_S,
    KEEPALIVE_PROBES,
    LINK_DEAD_S,
    CanBus,
    stream_of,
)
from host_api.board import Board
from host_api.online import configure_online
from tests.conftest import TIME_SCALE, start_card, taken, wait_until

CHANNEL = "can0"
NOTICED_S = 2.0
"""The bound on noticing a lost link: the card looks every 0.1 s; the rest is margin for a
loaded machine. Without the look it is never noticed: the unconfigured card sends nothing."""


FALSE_BUS_OFF_WINDOW_S = 1.0
"""How long a new Baud_rate's reconnection is watched for a bus-off that should not come:
ten of the card's looks at the connection."""


class SocketcandStandIn:
    """socketcand's greeting on 127.0.0.1, for each connection, and nothing more."""

    def __init__(self) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port: int = self.listener.getsockname()[1]
        self.opened: queue.Queue[socket.socket] = queue.Queue()
        """Connections that finished the greeting: the card's controller is on the bus."""
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while True:
            try:
                connection, _ = self.listener.accept()
            except OSError:  # the listener closed: the test is over
                return
            connection.settimeout(10 * TIME_SCALE)
            try:
                connection.sendall(b"< hi >")
                for expected in (f"< open {CHANNEL} >".encode(), b"< rawmode >"):
                    if connection.recv(256) != expected:
                        connection.close()
                        break
                    connection.sendall(b"< ok >")
                else:
                    connection.settimeout(None)
                    self.opened.put(connection)
            except OSError:
                connection.close()

    def next_connection(self) -> socket.socket:
        try:
            return taken(self.opened, 20)
        except queue.Empty:
            pytest.fail("the card's controller did not connect to the stand-in")

    def close(self) -> None:
        self.listener.close()
        while not self.opened.empty():
            self.opened.get().close()


def _bus_off_shown(diag: ComDiagnostics, before: ComDiagnostics) -> bool:
    """One more bus-off, and EVE (the card writes the counter, then the bit)."""
    return (diag.usBus_Off_Cnt == before.usBus_Off_Cnt + 1
            and bool(diag.bGlobalBits & GlobalBits.EVE))


@pytest.fixture
def server() -> Iterator[SocketcandStandIn]:
    made = SocketcandStandIn()
    try:
        yield made
    finally:
        made.close()


def test_a_link_closed_while_the_card_sends_nothing_is_a_bus_off_and_reconnects(
        server: SocketcandStandIn, tmp_path: Path) -> None:
    card = start_card(tmp_path, 0, "--interface", "socketcand", "--channel", CHANNEL,
                      "--bus-option", "host=127.0.0.1", "--bus-option", f"port={server.port}")
    try:
        first = server.next_connection()
        with Board(0, tmp_path, timeout=5000) as board:
            before = board.diagnostics()
            assert not before.bGlobalBits & GlobalBits.EVE
            first.close()  # the daemon gone: its end of the connection closes
            wait_until(lambda: _bus_off_shown(board.diagnostics(), before), NOTICED_S,
                       "the lost link counted as a bus-off, EVE set")
            assert board.diagnostics().usBus_Error_Cnt == before.usBus_Error_Cnt
            # The card opens the interface again every second: the next greeting is its.
            server.next_connection()
            assert board.diagnostics().usBus_Off_Cnt == before.usBus_Off_Cnt + 1
    finally:
        card.stop()


def test_a_new_baud_rate_opens_the_link_again_without_a_bus_off(
        server: SocketcandStandIn, tmp_path: Path) -> None:
    """The bus parameters' Baud_rate closes the connection and opens a new one (python-can's
    socketcand client has no set_bitrate): a closing of the card's own, not a lost link."""
    card = start_card(tmp_path, 0, "--interface", "socketcand", "--channel", CHANNEL,
                      "--bus-option", "host=127.0.0.1", "--bus-option", f"port={server.port}")
    try:
        server.next_connection()
        network = tmp_path / "network.toml"
        network.write_text("[bus]\nbitrate = 250000\n")
        with Board(0, tmp_path, timeout=5000) as board:
            before = board.diagnostics()
            configure_online(board, load_network(network))
            server.next_connection()  # the controller at its new Baud_rate
            time.sleep(FALSE_BUS_OFF_WINDOW_S)  # no event to wait for: the absence of one
            assert board.diagnostics().usBus_Off_Cnt == before.usBus_Off_Cnt
    finally:
        card.stop()


def test_no_remote_frame_goes_to_socketcand(server: SocketcandStandIn) -> None:
    """socketcand's protocol has no remote frames: python-can's client would write the
    guarding request as ``< send 701 1  >``, which the daemon drops as a syntax error. The
    controller sends none and counts it as not sent (Msg_Time_Out); a data frame after it
    is the only line the daemon gets. In process: what is checked is which lines reach the
    daemon, and the controller's own answer."""
    bus = CanBus("socketcand", CHANNEL, options={"host": "127.0.0.1", "port": server.port})
    timeouts: list[None] = []
    bus.on_send_timeout = lambda: timeouts.append(None)
    try:
        connection = server.next_connection()
        assert not bus.send(0x701, remote=True, dlc=1)
        assert timeouts == [None]
        assert bus.send(0x123, b"\x01")
        connection.settimeout(10 * TIME_SCALE)
        received = b""
        while not received.endswith(b">"):
            received += connection.recv(256)
        assert received == b"< send 123 1 1 >"
    finally:
        bus.shutdown()


def _probed(stream: socket.socket) -> tuple[int, int, int, int, int]:
    """The connection's keep-alive and user time-out, as the system reports them."""
    return (stream.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE),
            stream.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE),
            stream.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL),
            stream.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT),
            stream.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT))


def test_the_connection_is_probed_by_tcp_keep_alive_also_when_reopened(
        server: SocketcandStandIn) -> None:
    """A cable pulled between the card and socketcand closes nothing: without keep-alive
    the card would see only lost heartbeats until TCP gives up. The controller sets short
    probes and a user time-out on its connection (``keep_alive``), and again on the one it
    opens after a lost link. Checked on the real connection (getsockopt), not by pulling a
    cable: on loopback the kernel answers every probe for the peer, and silencing it (a
    packet filter, netem, a network namespace) needs what this machine's kernel or the suite
    lacks. In process, to reach the socket."""
    expected = (1, KEEPALIVE_IDLE_S, KEEPALIVE_INTERVAL_S, KEEPALIVE_PROBES, LINK_DEAD_S * 1000)
    bus = CanBus("socketcand", CHANNEL, options={"host": "127.0.0.1", "port": server.port})
    try:
        first = server.next_connection()
        stream = stream_of(bus.bus)
        assert stream is not None
        assert _probed(stream) == expected

        def reopened() -> bool:
            bus.check_link()  # the card's master looks every 0.1 s; here the test does
            found = stream_of(bus.bus)
            return found is not None and found is not stream

        first.close()  # the link lost: the controller opens a new connection
        wait_until(reopened, 10, "the connection opened again")
        server.next_connection()
        again = stream_of(bus.bus)
        assert again is not None and _probed(again) == expected
    finally:
        bus.shutdown()
