"""The Python host's mailbox transaction in C and in Python do the same (issue 22).

``put_inside`` and ``get_inside`` make a put or get that need not wait in one C call each
(``host_api._devflags.put_request``, ``take_answer``) and hand every other case to their
Python steps (``driver.native_transaction``). Each scenario below runs once per path on a
board of its own, with this test as the card (it takes requests and writes answers into the
image by hand, so every order of events is the test's to choose), and what a host and the
ledger's next holder can see must be the same: each call's code and message, the ledger
file's lines and this host's requests in memory after each step (the send time masked).
The crash tests with real cards and killed hosts run both paths too
(tests/test_libcif_hosts.py).
"""

from __future__ import annotations

import mmap
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from dpm import flags as fl
from dpm._quicklock import Lock as QuickLock
from dpm.commands import COM_TX_CAN_LAYER2
from dpm.doorbell import HostBell
from dpm.errors import Drv
from dpm.layout import DEV_FLAGS, DEV_MBX, DPM_SIZE, HOST_FLAGS, PC_MBX
from dpm.ledger import ledger_text
from dpm.message import Ext, Message, Task
from host_api import driver as d
from host_api.locks import ChannelLock, Transaction
from host_api.registry import Counters, MappedBoard
from tests.conftest import Card

Step = Callable[["FakeCard"], Any]


class FakeCard:
    """A board's image, bell and transaction lock with no firmware: the test plays the card."""

    def __init__(self, directory: Path) -> None:
        directory.mkdir()
        self.mm = mmap.mmap(-1, DPM_SIZE)
        self.path = directory / "board0.transaction.lock"
        self.transaction = Transaction(self.path)
        assert self.transaction.acquire(0)  # a session, as the 309-3 server's link holds
        self.board = MappedBoard(0, directory / "dpm0", self.mm, HostBell(directory / "dpm0"),
                                 QuickLock(), QuickLock(), ChannelLock(directory / "io.lock"),
                                 self.transaction, Counters())

    def put(self, msg: Message) -> int:
        return int(d.put_inside(self.board, msg, msg.encode(), 0, 0.0))

    def get(self, size: int = d.MSG_BUFFER_SIZE) -> tuple[int, Message | None]:
        code, msg = d.get_inside(self.board, size, 0, 0.0)
        return int(code), msg

    def take(self) -> Message:
        """The card takes the request in the device mailbox."""
        assert (self.mm[HOST_FLAGS] ^ self.mm[DEV_FLAGS]) & fl.DEV_MBX
        msg = Message.decode_at(self.mm, DEV_MBX)
        self.mm[HOST_FLAGS] ^= fl.DEV_MBX
        return msg

    def answer(self, msg: Message) -> None:
        """The card writes ``msg`` into the host mailbox, which must be free."""
        assert not (self.mm[HOST_FLAGS] ^ self.mm[DEV_FLAGS]) & fl.HOST_MBX
        raw = msg.encode()
        self.mm[PC_MBX : PC_MBX + len(raw)] = raw
        self.mm[HOST_FLAGS] ^= fl.HOST_MBX

    def seen(self) -> tuple[list[str], list[tuple[int, ...]]]:
        """The ledger's lines and this host's requests, without their send times."""
        lines = ledger_text(self.path.read_bytes()).decode().splitlines()
        own = self.transaction._own
        return ([" ".join(line.split()[2:7]) for line in lines],
                [(r.nr, r.b, r.rx, r.tx, r.multi, r.given_up) for r in own])

    def close(self) -> None:
        self.transaction.release()
        self.transaction.close()
        self.board.bell.close()
        self.board.io_lock.close()
        self.mm.close()


def request(b: int = 17, nr: int = 1, e: int = 0, rx: int = Task.PLC) -> Message:
    return Message(rx=rx, tx=Task.USER, b=b, nr=nr, e=e, data=bytes([0, 1, nr, 0, 0, 2, 5, 1]))


def answer_to(msg: Message, e: int = 0, f: int = 0, data: bytes = b"\1\2\3\4") -> Message:
    return msg.answer(f=f, data=data, e=e)


def plain(card: FakeCard) -> Iterator[Any]:
    yield card.put(request())
    yield card.seen()
    card.answer(answer_to(card.take()))
    yield card.get()
    yield card.seen()


def long_upload(card: FakeCard) -> Iterator[Any]:
    upload = request(b=66, nr=9, e=Ext.FIRST, rx=Task.CAN)
    yield card.put(upload)
    card.take()
    for e in (Ext.FIRST, Ext.CONT, Ext.LAST):
        card.answer(answer_to(upload, e=e))
        yield card.get()
        yield card.seen()


def unanswered(card: FakeCard) -> Iterator[Any]:
    yield card.put(request(e=Ext.NAK))
    yield card.seen()
    card.take()
    layer2 = Message(rx=Task.CAN, tx=Task.USER, b=COM_TX_CAN_LAYER2, nr=3, data=b"\x60\1\x77")
    yield card.put(layer2)
    yield card.seen()


def indication_and_mailbox_full(card: FakeCard) -> Iterator[Any]:
    card.answer(Message(rx=Task.USER, tx=Task.CAN, b=99, nr=0, a=0, data=b"\5"))
    yield card.get()
    yield card.put(request(nr=4))
    yield card.put(request(nr=5))  # the card has not taken nr 4
    yield card.seen()
    card.answer(answer_to(card.take(), data=bytes(40)))
    yield card.get(size=20)  # too short: the answer stays
    yield card.seen()
    yield card.get()
    yield card.get()  # nothing more
    yield card.seen()


def two_awaited_answered_in_reverse(card: FakeCard) -> Iterator[Any]:
    first, second = request(nr=1), request(nr=2, b=18)
    yield card.put(first)
    card.take()
    yield card.put(second)
    card.take()
    yield card.seen()
    card.answer(answer_to(second))
    yield card.get()
    yield card.seen()  # the ledger rewritten with the first one only
    card.answer(answer_to(first))
    yield card.get()
    yield card.seen()


def load_function_sequence(card: FakeCard) -> Iterator[Any]:
    first = Message(rx=Task.RCS, tx=Task.USER, b=6, nr=1, e=Ext.FIRST)
    yield card.put(first)
    card.answer(answer_to(card.take(), e=Ext.FIRST))
    yield card.get()
    yield card.seen()
    yield card.put(Message(rx=Task.RCS, tx=Task.USER, b=6, nr=2, e=Ext.CONT))
    yield card.seen()


def a_dead_hosts_answer(card: FakeCard) -> Iterator[Any]:
    """Another owner's request in the ledger (a host killed after its put): its answer is
    discarded and the next one, this host's, returned."""
    dead = request(nr=7)
    card.transaction.release()
    other = Transaction(card.path)
    try:
        assert other.acquire(0)
        other.sent(dead)
        other.release()  # given up: the lock goes; the file keeps the request
    finally:
        other.close()
    assert card.transaction.acquire(0)
    yield card.seen()
    mine = request(nr=7, b=18)
    yield card.put(mine)
    card.take()
    card.answer(answer_to(dead))
    yield card.seen()
    yield card.get()  # the dead host's, discarded; then none yet
    card.answer(answer_to(mine))
    yield card.get()
    yield card.seen()


SCENARIOS = [plain, long_upload, unanswered, indication_and_mailbox_full,
             two_awaited_answered_in_reverse, load_function_sequence, a_dead_hosts_answer]


def run(scenario: Callable[[FakeCard], Iterator[Any]], directory: Path) -> list[Any]:
    card = FakeCard(directory)
    try:
        return list(scenario(card))
    finally:
        card.close()


@pytest.mark.parametrize("scenario", SCENARIOS, ids=lambda s: s.__name__)
def test_the_transaction_in_c_does_what_the_python_steps_do(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        scenario: Callable[[FakeCard], Iterator[Any]]) -> None:
    monkeypatch.setattr(d, "native_transaction", False)
    python = run(scenario, tmp_path / "python")
    monkeypatch.setattr(d, "native_transaction", True)
    native = run(scenario, tmp_path / "c")
    assert native == python


def test_the_c_calls_do_the_usual_round_trip_themselves(tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """The plain round trip never reaches the Python steps: a put that needs no wait and a
    get of an awaited answer are the C calls' (else the C path would save nothing)."""
    card = FakeCard(tmp_path / "board")
    try:
        def no_python_steps(*args: Any, **kwargs: Any) -> None:
            raise AssertionError("the Python steps ran")

        monkeypatch.setattr(card.transaction, "sent", no_python_steps)
        monkeypatch.setattr(card.transaction, "answered", no_python_steps)
        monkeypatch.setattr(card.board, "change_dev_flags", no_python_steps)
        assert list(plain(card)) == [
            Drv.DRV_NO_ERROR, (["1 17 2 16 0"], [(1, 17, 2, 16, 0, False)]),
            (Drv.DRV_NO_ERROR, answer_to(request())), ([], [])]
        assert card.board.counters.write == 1 and card.board.counters.read == 1
    finally:
        card.close()


@pytest.mark.parametrize("native", [True, False], ids=["native", "python"])
def test_a_queue_of_answers_read_from_a_card_settles_each_request(
        card: Card, monkeypatch: pytest.MonkeyPatch, native: bool) -> None:
    """Requests put until the card's queue is full, then their answers read: a real card
    writes the next answer as soon as HOSTACK gives the mailbox back, so a get that looked at
    the mailbox's header after its handshake matched the next answer's and left its own
    request in the ledger, which made a later host discard an answer of its own as stale."""
    monkeypatch.setattr(d, "native_transaction", native)
    assert d.DevOpenDriver(card.directory) == 0 and d.DevInitBoard(0) == 0
    try:
        sent = 0
        while d.DevPutMessage(0, request(nr=sent & 0xFF), 200) == Drv.DRV_NO_ERROR:
            sent += 1
            assert sent < 200
        read = []
        while (got := d.DevGetMessage(0, d.MSG_BUFFER_SIZE, 200))[0] == Drv.DRV_NO_ERROR:
            assert got[1] is not None
            read.append(got[1].nr)
        assert sent > 8 and read == list(range(sent))
        ledger = ledger_text((card.directory / "board0.transaction.lock").read_bytes())
        assert ledger == b""
    finally:
        while d.DevCloseDriver() == 0:
            pass
