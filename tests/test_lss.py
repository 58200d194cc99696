"""CiA 305 LSS through the card: the host's LSS master against simulated LSS slaves.

Each test starts ``cifemu firmware --simulate NETWORK.toml``; the master on the host reaches
the slaves only through the card's layer-2 access (COM_CfgRx_Layer2, COM_Tx_CAN_Layer2 and
the COM_Rx_CAN_Layer2 indications). The master waits TIMEOUT_S for an answer it expects,
and SILENCE_S where no slave may answer (``expect_silence``): most tests check such a
silence somewhere, and waited 1 s for each.
"""

from __future__ import annotations

import queue
import struct
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import partial
from pathlib import Path

import pytest

from dbm_tools.network import GENERIC_PRODUCT_CODE, GENERIC_VENDOR_ID, parse_network
from dpm.cia305 import CONFIGURATION, UNCONFIGURED, WAITING, LssAddress
from dpm.commands import COM_CFGRX_LAYER2, COM_RX_CAN_LAYER2, COM_SDO_UP_DOWNLOAD, COM_TX_CAN_LAYER2
from dpm.message import Message, Task
from firmware.sim.generic import GENERIC_REVISION
from host_api.board import Board, CifError
from host_api.cia309.lss import LssError, LssErrorCode, LssMaster
from host_api.online import configure_online
from tests.conftest import Card, LoadDeadline, start_card, taken, wait_until

SLAVES = [LssAddress(0x1234, 2, 3, 1), LssAddress(0x1234, 2, 3, 2), LssAddress(0x1234, 2, 5, 4)]
NETWORK = "[[node]]\nid = 5\n" + "".join(
    f"[[node]]\nid = 255\nlss = {{ vendor = {a.vendor}, product = {a.product}, "
    f"revision = {a.revision}, serial = {a.serial} }}\n" for a in SLAVES)
NODE_5 = LssAddress(GENERIC_VENDOR_ID, GENERIC_PRODUCT_CODE, GENERIC_REVISION, 5)
"""The generic module's 1018h: its LSS address."""
TIMEOUT_S = 1.0
"""How long a confirmed LSS service waits for its answer. It ends every expected answer on
that answer and costs its full length only in the tests of silence; 0.3 s lost a slave's
answer with two busy processes beside the suite."""
SILENCE_S = 0.3
"""How long a service that no slave may answer listens for an answer. A right slave never
answers, so the length costs only time: a wrong answer comes within milliseconds, and only
one a loaded machine delays past 0.3 s (answers came later than that with two busy processes
beside the suite) would go unseen in that run."""


class Rig:
    """A card with simulated LSS slaves, opened as a ``Board``, and an LSS master on it."""

    def __init__(self, card: Card, board: Board) -> None:
        self.card = card
        self.board = board
        self.lss = LssMaster(board, timeout=TIMEOUT_S)

    def layer2(self, frames: bytes) -> None:
        """Raw layer-2 frames from the host (NMT, for one)."""
        self.board.put_message(Message(rx=Task.CAN, tx=Task.USER, b=COM_TX_CAN_LAYER2, data=frames))

    def listen(self, cob_id: int) -> None:
        answer = self.board.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_CFGRX_LAYER2,
                                             data=bytes([cob_id & 0xFF, cob_id >> 8])))
        assert answer.f == 0

    def frames_on(self, cob_id: int, timeout: float = 5.0) -> bytes:
        """The data of the next layer-2 frame received on ``cob_id``."""
        deadline = LoadDeadline(timeout)
        while deadline.left() > 0:
            try:
                msg = self.board.get_message(100)
            except CifError:
                continue
            d = msg.data
            if msg.b == COM_RX_CAN_LAYER2 and (d[0] << 3 | d[1] >> 5) == cob_id:
                return bytes(d[2 : 2 + (d[1] & 0x0F)])
        pytest.fail(f"no frame on {cob_id:#x} within {timeout} s")

    def sdo_read(self, node: int, index: int, sub: int) -> int:
        head = struct.pack("<BBHBBBB", node, 0, index, sub, 0, 0, 1)
        answer = self.board.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_SDO_UP_DOWNLOAD,
                                             data=head))
        assert answer.f == 0, f"SDO read of node {node}: msg.f {answer.f}"
        return int.from_bytes(answer.data[8:], "little")


@pytest.fixture
def make_rig(tmp_path: Path) -> Iterator[Callable[..., Rig]]:
    opened: list[Rig] = []

    def make(toml: str = NETWORK) -> Rig:
        path = tmp_path / "network.toml"
        path.write_text(toml)
        card = start_card(tmp_path, 0, "--simulate", str(path))
        rig = Rig(card, Board(0, tmp_path, timeout=5000).open())
        opened.append(rig)
        return rig

    yield make
    for rig in opened:
        rig.board.close()
        rig.card.stop()


@contextmanager
def expect_silence(lss: LssMaster) -> Iterator[None]:
    """The services inside get no answer from any slave: the master listens SILENCE_S."""
    lss.timeout = SILENCE_S
    try:
        yield
    finally:
        lss.timeout = TIMEOUT_S


def lss_error(call: Callable[[], object]) -> LssError:
    with pytest.raises(LssError) as caught:
        call()
    return caught.value


# --- the single services -----------------------------------------------------------------


def test_selected_slave_inquiry_and_configure_errors(make_rig: Callable[..., Rig]) -> None:
    lss = make_rig().lss
    lss.switch_state_selective(*SLAVES[2])
    assert lss.inquire_address() == SLAVES[2]
    assert lss.inquire_lss_number(3) == SLAVES[2].serial
    assert lss.inquire_node_id() == UNCONFIGURED
    for bad in (0, 128):  # CiA 305 error code 1: node-ID out of range -> 309-3 502
        error = lss_error(partial(lss.configure_node_id, bad))
        assert (error.code, error.lss_error) == (LssErrorCode.NODE_ID_NOT_SUPPORTED, 1)
    for table, index in ((0, 5), (0, 9), (1, 2)):  # reserved, automatic, another table
        error = lss_error(partial(lss.configure_bit_timing, table, index))
        assert (error.code, error.lss_error) == (LssErrorCode.BIT_RATE_NOT_SUPPORTED, 1)
    lss.configure_node_id(40)
    lss.configure_bit_timing(0, 3)
    lss.store_configuration()
    assert lss.inquire_node_id() == UNCONFIGURED  # pending until the slave starts up
    lss.switch_state_global(WAITING)
    with expect_silence(lss):
        error = lss_error(lss.inquire_node_id)  # nobody in configuration state any more
        assert (error.code, error.lss_error) == (LssErrorCode.TIME_OUT, None)
        assert lss_error(lss.store_configuration).code == LssErrorCode.TIME_OUT


def test_wrong_address_selects_nobody(make_rig: Callable[..., Rig]) -> None:
    lss = make_rig().lss
    wrong = SLAVES[0]._replace(serial=99)
    with expect_silence(lss):
        assert (lss_error(partial(lss.switch_state_selective, *wrong)).code
                == LssErrorCode.TIME_OUT)
        assert lss_error(lss.inquire_address).code == LssErrorCode.TIME_OUT


def test_switch_global_configures_every_slave(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig("[[node]]\nid = 255\n"
                   "lss = { vendor = 0x1234, product = 2, revision = 3, serial = 1 }\n")
    rig.lss.switch_state_global(CONFIGURATION)
    assert rig.lss.inquire_address() == SLAVES[0]
    rig.lss.configure_node_id(9)
    rig.listen(0x709)
    rig.lss.switch_state_global(WAITING)  # CiA 305: it starts up under its new node-ID
    assert rig.frames_on(0x709) == b"\x00"


def test_configured_node_answers_from_1018_and_moves_at_reset(
        make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    lss = rig.lss
    lss.switch_state_selective(*NODE_5)
    assert lss.inquire_address() == NODE_5
    assert lss.inquire_node_id() == 5
    lss.configure_node_id(20)
    lss.switch_state_global(WAITING)
    rig.listen(0x714)
    rig.layer2(bytes([0x00, 0x02, 0x82, 5]))  # NMT reset communication of node 5
    assert rig.frames_on(0x714) == b"\x00"  # boot-up under node-ID 20
    lss.switch_state_selective(*NODE_5)  # same device, same LSS address
    assert lss.inquire_node_id() == 20


def test_identify_remote_and_non_configured(make_rig: Callable[..., Rig]) -> None:
    lss = make_rig().lss
    assert lss.identify_remote_slave(0x1234, 2, 3, 3, 0, 1)  # revision 3, serial 1
    assert lss.identify_remote_slave(0x1234, 2, 4, 0xFFFF_FFFF, 4, 4)  # the revision-5 one
    with expect_silence(lss):
        assert not lss.identify_remote_slave(0x1234, 2, 6, 9, 0, 0xFFFF_FFFF)
        assert not lss.identify_remote_slave(0x1235, 2, 0, 9, 0, 9)
    assert lss.identify_remote_slave(NODE_5.vendor, NODE_5.product, 0, 0xFFFF_FFFF, 5, 5)
    assert lss.identify_non_configured_slave()
    lss.complete_node_id_configuration(start_id=10)
    with expect_silence(lss):
        assert not lss.identify_non_configured_slave()


def test_bit_timing_switch_delay_silences_the_slave(make_rig: Callable[..., Rig]) -> None:
    lss = make_rig().lss
    lss.switch_state_selective(*SLAVES[0])
    lss.configure_bit_timing(0, 2)  # 500 kbit/s
    start = time.monotonic()
    lss.activate_bit_timing(300)
    with expect_silence(lss):
        assert lss_error(lss.inquire_node_id).code == LssErrorCode.TIME_OUT

    def answers() -> bool:
        try:
            return lss.inquire_node_id() == UNCONFIGURED
        except LssError:
            return False

    wait_until(answers, 5, "the slave after twice the switch delay")
    assert time.monotonic() - start >= 0.6


def test_card_that_does_not_answer_is_a_media_error(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    rig.board.timeout = 300
    rig.card.freeze()
    try:
        assert lss_error(rig.lss.identify_non_configured_slave).code == LssErrorCode.MEDIA_ERROR
    finally:
        rig.card.thaw()


# --- fastscan and the composite services --------------------------------------------------


def test_fastscan_finds_the_unconfigured_slaves_lowest_first(
        make_rig: Callable[..., Rig]) -> None:
    lss = make_rig().lss
    found = lss.fastscan()
    assert found == min(SLAVES)  # zero bits are tried first
    assert lss.inquire_address() == found  # and it is selected
    lss.configure_node_id(30)
    lss.switch_state_global(WAITING)  # it starts up: no longer unconfigured
    assert lss.fastscan(vendor=0x1234, product=2) == SLAVES[1]  # known numbers: confirmed
    lss.switch_state_global(WAITING)
    assert lss.fastscan(vendor=0x9999) is None
    assert lss.fastscan_step(0, 0x80, 0, 0)  # 309-1 4.8.12 itself: the reset step


def test_fastscan_reads_no_late_answer_as_a_1_bit(make_rig: Callable[..., Rig]) -> None:
    """Every bit step's answer comes after the single-step wait when that wait is 0 s, as a
    loaded machine made some come after 50 ms: each read as a 1-bit and then as the next
    step's answer, the scans' confirmations failed (LssError 103 after three scans) or gave
    a wrong address. The scan waits for the answer to the marker behind each step instead."""
    rig = make_rig()
    lss = LssMaster(rig.board, timeout=TIMEOUT_S, scan_timeout=0.0)
    assert lss.fastscan() == min(SLAVES)
    assert lss.inquire_address() == min(SLAVES)
    lss.switch_state_global(WAITING)


class LateDuplicates:
    """The card's layer-2 indications, one frame each, with every marker answer (50h) but
    the first of each step held back ``HELD_S``: the duplicates of several slaves' answers
    coming later than the master's settle window, as a loaded machine delivered them.

    A stand-in for the card's indications (LssMaster's ``indications``) because the real
    card and its simulated slaves answer within 2 ms on a quiet machine, and a loaded one
    holds answers back only now and then; the frames themselves are the card's.
    """

    HELD_S = 0.01

    def __init__(self, board: Board, slaves: int) -> None:
        self.board = board
        self.slaves = slaves
        self.markers = 0
        self.frames: list[tuple[float, Message]] = []
        """(when it may be read, a one-frame indication), in the order they go out."""

    def __call__(self, timeout: float) -> Message | None:
        deadline = time.monotonic() + timeout
        while True:
            now = time.monotonic()
            if self.frames and self.frames[0][0] <= now:
                return self.frames.pop(0)[1]
            until = min(deadline, self.frames[0][0]) if self.frames else deadline
            try:
                msg = self.board.get_message(max(0, int((until - now) * 1000)))
            except CifError:
                if time.monotonic() >= deadline:
                    return None
                continue
            self._split(msg)

    def _split(self, msg: Message) -> None:
        now, d, at = time.monotonic(), msg.data, 0
        if msg.b != COM_RX_CAN_LAYER2:
            self.frames.append((now, msg))
            return
        while at + 2 <= len(d):
            size = 0 if d[at + 1] & 0x10 else min(d[at + 1] & 0x0F, 8)
            frame = Message(rx=msg.rx, tx=msg.tx, b=msg.b, data=bytes(d[at : at + 2 + size]))
            held = size == 8 and d[at + 2] == 0x50 and self.markers % self.slaves != 0
            self.markers += size == 8 and d[at + 2] == 0x50
            self.frames.append((now + self.HELD_S * held, frame))
            self.frames.sort(key=lambda pair: pair[0])  # stable: equal times keep order
            at += 2 + size


def test_fastscan_counts_the_slaves_when_their_duplicates_come_late(
        make_rig: Callable[..., Rig]) -> None:
    """Each duplicate marker answer comes 10 ms after the first, later than the 2 ms the
    master first waits for duplicates: the first scan reads wrong bits, the next counts the
    slaves from every marker answer and waits for all of them at each step. The master of
    eee042b waited 2 ms at every step in all three scans and raised LssError 103."""
    rig = make_rig()
    lss = LssMaster(rig.board, indications=LateDuplicates(rig.board, len(SLAVES)),
                    timeout=TIMEOUT_S)
    assert lss.fastscan() == min(SLAVES)
    assert lss.inquire_address() == min(SLAVES)
    lss.switch_state_global(WAITING)


def test_fastscan_without_unconfigured_slaves(make_rig: Callable[..., Rig]) -> None:
    lss = make_rig("[[node]]\nid = 5\n").lss
    with expect_silence(lss):  # not even fastscan's reset step is answered
        assert lss.fastscan() is None
        assert not lss.identify_non_configured_slave()


def test_assign_node_id_to_lss_address(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    rig.listen(0x70C)
    rig.lss.assign_node_id(SLAVES[2], 12)
    assert rig.frames_on(0x70C) == b"\x00"  # stored, and started up under node-ID 12
    with expect_silence(rig.lss):  # nobody has the address: its selection is not answered
        error = lss_error(partial(rig.lss.assign_node_id, SLAVES[2]._replace(serial=7), 13))
    assert error.code == LssErrorCode.TIME_OUT


def test_complete_configuration_then_the_card_runs_the_nodes(
        make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    assigned = rig.lss.complete_node_id_configuration(start_id=2, exclude=[3, 5])
    assert assigned == [(SLAVES[0], 2), (SLAVES[1], 4), (SLAVES[2], 6)]
    assert rig.lss.fastscan() is None
    ids = [2, 4, 5, 6]
    configure_online(rig.board, parse_network("".join(f"[[node]]\nid = {n}\n" for n in ids)))
    wait_until(lambda: rig.board.diagnostics().operating() == ids, 10,
               "the LSS-configured nodes in data exchange")
    for address, node_id in assigned:
        assert rig.sdo_read(node_id, 0x1018, 4) == address.serial


def test_shared_mailbox_reader_feeds_the_master(make_rig: Callable[..., Rig]) -> None:
    """As the 309 gateway does: one thread reads the mailbox, the master gets its share."""
    rig = make_rig()
    indications: queue.Queue[Message] = queue.Queue()
    answers: queue.Queue[Message] = queue.Queue()
    stop = threading.Event()

    def reader() -> None:
        while not stop.is_set():
            try:
                msg = rig.board.get_message(50)
            except CifError:
                continue
            (indications if msg.b == COM_RX_CAN_LAYER2 else answers).put(msg)

    def next_indication(timeout: float) -> Message | None:
        try:
            return indications.get(timeout=timeout) if timeout > 0 else indications.get_nowait()
        except queue.Empty:
            return None

    def transact(msg: Message) -> Message:
        rig.board.put_message(msg)
        return taken(answers, 5)

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    try:
        lss = LssMaster(rig.board, next_indication, transact, timeout=TIMEOUT_S)
        assert lss.fastscan() == SLAVES[0]
        assert lss.inquire_address() == SLAVES[0]
        lss.switch_state_global(WAITING)
    finally:
        stop.set()
        thread.join()
