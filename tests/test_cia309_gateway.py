"""The CiA 309-1 service layer against simulated nodes: real firmware processes, no mocks.

The driver serves one image directory per process, so every card of this module lives in one
directory: board 0 runs the main network (node 1 a generic I/O module, node 2 the device of
``tests/data/cia309_node.eds`` with one object of each data type and a DOMAIN at 2000h, node 3
generic for the faults a test provokes, node 9 on the bus but not configured in the card);
board 1 is a card without configuration (network 2); boards 2 and 3 are started by single
tests (faults injected at power-on; store, restore, initialise, controller).
"""

from __future__ import annotations

import operator
import os
import queue
import struct
import threading
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path

import pytest

from dpm.com import CanFrame
from dpm.commands import AREA_BUS, COM_UPLOAD, MAX_LEN_DATA_UNIT
from dpm.ledger import ledger_text
from dpm.message import Message, Task
from dpm.task2 import CanState
from firmware.can.sdo import DEFAULT_SDO_TIMEOUT
from host_api.cia309.gateway import VENDOR_ID, Gateway, SdoUploadInFlight
from host_api.cia309.model import (
    ALL_NODES,
    MAX_COMMAND_SIZE,
    BootUpEvent,
    Cia309Error,
    DataType,
    EmergencyEvent,
    ErrorCode,
    ErrorControlEvent,
    Event,
    NmtState,
    PdoMapping,
    RpdoEvent,
    SdoProgressEvent,
    decode_value,
)
from host_api.registry import MappedBoard, registry
from tests.conftest import ended, expect, silent, wait_until, within
from tests.gateway_cards import EDS, diagnostics, start, wait_operating

MAIN = f'[[node]]\nid = 1\n[[node]]\nid = 2\neds = "{EDS}"\n[[node]]\nid = 3\n[[node]]\nid = 9\n'


def reason(call: Callable[[], object]) -> Cia309Error:
    """The Cia309Error ``call`` raises."""
    with pytest.raises(Cia309Error) as failure:
        call()
    return failure.value


@pytest.fixture(scope="module")
def directory(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("cia309")


@pytest.fixture(scope="module")
def main(directory: Path) -> Iterator[Gateway]:
    """Networks 1 (board 0, simulated and configured) and 2 (board 1, no configuration)."""
    cards = [start(directory, 0, MAIN), start(directory, 1, None)]
    try:
        with Gateway([0, 1], directory) as gateway:
            wait_operating(0, [1, 2, 3])
            yield gateway
    finally:
        for card in cards:
            card.stop()


@pytest.fixture
def gw(main: Gateway) -> Gateway:
    """A fresh session on network 1: defaults of its own, no default node yet."""
    session = main.session()
    session.set_default_network(1)
    return session


def is_error(node: int, error: ErrorCode) -> Callable[[Event], bool]:
    return lambda e: isinstance(e, ErrorControlEvent) and e.node == node and e.error == error


# --- 4.1 SDO ----------------------------------------------------------------------------------

VALUES: list[tuple[int, DataType, object]] = [
    (0x2001, DataType.BOOLEAN, 1),
    (0x2002, DataType.INTEGER8, -100),
    (0x2003, DataType.INTEGER16, -30000),
    (0x2004, DataType.INTEGER32, -2_000_000_000),
    (0x2005, DataType.UNSIGNED8, 200),
    (0x2006, DataType.UNSIGNED16, 65000),
    (0x2007, DataType.UNSIGNED32, 4_000_000_000),
    (0x2008, DataType.REAL32, 1.5),
    (0x2009, DataType.VISIBLE_STRING, "hello 309"),
    (0x200A, DataType.OCTET_STRING, b"\x00\x01\xfe\xff"),
    (0x200B, DataType.UNICODE_STRING, "\u00e4b"),
    (0x200C, DataType.TIME_OF_DAY, (14000, 43_200_000)),
    (0x200D, DataType.TIME_DIFFERENCE, (1, 500)),
    (0x2011, DataType.REAL64, -2.25),
    (0x2015, DataType.INTEGER64, -(1 << 62)),
    (0x201B, DataType.UNSIGNED64, (1 << 64) - 1),
    (0x2000, DataType.DOMAIN, b"a short domain"),
]


def test_sdo_every_data_type(gw: Gateway) -> None:
    gw.sdo_download(0x2001, 0, 0, node_id=2, data_type=DataType.BOOLEAN)  # node 2: the default
    for index, dtype, value in VALUES:
        gw.sdo_download(index, 0, value, data_type=dtype)  # type: ignore[arg-type]
        assert decode_value(dtype, gw.sdo_upload(index, 0)) == value, dtype
    identity = gw.extended_sdo_upload(0x1018)
    assert identity[0] == b"\x04" and struct.unpack("<I", identity[1])[0] == 0x1234
    assert sorted(identity) == [0, 1, 2, 3, 4]


def test_sdo_offset_and_length(gw: Gateway) -> None:
    vs = DataType.VISIBLE_STRING
    gw.sdo_download(0x2009, 0, "abcdef", node_id=2, data_type=vs)
    gw.sdo_download(0x2009, 0, "XY", data_type=vs, offset=2)
    assert gw.sdo_upload(0x2009, 0) == b"abXYef"
    assert gw.sdo_upload(0x2009, 0, data_type=vs, offset=1, length=3) == b"bXY"
    gw.sdo_download(0x2009, 0, b"tail", offset=8)  # past the end: the gap is zeros
    assert gw.sdo_upload(0x2009, 0) == b"abXYef\0\0tail"
    assert reason(lambda: gw.sdo_upload(0x2006, 0, data_type=DataType.UNSIGNED16,
                                        offset=1)).error == ErrorCode.SYNTAX_ERROR
    assert reason(lambda: gw.sdo_download(0x2009, 0, b"abc", length=2)).error == 101


def test_domain_of_64_kib_round_trip_with_progress(gw: Gateway, main: Gateway) -> None:
    data = os.urandom(65536)
    other = main.session()
    other.set_default_network(1)
    failures: list[BaseException] = []

    def download() -> None:
        try:
            gw.sdo_download(0x2000, 0, data, node_id=2, data_type=DataType.DOMAIN)
        except BaseException as exc:  # the test thread reports it
            failures.append(exc)

    with gw.events() as stream:
        writer = threading.Thread(target=download)
        writer.start()
        first = expect(stream, lambda e: isinstance(e, SdoProgressEvent), 10)
        assert first == SdoProgressEvent(1, 2, False, 247)
        # Another session's transfer to the node waits its turn instead of failing (f 54).
        assert other.sdo_upload(0x1018, 1, node_id=2) == struct.pack("<I", 0x1234)
        assert ended(writer, 30), "the download did not end"
        assert not failures
        assert gw.sdo_upload(0x2000, 0) == data
        expect(stream, lambda e: e == SdoProgressEvent(1, 2, False, 65536), 5)
        expect(stream, lambda e: e == SdoProgressEvent(1, 2, True, 247), 5)
        expect(stream, lambda e: e == SdoProgressEvent(1, 2, True, 65536), 5)
    too_long = reason(lambda: gw.sdo_download(0x2000, 0, bytes(65537)))
    assert too_long.error == ErrorCode.OUT_OF_MEMORY


def test_sdo_failures(gw: Gateway, main: Gateway) -> None:
    assert reason(lambda: gw.sdo_upload(0x1000, 0)).error == ErrorCode.NO_DEFAULT_NODE
    assert reason(lambda: gw.sdo_upload(0x2345, 0, node_id=2)).abort_code == 0x06020000
    wrong = reason(lambda: gw.sdo_download(0x2006, 0, b"\x01"))  # 1 byte into a u16
    assert wrong.abort_code == 0x06070010
    assert reason(lambda: gw.sdo_upload(0x1000, 0, network=3)).error == 106
    assert reason(lambda: gw.sdo_upload(0x1000, 0, node_id=0)).error == 107
    assert reason(lambda: gw.sdo_upload(0x1000, 0, node_id=128)).error == 107
    unconfigured = reason(lambda: gw.sdo_upload(0x1000, 0, network=2, node_id=1))
    assert (unconfigured.error, unconfigured.f) == (ErrorCode.INTERNAL_STATE, 200)
    assert reason(lambda: gw.sdo_download(0x2006, 0, 70000, data_type=DataType.UNSIGNED16)
                  ).error == ErrorCode.SYNTAX_ERROR
    assert reason(lambda: gw.sdo_download(0x2006, 0, 5)).error == 101  # a value needs a type
    fresh = main.session()
    assert reason(lambda: fresh.sdo_upload(0x1000, 0, node_id=1)).error == 104  # two networks


def test_sdo_time_outs(gw: Gateway) -> None:
    gw.configure_sdo_timeout(50)
    try:
        started = time.monotonic()
        absent = reason(lambda: gw.sdo_upload(0x1000, 0, node_id=42))
        assert (absent.error, absent.f) == (ErrorCode.TIME_OUT, 17)
        assert time.monotonic() - started < 0.25
    finally:
        gw.configure_sdo_timeout(300)
    assert reason(lambda: gw.configure_sdo_timeout(0)).error == ErrorCode.SYNTAX_ERROR
    gw.set_command_timeout(20)
    started = time.monotonic()
    assert reason(lambda: gw.sdo_upload(0x1000, 0, node_id=42)).error == 103  # ours, not f 17
    assert time.monotonic() - started < 0.2
    gw.set_command_timeout(0)
    assert gw.sdo_upload(0x1000, 0, node_id=1) == struct.pack("<I", 0x000F0191)
    gw.set_command_size(MAX_COMMAND_SIZE)
    assert reason(lambda: gw.set_command_size(MAX_COMMAND_SIZE + 1)).error == 600


def test_sdo_upload_sent_without_waiting(gw: Gateway) -> None:
    """``try_sdo_upload`` (the 309-3 server's event loop): the answer is announced from the
    mailbox reader; a second transfer to a node whose transfer runs is not sent (the caller
    then blocks in a thread instead); one given up on frees the node's channel at once."""
    done = [threading.Event() for _ in range(3)]
    flight = gw.try_sdo_upload(0x1000, 0, done[0].set, node_id=1)
    assert flight is not None
    assert within(done[0].wait, 5)
    assert flight.result() == struct.pack("<I", 0x000F0191)
    # A transfer to node 42 that an earlier test gave up on may still run in the card, which
    # then refuses the next one at once (f 54: 102): wait for one that runs its whole time.
    wait_until(lambda: reason(lambda: gw.sdo_upload(0x1000, 0, node_id=42)).error
               == ErrorCode.TIME_OUT, 5, "node 42's earlier transfer over")
    # The card's own SDO time-out (0.5 s by default) must outlast the two calls below: a
    # test beside busy processes can be held that long between them.
    gw.configure_sdo_timeout(3000)
    try:
        absent = gw.try_sdo_upload(0x1000, 0, lambda: None, node_id=42)  # not on the bus
        assert absent is not None
        assert gw.try_sdo_upload(0x1000, 0, lambda: None, node_id=42) is None
        assert absent.abandon().error == ErrorCode.TIME_OUT
        sent: list[SdoUploadInFlight | None] = []  # None while the card's mailbox is full

        def sent_again() -> bool:
            sent.append(gw.try_sdo_upload(0x1000, 0, done[1].set, node_id=42))
            return sent[-1] is not None

        wait_until(sent_again, 5, "node 42's channel free again")
        again = sent[-1]
        assert again is not None and within(done[1].wait, 10)  # refused (42's runs) or timed out
        assert reason(again.result).error in (ErrorCode.TIME_OUT, ErrorCode.INTERNAL_STATE)
    finally:
        gw.configure_sdo_timeout(int(DEFAULT_SDO_TIMEOUT * 1000))
    wrong: list[SdoUploadInFlight | None] = []

    def sent_to_node_2() -> bool:
        wrong.append(gw.try_sdo_upload(0x2345, 0, done[2].set, node_id=2))
        return wrong[-1] is not None

    wait_until(sent_to_node_2, 5, "the card's mailbox free")
    sent_last = wrong[-1]
    assert sent_last is not None and within(done[2].wait, 5)
    assert reason(sent_last.result).abort_code == 0x06020000


def test_the_mailbox_reader_does_not_poll_after_the_card_rang(gw: Gateway) -> None:
    """A card that rang for its answers needs no fallback look: the reader thread looks at
    the mailbox when rung, and its look without a ring backs off as when nothing happens.
    Before, every ring restarted that look at 5 ms (then 10, 20, 40 ms...): a wake-up and a
    mailbox turn for nothing after each read, one or two per read under User-Mode Linux,
    where reads are 3-10 ms apart (issue 22). The fallback is for a card that does not
    ring this host (one started again)."""
    link = gw._link(1)
    for _ in range(50):  # each read answered after a ring
        assert gw.sdo_upload(0x1000, 0, node_id=1) == struct.pack("<I", 0x000F0191)
    looks = 0
    take = link._take_messages

    def counting(board: MappedBoard | None = None) -> int:
        nonlocal looks
        looks += 1
        return take(board)

    link._take_messages = counting  # type: ignore[method-assign]
    try:
        # Not a wait for a condition: the window in which the looks are counted.
        threading.Event().wait(0.2)
    finally:
        del link._take_messages
    assert looks <= 1, f"{looks} looks within 0.2 s after the last answer"


# --- 4.2 PDO ----------------------------------------------------------------------------------


def test_gateway_pdos_through_a_node(gw: Gateway) -> None:
    """A gateway TPDO drives node 9's outputs, node 9's inputs echo them in its TPDO, which
    the gateway receives as its RPDO (node 9 is not the card's, so its identifiers are free)."""
    u8 = DataType.UNSIGNED8
    gw.configure_rpdo(1, 0x189, 255, [PdoMapping(0x6000, sub, u8) for sub in range(1, 9)])
    gw.configure_tpdo(1, 0x209, 255, [PdoMapping(0x6200, sub, u8) for sub in range(1, 9)],
                      inhibit_time=100)
    with gw.events() as stream:
        gw.start_node(9)
        values = tuple(range(1, 9))
        gw.write_pdo_data(1, values)  # node 9 first reports its zeros as it starts
        expect(stream, lambda e: e == RpdoEvent(1, 1, values), 5)
    assert gw.read_pdo_data(1) == values
    gw.write_pdo_data(1, [2] * 8)
    started = time.monotonic()
    gw.write_pdo_data(1, [3] * 8)  # held back by the inhibit time
    assert time.monotonic() - started > 0.08
    gw.configure_rpdo(1, 0x189, 252, [PdoMapping(0x6000, sub, u8) for sub in range(1, 9)])
    wait_until(lambda: gw.read_pdo_data(1) == (3,) * 8, 5, "the answer to the remote frame")
    # Lely's dummy mappings: a type's CiA 301 index alone.
    gw.configure_rpdo(4, 0x1A0, 255, [PdoMapping(0x0007, 0, None), PdoMapping(0x0006, 0, None)])
    assert gw.read_pdo_data(4) == (0, 0)


def test_pdo_failures(gw: Gateway) -> None:
    u8 = DataType.UNSIGNED8
    one = [PdoMapping(0x6000, 1, u8)]
    gw.configure_rpdo(5, 0x1B0, 255, one)
    assert reason(lambda: gw.configure_rpdo(6, 0x1B0, 255, one)).error == 400  # RPDO 5's
    assert reason(lambda: gw.configure_tpdo(6, 0x1B0, 255, one)).error == 400
    assert reason(lambda: gw.configure_rpdo(6, 0x181, 255, one)).error == 400  # the card's
    nine = [PdoMapping(0x6000, 1, u8)] * 9
    assert reason(lambda: gw.configure_rpdo(6, 0x1B1, 255, nine)).error == 401
    untyped = [PdoMapping(0x6000, 1, None)]
    assert reason(lambda: gw.configure_rpdo(6, 0x1B1, 255, untyped)).error == 101
    assert reason(lambda: gw.configure_rpdo(6, 0x1B1, 241, one)).error == 101
    assert reason(lambda: gw.configure_rpdo(0, 0x1B1, 255, one)).error == 101
    assert reason(lambda: gw.configure_rpdo(6, 0x2000_01B1, 255, one)).error == 100
    assert reason(lambda: gw.read_pdo_data(7)).error == ErrorCode.INTERNAL_STATE
    assert reason(lambda: gw.write_pdo_data(7, [1])).error == ErrorCode.INTERNAL_STATE
    gw.configure_tpdo(5, 0x2B0, 255, [PdoMapping(0x6200, 1, DataType.INTEGER8)])
    assert reason(lambda: gw.write_pdo_data(5, [1, 2])).error == 401
    assert reason(lambda: gw.write_pdo_data(5, [256])).error == 101  # values are raw bytes
    gw.write_pdo_data(5, [-1])
    gw.configure_rpdo(5, 0x8000_01B0, 255, one)  # bit 31: the PDO is gone
    assert reason(lambda: gw.read_pdo_data(5)).error == ErrorCode.INTERNAL_STATE
    gw.configure_rpdo(6, 0x1B0, 255, one)  # and its identifier free again


# --- 4.3 NMT and error control ------------------------------------------------------------------


def test_nmt_services_and_their_events(gw: Gateway) -> None:
    heartbeat = ErrorCode.HEARTBEAT_STARTED
    with gw.events() as stream:
        gw.stop_node(1)
        expect(stream, lambda e: e == ErrorControlEvent(1, 1, NmtState.STOPPED), 5)
        gw.start_node()  # node 1 is the default now
        expect(stream, lambda e: e == ErrorControlEvent(1, 1, NmtState.OPERATIONAL, heartbeat),
                        5)
        gw.set_node_to_preoperational()
        expect(stream, lambda e: e == ErrorControlEvent(1, 1, NmtState.PRE_OPERATIONAL), 5)
        gw.start_node()
        expect(stream, lambda e: e == ErrorControlEvent(1, 1, NmtState.OPERATIONAL, heartbeat),
                        5)
        for reset in (gw.reset_node, gw.reset_communication):
            reset()  # the card boots node 1 again, maybe within one look at Task2State
            expect(stream, lambda e: e == ErrorControlEvent(1, 1, NmtState.OPERATIONAL,
                                                             heartbeat), 10)
        gw.stop_node(ALL_NODES)
        for node in (1, 2, 3):
            expect(stream, partial(operator.eq, ErrorControlEvent(1, node, NmtState.STOPPED)), 5)
        gw.start_node(ALL_NODES)
    wait_operating(0, [1, 2, 3])
    assert gw.default_node_id == 1  # "all" does not become the default
    assert reason(lambda: gw.stop_node(1, network=2)).f == 200
    assert reason(lambda: gw.start_node(200)).error == ErrorCode.UNSUPPORTED_NODE


def test_guarding_and_heartbeat_consumer(gw: Gateway) -> None:
    with gw.events() as stream:
        assert reason(lambda: gw.enable_node_guarding(100, 3, node_id=3)).error == 102
        gw.disable_heartbeat_consumer()
        gw.enable_node_guarding(100, 3)  # the card writes 1017h = 0: the node answers
        # no error control event: the node answers the card's guarding
        silent(stream, lambda e: isinstance(e, ErrorControlEvent) and e.node == 3
               and e.error is not None, 0.5, "an error control event after guarding was enabled")
        gw.sdo_download(0x1017, 0, 100, data_type=DataType.UNSIGNED16)  # heartbeat again:
        expect(stream, is_error(3, ErrorCode.LOST_GUARDING_MESSAGE), 5)  # no guarding
        gw.start_heartbeat_consumer(1000)  # the card boots it with its heartbeat again
        expect(stream, lambda e: e == ErrorControlEvent(
            1, 3, NmtState.OPERATIONAL, ErrorCode.HEARTBEAT_STARTED), 10)
        gw.disable_node_guarding()  # supervised by heartbeat: nothing to disable
    wait_operating(0, [1, 2, 3])
    for call in (lambda: gw.enable_node_guarding(100, 3, node_id=9),
                 lambda: gw.start_heartbeat_consumer(100, node_id=9)):
        assert reason(call).error == ErrorCode.UNSUPPORTED_NODE  # not the card's (f 20)
    assert reason(lambda: gw.start_heartbeat_consumer(100, network=2, node_id=1)).f == 200
    assert reason(lambda: gw.enable_node_guarding(70000, 1, node_id=1)).error == 101


def test_layer2_sends_leave_no_awaited_request_in_the_ledger(gw: Gateway) -> None:
    """[ours] COM_Tx_CAN_Layer2 goes with msg.e NAK (the card answers it only when it fails):
    after sends and a read the board's transaction ledger is empty. Each send awaited an
    answer for ever before, and every later answer rewrote all of them into the file."""
    board = registry.boards[0]
    for _ in range(3):
        gw.send_frames([CanFrame(0x7E5, b"\x04\x00")])  # an LSS switch state global
    assert gw.sdo_upload(0x1000, 0, node_id=1)
    assert ledger_text(board.transaction.path.read_bytes()) == b""


# --- 4.4 and 4.5.7/4.5.8 emergencies ----------------------------------------------------------


def test_emergency_consumer_and_read_device_error(gw: Gateway) -> None:
    short = [CanFrame(0x203, b"\x01")]  # 1 byte into node 3's 8-byte RPDO: EMCY 8210h
    with gw.events() as stream:
        gw.send_frames(short)
        emcy = expect(stream, lambda e: isinstance(e, EmergencyEvent), 5)
    assert isinstance(emcy, EmergencyEvent) and (emcy.net, emcy.node, emcy.code) == (1, 3, 0x8210)
    error = gw.read_device_error(node_id=3)
    assert 0x8210 in [e.code for e in error.emergencies]  # after the life guarding's 8130h
    assert (error.error == 0) == (error.error_text == "no error")  # 32 after guarding
    assert gw.read_device_error().emergencies == ()  # read: gone
    healthy = gw.read_device_error(node_id=2)
    assert (healthy.error, healthy.error_text, healthy.emergencies) == (0, "no error", ())
    gw.set_default_node_id(3)
    gw.stop_emergency_consumer()
    gw.send_frames(short)
    gw.sdo_upload(0x1000, 0)  # the node answers after its EMCY went out
    assert gw.read_device_error().emergencies == ()
    with gw.events() as stream:
        gw.start_emergency_consumer(0)  # 0: 80h + node-ID
        gw.send_frames(short)
        expect(stream, lambda e: isinstance(e, EmergencyEvent) and e.node == 3, 5)
    assert reason(lambda: gw.start_emergency_consumer(0x83, node_id=9)).error == 107
    assert reason(lambda: gw.start_emergency_consumer(0x800, node_id=3)).error == 101


# --- 4.5 interface configuration, 4.6 gateway management ---------------------------------------


def test_boot_up_forwarding(gw: Gateway) -> None:
    with gw.events() as stream:
        gw.set_bootup_forwarding(True)
        gw.reset_node(9)
        boot_ups = (e for e in stream if isinstance(e, BootUpEvent))  # the stream iterates too
        assert next(boot_ups) == BootUpEvent(1, 9)
        gw.set_bootup_forwarding(False)
        with gw.listen([0x709]) as listener:
            gw.reset_node(9)

            def boot_up(seconds: float) -> bool:
                try:
                    return listener.get(timeout=seconds).data == b"\x00"
                except queue.Empty:
                    return False

            assert within(boot_up, 10), "node 9's boot-up"
        silent(stream, lambda e: isinstance(e, BootUpEvent), 0.3, "a forwarded boot-up")
    assert reason(lambda: gw.set_bootup_forwarding(True, network=3)).error == 106


def test_own_node_id_and_heartbeat_producer(gw: Gateway) -> None:
    gw.set_node_id(100)
    assert reason(lambda: gw.set_node_id(1)).f == 60  # node 1 is configured
    assert reason(lambda: gw.set_node_id(0)).error == ErrorCode.UNSUPPORTED_NODE
    gw.set_heartbeat_producer(100)
    gw.set_heartbeat_producer(0)
    assert reason(lambda: gw.set_heartbeat_producer(70000)).error == 101
    with gw.listen([0x1C0]):  # a free identifier is accepted; a used one is 400
        pass
    assert reason(lambda: gw.listen([0x701])).error == ErrorCode.PDO_ALREADY_USED


def test_defaults_version_and_networks(main: Gateway) -> None:
    session = main.session()
    assert session.networks == [1, 2]
    assert reason(lambda: session.set_default_network(3)).error == 106
    session.set_default_network(2)
    assert reason(lambda: session.set_default_node_id(0)).error == 107
    session.set_default_node_id(5, network=2)
    assert session.default_node_id == 5
    first, second = session.get_version(network=1), session.get_version()
    assert (first.vendor_id, first.product_code, first.gateway_class) == (VENDOR_ID, 1250100, 3)
    assert first.revision == (1 << 16) | 70 and first.protocol_version == (2, 0)
    assert (first.serial, second.serial) == (1, 2)  # board 0 and board 1


def test_remote_controller(gw: Gateway) -> None:
    for call, value in ((gw.start_controller, 1), (gw.stop_controller, 0),
                        (gw.reset_controller, 2)):
        call(node_id=2)
        assert gw.sdo_upload(0x1F51, 1) == bytes([value])
    assert reason(lambda: gw.start_controller(node_id=1)).abort_code == 0x06020000


# --- faults: every error control event the card can report ---------------------------------


FAULTS = """
[[node]]
id = 10
[node.sim]
heartbeat_stop_after_s = 0.5
[[node]]
id = 11
error_control = "guarding"
guard_time_ms = 100
life_time_factor = 2
[node.sim]
guarding_fail_after_s = 0.5
[[node]]
id = 12
[node.sim]
leave_operational_after_s = 0.5
[[node]]
id = 13
[node.sim]
silent = true
[[node]]
id = 14
[node.sim]
bus_errors = { after_s = 2.5, count = 2, kind = "warning" }
[[node]]
id = 15
[node.sim]
bus_errors = { after_s = 2.5, count = 2, kind = "bus_off" }
"""


def test_error_control_events_of_failing_nodes(main: Gateway, directory: Path) -> None:
    card = start(directory, 2, FAULTS)
    try:
        with Gateway([2], directory) as gateway, gateway.events() as stream:
            wanted = {
                (10, ErrorCode.HEARTBEAT_LOST), (11, ErrorCode.LOST_GUARDING_MESSAGE),
                (12, ErrorCode.WRONG_NMT_STATE), (13, ErrorCode.LOST_CONNECTION),
                (0, ErrorCode.ERROR_PASSIVE), (0, ErrorCode.BUS_OFF),
            }
            seen: dict[tuple[int, ErrorCode], ErrorControlEvent] = {}

            def collect(event: Event) -> bool:
                if isinstance(event, ErrorControlEvent) and event.error is not None:
                    seen.setdefault((event.node, event.error), event)
                return wanted <= set(seen)

            expect(stream, collect, 15)
            assert seen[(12, ErrorCode.WRONG_NMT_STATE)].state == NmtState.PRE_OPERATIONAL
            assert all(event.net == 3 for event in seen.values())
            image = card.map()
            struct.pack_into("<H", image, 0x1F4A, 1)  # as if the layer-2 queue had overflowed
            expect(stream, is_error(0, ErrorCode.CAN_BUFFER_OVERFLOW), 5)
            assert gateway.read_device_error(node_id=13).error == 34  # no answer at boot-up
    finally:
        card.stop()


# --- store, restore, initialise, the card's own controller ----------------------------------------


def bit_rate(gateway: Gateway) -> int:
    """Baud_rate of the bus parameters the card runs with (COM_Upload of area 127)."""
    request = bytes([0, AREA_BUS, 0, 0, MAX_LEN_DATA_UNIT])
    answer = gateway.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_UPLOAD, data=request))
    assert answer.f == 0
    return answer.data[0]


def test_configuration_store_restore_and_initialise(main: Gateway, directory: Path) -> None:
    card = start(directory, 3, "[[node]]\nid = 1\n")
    try:
        with Gateway([3], directory) as gateway, gateway.events() as stream:
            wait_operating(3, [1])
            assert reason(gateway.restore_configuration).error == 102  # nothing stored
            gateway.store_configuration()
            assert reason(lambda: gateway.store_configuration(1)).error == 100
            assert reason(lambda: gateway.initialize_gateway(9)).error == 503
            gateway.initialize_gateway(4)  # 125 kbit/s: the card starts anew with it
            expect(stream, is_error(0, ErrorCode.CAN_INIT), 5)
            expect(stream, is_error(0, ErrorCode.CAN_ACTIVE), 10)
            wait_operating(3, [1])
            assert bit_rate(gateway) == 4
            gateway.reset_controller()  # a warm start: the stored configuration comes back
            wait_operating(3, [1])
            assert bit_rate(gateway) == 2
            gateway.initialize_gateway(4)
            wait_operating(3, [1])
            gateway.restore_configuration()
            wait_operating(3, [1])
            assert bit_rate(gateway) == 2
            gateway.stop_controller()
            wait_until(lambda: diagnostics(3).bCAN_State == CanState.STOP, 5, "STOP")
            gateway.start_controller()
            wait_until(lambda: diagnostics(3).bCAN_State == CanState.OPERATE, 5, "OPERATE")
    finally:
        card.stop()
    for call in (lambda: main.store_configuration(network=2),
                 lambda: main.initialize_gateway(4, network=2)):
        assert reason(call).error == ErrorCode.INTERNAL_STATE  # no configuration there
