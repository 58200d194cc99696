"""Frames the card reads late are judged by when they were on the bus, not when it read them.

On a loaded machine (one CPU under User-Mode Linux, booting many nodes) the card's receive
thread falls behind the bus by up to a second; candump showed a node's last pre-operational
heartbeat, sent before the card's NMT Start_Node, read more than START_GRACE after the start,
and the card failed the node with Err_Event 31 although it had done nothing wrong. Here the
frame is injected on the ``shm`` bus with that time stamp (a station that keeps the stamps it
is given), as the card would read it from a queue it fell behind on.
"""

from __future__ import annotations

import struct
import time

from dbm_tools.network import parse_network
from firmware.can.supervision import START_GRACE
from firmware.shm.bus import ShmBus
from host_api.online import configure_online
from tests.conftest import wait_until
from tests.shm_rig import NETWORK, NODE, Rig

pytest_plugins = ["tests.shm_rig"]

PRE_OPERATIONAL, TOGGLE, NMT_START = 0x7F, 0x80, 0x01


def start_stamp(station: ShmBus, deadline: float) -> float:
    """The bus time stamp of the card's NMT Start_Node to the node."""
    while time.monotonic() < deadline:
        msg = station.recv(0.1)
        if msg is not None and msg.arbitration_id == 0 and bytes(msg.data) == bytes(
                [NMT_START, NODE]):
            return msg.timestamp
    raise AssertionError("no Start_Node for the node on the bus")


def test_a_pre_operational_report_sent_before_the_start_and_read_late_is_no_departure(
        rig: Rig) -> None:
    configure_online(rig.board, parse_network(NETWORK))
    started = start_stamp(rig.station, time.monotonic() + 10)
    wait_until(lambda: rig.diag().operating() == [NODE], 10, "the node in data exchange")
    read_late = started + START_GRACE + 0.2
    wait_until(lambda: time.time() > read_late, 5, "the start's grace to pass")
    # On the bus 50 ms before the start, read now: the card fell behind, the node did not.
    rig.send(0x700 + NODE, bytes([PRE_OPERATIONAL]), started - 0.05)
    # An EMCY behind it: the card reads a station's frames in order, so once the EMCY shows
    # in Nd_diag the heartbeat before it has been judged.
    rig.send(0x80 + NODE, struct.pack("<HB5x", 0x1000, 1), time.time())
    wait_until(lambda: NODE in rig.diag().diagnostic(), 5, "the EMCY in Nd_diag")
    assert rig.diag().bErr_event == 0
    assert rig.diag().operating() == [NODE]
    # The same report sent now is a departure (Err_Event 31): the frames do reach the card.
    # (Its toggle bit differs from the first one's, as a guarded node's answers alternate.)
    rig.send(0x700 + NODE, bytes([TOGGLE | PRE_OPERATIONAL]), time.time())
    wait_until(lambda: rig.diag().bErr_event == 31, 5, "Err_Event 31")
    assert rig.diag().bErr_rem_adr == NODE


def test_an_adapter_stamping_by_its_own_clock_still_reports_a_departure(rig: Rig) -> None:
    """Some adapters stamp frames in seconds since their own power-on. Such a stamp is not
    the wall clock's, so it must not make a node's departure look older than its start."""
    configure_online(rig.board, parse_network(NETWORK))
    started = start_stamp(rig.station, time.monotonic() + 10)
    wait_until(lambda: rig.diag().operating() == [NODE], 10, "the node in data exchange")
    wait_until(lambda: time.time() > started + START_GRACE + 0.2, 5, "the start's grace")
    rig.send(0x700 + NODE, bytes([PRE_OPERATIONAL]), 1234.5)  # 20 min after power-on
    wait_until(lambda: rig.diag().bErr_event == 31, 5, "Err_Event 31")
    assert rig.diag().bErr_rem_adr == NODE
