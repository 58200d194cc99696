"""A node configured without error control that produces heartbeats anyway.

Many CANopen devices produce a heartbeat from power-on (1017h non-zero by default). When the
network description gives the node no error control, the card neither sets 1017h nor
supervises the node; its heartbeats are then no guarding answers, and their toggle bit (always
0 in a heartbeat) is no guarding sequence error (Err_Event 32): the node stays in data
exchange.
"""

from __future__ import annotations

import time

from dbm_tools.network import parse_network
from host_api.online import configure_online
from tests.conftest import wait_until
from tests.shm_rig import NETWORK, NODE, Rig

pytest_plugins = ["tests.shm_rig"]
OPERATIONAL, PRE_OPERATIONAL = 0x05, 0x7F


def test_heartbeats_of_an_unsupervised_node_are_no_guarding_sequence_error(rig: Rig) -> None:
    configure_online(rig.board, parse_network(NETWORK))
    wait_until(lambda: rig.diag().operating() == [NODE], 10, "the node in data exchange")
    for _ in range(3):
        rig.send(0x700 + NODE, bytes([OPERATIONAL]), time.time())
    # Its state still counts: a heartbeat saying pre-operational is a departure (31), and it
    # comes after the three above, so once it shows they have been judged.
    rig.send(0x700 + NODE, bytes([PRE_OPERATIONAL]), time.time())
    wait_until(lambda: rig.diag().bErr_event != 0, 5, "an Err_Event")
    assert (rig.diag().bErr_rem_adr, rig.diag().bErr_event) == (NODE, 31)
