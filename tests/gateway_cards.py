"""Cards with simulated networks, configured on line, for the CiA 309 gateway's tests.

``start`` brings up a card on a board of a shared directory (module-scoped fixtures keep
several boards in one), simulating a network and configured with it; nodes in
``NOT_IN_CARD`` are simulated but left out of the card's configuration.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from dbm_tools.network import load_network
from dpm.task2 import ComDiagnostics
from host_api import driver as d
from host_api.board import Board
from host_api.online import configure_online
from tests.conftest import Card, start_card, wait_until

EDS = Path(__file__).with_name("data") / "cia309_node.eds"
NOT_IN_CARD = {9, 255}
"""Simulated, but not configured in the card: node 9 leaves its identifiers free for layer-2
access; 255 (an unconfigured LSS slave) cannot be configured."""


def start(directory: Path, board: int, toml: str | None) -> Card:
    """A card on ``board``; with ``toml`` it simulates that network and is configured on line."""
    args = ["--flash", str(directory / f"flash{board}")]
    if toml is not None:
        path = directory / f"network{board}.toml"
        path.write_text(toml)
        args += ["--simulate", str(path)]
    card = start_card(directory, board, *args)
    if toml is not None:
        network = load_network(directory / f"network{board}.toml")
        network = dataclasses.replace(
            network, nodes=[node for node in network.nodes if node.id not in NOT_IN_CARD])
        with Board(board, directory, timeout=5000) as opened:
            configure_online(opened, network)
    return card


def diagnostics(board: int) -> ComDiagnostics:
    code, raw = d.DevGetTaskState(board, 2, 64)
    assert code == 0
    return ComDiagnostics.decode(raw)


def wait_operating(board: int, nodes: list[int], timeout: float = 10) -> None:
    wait_until(lambda: diagnostics(board).operating() == nodes, timeout,
               f"nodes {nodes} of board {board} in data exchange")
