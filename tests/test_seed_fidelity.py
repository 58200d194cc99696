"""Behaviour a host written for the real card notices: each test provokes one item of the seed
manual through the mailbox or the image and asserts what the host sees (msg.f, Task2State
fields, frames on the bus). The card runs as a real firmware process with simulated nodes, on
every bus of the back-to-back network fixture (``tests/can_net.py``).
"""

from __future__ import annotations

import contextlib
import os
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from dbm_tools.builder import build_dbm
from dbm_tools.container import save_dbm
from dbm_tools.network import load_network
from dpm.card_info import read_card_info
from dpm.errors import Drv
from dpm.message import Message
from host_api import driver as d
from host_api.board import Board
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload, delete_database
from tests.can_net import Net, actual_error, candump, exchange, frame, node_set, window
from tests.conftest import start_card, wait_until

pytest_plugins = ["tests.can_net"]
"""The back-to-back network fixture: every test here runs on each interface."""

SYNC_ID = 0x080


def test_no_sync_without_a_sync_controlled_pdo(make_net: Callable[..., Net],
                                               tmp_path: Path) -> None:
    """Seed 4.2: SYNC is activated only if a node uses a SYNC controlled transmission type.

    The generic nodes' PDOs are event-driven (255): with SYNC_Timer 5 ms the card still sends
    no SYNC.
    """
    trace = tmp_path / "trace.log"
    net = make_net("[bus]\nsync_period_ms = 5\n[[node]]\nid = 1\n[[node]]\nid = 2\n",
                   "--trace", str(trace))
    net.configure()
    net.wait_operating([1, 2])
    wait_until(lambda: exchange(net, b"\x11" * 8) == b"\x11" * 8, 5, "node 1's echo")
    window(0.5, "no SYNC in 100 periods of SYNC_Timer")
    # A marker after the window: the card ran through it (a stalled card sends no SYNC either).
    wait_until(lambda: exchange(net, b"\x22" * 8) == b"\x22" * 8, 5, "node 1's echo again")
    net.card.stop()  # flushes the trace
    frames = candump(trace)
    assert [ident for _, ident, _ in frames if ident == 0x201], "the outputs went out"
    assert not [t for t, ident, _ in frames if ident == SYNC_ID]


def test_sync_starts_with_the_first_sync_controlled_pdo(make_net: Callable[..., Net],
                                                        tmp_path: Path) -> None:
    """A node with one synchronous RPDO (type 1) beside an event-driven one turns SYNC on."""
    trace = tmp_path / "trace.log"
    net = make_net("""[bus]
sync_period_ms = 5
[[node]]
id = 1
[[node]]
id = 2
[[node.pdo]]
direction = "output"
cob_id = 0x202
transmission = 1
""", "--trace", str(trace))
    net.configure()
    net.wait_operating([1, 2])
    net.watch().wait_for(frame(SYNC_ID), 41, "41 SYNCs")
    net.card.stop()  # flushes the trace
    syncs = [t for t, ident, _ in candump(trace) if ident == SYNC_ID]
    assert len(syncs) > 40


def test_start_seq_time_out_expires_without_a_message(make_net: Callable[..., Net]) -> None:
    """Seed 5.2.3: Start_Seq's time-out ends the sequence even when no message follows it.

    The whole data set arrives in time, but End_Seq comes after the time-out: f 48, and the
    node is not configured. The time-out is 400 ms, so that a loaded machine still brings
    the data set within it (30 ms missed it once beside two busy processes); the wait for it
    to run out counts from before Start_Seq, on the card's own (wall) clock.
    """
    net = make_net("")
    started = time.monotonic()
    assert net.send(67, bytes([0, 4]) + struct.pack("<H", 400)).f == 0
    assert net.send(68, bytes([0, 4, 0, 0]) + node_set(4)).f == 0
    wait_until(lambda: time.monotonic() - started > 0.45, what="the sequence time-out")
    assert net.send(69, b"\0").f == 48
    assert not net.diag().configured()
    assert net.send(69, b"\0").f == 57  # the sequence is gone


# --- COM_Start_Seq (seed 5.2.3) ----------------------------------------------------------


def test_an_expired_start_seq_blocks_no_other_download(make_net: Callable[..., Net]) -> None:
    """Seed 5.2.3: Start_Seq's time-out ends the sequence. A single COM_Download for another
    node after it is that node's download (f 0, configured), not a sequence error (57)."""
    net = make_net("")
    assert net.send(67, bytes([0, 4]) + struct.pack("<H", 20)).f == 0
    started = time.monotonic()
    wait_until(lambda: time.monotonic() - started > 0.1, what="the sequence time-out")
    assert net.send(68, bytes([0, 5, 0, 0]) + node_set(5)).f == 0
    assert net.diag().configured() == [5]


@pytest.mark.parametrize(("request_data", "f"), [
    (bytes([0, 0, 0, 0]), 52),  # Area_Code 0
    (bytes([0, 127, 0, 0]), 52),  # the bus parameters have no sequence
    (bytes([0]), 55),  # too short to read
])
def test_start_seq_error_answers_keep_the_table_layout(make_net: Callable[..., Net],
                                                       request_data: bytes, f: int) -> None:
    """Seed 5.2.3's answer table: msg.ln 1, d[0] 240 (Max_Len_Data_Unit); only f varies."""
    net = make_net("")
    answer = net.send(67, request_data)
    assert (answer.f, answer.ln, answer.data) == (f, 1, bytes([240]))


def test_global_start_waits_for_a_late_node_without_faults(make_net: Callable[..., Net],
                                                           tmp_path: Path) -> None:
    """Seed 4.3 (biNoGobalStartNode): nodes waiting for the global Start_Node are no faults.

    Node 3 boots 1.5 s after the others; with auto-clear on, one fault would stop the card.
    All three come up, no Err_Event, and one global start goes out after the last boot-up.
    """
    trace = tmp_path / "trace.log"
    net = make_net("""[bus]
global_start = true
auto_clear = true
[[node]]
id = 1
[[node]]
id = 2
[[node]]
id = 3
[node.sim]
boot_delay_s = 1.5
""", "--trace", str(trace))
    net.configure()
    net.wait_operating([1, 2, 3], timeout=15)
    watch = net.watch()  # two heartbeats of every node (500 ms) with no fault between
    since = watch.mark()
    for node in (1, 2, 3):
        watch.wait_for(frame(0x700 + node, b"\x05"), 2, f"two heartbeats of node {node}",
                       since=since)
    diag = net.diag()
    assert diag.operating() == [1, 2, 3] and diag.bErr_event == 0
    assert diag.can_state_name == "OPERATE" and diag.global_bits == 0
    net.card.stop()
    starts = [data for _, ident, data in candump(trace) if ident == 0 and data.startswith("01")]
    assert starts and all(data == "0100" for data in starts)  # global: node-ID 0 only


def test_start_bit_leaves_the_node_as_it_is(make_net: Callable[..., Net],
                                            tmp_path: Path) -> None:
    """bitConfigNdState START set: the card sends no Start_Node and supervises the node in
    PRE-OPERATIONAL: no Err_Event 31, no reboot, Nd_state 0 until the host starts it.

    Supervision is not the subject: a 3 s heartbeat consumer time, so a `cifemu sim` starved
    on a loaded machine is not lost (Err_Event 30) and booted again. The reboot is asserted
    on the frames after node 1's boot (Guard_active in its COM_Node_Diag): no Reset Node
    for it. A count of the whole run's resets (2) saw 3 on a loaded machine, where a node
    that fails is booted again, which is not the START bit's doing."""
    trace = tmp_path / "trace.log"
    net = make_net("""[[node]]
id = 1
heartbeat_ms = 3000
boot = ["reset", "device", "guard", "sync", "emcy", "sdo", "pdo"]
[[node]]
id = 2
heartbeat_ms = 3000
""", "--trace", str(trace))
    net.configure()
    net.wait_operating([2])

    def guarded() -> bool:  # COM_Node_Diag of node 1: Nodestatus_1 says Guard_active
        return bool(net.send(66, bytes([1, 0, 0, 0, 0, 0, 5, 1])).data[8] & 0x08)

    wait_until(guarded, 10, "node 1 booted and supervised (Guard_active)")
    watch = net.watch()
    booted = watch.mark()  # two heartbeats (3 s) of node 1 supervised in PRE-OPERATIONAL
    watch.wait_for(frame(0x701, b"\x7f"), 2, "node 1's heartbeats", since=booted)
    diag = net.diag()
    assert diag.operating() == [2] and diag.bErr_event == 0 and guarded()
    assert watch.matching(lambda msg: msg.arbitration_id == 0 and bytes(msg.data[:1]) == b"\x81"
                          and msg.data[1] in (0, 1), since=booted) == []  # no reboot
    assert net.send(96, bytes([0x01, 1])).f == 0  # COM_NMT_Module_Protocol: start node 1
    net.wait_operating([1, 2])
    net.card.stop()
    frames = candump(trace)
    assert not [d for _, ident, d in frames if ident == 0 and d == "0101"][:-1]  # host's only


EDS = Path(__file__).parent / "data" / "cia309_node.eds"
DOMAIN = 0x2000


def sdo_request(node: int, index: int, write: bytes | None = None) -> bytes:
    """A COM_SDO_Up_Download telegram (seed 5.2.8): header, then the data of a write."""
    data = write or b""
    return struct.pack("<BBHBBBB", node, 0, index, 0, len(data), 0,
                       2 if write is not None else 1) + data


def test_sdo_upload_longer_than_247_bytes(make_net: Callable[..., Net]) -> None:
    """Seed 5.2.8: one answer of at most 247 data bytes, else f 51. The several answers of a
    long upload (docs/card-commands.md) come only when the host asks with msg.e 4."""
    net = make_net(f'[[node]]\nid = 3\neds = "{EDS}"\n')
    net.configure()
    net.wait_operating([3])
    value = bytes(range(256)) + bytes(44)  # 300 bytes: one part of 247 and one of 53
    assert net.send(74, sdo_request(3, DOMAIN, value[:247]), e=4).f == 0
    assert net.send(74, sdo_request(3, DOMAIN, value[247:]), e=0x0C).f == 0

    plain = net.send(74, sdo_request(3, DOMAIN))
    assert plain.f == 51 and plain.e == 0
    # Nothing follows it: a marker request's answer is the next message (a second part
    # would have been posted with the first, before the marker was even sent).
    marker = Message(rx=3, tx=16, b=66, nr=9, data=struct.pack("<BBHBBBB", 3, 0, 0, 0, 0, 0, 1))
    assert d.DevPutMessage(0, marker, 1000) == 0
    rc, next_message = d.DevGetMessage(0, 288, 2000)
    assert rc == 0 and next_message is not None and (next_message.a, next_message.nr) == (66, 9)

    first = net.send(74, sdo_request(3, DOMAIN), e=4)
    rc, last = d.DevGetMessage(0, 288, 2000)
    assert rc == 0 and last is not None
    assert (first.f, first.e, last.f, last.e) == (0, 4, 0, 0x0C)
    assert first.data[8:] + last.data[8:] == value


def test_stray_msg_e_bits_leave_an_sdo_download_plain(make_net: Callable[..., Net]) -> None:
    """Bits of msg.e other than the sequence markings do not start a long download: the
    write happens at once, with its one answer."""
    net = make_net(f'[[node]]\nid = 3\neds = "{EDS}"\n')
    net.configure()
    net.wait_operating([3])
    answer = net.send(74, sdo_request(3, DOMAIN, b"abcd"), e=0x14)  # 4 among other bits
    assert answer.f == 0
    upload = net.send(74, sdo_request(3, DOMAIN))
    assert upload.f == 0 and upload.data[8:] == b"abcd"


def test_sdo_download_of_zero_bytes(make_net: Callable[..., Net], tmp_path: Path) -> None:
    """data_cnt 0 (seed 5.2.8 allows 0-247) empties a DOMAIN: a segmented download of size 0
    (CiA 301 initiate 0x21 with size 0, then one segment without data), never a 4-byte
    expedited write of zeros."""
    trace = tmp_path / "trace.log"
    net = make_net(f'[[node]]\nid = 3\neds = "{EDS}"\n', "--trace", str(trace))
    net.configure()
    net.wait_operating([3])
    assert net.send(74, sdo_request(3, DOMAIN, b"abcd")).f == 0
    assert net.send(74, sdo_request(3, DOMAIN, b"")).f == 0
    upload = net.send(74, sdo_request(3, DOMAIN))  # the node has no data left to give
    assert upload.f == 3 and struct.unpack_from("<I", upload.data, 8)[0] == 0x08000024
    net.card.stop()
    requests = [data for _, ident, data in candump(trace) if ident == 0x603]
    assert "2100200000000000" in requests and "0F00000000000000" in requests
    assert not [data for data in requests if data.startswith("33")]


def test_online_download_is_refused_while_a_flash_database_runs(
        make_net: Callable[..., Net], tmp_path: Path) -> None:
    """Seed 5.2.2: with a database from flash running, the on-line download cannot be used
    (flash ranks above it). [ours] COM_Start_Seq, COM_Download and COM_End_Seq get f 201,
    and the running configuration stays; after the database is deleted and the card started
    again, the on-line download works."""
    net = make_net("[[node]]\nid = 1\n[[node]]\nid = 2\n")
    dbm = tmp_path / "plant.dbm"
    save_dbm(dbm, build_dbm(load_network(net.toml)))
    assert DevDownload(0, CONFIGURATION_DOWNLOAD, dbm) == 0
    assert d.DevReset(0, d.COLDSTART, 5000) == 0
    net.wait_operating([1, 2])
    assert net.send(67, bytes([0, 5]) + struct.pack("<H", 1000)).f == 201
    assert net.send(68, bytes([0, 5, 0, 0]) + node_set(5)).f == 201
    assert net.send(68, bytes([0, 127, 0, 0, 2]) + bytes(6)).f == 201  # bus parameters too
    assert net.send(69, b"\0").f == 201
    assert net.diag().configured() == [1, 2] and net.diag().operating() == [1, 2]
    assert delete_database(0) == 0
    assert d.DevReset(0, d.COLDSTART, 5000) == 0
    assert net.send(68, bytes([0, 5, 0, 0]) + node_set(5)).f == 0
    assert net.diag().configured() == [5]


def test_a_node_address_downloaded_twice_is_refused(make_net: Callable[..., Net]) -> None:
    """A second data set for a configured address is f 60 (double node address), not a silent
    replacement of the first; the node keeps running on its first data set."""
    net = make_net("[[node]]\nid = 1\n")
    net.configure()
    net.wait_operating([1])
    first = net.send(80, bytes([0, 1, 0, 0, 240]))
    assert net.send(68, bytes([0, 1, 0, 0]) + node_set(1)).f == 60
    assert net.send(80, bytes([0, 1, 0, 0, 240])).data == first.data
    assert net.diag().operating() == [1]


def test_actual_error_is_cleared_when_the_node_recovers(make_net: Callable[..., Net]) -> None:
    """Node 1 leaves OPERATIONAL after a second (31), is booted again and operates: its
    Actual_Error goes back to 0 with Err_Event."""
    net = make_net("[[node]]\nid = 1\n[node.sim]\nleave_operational_after_s = 1.5\n"
                   "[[node]]\nid = 2\n")
    net.configure()
    net.wait_operating([1, 2])
    wait_until(lambda: net.diag().bErr_event == 31, 5, "Err_Event 31 of node 1")
    assert actual_error(net, 1) == 31
    net.wait_operating([1, 2], timeout=5)
    assert net.diag().bErr_event == 0
    assert actual_error(net, 1) == 0


def test_host_not_ready_stops_the_nodes_with_err_event_39(make_net: Callable[..., Net],
                                                          tmp_path: Path) -> None:
    """Seed 4.3: HOST_NOT_READY stops the nodes: NMT Stop on the bus, Nd_state cleared,
    Err_Event 39 ("node not handled, node in stop") in Task2State and in each node's
    Actual_Error. HOST_READY boots them again, without an error."""
    trace = tmp_path / "trace.log"
    net = make_net("[[node]]\nid = 1\n[[node]]\nid = 2\n", "--trace", str(trace))
    net.configure()
    net.wait_operating([1, 2])
    assert d.DevSetHostState(0, d.HOST_NOT_READY, 1000) == 0
    # The card stops the nodes one after another: Err_Event 39 shows with node 1's stop,
    # node 2 leaves Nd_state a moment later (CI on SocketCAN read [2] in between).
    wait_until(lambda: net.diag().bErr_event == 39 and net.diag().operating() == [], 5,
               "Err_Event 39 and no node in Nd_state")
    diag = net.diag()
    assert diag.operating() == [] and diag.bErr_rem_adr == 1
    assert diag.can_state_name == "STOP"
    assert actual_error(net, 1) == actual_error(net, 2) == 39
    assert d.DevSetHostState(0, d.HOST_READY, 1000) == 0
    net.wait_operating([1, 2], timeout=10)
    assert net.diag().bErr_event == 0
    net.card.stop()
    assert "0200" in [data for _, ident, data in candump(trace) if ident == 0]


def test_a_node_booting_after_auto_clear_never_shows_as_operating(
        make_net: Callable[..., Net]) -> None:
    """Node 1's heartbeat stops (30) and auto-clear stops all; node 2 finishes its boot-up
    later. It never shows in Nd_state, and it gets Err_Event 39 like the others."""
    net = make_net("""[bus]
auto_clear = true
[[node]]
id = 1
heartbeat_ms = 200
[node.sim]
heartbeat_stop_after_s = 0.3
[[node]]
id = 2
[node.sim]
boot_delay_s = 2.0
""")
    net.configure()
    seen: set[int] = set()

    def node_2_booted() -> bool:
        diag = net.diag()
        seen.update(diag.operating())
        return diag.can_state_name == "CLEAR" and actual_error(net, 2) == 39

    wait_until(node_2_booted, 8, "node 2 stopped by auto-clear after its boot-up")
    assert 2 not in seen


def test_a_non_default_guarding_cob_id_is_written_and_used(make_net: Callable[..., Net],
                                                           tmp_path: Path) -> None:
    """Seed 4.2: usCobIDGuard is written into the node's object directory at start-up (100Eh),
    and guarding runs on it: the node, which starts at 700h + node-ID, answers on 77Fh."""
    trace = tmp_path / "trace.log"
    net = make_net("""[[node]]
id = 1
error_control = "guarding"
guard_time_ms = 100
life_time_factor = 3
guard_cob_id = 0x77F
""", "--trace", str(trace))
    net.configure()
    net.wait_operating([1])
    watch = net.watch()
    watch.wait_for(frame(0x77F, remote=False), 5, "five guarding answers on 77Fh",
                   since=watch.mark())
    diag = net.diag()
    assert diag.operating() == [1] and diag.bErr_event == 0
    net.card.stop()
    frames = candump(trace)
    assert "230E10007F070000" in [data for _, ident, data in frames if ident == 0x601]
    assert len([data for _, ident, data in frames if ident == 0x77F and data != "R"]) >= 5
    assert {data for _, ident, data in frames if ident == 0x701} == {"00"}  # boot-ups only


def test_bus_error_cnt_counts_warning_limit_crossings_only(
        make_net: Callable[..., Net]) -> None:
    """Seed 4.3: Bus_Error_Cnt counts the times the controller's error counter reached the
    warning limit. Three protocol errors (a form error each, the counters below the limit)
    are no event: the counter stays 0 and EVE clear; two warning-limit crossings count 2."""
    net = make_net("[[node]]\nid = 1\n[node.sim]\n"
                   "bus_errors = { after_s = 0.1, count = 3, kind = \"protocol\" }\n"
                   "[[node]]\nid = 2\n[node.sim]\n"
                   "bus_errors = { after_s = 0.6, count = 2, kind = \"warning\" }\n")
    image = net.card.map()
    wait_until(lambda: struct.unpack_from("<H", image, 0x1F44)[0] == 2, 5, "2 crossings")
    window(0.2, "no third count after the two crossings")
    assert struct.unpack_from("<H", image, 0x1F44)[0] == 2
    assert struct.unpack_from("<H", image, 0x1F46)[0] == 0  # no bus-off either


def test_a_node_without_a_boot_up_message_boots(make_net: Callable[..., Net],
                                                tmp_path: Path) -> None:
    """Seed appendix: "no reaction on Bootup Events"; the boot-up reads object 1000h. Node 2
    (CiA 301 before 4.0) sends no boot-up message after its reset: the card identifies it by
    reading 1000h and brings it up like node 1, without an Err_Event."""
    trace = tmp_path / "trace.log"
    net = make_net("[[node]]\nid = 1\n[[node]]\nid = 2\n[node.sim]\nno_bootup = true\n",
                   "--trace", str(trace))
    net.configure()
    net.wait_operating([1, 2], timeout=8)
    assert net.diag().bErr_event == 0
    net.card.stop()
    frames = candump(trace)
    assert not [data for _, ident, data in frames if ident == 0x702 and data == "00"]
    assert "4000100000000000" in [data for _, ident, data in frames if ident == 0x602]


@pytest.mark.parametrize("mode", [0, 4])
def test_bmode_0_and_4(make_net: Callable[..., Net], mode: int) -> None:
    """Seed 2.2 lists bMode 0-4, 2.3 only 1-3; the card keeps 2.3 (docs/dpm.md). What a host
    that writes 0 or 4 sees after the warm start, and how a valid bMode brings it back."""
    net = make_net("[[node]]\nid = 1\n")
    assert d.DevPutTaskParameter(0, 2, struct.pack("<BH", mode, 0)) == 0
    assert d.DevReset(0, d.WARMSTART, 5000) == 0
    diag = net.diag()
    assert (diag.bErr_rem_adr, diag.bErr_event) == (255, 52)
    rc, _ = d.DevExchangeIO(0, 0, b"\0", 0, 1, 100)
    assert rc == Drv.DRV_DEV_COM_MODE_UNKNOWN  # -24: no exchange mode
    assert d.DevPutTaskParameter(0, 2, struct.pack("<BH", 3, 0)) == 0
    assert d.DevReset(0, d.WARMSTART, 5000) == 0
    assert net.diag().bErr_event == 0
    net.configure()
    net.wait_operating([1])
    wait_until(lambda: exchange(net, b"\x33" * 8) == b"\x33" * 8, 5, "the echo")


def test_baud_rate_reaches_a_controller_that_takes_one(tmp_path: Path) -> None:
    """Seed 5.2.5.4: Baud_rate fixes the bus's rate. An slcan adapter (python-can's slcan on
    a pseudo-terminal, read on the other side as the adapter would) is opened at the
    command line's 125 kbit/s ("S4"); the bus parameters' Baud_rate 2 sets it to 500 kbit/s
    ("S6"), and the card's facts say so. A rate the adapter lacks (800 kbit/s) is Err_Event
    56 at 255, and the controller keeps its rate."""
    adapter, tty = os.openpty()
    heard = bytearray()

    def listen() -> None:
        with contextlib.suppress(OSError):
            while chunk := os.read(adapter, 4096):
                heard.extend(chunk)

    threading.Thread(target=listen, daemon=True).start()
    card = start_card(tmp_path, 0, "--interface", "slcan", "--channel", os.ttyname(tty),
                      "--bitrate", "125000")
    try:
        wait_until(lambda: b"S4\r" in heard and b"O\r" in heard, 5, "the adapter opened")
        with Board(0, tmp_path) as board:
            for code, f in ((2, 0), (1, 0)):  # 500 kbit/s, then 800 kbit/s
                bus = bytes([code]) + struct.pack("<HH", 0x80, 0) + bytes(2)
                answer = board.transact(Message(rx=3, tx=16, b=68, data=bytes([0, 127, 0, 0])
                                                + bus))
                assert answer.f == f
                if code == 2:
                    wait_until(lambda: b"S6\r" in heard, 5, "the adapter set to 500 kbit/s")
                    info = read_card_info(tmp_path, 0)
                    assert info is not None and info["bus"]["bitrate"] == 500000
            diag = board.diagnostics()
            assert (diag.bErr_rem_adr, diag.bErr_event) == (255, 56)
            info = read_card_info(tmp_path, 0)
            assert info is not None and info["bus"]["bitrate"] == 500000
            assert info["bus"]["baud_rate"] == 800000
    finally:
        card.stop()
        os.close(adapter)
        os.close(tty)
