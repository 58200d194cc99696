"""The card rings a host for a message it took only when the host asks (issue 22).

Taking a message (DEVACK) used to ring every host. A host that waits for its answer only
woke for nothing: one thread hand-off more per request whose answer comes later, an SDO
transfer above all. Now a host waiting for the device mailbox asks for the ring
(DevPutMessage, ``dpm.doorbell._RING_WANT_MAILBOX``), and the others sleep until their
answer. A real firmware process; its slow-card and stalled-mailbox faults keep the answer
and the take apart long enough to tell the rings apart.
"""

from __future__ import annotations

from dpm import flags as fl
from dpm.commands import COM_RESET_ERR_EVENT
from dpm.errors import Drv
from dpm.message import Message, Task
from host_api import driver as d
from host_api import faults
from host_api.board import Board
from host_api.registry import MappedBoard, lookup
from tests.conftest import Card, wait_until, within

RING_WAIT_S = 10.0
"""The longest a ring may take on a loaded machine; a passing test waits far less."""


def request() -> Message:
    """A command the CAN task answers at once (seed 5.2.12); the slow card holds the answer."""
    return Message(rx=Task.CAN, tx=Task.USER, b=COM_RESET_ERR_EVENT)


def mapped(board: Board) -> MappedBoard:
    found = lookup(board.number)
    assert isinstance(found, MappedBoard)
    return found


def drained(board: MappedBoard) -> MappedBoard:
    """The board with no ring left in its bell's queue."""
    while board.bell.wait(0):
        pass
    return board


def test_a_host_sleeps_until_its_answer_and_is_rung_for_the_mailbox_when_it_asks(
        card: Card) -> None:
    faults.inject("slow", 0, card.directory, delay_ms=500)
    with Board(0, card.directory, timeout=5000) as opened:
        board = drained(mapped(opened))
        # A host waiting for its answer: the card's first ring after the put is the answer's.
        assert d.DevPutMessage(0, request(), 1000) == Drv.DRV_NO_ERROR
        assert within(board.bell.wait, RING_WAIT_S), "no ring for the answer"
        assert fl.pending(board.host(), board.dev(), fl.HOST_MBX), \
            "the card rang before the answer was there (for taking the message)"
        assert opened.get_message().f == 0

        # A host waiting for the mailbox: rung when the card takes the waiting message.
        faults.inject("stall", 0, card.directory, for_ms=300)
        assert d.DevPutMessage(0, request(), 1000) == Drv.DRV_NO_ERROR
        rung = board.counters.irq
        assert d.DevPutMessage(0, request(), int(RING_WAIT_S * 1000)) == Drv.DRV_NO_ERROR
        if board.counters.irq == rung:
            # The host's fallback poll can see the flag before the ring that follows it
            # arrives (a loaded machine holds the card between the two): the ring still comes.
            assert within(board.bell.wait, RING_WAIT_S), "no ring for the free mailbox"
        assert not fl.pending(board.host(), board.dev(), fl.HOST_MBX), \
            "the ring was the first answer's, not the free mailbox's"
        wait_until(lambda: fl.pending(board.host(), board.dev(), fl.HOST_MBX), RING_WAIT_S,
                   "the first answer")
