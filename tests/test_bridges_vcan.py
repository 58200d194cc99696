"""The card through socketcand and cannelloni, on SocketCAN inside tools/vcan-vm.

Both daemons are built from their public sources outside this repository
(``tools/build-bridges``, docs/remote-bus.md). Where they are found (in
``$CIFEMU_BRIDGES/bin``, default ``~/.cache/cifemu/bridges/bin``, or on PATH) the tests
are ``vcan`` tests and run in ``make test-vcan``; where they are not, they skip saying how
to build them (and are no ``vcan`` tests, so ``make test-vcan`` does not fail for a daemon
the machine never had).

- socketcand: the daemon serves vcan0 on 127.0.0.1; ``cifemu sim`` sits on vcan0; the
  card is python-can's ``socketcand`` client, its host and port given as ``--bus-option``.
- cannelloni: two instances tunnel vcan0 <-> vcan1 over UDP on 127.0.0.1; the card on
  vcan0, ``cifemu sim`` on vcan1 (``tools/vcan-vm --vcan 2``).
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from dbm_tools.network import load_network
from host_api.board import Board
from host_api.online import configure_online
from tests.buses import HOW_TO_RUN, SOCKETCAN_CHANNEL, socketcan_missing
from tests.conftest import start_card, wait_until

NETWORK = "[[node]]\nid = 1\nheartbeat_ms = 600\n[[node]]\nid = 2\nheartbeat_ms = 600\n"
BRIDGES = Path(os.environ.get("CIFEMU_BRIDGES",
                              Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
                              / "cifemu" / "bridges")) / "bin"
BUILD = ("build it with `tools/build-bridges --socketcand DIR --cannelloni DIR` from "
         "checkouts of github.com/linux-can/socketcand and github.com/mguentner/cannelloni "
         "(docs/remote-bus.md)")


def daemon(name: str) -> str | None:
    found = BRIDGES / name
    return str(found) if found.is_file() else shutil.which(name)


SOCKETCAND, CANNELLONI = daemon("socketcand"), daemon("cannelloni")


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port free now on 127.0.0.1 (the daemons take no port 0; the guest is ours alone)."""
    with socket.socket(socket.AF_INET, kind) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def needs(path: str | None, name: str) -> list[pytest.MarkDecorator]:
    if path is None:
        return [pytest.mark.skip(reason=f"{name} not found in {BRIDGES} or on PATH: {BUILD}")]
    return [pytest.mark.vcan]


@pytest.fixture
def socketcan() -> None:
    reason = socketcan_missing()
    if reason is not None:
        pytest.skip(reason)


def _spawn(command: list[str]) -> subprocess.Popen[bytes]:
    return subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def _sim(network: Path, channel: str) -> subprocess.Popen[bytes]:
    sim = subprocess.Popen([sys.executable, "-m", "cifemu", "sim", str(network), "--interface",
                            "socketcan", "--channel", channel, "--log-level", "WARNING"],
                           stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)
    assert sim.stdout is not None
    if not sim.stdout.readline().startswith(b"simulating"):
        sim.kill()
        sim.wait(timeout=10)
        pytest.fail("cifemu sim did not start")
    threading.Thread(target=sim.stdout.read, daemon=True).start()
    return sim


@pytest.fixture
def processes() -> Iterator[list[subprocess.Popen[bytes]]]:
    started: list[subprocess.Popen[bytes]] = []
    yield started
    for proc in reversed(started):
        if proc.poll() is None:
            proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


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
                             "-n"]))
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


def _listening(port: int) -> bool:
    with socket.socket() as probe:
        return probe.connect_ex(("127.0.0.1", port)) == 0
