"""The card powers off while its nodes boot, or while a worker thread configures one: every
frame it handled and every job it began ends cleanly, and promptly.

With ``--simulate`` a simulated node's thread handles the card's frames itself when the card's
receive thread is idle (``firmware.inline``): a boot step's answer, and the card's next
request sent from there. The card's log once held "frame handler failed on 0x581" at its
power-off after a CiA 309 client had written 1017h = 0 to node 1 until the card refused
(the node's heartbeat stopped, the card failed it and booted it again): such a thread went
on in a card handler while the card closed its bus and unmapped its image, so the next
request was "not sent" and the Msg_Time_Out it counted raised ValueError (mmap closed).
``tests/test_can_bus.py`` holds the controller's side of it; here is what a user saw.

COM_Set_Guarding's SDO writes run in a worker thread of the card (``firmware.can.workers``),
which the power-off did not wait for, nor end: one that waited for its node's SDO channel
held the firmware process after SIGTERM for good, one in a transfer until its time-out.
"""

from __future__ import annotations

import time
from pathlib import Path

from dpm.com import NodeSwitch, SdoTimeoutRequest
from dpm.commands import COM_SET_GUARDING, COM_SET_SDO_TIMEOUT
from dpm.message import Message
from host_api.board import Board
from host_api.cia309.gateway import Gateway
from host_api.cia309.model import Cia309Error, DataType
from tests.conftest import wait_until
from tests.gateway_cards import start, wait_operating

NODES = list(range(1, 9))
SDO_LIST = "".join(f"[[node.sdo]]\nindex = 0x6200\nsubindex = 1\nvalue = {value}\nsize = 1\n"
                   for value in range(90))
"""Each node's boot-up writes 90 objects: the boot-ups of the eight nodes are under way for
some tens of milliseconds, their answers handled by the nodes' thread, when the card powers
off (the most the node parameters hold, 1000 bytes)."""
NETWORK = "".join(f"[[node]]\nid = {node}\n{SDO_LIST}" for node in NODES)
GENERIC_DEVICE_TYPE = 0x000F0191
NODE_BUSY = 19
"""msg.f of a request to a node the card is booting (309-3: error 102)."""


def refused_while_it_boots_again(gateway: Gateway) -> Cia309Error:
    """Write 1017h = 0 to node 1 until the card refuses: the node's heartbeat stopped, the
    card failed the node and boots it again."""
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            gateway.sdo_download(0x1017, 0, 0, node_id=1, data_type=DataType.UNSIGNED16)
        except Cia309Error as exc:
            return exc
    raise AssertionError("the card never refused a write to node 1")


def test_a_card_powered_off_while_its_nodes_boot_logs_no_failed_frame_handler(
        tmp_path: Path) -> None:
    card = start(tmp_path, 0, NETWORK)
    try:
        with Gateway([0], tmp_path) as gateway:
            wait_operating(0, NODES)
            refusal = refused_while_it_boots_again(gateway)
            assert refusal.f == NODE_BUSY, refusal
            wait_operating(0, NODES)
            # back from its boot-up (with 1017h from its configuration): answered as before
            assert gateway.sdo_upload(0x1000, 0, node_id=1, data_type=DataType.UNSIGNED32) \
                == GENERIC_DEVICE_TYPE.to_bytes(4, "little")
            gateway.sdo_download(0x6200, 1, 0x5A, node_id=1, data_type=DataType.UNSIGNED8)
            for node in NODES:
                gateway.reset_node(node)
            card.proc.terminate()  # while the eight boot-ups run
        wait_until(lambda: card.proc.poll() is not None, 10, "the card's end")
    finally:
        card.stop()
    log = card.log()
    assert "frame handler failed" not in log, log
    assert "not sent" not in log, log
    assert "Traceback" not in log, log


SILENT = "[[node]]\nid = 1\n[[node]]\nid = 5\n[node.sim]\nsilent = true\n"
"""Node 5 never answers: the card's boot-ups of it, and a worker's writes to it, wait for
the SDO time-out."""
SDO_TIMEOUT_MS = 60_000
"""Far past ``Card.stop``'s 10 s: a power-off that waits for a transfer's time-out fails."""


def test_a_card_powered_off_while_it_writes_guarding_to_a_silent_node_stops_at_once(
        tmp_path: Path) -> None:
    card = start(tmp_path, 0, SILENT)
    try:
        with Board(0, tmp_path, timeout=5000) as board:
            wait_operating(0, [1])
            timeout = SdoTimeoutRequest(0, SDO_TIMEOUT_MS).encode()
            assert board.transact(Message(rx=3, tx=16, b=COM_SET_SDO_TIMEOUT,
                                          data=timeout)).f == 0
            board.put_message(Message(rx=3, tx=16, b=COM_SET_GUARDING,
                                      data=NodeSwitch(5, True, 100, 3).encode()))
            # answered after the card handed COM_Set_Guarding to its worker, which waits
            # for node 5's channel (a boot-up holds it) or for node 5's answer
            assert board.transact(Message(rx=3, tx=16, b=COM_SET_SDO_TIMEOUT,
                                          data=timeout)).f == 0
            assert card.stop() == 0  # within its 10 s: no wait for the 60 s time-out
    finally:
        card.stop()
    log = card.log()
    assert "not sent" not in log, log
    assert "Traceback" not in log, log
