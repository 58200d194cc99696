"""A legacy host's shutdown and restart: HOST_NOT_READY, DevReset, configure again.

Issue 13, defect 2: after ``DevSetHostState(HOST_NOT_READY)`` and a ``DevReset`` the
card came back READY with NOTREADY clear in DevFlags, but still held its outputs as if
the host were not ready: CAN_state STOP, no COM, DevExchangeIO -21 and even
``DevSetHostState(HOST_READY)`` -21 after the next on-line configuration.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from dbm_tools.network import load_network
from dpm.errors import Drv
from dpm.task2 import ComPlcParameter
from host_api import driver as d
from host_api.board import Board
from host_api.online import configure_online
from tests.conftest import start_card, wait_until

NETWORK = "\n".join(f"[[node]]\nid = {n}" for n in (1, 2))
COM_TIMEOUT_S = 3.0
"""The same sequence without HOST_NOT_READY has COM back within 0.05 s."""


@pytest.fixture
def host(tmp_path: Path) -> Iterator[tuple[Board, Path]]:
    """A card with two simulated nodes and a host that keeps board 0 open throughout."""
    network = tmp_path / "network.toml"
    network.write_text(NETWORK)
    card = start_card(tmp_path, 0, "--simulate", str(network), "--channel", "restart")
    board = Board(0, tmp_path, timeout=5000).open()
    yield board, network
    board.close()
    card.stop()


def _configure_and_exchange(board: Board, network: Path) -> None:
    configure_online(board, load_network(network))
    wait_until(lambda: d.DevExchangeIO(0, 0, b"\x11", 0, 8, 100)[0] == 0, COM_TIMEOUT_S,
               "DevExchangeIO to succeed (COM)")
    wait_until(lambda: d.DevExchangeIO(0, 0, b"\x11", 0, 1, 100)[1] == b"\x11", COM_TIMEOUT_S,
               "node 1 to echo the outputs")


@pytest.mark.parametrize("reset", [d.WARMSTART, d.COLDSTART])
def test_bus_comes_back_after_host_not_ready_and_reset(host: tuple[Board, Path],
                                                      reset: int) -> None:
    board, network = host
    _configure_and_exchange(board, network)
    assert d.DevSetHostState(0, d.HOST_NOT_READY, 1000) == 0
    assert d.DevReset(0, reset, 5000) == 0
    _configure_and_exchange(board, network)
    assert d.DevSetHostState(0, d.HOST_READY, 1000) == 0
    # and the host can still take the card down and up again without a reset
    assert d.DevSetHostState(0, d.HOST_NOT_READY, 1000) == 0
    assert d.DevExchangeIO(0, 0, b"\x22", 0, 1, 100)[0] == Drv.DRV_DEV_NO_COM_FLAG
    assert d.DevSetHostState(0, d.HOST_READY, 1000) == 0
    wait_until(lambda: d.DevExchangeIO(0, 0, b"\x22", 0, 1, 100)[1] == b"\x22", COM_TIMEOUT_S,
               "the outputs to reach the node again after HOST_READY")


def test_bus_comes_back_after_watchdog_expiry_and_reset(host: tuple[Board, Path]) -> None:
    """The same hold-over after an expired host watchdog: the next start ends it."""
    board, network = host
    assert d.DevPutTaskParameter(0, 2, ComPlcParameter(usWatchDogTime=100).encode()) == 0
    assert d.DevReset(0, d.WARMSTART, 5000) == 0  # a warm start takes the host's parameters
    _configure_and_exchange(board, network)
    assert d.DevTriggerWatchDog(0, d.WATCHDOG_START)[0] == 0
    wait_until(lambda: d.DevExchangeIO(0, 0, b"\x11", 0, 1, 100)[0] != 0, 5,
               "the host watchdog to expire (COM off)")
    assert d.DevReset(0, d.WARMSTART, 5000) == 0
    _configure_and_exchange(board, network)
