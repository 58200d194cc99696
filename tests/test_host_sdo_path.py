"""A host's expedited SDO through the mailbox with ``--simulate``: what the device loop spends.

Why in process: the count is of one thread's Python calls, which only a profile function
in that thread sees. The parts are the real ones: a card (``Device``) serving its image
from its own thread, the generic node simulated on a ``virtual`` bus beside it, as
``cifemu firmware --simulate`` runs them, configured on line and asked through the
driver API by a host in the test's thread.
"""

from __future__ import annotations

import _thread
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dbm_tools.network import GENERIC_DEVICE_TYPE, parse_network
from dpm import flags as fl
from dpm.commands import COM_SDO_UP_DOWNLOAD
from dpm.image import image_path
from dpm.layout import HOST_FLAGS
from dpm.message import Ext, Message, Task, TelegramHeader, Tfc
from dpm.tap import tap_address
from dpm.task2 import ComDiagnostics
from firmware.can.bus import BusConfig
from firmware.device import Device
from firmware.sim import SimulatedNetwork
from host_api.board import Board
from host_api.driver import MSG_BUFFER_SIZE, DevGetMessage, DevGetTaskState, DevPutMessage
from host_api.online import configure_online
from tests.conftest import ROOT, wait_until

NETWORK = '[bus]\nhost_watchdog_ms = 0\nhandshake = "uncontrolled"\n\n[[node]]\nid = 1\n'
DOMAIN_NETWORK = NETWORK + f'eds = "{ROOT / "tests" / "data" / "cia309_node.eds"}"\n'
"""Node 1 with a DOMAIN at 2000h, for values longer than one message."""
DOMAIN = 0x2000
UPLOAD_1000H = Message(rx=Task.CAN, tx=Task.USER, b=COM_SDO_UP_DOWNLOAD, data=TelegramHeader(
    device_adr=1, data_adr=0x1000, data_idx=0, function=Tfc.READ).encode())


CARD_SDO_PATH = tuple(str(ROOT / "firmware" / name) for name in (
    "can/", "can_host_sdo.py", "device.py"))
"""The card's own modules on a host SDO's path (not the simulated node's, nor the shared
``virtual`` station's in ``firmware/inline.py``)."""
THREAD_LOCKS = (_thread.LockType, _thread.RLock)
CLOCKS = frozenset({time.monotonic, time.monotonic_ns, time.time, time.time_ns,
                    time.perf_counter, time.perf_counter_ns})


class LoopCalls:
    """Counts the Python calls of the thread it is installed in while ``on``, and the
    acquires of CPython's thread locks and the clock readings that the card's own modules
    on the SDO path make there (``CARD_SDO_PATH``)."""

    def __init__(self) -> None:
        self.on = False
        self.calls = 0
        self.locks = 0
        self.clocks = 0

    def install(self) -> None:
        sys.setprofile(self._count)

    def _count(self, frame: FrameType, event: str, arg: object) -> None:
        if not self.on:
            return
        if event == "call":
            self.calls += 1
        elif event == "c_call" and frame.f_code.co_filename.startswith(CARD_SDO_PATH):
            if isinstance(getattr(arg, "__self__", None), THREAD_LOCKS):
                # ``with`` shows only its __exit__
                self.locks += getattr(arg, "__name__", "") in ("acquire", "__exit__")
            elif arg in CLOCKS:
                self.clocks += 1


class CountingLock:
    """The process image's lock, counting its acquires while ``on``: the turn in C takes
    it through ``acquire``, which no profile function sees."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self.on = False
        self.acquires = 0

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        self.acquires += self.on
        return self._lock.acquire(blocking, timeout)

    def release(self) -> None:
        self._lock.release()

    def __enter__(self) -> bool:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self._lock.release()


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
    with _simulated_card(tmp_path, 0) as card:
        yield card


@contextmanager
def _simulated_card(directory: Path, board: int, *, native: bool = True,
                    text: str = NETWORK) -> Iterator[SimulatedCard]:
    """Board ``board`` in ``directory``, with its own simulated node 1 on a channel of its
    own; ``native`` False: every turn of its device loop in Python; ``text``: the network."""
    channel = f"test-host-sdo-{uuid.uuid4().hex}"
    network = parse_network(text)
    sim_bus = can.Bus(interface="virtual", channel=channel)
    sim = SimulatedNetwork(network, sim_bus)
    device = Device(board, directory, bus=BusConfig(
        "virtual", channel, tap=tap_address(image_path(directory, board))),
        flash_dir=directory / f"flash{board}")
    device.native = native
    loop_calls = LoopCalls()

    def started() -> None:  # in the loop's thread, as the firmware starts its nodes
        loop_calls.install()
        sim.start()

    loop = threading.Thread(target=device.run, args=(started,), name=f"device-loop-{board}")
    loop.start()
    host = None
    try:
        wait_until(lambda: device.mm[HOST_FLAGS] & fl.READY, 20, "READY")
        host = Board(board, directory, timeout=5000).open()
        configure_online(host, network)
        wait_until(lambda: operating(board) == [1], 20, "node 1 operating")
        yield SimulatedCard(device, host, sim, loop_calls)
    finally:
        if host is not None:
            host.close()
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
    """An expedited COM_SDO_Up_Download answered by a simulated node runs at most 46 Python
    calls in the device loop's thread (43 on 2026-12-04 afternoon, branch cardsdo again: the
    controller's frame made without ``can.Message``'s constructor and copied to the other
    stations without a function per copy, no ``Event.is_set`` per frame sent, the expedited
    upload's answer finished in ``_on_frame`` and posted in ``_answer_sdo`` without their
    helpers, ``start_host`` written out; 50 on 2026-12-04, branch cardsdo: the request and its
    answer handled as the mailbox's bytes, without a ``Message``, a telegram header object,
    an answer object and their encodes, and the answer kept in one slot instead of an
    object per request; 58 before it; 61 on 2026-12-03 with the request taken by the
    turn in C and handed to ``HostSdo.native_request``, branch sdoc: no Python turn of the
    loop, no mailbox message decoded and dispatched by it; 104 before, on 2026-12-03 after
    the merge of branch cardmb,
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
    assert per_transfer <= 46, f"{per_transfer:.1f} Python calls per transfer in the loop"


def test_an_expedited_upload_takes_no_cpython_lock_and_two_clock_readings_in_the_card(
        simulated_card: SimulatedCard) -> None:
    """The card's own code on an expedited upload's path takes no CPython thread lock and
    reads the clock twice (the request's time stamp, the transfer's deadline); the turn in C
    leaves the process image's lock alone for a message that is not COM_Shared_Memory.
    CPython 3.11's thread lock reads the monotonic clock on every acquire, and inside
    User-Mode Linux (no vDSO) each reading is a system call of about 30 us (issue 22's
    vcan 309-3 target). Before (355b700): 4.0 acquires (the SDO channel, the lent response
    identifier twice, the controller's dispatch of the answer) and 4 readings (the deadline
    twice, the frame tap per frame), and the turn in C took the image's lock (an RLock) and
    its turn's lock (a CPython lock) on every request.
    Counted with a profile function on the device loop's thread, where with ``--simulate``
    the whole transfer runs, the node's answer too."""
    card = simulated_card
    image_lock = CountingLock()
    card.device.plc.image.lock = image_lock  # type: ignore[assignment]
    for _ in range(50):
        assert upload_1000h(card.board) == GENERIC_DEVICE_TYPE
    transfers = 300
    card.loop_calls.on = image_lock.on = True
    try:
        for _ in range(transfers):
            assert upload_1000h(card.board) == GENERIC_DEVICE_TYPE
    finally:
        card.loop_calls.on = image_lock.on = False
    calls = card.loop_calls
    assert calls.locks <= 0.05 * transfers, f"{calls.locks / transfers:.2f} lock acquires"
    assert calls.clocks <= 2.05 * transfers, f"{calls.clocks / transfers:.2f} clock readings"
    assert image_lock.acquires <= 0.05 * transfers, (
        f"{image_lock.acquires / transfers:.2f} acquires of the process image's lock")


def test_an_expedited_upload_costs_the_host_few_python_calls(
        simulated_card: SimulatedCard) -> None:
    """The host's side of the same transfer, ``Board.transact``: at most 31 Python calls
    (28 on 2026-12-04, branch hostsdo; 40 before: DevPutMessage and DevGetMessage with
    their board look-up, the transaction lock's ``enter`` and ``leave`` inside the session,
    ``_take_message`` below DevGetMessage, the ring's ``change_dev_flags`` →
    ``ring_device`` → ``_send`` → ``sendto`` now one C call; 58 before branch sdo08). The
    host's CPU is half the transfer's on the machine of issue 22, and the Python driver is
    the benchmark's host."""
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
    assert per_transfer <= 31, f"{per_transfer:.1f} Python calls per transfer in the host"


@pytest.fixture
def two_cards(tmp_path: Path) -> Iterator[tuple[SimulatedCard, SimulatedCard]]:
    """Board 0 with the turn in C (the default), board 1 with every turn in Python, each
    beside its own simulated node 1, configured alike."""
    with _simulated_card(tmp_path, 0) as native, \
            _simulated_card(tmp_path, 1, native=False) as python:
        yield native, python


SDO_TELEGRAMS = st.builds(
    lambda adr, index, sub, cnt, data_type, function, payload: TelegramHeader(
        adr, 0, index, sub, len(payload) if cnt is None else cnt, data_type, function,
        payload).encode(),
    st.sampled_from([1, 1, 1, 1, 1, 0, 2, 128, 255]),
    st.sampled_from([0x1000, 0x1000, 0x1018, 0x1800, 0x6200, 0x6000, 0x2000, 0xFFFF]),
    st.sampled_from([0, 0, 1, 2, 4, 255]), st.one_of(st.none(), st.integers(0, 255)),
    st.sampled_from([0, 5, 6, 7]), st.sampled_from([1, 1, 2, 2, 0, 3, 255]),
    st.binary(max_size=6))
"""COM_SDO_Up_Download's telegram: reads and writes of objects that exist, are read-only,
write-only or missing, other nodes, bad functions and counts that disagree with the data."""


@settings(max_examples=120, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.one_of(SDO_TELEGRAMS, st.binary(max_size=10)), nr=st.integers(0, 255),
       tx=st.sampled_from([Task.USER, 0, 255]), e=st.sampled_from([0, 0, 0, 4, 8, 12]))
def test_the_turn_in_c_answers_host_sdo_as_the_python_turn(
        two_cards: tuple[SimulatedCard, SimulatedCard], data: bytes, nr: int, tx: int,
        e: int) -> None:
    """Valid and malformed COM_SDO_Up_Download requests get the same answer bytes (header,
    msg.f, data, SDO abort codes) and leave the same HostFlags from the card whose turn in C
    takes them as from the card that takes every message in its Python turn; msg.e 4 (a long
    upload, a long download's first part) is the turn in C's too, 8 and 0x0C (later parts)
    stay on the Python turn in both. Node 2 does not
    exist: its transfers end by the time-out, in the CAN master's thread (an answer posted
    after the call, while the turn in C goes on serving)."""
    request = Message(rx=Task.CAN, tx=tx, b=COM_SDO_UP_DOWNLOAD, nr=nr, e=e, data=data)
    answers = []
    for card in two_cards:
        assert DevPutMessage(card.board.number, request, 1000) == 0
        rc, answer = DevGetMessage(card.board.number, MSG_BUFFER_SIZE, 2000)
        answers.append((rc, answer.encode() if answer is not None else None))
    assert answers[0] == answers[1]
    native, python = two_cards
    assert native.device.mm[HOST_FLAGS] == python.device.mm[HOST_FLAGS]


def test_expedited_transfers_take_no_python_turn(
        two_cards: tuple[SimulatedCard, SimulatedCard]) -> None:
    """A host's expedited uploads and downloads in a row are taken by the turn in C (its
    count grows by about one per transfer), each with the right answer; on the old code
    every host SDO request took the device loop's Python turn and the count stayed 0."""
    native = two_cards[0]
    transfers = 200
    before = native.device.native_turns
    for n in range(transfers):
        if n % 2:
            write = TelegramHeader(1, 0, 0x6200, 1, 1, 0, Tfc.WRITE, bytes([n & 0xFF]))
            answer = native.board.transact(Message(rx=Task.CAN, tx=Task.USER,
                                                   b=COM_SDO_UP_DOWNLOAD, data=write.encode()))
            assert answer.f == 0 and answer.data[:8] == TelegramHeader(
                1, 0, 0x6200, 1, 0, 0, Tfc.WRITE).encode()
        else:
            assert upload_1000h(native.board) == GENERIC_DEVICE_TYPE
    native.device.bell.ring_self()  # the turn in C returns and counts what it served
    wait_until(lambda: native.device.native_turns - before >= transfers * 0.9,
               what="the turns in C")


@pytest.fixture
def two_domain_cards(tmp_path: Path) -> Iterator[tuple[SimulatedCard, SimulatedCard]]:
    """As ``two_cards``, node 1 with a DOMAIN at 2000h (``DOMAIN_NETWORK``)."""
    with _simulated_card(tmp_path, 0, text=DOMAIN_NETWORK) as native, \
            _simulated_card(tmp_path, 1, native=False, text=DOMAIN_NETWORK) as python:
        yield native, python


def sdo(card: SimulatedCard, head: TelegramHeader, e: int, nr: int) -> list[bytes]:
    """The answers to one COM_SDO_Up_Download with msg.e ``e``, as bytes: up to the one whose
    msg.e ends a long upload's sequence (0, or 0x0C)."""
    request = Message(rx=Task.CAN, tx=Task.USER, b=COM_SDO_UP_DOWNLOAD, nr=nr, e=e,
                      data=head.encode())
    assert DevPutMessage(card.board.number, request, 1000) == 0
    answers: list[bytes] = []
    while not answers or answers[-1][7] == Ext.FIRST or answers[-1][7] == Ext.CONT:
        rc, answer = DevGetMessage(card.board.number, MSG_BUFFER_SIZE, 2000)
        assert rc == 0 and answer is not None
        answers.append(answer.encode())
    return answers


def test_long_uploads_are_taken_by_the_turn_in_c_as_by_the_python_turn(
        two_domain_cards: tuple[SimulatedCard, SimulatedCard]) -> None:
    """COM_SDO_Up_Download with msg.e 4 (a long upload's request) is taken by the turn in C:
    a value that fits one message gets its one answer from that turn, the short form's
    (msg.e 0), in a row of uploads each served there; a longer one its parts (msg.e 4, then
    0x0C), posted in order; both byte for byte the card's whose every turn is Python's
    (docs/card-commands.md). Before, every msg.e 4 request took the Python turn (the turns
    in C did not grow), so the 309 gateway asked its reads with msg.e 0 and again with 4
    after an f 51."""
    native, python = two_domain_cards
    device_type = TelegramHeader(1, 0, 0x1000, 0, 0, 0, Tfc.READ)
    short = sdo(python, device_type, 0, 7)  # the short form's answer
    uploads = 100
    before = native.device.native_turns
    for _ in range(uploads):
        assert sdo(native, device_type, Ext.FIRST, 7) == short

    def served() -> bool:
        # the turn in C counts what it served when it returns, which a ring makes it do
        # (again: a ring that came while the loop's Python turn ran went to that turn)
        native.device.bell.ring_self()
        return native.device.native_turns - before >= uploads * 0.9

    wait_until(served, what="the turns in C")
    assert sdo(python, device_type, Ext.FIRST, 7) == short
    value = bytes(range(256)) + bytes(44)  # 300 bytes: parts of 247 and 53
    for card in two_domain_cards:  # the value, by a long download (its first part in C)
        first = TelegramHeader(1, 0, DOMAIN, 0, 247, 0, Tfc.WRITE, value[:247])
        last = TelegramHeader(1, 0, DOMAIN, 0, 53, 0, Tfc.WRITE, value[247:])
        assert Message.decode(sdo(card, first, Ext.FIRST, 1)[0]).f == 0
        assert Message.decode(sdo(card, last, Ext.LAST, 2)[0]).f == 0
    domain = TelegramHeader(1, 0, DOMAIN, 0, 0, 0, Tfc.READ)
    for nr in range(10):
        answers = [sdo(card, domain, Ext.FIRST, nr) for card in two_domain_cards]
        assert answers[0] == answers[1]
        parts = [Message.decode(answer) for answer in answers[0]]
        assert [(part.f, part.e) for part in parts] == [(0, Ext.FIRST), (0, Ext.LAST)]
        assert parts[0].data[8:] + parts[1].data[8:] == value
