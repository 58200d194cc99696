"""Configure a card on line, as seed chapter 7 describes, from a network description.

The node parameter sets, extended bus parameters and bus parameters are the
same records ``cifemu dbm build`` would store in a DBM; here they go to the
CAN task with COM_Start_Seq / COM_Download / COM_End_Seq instead, and the bus
parameters come last because their download starts the network. Nothing is
stored in the card's flash: a reset forgets it.

``download_data_set`` is the one host-side routine for that sequence; it talks to
the card through a ``Transact`` callable, so a client with its own mailbox
handling (the CiA 309 gateway) uses it as well as a ``Board``.
"""

from __future__ import annotations

from collections.abc import Callable

from dbm_tools.builder import build_dbm
from dbm_tools.network import Network
from dbm_tools.tables import BUS_CAN, BUS_CAN_EXT, NODES
from dpm.com import END_SEQ_REQUEST, DownloadRequest, StartSeqRequest, decode_start_seq_confirm
from dpm.commands import (
    AREA_BUS,
    AREA_EXTENDED,
    COM_DOWNLOAD,
    COM_END_SEQ,
    COM_START_SEQ,
    MAX_LEN_DATA_UNIT,
)
from dpm.message import Message, MessageError, Task
from host_api.board import Board
from host_api.errors import HostApiError

Transact = Callable[[int, bytes], Message]
"""Sends one CAN-task request (msg.b and its data) and returns the card's answer to it."""

SEQUENCE_TIMEOUT_MS = 1000
"""[ours] COM_Start_Seq's Timeout: the longest pause between two messages of a sequence."""


class ConfigurationError(HostApiError, RuntimeError):
    """The CAN task refused a data set: ``f`` is the seed's msg.f number."""

    def __init__(self, what: str, f: int) -> None:
        super().__init__(f"{what}: the CAN task answered msg.f = {f}")
        self.f = f


def board_transact(board: Board) -> Transact:
    """A ``Transact`` over a ``Board``: msg.rx 3 from msg.tx 16, one answer per request."""
    return lambda b, data: board.transact(Message(rx=Task.CAN, tx=Task.USER, b=b, data=data))


def download_data_set(transact: Transact, area: int, data: bytes, what: str = "") -> None:
    """Hand one data set to the CAN task on line (seed 5.2.3 - 5.2.5).

    ``area`` is the Area_Code: a node address 1..126, 127 the bus parameters (their download
    starts the network), 128 the extended bus parameters. A set that fits one message goes
    in a single COM_Download; a longer one in a COM_Start_Seq sequence whose pieces have the
    length the card answers (Max_Len_Data_Unit), closed by COM_End_Seq.

    Raises ``ConfigurationError`` when the card answers an msg.f other than 0; whatever
    ``transact`` raises (a driver error, a time-out) passes through.
    """
    what = what or f"area {area}"

    def request(b: int, payload: bytes) -> Message:
        answer = transact(b, payload)
        if answer.f:
            raise ConfigurationError(what, answer.f)
        return answer

    if len(data) <= MAX_LEN_DATA_UNIT:
        request(COM_DOWNLOAD, DownloadRequest(area, data).encode())
        return
    answer = request(COM_START_SEQ, StartSeqRequest(area, SEQUENCE_TIMEOUT_MS).encode())
    try:
        unit = decode_start_seq_confirm(answer.data)
    except MessageError:
        unit = MAX_LEN_DATA_UNIT  # a card that does not say takes the seed's 240
    for offset in range(0, len(data), unit):
        request(COM_DOWNLOAD, DownloadRequest(area, data[offset : offset + unit], offset).encode())
    request(COM_END_SEQ, END_SEQ_REQUEST)


def configure_online(board: Board, network: Network,
                     progress: Callable[[str], None] = lambda text: None) -> None:
    """Download every node, the extended bus parameters, then the bus parameters."""
    transact = board_transact(board)
    dbm = build_dbm(network)
    nodes = dbm.table(NODES)
    for record in nodes.records if nodes else []:
        progress(f"node {record[0]}")
        download_data_set(transact, record[0], record[1:], f"node {record[0]}")
    extended = dbm.table(BUS_CAN_EXT)
    if extended and extended.records:
        progress("extended bus parameters")
        download_data_set(transact, AREA_EXTENDED, extended.records[0], "extended bus parameters")
    bus = dbm.table(BUS_CAN)
    assert bus is not None and bus.records, "build_dbm always writes BUS_CAN"
    progress("bus parameters: the network starts")
    download_data_set(transact, AREA_BUS, bus.records[0], "bus parameters")
