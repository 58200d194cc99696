"""Configure a card on line, as seed chapter 7 describes, from a network description.

The node parameter sets, extended bus parameters and bus parameters are the
same records ``cifemu dbm build`` would store in a DBM; here they go to the
CAN task with COM_Start_Seq / COM_Download / COM_End_Seq instead, and the bus
parameters come last because their download starts the network. Nothing is
stored in the card's flash: a reset forgets it.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from dbm_tools.builder import build_dbm
from dbm_tools.network import Network
from dbm_tools.tables import BUS_CAN, BUS_CAN_EXT, NODES
from dpm.commands import AREA_BUS, AREA_EXTENDED, COM_DOWNLOAD, COM_END_SEQ, COM_START_SEQ
from dpm.message import Message, Task
from host_api.board import Board


class ConfigurationError(RuntimeError):
    """The CAN task refused a data set: ``f`` is the seed's msg.f number."""

    def __init__(self, what: str, f: int) -> None:
        super().__init__(f"{what}: the CAN task answered msg.f = {f}")
        self.f = f


def _download(board: Board, area: int, data: bytes, what: str) -> None:
    """One data set: a single COM_Download when it fits, else a sequence."""
    unit = 240
    if len(data) <= unit:
        answer = board.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_DOWNLOAD,
                                        data=bytes([0, area, 0, 0]) + data))
        if answer.f:
            raise ConfigurationError(what, answer.f)
        return
    answer = board.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_START_SEQ,
                                    data=bytes([0, area]) + struct.pack("<H", 1000)))
    if answer.f:
        raise ConfigurationError(what, answer.f)
    unit = answer.data[0] if answer.data else unit
    for offset in range(0, len(data), unit):
        chunk = data[offset : offset + unit]
        answer = board.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_DOWNLOAD,
                                        data=bytes([0, area]) + struct.pack("<H", offset) + chunk))
        if answer.f:
            raise ConfigurationError(what, answer.f)
    answer = board.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_END_SEQ, data=b"\0"))
    if answer.f:
        raise ConfigurationError(what, answer.f)


def configure_online(board: Board, network: Network,
                     progress: Callable[[str], None] = lambda text: None) -> None:
    """Download every node, the extended bus parameters, then the bus parameters."""
    dbm = build_dbm(network)
    nodes = dbm.table(NODES)
    for record in nodes.records if nodes else []:
        progress(f"node {record[0]}")
        _download(board, record[0], record[1:], f"node {record[0]}")
    extended = dbm.table(BUS_CAN_EXT)
    if extended and extended.records:
        progress("extended bus parameters")
        _download(board, AREA_EXTENDED, extended.records[0], "extended bus parameters")
    bus = dbm.table(BUS_CAN)
    assert bus is not None and bus.records, "build_dbm always writes BUS_CAN"
    progress("bus parameters: the network starts")
    _download(board, AREA_BUS, bus.records[0], "bus parameters")
