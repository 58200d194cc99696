"""Tests of a host program (host_program.py) against the emulated card.

The ``cif_card`` fixture comes from the cifemu pytest plugin, installed with cifemu:
no conftest.py is needed. See docs/pytest-plugin.md.
"""

from __future__ import annotations

import pytest
from host_program import write_and_confirm

from cifemu.pytest_plugin import CifCard
from host_api.board import Board, CifError

ONE_NODE = {"bus": {"bitrate": 500_000}, "node": [{"id": 1, "name": "digital I/O"}]}


@pytest.mark.cif_network(ONE_NODE)
def test_the_node_echoes_what_the_program_writes(cif_card: CifCard) -> None:
    cif_card.wait_until_operating()
    assert write_and_confirm(cif_card.board, 0, b"\x01\x02\x04\x08\x10\x20\x40\x80") == (
        b"\x01\x02\x04\x08\x10\x20\x40\x80")


@pytest.mark.cif_network("network.toml", board=1)
def test_the_second_node_on_board_1(cif_card: CifCard) -> None:
    diag = cif_card.wait_until_operating()
    assert diag.operating() == [1, 2]
    assert write_and_confirm(1, 8, b"\xa5" * 8) == b"\xa5" * 8


@pytest.mark.cif_network(ONE_NODE)
def test_the_program_notices_a_card_that_stops(cif_card: CifCard) -> None:
    cif_card.wait_until_operating()
    with Board(cif_card.board) as board:
        cif_card.stop()
        with pytest.raises(CifError) as refused:
            board.exchange_io(b"\xff" * 8, receive_size=8, timeout=200)
    assert refused.value.name == "DRV_DEV_NOT_READY"
