"""A card with one simulated node on a ``shm`` bus, and a station of the test's own on it.

The station (``Rig.send``) injects frames with the time stamp the test chooses, as a card
would read them from a receive queue it fell behind on, or as a node that breaks the rules
would send them. The node (``NETWORK``) has no error control: every error-control frame the
card sees is the test's.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from dpm.task2 import ComDiagnostics
from firmware.shm.bus import ShmBus
from host_api.board import Board
from tests import commands
from tests.can_net import start_sim
from tests.conftest import start_card

NODE = 2
NETWORK = f'[[node]]\nid = {NODE}\nerror_control = "none"\n'
"""A node without heartbeat: every error-control frame the card sees is the test's."""


class Rig:
    def __init__(self, board: Board, station: ShmBus) -> None:
        self.board = board
        self.station = station

    def diag(self) -> ComDiagnostics:
        return self.board.diagnostics()

    def send(self, ident: int, data: bytes, stamp: float) -> None:
        self.station.send(can.Message(timestamp=stamp, arbitration_id=ident, data=data,
                                      is_extended_id=False))


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    channel = f"test-{uuid.uuid4().hex}"
    toml = tmp_path / "network.toml"
    toml.write_text(NETWORK)
    card = start_card(tmp_path, 0, "--interface", "shm", "--channel", channel)
    sim = start_sim(toml, "shm", channel)
    station = ShmBus(channel, preserve_timestamps=True)
    board = Board(0, tmp_path, timeout=5000).open()
    try:
        yield Rig(board, station)
    finally:
        board.close()
        station.shutdown()
        card.stop()
        sim.terminate()
        commands.wait(sim, 10)
