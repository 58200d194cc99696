"""The card through socketcand and cannelloni, on SocketCAN inside tools/vcan-vm.

Both daemons are built from their public sources outside this repository
(built outside this repository, docs/remote-bus.md). Where they are found (in
``$CIFEMU_BRIDGES/bin``, default ``~/.cache/cifemu/bridges/bin``, or on PATH) the tests
are ``vcan`` tests and run in ``make test-vcan``; where they are not, they skip saying how
to build them (and are no ``vcan`` tests, so ``make test-vcan`` does not fail for a daemon
the machine never had).

- socketcand: the daemon serves vcan0 on 127.0.0.1; ``cifemu sim`` sits on vcan0; the
  card is python-can's ``socketcand`` client, its host and port given as ``--bus-option``.
- cannelloni: two instances tunnel vcan0 <-> vcan1 over UDP on 127.0.0.1; the card on
  vcan0, ``cifemu sim`` on vcan1 (``tools/vcan-vm --vcan 2``).
- a socketcand connection lost while the card sends nothing (its nodes supervised by
  heartbeat consumers alone): a bus-off within a bound, and the card connects again.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from bench.remote import BRIDGES_DIR, bridge_program, children_of, free_port
from dbm_tools.network import load_network
from host_api.board import Board
from host_api.online import configure_online
from tests import commands
from tests.buses import HOW_TO_RUN, SOCKETCAN_CHANNEL, socketcan_missing
from tests.conftest import start_card, wait_until

NETWORK = "[[node]]\nid = 1\nheartbeat_ms = 600\n[[node]]\nid = 2\nheartbeat_ms = 600\n"
QUIET_NETWORK = "[[node]]\nid = 1\nheartbeat_ms = 8000\n"
"""A node whose heartbeat the card misses only after 8 s: until then the card, in data
exchange with no output changing, sends nothing that could find a lost link."""
NOTICED_S = 2.5
"""The bound on noticing a lost link while the card sends nothing (it looks every 0.1 s)."""
BUILD = ("build it from github.com/linux-can/socketcand or github.com/mguentner/cannelloni "
         "as its README says, and put it on PATH or in $CIFEMU_BRIDGES/bin "
         "(docs/remote-bus.md)")
SOCKETCAND, CANNELLONI = bridge_program("socketcand"), bridge_program("cannelloni")


def needs(path: str | None, name: str) -> list[pytest.MarkDecorator]:
    if path is None:
        return [pytest.mark.skip(reason=f"{name} not found in {BRIDGES_DIR} or on PATH: {BUILD}")]
    return [pytest.mark.vcan]


@pytest.fixture
def socketcan() -> None:
    reason = socketcan_missing()
    if reason is not None:
        pytest.skip(reason)


def _spawn(command: list[str], session: bool = False) -> subprocess.Popen[bytes]:
    """``session``: in a session of its own, so that ``processes`` ends the children it
    forks with it (socketcand serves each client from one)."""
    return subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=session)


def _sim(network: Path, channel: str) -> subprocess.Popen[bytes]:
    sim = subprocess.Popen([sys.executable, "-m", "cifemu", "sim", str(network), "--interface",
                            "socketcan", "--channel", channel, "--log-level", "WARNING"],
                           stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)
    assert sim.stdout is not None
    if not sim.stdout.readline().startswith(b"simulating"):
        sim.kill()
        commands.wait(sim, 10)
        pytest.fail("cifemu sim did not start")
    threading.Thread(target=sim.stdout.read, daemon=True).start()
    return sim


@pytest.fixture
def processes() -> Iterator[list[subprocess.Popen[bytes]]]:
    started: list[subprocess.Popen[bytes]] = []
    yield started
    for proc in reversed(started):
        with contextlib.suppress(OSError):  # a session's leader ends with its children
            if os.getpgid(proc.pid) == proc.pid:
                os.killpg(proc.pid, signal.SIGTERM)
        if proc.poll() is None:
            proc.terminate()
        try:
            commands.wait(proc, 10)
        except subprocess.TimeoutExpired:
            proc.kill()
            commands.wait(proc, 10)


def _boot_sdo_pdo(tmp_path: Path, network: Path, *card_args: str) -> None:
    """The card boots both nodes, and node 1 echoes its outputs back (a PDO loop)."""
    card = start_card(tmp_path, 0, *card_args)
    try:
        with Board(0, tmp_path, timeout=5000) as board:
            configure_online(board, load_network(network))
            wait_until(lambda: board.diagnostics().operating() == [1, 2], 20,
                       "the nodes in data exchange through the bridge")
            wait_until(lambda: board.exchange_io(b"\x5a", receive_size=1) == b"\x5a", 5,
                       "node 1 to echo its outputs through the bridge")
    finally:
        card.stop()


@pytest.mark.parametrize("bridge", [pytest.param("socketcand", marks=needs(SOCKETCAND,
                                                                            "socketcand"))])
def test_card_through_socketcand(bridge: str, socketcan: None, tmp_path: Path,
                                 processes: list[subprocess.Popen[bytes]]) -> None:
    del bridge, socketcan
    network = tmp_path / "network.toml"
    network.write_text(NETWORK)
    port = free_port()
    assert SOCKETCAND is not None
    processes.append(_spawn([SOCKETCAND, "-i", SOCKETCAN_CHANNEL, "-l", "lo", "-p", str(port),
                             "-n"], session=True))
    processes.append(_sim(network, SOCKETCAN_CHANNEL))
    wait_until(lambda: _listening(port), 10, f"socketcand listening on {port}")
    _boot_sdo_pdo(tmp_path, network, "--interface", "socketcand", "--channel",
                  SOCKETCAN_CHANNEL, "--bus-option", "host=127.0.0.1", "--bus-option",
                  f"port={port}")


@pytest.mark.parametrize("bridge", [pytest.param("cannelloni", marks=needs(CANNELLONI,
                                                                            "cannelloni"))])
def test_card_through_cannelloni(bridge: str, socketcan: None, tmp_path: Path,
                                 processes: list[subprocess.Popen[bytes]]) -> None:
    del bridge, socketcan
    if not Path("/sys/class/net/vcan1").exists():
        pytest.skip(f"no vcan1 for the far side: run it with `tools/vcan-vm --vcan 2 -- "
                    f"...pytest -m vcan tests/test_bridges_vcan.py` ({HOW_TO_RUN})")
    network = tmp_path / "network.toml"
    network.write_text(NETWORK)
    near, far = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    assert CANNELLONI is not None
    # -t 1000: a UDP packet leaves after 1 ms, not cannelloni's default 100 ms of buffering
    for vcan, local, remote in (("vcan0", near, far), ("vcan1", far, near)):
        processes.append(_spawn([CANNELLONI, "-I", vcan, "-R", "127.0.0.1", "-r", str(remote),
                                 "-L", "127.0.0.1", "-l", str(local), "-t", "1000"]))
    processes.append(_sim(network, "vcan1"))
    _boot_sdo_pdo(tmp_path, network, "--interface", "socketcan", "--channel", "vcan0")


@pytest.mark.parametrize("bridge", [pytest.param("socketcand", marks=needs(SOCKETCAND,
                                                                            "socketcand"))])
def test_a_socketcand_link_lost_while_idle_is_a_bus_off_and_comes_back(
        bridge: str, socketcan: None, tmp_path: Path,
        processes: list[subprocess.Popen[bytes]]) -> None:
    """socketcand serves each client from a child process of its own: that child killed,
    the card's connection ends while the card sends nothing. python-can's client would
    not tell (its recv returns nothing from a closed connection); the card looks at the
    connection itself, counts a bus-off within ``NOTICED_S``, and connects again to the
    daemon, which still listens: the node's PDO loop works through the new connection."""
    del bridge, socketcan
    network = tmp_path / "network.toml"
    network.write_text(QUIET_NETWORK)
    port = free_port()
    assert SOCKETCAND is not None
    daemon = _spawn([SOCKETCAND, "-i", SOCKETCAN_CHANNEL, "-l", "lo", "-p", str(port), "-n"],
                    session=True)
    processes.append(daemon)
    processes.append(_sim(network, SOCKETCAN_CHANNEL))
    wait_until(lambda: _listening(port), 10, f"socketcand listening on {port}")
    card = start_card(tmp_path, 0, "--interface", "socketcand", "--channel", SOCKETCAN_CHANNEL,
                      "--bus-option", "host=127.0.0.1", "--bus-option", f"port={port}")
    try:
        with Board(0, tmp_path, timeout=5000) as board:
            configure_online(board, load_network(network))
            wait_until(lambda: board.diagnostics().operating() == [1], 20,
                       "node 1 in data exchange through socketcand")
            wait_until(lambda: board.exchange_io(b"\x5a", receive_size=1) == b"\x5a", 5,
                       "node 1 to echo its outputs")
            before = board.diagnostics()
            served = children_of(daemon.pid)
            assert len(served) == 1, f"socketcand serves {len(served)} connections, not the card's"
            os.kill(served[0], signal.SIGKILL)
            wait_until(lambda: board.diagnostics().usBus_Off_Cnt == before.usBus_Off_Cnt + 1,
                       NOTICED_S, "the lost link counted as a bus-off")
            # A PDO the card sent while the link was down is lost (Msg_Time_Out), and the
            # card sends one only when the outputs change: a new value each try.
            values = itertools.cycle(bytes([v]) for v in range(0x60, 0x80))
            wait_until(lambda: _echoed(board, next(values)), 10,
                       "node 1 to echo its outputs through the new connection")
            after = board.diagnostics()
            assert after.usBus_Off_Cnt == before.usBus_Off_Cnt + 1
            assert after.operating() == [1]
    finally:
        card.stop()


def _echoed(board: Board, value: bytes) -> bool:
    """Write ``value`` to node 1's outputs; True when its echo is in the inputs within
    0.2 s."""
    board.exchange_io(value, receive_size=1)
    deadline = time.monotonic() + 0.2
    while time.monotonic() < deadline:
        if board.exchange_io(value, receive_size=1) == value:
            return True
    return False


def _listening(port: int) -> bool:
    with socket.socket() as probe:
        return probe.connect_ex(("127.0.0.1", port)) == 0
