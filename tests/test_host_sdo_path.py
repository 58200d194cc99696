"""A host's expedited SDO through the mailbox with ``--simulate``: what the device loop spends.

Why in process: the count is of one thread's Python calls, which only a profile function
in that thread sees. The parts are the real ones: a card (``Device``) serving its image
from its own thread, the generic node simulated on a ``virtual`` bus beside it, as
``cifemu firmware --simulate`` runs them, configured on line and asked through the
driver API by a host in the test's thread.
"""

from __future__ import annotations

import sys
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

import can
import pytest

from dbm_tools.network import GENERIC_DEVICE_TYPE, parse_network
from dpm import flags as fl
from dpm.commands import COM_SDO_UP_DOWNLOAD
from dpm.image import image_path
from dpm.layout import HOST_FLAGS
from dpm.message import Message, Task, TelegramHeader, Tfc
from dpm.tap import tap_address
from dpm.task2 import ComDiagnostics
from firmware.can.bus import BusConfig
from firmware.device import Device
from firmware.sim import SimulatedNetwork
from host_api.board import Board
from host_api.driver import DevGetTaskState
from host_api.online import configure_online
from tests.conftest import wait_until

NETWORK = '[bus]\nhost_watchdog_ms = 0\nhandshake = "uncontrolled"\n\n[[node]]\nid = 1\n'
UPLOAD_1000H = Message(rx=Task.CAN, tx=Task.USER, b=COM_SDO_UP_DOWNLOAD, data=TelegramHeader(
    device_adr=1, data_adr=0x1000, data_idx=0, function=Tfc.READ).encode())


class LoopCalls:
    """Counts the Python calls of the thread it is installed in while ``on``."""

    def __init__(self) -> None:
        self.on = False
        self.calls = 0

    def install(self) -> None:
        sys.setprofile(self._count)

    def _count(self, frame: FrameType, event: str, arg: object) -> None:
        if self.on and event == "call":
            self.calls += 1


@dataclass
class SimulatedCard:
    device: Device
    board: Board
    sim: SimulatedNetwork
    loop_calls: LoopCalls


def operating(board: int) -> list[int]:
    rc, raw = DevGetTaskState(board, 2, 64)
    assert rc == 0
    return ComDiagnostics.decode(raw).operating()


@pytest.fixture
def simulated_card(tmp_path: Path) -> Iterator[SimulatedCard]:
    """A configured card beside its simulated node 1 (``--simulate``), node 1 operating; its
    device loop's thread counts its Python calls while ``loop_calls.on``."""
    channel = f"test-host-sdo-{uuid.uuid4().hex}"
    network = parse_network(NETWORK)
    sim_bus = can.Bus(interface="virtual", channel=channel)
    sim = SimulatedNetwork(network, sim_bus)
    device = Device(0, tmp_path, bus=BusConfig(
        "virtual", channel, tap=tap_address(image_path(tmp_path, 0))), flash_dir=tmp_path / "flash")
    loop_calls = LoopCalls()

    def started() -> None:  # in the loop's thread, as the firmware starts its nodes
        loop_calls.install()
        sim.start()

    loop = threading.Thread(target=device.run, args=(started,), name="device-loop")
    loop.start()
    board = None
    try:
        wait_until(lambda: device.mm[HOST_FLAGS] & fl.READY, 20, "READY")
        board = Board(0, tmp_path, timeout=5000).open()
        configure_online(board, network)
        wait_until(lambda: operating(0) == [1], 20, "node 1 operating")
        yield SimulatedCard(device, board, sim, loop_calls)
    finally:
        if board is not None:
            board.close()
        device.stop()
        loop.join(10)
        sim.stop()
        sim_bus.shutdown()


def upload_1000h(board: Board) -> int:
    answer = board.transact(UPLOAD_1000H)
    assert answer.f == 0, f"msg.f {answer.f}"
    return int.from_bytes(answer.data[8:12], "little")


def test_an_expedited_upload_costs_the_device_loop_few_python_calls(
        simulated_card: SimulatedCard) -> None:
    """An expedited COM_SDO_Up_Download answered by a simulated node runs at most 108 Python
    calls in the device loop's thread (104 on 2026-12-03 after the merge of branch cardmb,
    whose pre-checks before the C mailbox turn add about 11 to every Python turn; 93 on
    branch sdo08 alone; 112-114 before it: the
    frames deep-copied by ``copy`` for each station, canopen's listener, ``notify`` and a
    listener of remote frames per frame to the nodes, canopen's ``init_upload`` with its
    log call, a closure and a header object for the answer; 143 before branch sdocut):
    with ``--simulate`` the request, the node's SDO server, its answer and the host's answer
    all run there, and that thread's CPU is most of the card's per transfer (issue 22)."""
    card = simulated_card
    for _ in range(50):  # warm: the channel, canopen's caches
        assert upload_1000h(card.board) == GENERIC_DEVICE_TYPE
    transfers = 300
    card.loop_calls.on = True
    try:
        for _ in range(transfers):
            assert upload_1000h(card.board) == GENERIC_DEVICE_TYPE
    finally:
        card.loop_calls.on = False
    per_transfer = card.loop_calls.calls / transfers
    assert per_transfer <= 108, f"{per_transfer:.1f} Python calls per transfer in the loop"


def test_an_expedited_upload_costs_the_host_few_python_calls(
        simulated_card: SimulatedCard) -> None:
    """The host's side of the same transfer, ``Board.transact``: at most 44 Python calls
    (40 on 2026-12-03, branch sdo08; 58 before: ``put_message``/``get_message`` and their
    time-out and return-code helpers around the driver's calls, ``fl.pending`` with the
    board's ``host``/``dev`` for each look at the flags, ``_take`` for a free channel, and a
    list made anew at each session's end). The host's CPU is half the transfer's on the
    machine of issue 22, and the Python driver is the benchmark's host."""
    card = simulated_card
    for _ in range(50):
        assert upload_1000h(card.board) == GENERIC_DEVICE_TYPE
    host_calls = LoopCalls()
    host_calls.install()
    transfers = 300
    host_calls.on = True
    try:
        for _ in range(transfers):
            card.board.transact(UPLOAD_1000H)
    finally:
        host_calls.on = False
        sys.setprofile(None)
    per_transfer = host_calls.calls / transfers
    assert per_transfer <= 44, f"{per_transfer:.1f} Python calls per transfer in the host"
