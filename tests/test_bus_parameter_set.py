"""The bus parameter set as a host sees it: SYNC_Timer 0 and another station's SYNC, the
29-bit acceptance filter, Baud_rate against the link's rate (Err_Event 56) and
Bus_Error_Cnt. Each test sets the parameter through a database or the mailbox, as a host
would, and asserts the seed manual's values in the image or the frames on the bus. The card
runs as a real firmware process with simulated nodes on the back-to-back buses of
``tests/can_net.py``, where the behaviour is not bound to one bus.
"""

from __future__ import annotations

import os
import shutil
import struct
import uuid
from collections.abc import Callable
from pathlib import Path

import can
import pytest

from dbm_tools.builder import build_dbm
from dbm_tools.container import save_dbm
from dbm_tools.network import load_network
from dpm.card_info import read_card_info
from dpm.com import ACCEPT_ALL_MASK, acceptance_long
from dpm.commands import COM_SHARED_MEMORY
from dpm.errors import Drv
from dpm.message import Message, Tdt, TelegramHeader, Tfc
from firmware.can.bus import bitrate_of_link
from firmware.frames import (
    CAN_ERR_CRTL,
    CAN_ERR_CRTL_ACTIVE,
    CAN_ERR_CRTL_RX_WARNING,
    CAN_ERR_CRTL_TX_PASSIVE,
    CAN_ERR_CRTL_TX_WARNING,
)
from host_api import driver as d
from host_api.board import Board, CifError
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload
from tests.buses import socketcan_missing
from tests.can_net import Net, bus_parameters, candump, exchange, node_set, window
from tests.conftest import TIME_SCALE, start_card, wait_until

pytest_plugins = ["tests.can_net"]
"""The back-to-back fixtures: this module's tests run on every bus that file's run on."""

SYNC_ID = 0x080
CTRL = 0x01
"""Task2State's global bit CONTROL-ERROR (seed 4.3)."""
BAUD_RATE_OUT_OF_RANGE = 56
"""Err_Event 56 at Err_Rem_Adr 255: "baudrate out of range" (seed 4.3)."""


# --- SYNC_Timer 0 with a synchronous PDO (seed revision 16, 5.2.5.4.1) -----------------


SYNCHRONOUS_NODE = """[bus]
sync_period_ms = 0
[[node]]
id = 1
[[node.pdo]]
direction = "output"
cob_id = 0x201
transmission = 1
[[node.pdo]]
direction = "input"
cob_id = 0x181
"""


def test_sync_timer_0_with_a_synchronous_pdo_is_downloaded(make_net: Callable[..., Net],
                                                           tmp_path: Path) -> None:
    """Seed revision 16, "SYNC timer can be configured to value 0 also", and 5.2.5.4.1, "A
    value of 0 disables the timer": the SYNC then comes from another station. A node with a
    synchronous RX-PDO (type 1) and SYNC_Timer 0 is f 0, not 67; the node comes up and the
    card sends no SYNC of its own."""
    trace = tmp_path / "trace.log"
    net = make_net(SYNCHRONOUS_NODE, "--trace", str(trace))
    assert net.send(68, bytes([0, 1, 0, 0]) + node_set(1, output_type=1)).f == 0
    assert net.send(68, bus_parameters(sync_timer=0)).f == 0
    net.wait_operating([1])
    window(0.3, "no SYNC of the card's own while the node runs")
    net.card.stop()
    assert not [t for t, ident, _ in candump(trace) if ident == SYNC_ID]


def test_sync_timer_0_in_a_flash_database_starts_the_network(make_net: Callable[..., Net],
                                                             tmp_path: Path) -> None:
    """The same from a database in flash: the card starts it (no Err_Event 212, no 67)."""
    net = make_net(SYNCHRONOUS_NODE)
    dbm = tmp_path / "plant.dbm"
    save_dbm(dbm, build_dbm(load_network(net.toml)))
    assert DevDownload(0, CONFIGURATION_DOWNLOAD, dbm) == 0
    assert d.DevReset(0, d.COLDSTART, 5000) == 0
    net.wait_operating([1])
    diag = net.diag()
    assert (diag.bErr_rem_adr, diag.bErr_event) == (0, 0)


# --- the 29-bit acceptance filter (seed 5.2.5.3, 5.2.11.1, revision 17) ---------------


@pytest.mark.parametrize(("code", "mask", "passed", "held"), [
    # SyCon's "accept all": every mask bit "don't care" (0xF8FFFFFF, revision 17's maximum)
    (0, ACCEPT_ALL_MASK, [0x00000001, 0x1FFFFFFF, 0x12345678], []),
    # 0x1ABCxxxx: ID.28..16 compared, ID.15..0 "don't care", in the SJA1000 register layout
    (acceptance_long(0x1ABC0000), acceptance_long(0x0000FFFF), [0x1ABC1234, 0x1ABC0000],
     [0x12340000, 0x1ABD0000]),
    # every bit compared: exactly one identifier
    (acceptance_long(0x00012345), 0, [0x00012345], [0x00012344, 0x10012345]),
])
def test_the_acceptance_filter_reads_sja1000_registers(tmp_path: Path, code: int, mask: int,
                                                       passed: list[int],
                                                       held: list[int]) -> None:
    """Seed 5.2.5.3.1 (revision 17): code and mask are 0..0xF8FFFFFF, the SJA1000's ACR0..3
    and AMR0..3 in register order, laid out as the Rx-Identifier bytes of 5.2.11.1 (ID.28
    first, ID.4..0 in bits 7..3 of the last byte); a mask bit 1 is "don't care". Another
    station on an ``shm`` channel sends extended frames; the host gets exactly those the
    filter passes, as COM_Receive_CANMsg_Transparent (b 65, ln 13)."""
    channel = f"test-{uuid.uuid4().hex}"
    card = start_card(tmp_path, 0, "--interface", "shm", "--channel", channel)
    sender = can.Bus(interface="shm", channel=channel)
    try:
        with Board(0, tmp_path, timeout=5000) as board:
            ext = struct.pack("<BIIBHB", 0x01, code, mask, 0, 0, 0) + bytes(28)
            assert board.transact(Message(rx=3, tx=16, b=68,
                                          data=bytes([0, 128, 0, 0]) + ext)).f == 0
            assert board.transact(Message(rx=3, tx=16, b=68, data=bus_parameters())).f == 0
            for ident in held + passed:
                sender.send(can.Message(arbitration_id=ident, is_extended_id=True, data=b"\x01"))
            got = []
            for _ in passed:
                rc, indication = d.DevGetMessage(0, 288, 5000)
                assert rc == 0 and indication is not None
                assert indication.b == 65 and indication.ln == 13
                got.append(int.from_bytes(indication.data[1:5], "big") >> 3)
            assert got == passed
            assert d.DevGetMessage(0, 288, 300)[0] == Drv.DRV_DEV_GET_TIMEOUT
    finally:
        sender.shutdown()
        card.stop()


# --- Baud_rate against the link's rate (seed 5.2.5.4.1, Err_Event 56) -----------------


@pytest.mark.parametrize("interface", ["shm"], indirect=True)
def test_a_baud_rate_the_shm_channel_does_not_run_is_err_event_56(
        make_net: Callable[..., Net], tmp_path: Path) -> None:
    """[ours] An ``shm`` channel runs at the rate of its first station that gave one: here
    ``cifemu sim``'s 500 kbit/s. Bus parameters asking for 125 kbit/s are Err_Event 56 at
    255 with CONTROL-ERROR (seed 4.3, "baudrate out of range"), at once, not the nodes' 34s
    seconds later; the card's facts show the channel's rate beside the Baud_rate."""
    net = make_net("[[node]]\nid = 1\n")
    assert net.send(68, bus_parameters(baud_rate=4)).f == 0  # 125 kbit/s
    diag = net.diag()
    assert (diag.bErr_rem_adr, diag.bErr_event) == (255, BAUD_RATE_OUT_OF_RANGE)
    assert diag.bGlobalBits & CTRL
    info = read_card_info(tmp_path, 0)
    assert info is not None
    assert (info["bus"]["bitrate"], info["bus"]["baud_rate"]) == (500000, 125000)


@pytest.mark.parametrize("interface", ["shm"], indirect=True)
def test_the_shm_channel_rate_matches_the_baud_rate(make_net: Callable[..., Net]) -> None:
    """The channel's 500 kbit/s and Baud_rate 2: no Err_Event, the node comes up."""
    net = make_net("[[node]]\nid = 1\n")
    assert net.send(68, bytes([0, 1, 0, 0]) + node_set(1)).f == 0
    assert net.send(68, bus_parameters(baud_rate=2)).f == 0
    net.wait_operating([1])
    diag = net.diag()
    assert (diag.bErr_rem_adr, diag.bErr_event) == (0, 0)
    assert not diag.bGlobalBits & CTRL


@pytest.mark.parametrize("interface", ["virtual", "socketcan"], indirect=True)
def test_no_false_56_where_the_link_has_no_rate(make_net: Callable[..., Net]) -> None:
    """``virtual`` has no bit rate, and neither has ``vcan`` (the kernel reports no bit
    timing for it): nothing to compare, so any Baud_rate is no error. (A real SocketCAN
    link's rate comes from the kernel, see the next test; vcan cannot show a mismatch.)"""
    net = make_net("[[node]]\nid = 1\n")
    assert net.send(68, bus_parameters(baud_rate=4)).f == 0
    diag = net.diag()
    assert (diag.bErr_rem_adr, diag.bErr_event) == (0, 0)
    assert not diag.bGlobalBits & CTRL


HELD_IP = """#!/bin/sh
# iproute2's ip, held while {hold} exists (tests/test_bus_parameter_set.py)
if [ -e {hold} ]; then echo "held $*" >> {calls}; else echo "$*" >> {calls}; fi
while [ -e {hold} ]; do sleep 0.05; done
exec {real} "$@"
"""


@pytest.mark.vcan
def test_the_device_loop_answers_while_ip_is_slow(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """A bus parameter download on SocketCAN compares Baud_rate with the link's rate, which
    ``ip`` reports, about a second a call inside User-Mode Linux. The card reads it once,
    when it opens the link, not from the device loop at each download: with ``ip`` held,
    the download and a COM_Shared_Memory behind it are both answered, in order, f 0, and
    no ``ip`` held them back (the card waited up to 2 s for each, twice per download on
    vcan, and answered nothing meanwhile).

    The ``ip`` first on the firmware's PATH is a stand-in that holds while a file exists:
    the real one cannot be slowed. It runs the real one after, and logs every call, which
    shows the card did look at vcan0's rate through it, and which calls were held."""
    reason = socketcan_missing()
    if reason is not None:
        pytest.skip(reason)
    real = shutil.which("ip")
    if real is None:
        pytest.skip("no ip (iproute2) on this machine")
    bin_dir, card_dir = tmp_path / "bin", tmp_path / "card"
    bin_dir.mkdir()
    card_dir.mkdir()
    hold, calls = tmp_path / "hold", tmp_path / "ip-calls"
    fake = bin_dir / "ip"
    fake.write_text(HELD_IP.format(hold=hold, calls=calls, real=real), encoding="utf-8")
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    card = start_card(card_dir, 0, "--interface", "socketcan", "--channel", "vcan0")
    timeout = int(5000 * TIME_SCALE)
    try:
        wait_until(lambda: calls.exists() and "vcan0" in calls.read_text(encoding="utf-8"),
                   5 * TIME_SCALE, "the card looked at vcan0's rate through the stand-in ip")
        hold.touch()
        read = TelegramHeader(data_area=1, data_cnt=8, data_type=Tdt.UINT8,
                              function=Tfc.READ).encode()
        with Board(0, card_dir, timeout=timeout) as board:
            board.put_message(Message(rx=3, tx=16, b=68, data=bus_parameters()))
            try:
                board.put_message(Message(rx=2, tx=16, b=COM_SHARED_MEMORY, nr=7, data=read))
                answers = [board.get_message() for _ in range(2)]
            except CifError as exc:
                pytest.fail(f"the card answered nothing while ip was held ({exc})")
        held = [line for line in calls.read_text(encoding="utf-8").splitlines()
                if line.startswith("held")]
        assert not held, f"the answers waited for ip: {held}"
        assert [(a.a, a.f) for a in answers] == [(68, 0), (COM_SHARED_MEMORY, 0)]
    finally:
        hold.unlink(missing_ok=True)
        card.stop()


def test_the_rate_of_a_socketcan_link_is_its_bit_timing() -> None:
    """``ip -details -json link show`` of a CAN link carries the kernel's bit timing
    (IFLA_CAN_BITTIMING); a vcan link has none."""
    can0 = [{"ifname": "can0", "linkinfo": {"info_kind": "can", "info_data": {
        "ctrlmode": [], "state": "ERROR-ACTIVE", "restart_ms": 0,
        "bittiming": {"bitrate": 125000, "sample_point": "0.875", "tq": 500}}}}]
    vcan0 = [{"ifname": "vcan0", "linkinfo": {"info_kind": "vcan"}}]
    assert bitrate_of_link(can0) == 125000
    assert bitrate_of_link(vcan0) is None
    assert bitrate_of_link([]) is None


# --- Bus_Error_Cnt counts an overstep once (seed 4.3) --------------------------------

BUS_ERROR_CNT = 0x1F44
"""Task2State's usBus_Error_Cnt (seed 4.3)."""


def controller_state(status: int) -> can.Message:
    """A SocketCAN controller-state error frame (CAN_ERR_CRTL, the state in data byte 1)."""
    return can.Message(is_error_frame=True, arbitration_id=CAN_ERR_CRTL, dlc=8,
                       data=bytes([0, status, 0, 0, 0, 0, 0, 0]))


def test_bus_error_cnt_counts_one_escalation_once(tmp_path: Path) -> None:
    """Seed 4.3: Bus_Error_Cnt is the "number of detected bus error limit oversteps". The
    controller's counters climb past the warning limit and on past the error-passive limit:
    two error frames, one overstep, 1. Back to error-active, a new warning crossing is 2."""
    channel = f"test-{uuid.uuid4().hex}"
    card = start_card(tmp_path, 0, "--interface", "shm", "--channel", channel)
    station = can.Bus(interface="shm", channel=channel)
    image = card.map()
    try:
        station.send(controller_state(CAN_ERR_CRTL_TX_WARNING))
        wait_until(lambda: struct.unpack_from("<H", image, BUS_ERROR_CNT)[0] == 1, 5,
                   "the warning crossing counted")
        for status in (CAN_ERR_CRTL_TX_PASSIVE, CAN_ERR_CRTL_ACTIVE, CAN_ERR_CRTL_RX_WARNING):
            station.send(controller_state(status))
        wait_until(lambda: struct.unpack_from("<H", image, BUS_ERROR_CNT)[0] >= 2, 5,
                   "the second overstep counted")
        window(0.3, "no third count after the two crossings")
        assert struct.unpack_from("<H", image, BUS_ERROR_CNT)[0] == 2
    finally:
        image.close()
        station.shutdown()
        card.stop()


@pytest.mark.parametrize("interface", ["shm"], indirect=True)
def test_synchronous_outputs_follow_another_stations_sync(make_net: Callable[..., Net]) -> None:
    """Seed revision 16: with SYNC_Timer 0 the SYNC comes from another station, and the
    card's synchronous RX-PDO (type 1) follows it: the host's outputs reach the node, whose
    echo comes back into the input image."""
    net = make_net(SYNCHRONOUS_NODE)
    net.configure()
    net.wait_operating([1])
    station = can.Bus(interface="shm", channel=net.channel)
    sync = station.send_periodic(can.Message(arbitration_id=SYNC_ID, is_extended_id=False),
                                 0.02)
    try:
        wait_until(lambda: exchange(net, b"\x11" * 8) == b"\x11" * 8, 5,
                   "node 1's echo of outputs sent at the foreign SYNC")
    finally:
        sync.stop()
        station.shutdown()
