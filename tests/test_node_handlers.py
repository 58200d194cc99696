"""The node handlers as a host sees them: boot-up, supervision, Nd_state and NEXC.

Each test brings a card up with simulated nodes, provokes one behaviour through the mailbox or
the image, and asserts what the seed manual gives the host to see (Err_Event, Nd_state, NEXC,
frames in the card's trace). Like ``tests/test_seed_fidelity.py`` it runs on every bus of
``tests/can_net.py``'s back-to-back fixture; the test of a boot-up message injects its
frames on the ``shm`` bus (``tests/shm_rig.py``).
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable
from pathlib import Path

import can
import pytest

from dbm_tools.network import parse_network
from dpm.message import Message
from dpm.task2 import ComDiagnostics, GlobalBits
from host_api import driver as d
from host_api.online import configure_online
from tests.can_net import Net, actual_error, bus_parameters, candump, node_set, window
from tests.conftest import LoadDeadline, wait_until
from tests.shm_rig import NODE, Rig

pytest_plugins = ["tests.can_net", "tests.shm_rig"]
"""The back-to-back fixtures (make_net on every bus) and the shm rig."""

NMT_START, NMT_STOP, NMT_RESET = 0x01, 0x02, 0x81


def nexc(net: Net) -> bool:
    return bool(net.diag().global_bits & GlobalBits.NEXC)


# --- a 252 input whose node never answers the remote request ---------------------------


def test_an_unanswered_252_remote_request_is_err_event_33(make_net: Callable[..., Net]) -> None:
    """Seed 4.3, Err_Event 33 "no response to a configured remote frame PDO". Node 1's TPDO1
    is of type 252 but refuses remote frames (1800h:1 bit 30, written by the card from the
    SDO list): the card asks at every SYNC and never gets it. [ours] No answer within two
    SYNC periods of the first unanswered request is 33, however punctual the SYNCs are."""
    net = make_net("""[bus]
sync_period_ms = 100
[[node]]
id = 1
[[node.sdo]]
index = 0x1800
subindex = 2
value = 252
size = 1
[[node.sdo]]
index = 0x1800
subindex = 1
value = 0x40000181
size = 4
[[node.pdo]]
direction = "input"
cob_id = 0x181
transmission = 252
""")
    net.configure()
    wait_until(lambda: net.diag().bErr_event == 33, 10, "Err_Event 33 of node 1")
    assert net.diag().bErr_rem_adr == 1
    assert actual_error(net, 1) == 33


# --- a node that finishes its boot-up after auto-clear ---------------------------------


def test_a_node_booting_after_auto_clear_is_stopped_on_the_bus(make_net: Callable[..., Net],
                                                                tmp_path: Path) -> None:
    """Seed 4.3 (39, "node in stop") and 5.2.5.4.1 (Auto_Clear): node 2 finishes its boot-up
    after auto-clear stopped the network. The card reports it stopped, so it must be stopped:
    no Start_Node for it after the broadcast Stop, and its heartbeat reads STOPPED (04) to the
    end, not OPERATIONAL."""
    trace = tmp_path / "trace.log"
    net = make_net("""[bus]
auto_clear = true
[[node]]
id = 1
heartbeat_ms = 200
[node.sim]
heartbeat_stop_after_s = 0.3
[[node]]
id = 2
heartbeat_ms = 200
[node.sim]
boot_delay_s = 2.0
""", "--trace", str(trace))
    net.configure()
    wait_until(lambda: net.diag().can_state_name == "CLEAR" and actual_error(net, 2) == 39, 10,
               "node 2 stopped by auto-clear after its boot-up")
    window(0.6, "several of node 2's heartbeats (100 ms) with no start for it")
    net.card.stop()
    frames = candump(trace)
    cleared = min(t for t, ident, data in frames if ident == 0 and data == "0200")
    assert "0102" not in [data for t, ident, data in frames if ident == 0 and t > cleared]
    beats = [data for _, ident, data in frames if ident == 0x702]
    assert beats and beats[-1] == "04"


# --- Nd_state of a node without supervision after a start its boot did not send --------


def test_unsupervised_nodes_show_in_nd_state_after_the_global_start(
        make_net: Callable[..., Net]) -> None:
    """Seed 4.3 (Nd_state) and 5.2.9: nodes without error control, started by the global
    Start_Node (biNoGobalStartNode), are in data exchange: their Nd_state bits come."""
    net = make_net("""[bus]
global_start = true
[[node]]
id = 1
error_control = "none"
[[node]]
id = 2
error_control = "none"
""")
    net.configure()
    net.wait_operating([1, 2])
    assert net.diag().bErr_event == 0


def test_an_unsupervised_node_started_by_the_host_shows_in_nd_state(
        make_net: Callable[..., Net]) -> None:
    """Seed 5.2.5.3 (START skipped) and 5.2.9 (COM_NMT_Module_Protocol): node 1, whose boot
    leaves the start to the host, comes into Nd_state when the host starts it; node 2,
    stopped by the host, leaves it and comes back when the host starts it again."""
    net = make_net("""[[node]]
id = 1
error_control = "none"
boot = ["reset", "device", "guard", "sync", "emcy", "sdo", "pdo"]
[[node]]
id = 2
error_control = "none"
""")
    net.configure()
    net.wait_operating([2])

    def started() -> bool:
        # node 1 may still be booting when node 2 is up (inside User-Mode Linux it was): a
        # Start before its boot ends is no start the card can take, so the host sends it
        # again until node 1 shows, as a host polling Nd_state would
        assert net.send(96, bytes([NMT_START, 1])).f == 0
        return net.diag().operating() == [1, 2]

    wait_until(started, 10, "node 1 in data exchange after the host's Start")
    assert net.send(96, bytes([NMT_STOP, 2])).f == 0
    net.wait_operating([1])
    assert net.send(96, bytes([NMT_START, 2])).f == 0
    net.wait_operating([1, 2])
    assert net.diag().bErr_event == 0


# --- the first TX-PDO is requested at boot, whatever its type --------------------------


def test_the_first_tx_pdo_of_every_type_is_requested_after_the_boot(
        make_net: Callable[..., Net], tmp_path: Path) -> None:
    """Seed 5.2.5.1.1, bitConfigNdState TXRXPDO: "Request first TX or send first RX PDO after
    initialization sequence is finished". Node 1's input is event-driven (255), node 2's
    synchronous (1): each gets a remote request once its boot-up is through."""
    trace = tmp_path / "trace.log"
    net = make_net("""[bus]
sync_period_ms = 100
[[node]]
id = 1
[[node.pdo]]
direction = "input"
cob_id = 0x181
transmission = 255
[[node]]
id = 2
[[node.pdo]]
direction = "input"
cob_id = 0x182
transmission = 1
""", "--trace", str(trace))
    net.configure()
    net.wait_operating([1, 2])
    window(0.3, "the remote requests after the boot-up to reach the trace")
    net.card.stop()
    frames = candump(trace)
    for node in (1, 2):
        start = min(t for t, ident, data in frames if ident == 0 and data in (
            f"01{node:02X}", "0100"))
        assert [t for t, ident, data in frames if ident == 0x180 + node and data == "R"
                and t >= start], f"no remote request of node {node}'s TX-PDO"


# --- NEXC while nodes do not exchange data --------------------------------------------


def test_nexc_while_a_node_waits_for_its_start_and_while_the_host_is_not_ready(
        make_net: Callable[..., Net]) -> None:
    """Seed 4.3 NEXC: "At least one node has not reached the data exchange state". Node 1
    skips START and sits in PRE-OPERATIONAL: NEXC set; the host starts it: clear; the host
    goes NOT_READY and every node is stopped (39): set again."""
    net = make_net("""[[node]]
id = 1
boot = ["reset", "device", "guard", "sync", "emcy", "sdo", "pdo"]
[[node]]
id = 2
""")
    net.configure()
    net.wait_operating([2])
    wait_until(lambda: nexc(net), 5, "NEXC while node 1 waits for its start")
    assert net.send(96, bytes([NMT_START, 1])).f == 0
    net.wait_operating([1, 2])
    wait_until(lambda: not nexc(net), 5, "NEXC clear with both nodes in data exchange")
    assert d.DevSetHostState(0, d.HOST_NOT_READY, 1000) == 0
    wait_until(lambda: net.diag().bErr_event == 39, 5, "Err_Event 39")
    wait_until(lambda: nexc(net), 5, "NEXC with the nodes stopped")


def test_a_start_the_host_sends_while_the_node_boots_is_not_forgotten(rig: Rig) -> None:
    """Seed 4.3 NEXC and 5.2.9: a node with START skipped waits for the host's Start_Node.
    When that comes while the card still configures the node (after its reset), the node is
    running when its boot-up ends: Nd_state set, NEXC clear. The test's station plays node 3
    and holds its answer to the 1000h read until the host's start has gone out (seen under
    load: the start came mid-boot, and NEXC stayed set for good)."""
    configure_online(rig.board, parse_network(
        f'[[node]]\nid = {NODE}\nerror_control = "none"\n'
        '[[node]]\nid = 3\nerror_control = "none"\ndevice_type = 0x191\n'
        'boot = ["reset", "device"]\n'))

    def frame(ident: int, data: bytes | None = None) -> can.Message:
        deadline = LoadDeadline(10)
        while (left := deadline.left()) > 0:
            msg = rig.station.recv(min(left, 0.5))
            if (msg is not None and msg.arbitration_id == ident
                    and (data is None or bytes(msg.data) == data)):
                return msg
        raise AssertionError(f"no frame {ident:03X} from the card")

    frame(0x000, bytes([NMT_RESET, 3]))
    rig.send(0x703, b"\x00", time.time())  # the boot-up message
    request = frame(0x603)
    assert request.data[:4] == bytes([0x40, 0x00, 0x10, 0x00])  # 1000h upload
    assert rig.board.transact(Message(rx=3, tx=16, b=96, data=bytes([NMT_START, 3]))).f == 0
    frame(0x000, bytes([NMT_START, 3]))
    rig.send(0x583, bytes([0x43, 0x00, 0x10, 0x00, 0x91, 0x01, 0x00, 0x00]), time.time())
    wait_until(lambda: rig.diag().operating() == [NODE, 3], 5, "both nodes in Nd_state")
    wait_until(lambda: not rig.diag().global_bits & GlobalBits.NEXC, 5, "NEXC clear")
    assert rig.diag().bErr_event == 0


# --- no reaction on the boot-up message of an unsupervised node -----------------------


def test_the_boot_up_message_of_an_unsupervised_node_gets_no_reaction(rig: Rig) -> None:
    """Seed 8.1: "Bootup Protocol, no reaction on Bootup Events of a Node". A node without
    error control sends a boot-up message while in data exchange: no Err_Event, it stays in
    Nd_state."""
    configure_online(rig.board, parse_network(f'[[node]]\nid = {NODE}\nerror_control = "none"\n'))
    wait_until(lambda: rig.diag().operating() == [NODE], 10, "the node in data exchange")
    rig.send(0x700 + NODE, b"\x00", time.time())
    # An EMCY behind it: once it shows in Nd_diag, the boot-up before it has been judged.
    rig.send(0x80 + NODE, struct.pack("<HB5x", 0x1000, 1), time.time())
    wait_until(lambda: NODE in rig.diag().diagnostic(), 5, "the EMCY in Nd_diag")
    assert rig.diag().bErr_event == 0
    assert rig.diag().operating() == [NODE]


# --- a heartbeat node that refuses the write of 1017h ----------------------------------


def test_a_heartbeat_node_refusing_1017h_still_boots(make_net: Callable[..., Net]) -> None:
    """Seed 5.2.5.1.1: the card consumes heartbeats; a node whose producer time 1017h is not
    writable (it produces at its own rate, here 500 ms) boots as one that takes it: no 34,
    no Prm_Fault, in data exchange and supervised (consumer time 1000 ms). The data set comes
    by COM_Download, as a host sends it: a heartbeat node without 1017h in its SDO list."""
    net = make_net("""[[node]]
id = 1
heartbeat_ms = 1000
[node.sim]
sdo_abort = { "1017:0" = 0x06010002 }
""")
    assert net.send(68, bytes([0, 1, 0, 0]) + node_set(1)).f == 0
    assert net.send(68, bus_parameters()).f == 0
    net.wait_operating([1])
    window(1.5, "supervision: its own heartbeat keeps it operating")
    assert net.diag().operating() == [1]
    assert net.diag().bErr_event == 0
    answer = net.send(66, struct.pack("<BBHBBBB", 1, 0, 0, 0, 0, 0, 1))
    assert answer.f == 0 and not answer.data[8] & 0x04  # Nodestatus_1: no Prm_Fault


def boot_outcome(net: Net, node: int) -> int:
    """Configure the network from its TOML (``configure_online``) and wait for ``node`` to
    end a boot-up that got every answer: 0 in data exchange, else its Err_Event (seed 4.3).

    A boot-up that ran into the card's SDO time-out (0.5 s on the wall clock, the card's
    own timer) ends with 34 and No_Response but no Prm_Fault; the card boots the node again
    a second later. That is the loaded machine's doing (a starved node answered late), not
    the outcome a test looks for: a refused write is 34 *with* Prm_Fault. So such an end is
    waited past, to the retry's."""
    net.configure()

    def ended() -> bool:
        if net.diag().operating() == [node]:
            return True
        error = actual_error(net, node)
        return error != 0 and (error != 34 or prm_fault(net, node))

    wait_until(ended, 15, f"node {node}'s boot-up to end other than on an SDO time-out")
    return actual_error(net, node)


def prm_fault(net: Net, node: int) -> bool:
    """Nodestatus_1's Prm_Fault in the node's COM_Node_Diag answer (seed 5.2.7)."""
    answer = net.send(66, struct.pack("<BBHBBBB", node, 0, 0, 0, 0, 0, 1))
    assert answer.f == 0
    return bool(answer.data[8] & 0x04)


def test_a_heartbeat_node_refusing_1017h_boots_from_its_network_description(
        make_net: Callable[..., Net]) -> None:
    """The same node configured from a network description: the builder puts 1017h = half
    the consumer time into its SDO list, and that write's abort is tolerated as well
    ([ours], firmware/can/boot.py: the card consumes the heartbeat, whoever writes 1017h)."""
    net = make_net("""[[node]]
id = 1
heartbeat_ms = 1000
[node.sim]
sdo_abort = { "1017:0" = 0x06010002 }
""")
    assert boot_outcome(net, 1) == 0
    assert not prm_fault(net, 1)


@pytest.mark.parametrize("refused", ["1005:0", "1014:0"])
def test_a_node_refusing_the_default_sync_or_emcy_cob_id_still_boots(
        make_net: Callable[..., Net], refused: str) -> None:
    """[ours] A node without 1005h/1014h, or with them read-only, uses the CiA 301 defaults
    80h and 80h + node-ID: a refused write of that default is no configuration failure."""
    net = make_net(f"""[[node]]
id = 1
[node.sim]
sdo_abort = {{ "{refused}" = 0x06010002 }}
""")
    assert boot_outcome(net, 1) == 0
    assert not prm_fault(net, 1)


def test_an_unguarded_node_without_guarding_objects_still_boots(
        make_net: Callable[..., Net]) -> None:
    """[ours] With no error control the GUARD step writes guard time 0 (100Ch) and the life
    time factor (100Dh) only to switch guarding off; a node without those objects (CiA 301
    lets a heartbeat producer do without them, as a CANopenNode device does) is not guarded
    either way, so their refusal is no configuration failure."""
    net = make_net("""[[node]]
id = 1
error_control = "none"
[node.sim]
sdo_abort = { "100C:0" = 0x06020000, "100D:0" = 0x06020000 }
""")
    assert boot_outcome(net, 1) == 0
    assert not prm_fault(net, 1)


def test_a_guarded_node_refusing_its_guard_time_fails_its_configuration(
        make_net: Callable[..., Net]) -> None:
    """The other side: a guard time the node refuses fails its configuration (34 with
    Prm_Fault), or the card would guard a node that never answers."""
    net = make_net("""[[node]]
id = 1
error_control = "guarding"
guard_time_ms = 200
[node.sim]
sdo_abort = { "100C:0" = 0x06020000 }
""")
    assert boot_outcome(net, 1) == 34
    assert prm_fault(net, 1)


def test_a_node_refusing_another_emcy_cob_id_fails_its_configuration(
        make_net: Callable[..., Net]) -> None:
    """The other side of the rule: a COB-ID other than the default must be taken, or the
    card would expect EMCY frames the node never sends: 34 with Prm_Fault."""
    net = make_net("""[[node]]
id = 1
emcy_cob_id = 0x0A1
[node.sim]
sdo_abort = { "1014:0" = 0x06010002 }
""")
    assert boot_outcome(net, 1) == 34
    assert prm_fault(net, 1)


# --- auto-clear and a node that never booted ---------------------------------------------


def test_auto_clear_leaves_the_network_running_when_a_node_fails_its_first_boot(
        make_net: Callable[..., Net]) -> None:
    """Seed 5.2.5.4.1: auto-clear stops all "if one as active classified node has been
    disconnected". [ours] A node that never reached data exchange was never connected: its
    failed boot is reported (34) and retried, the others keep running (OPERATE, no ACLR)."""
    net = make_net("""[bus]
auto_clear = true
[[node]]
id = 1
[node.sim]
silent = true
[[node]]
id = 2
""")
    net.configure()
    wait_until(lambda: actual_error(net, 1) == 34, 15, "node 1's boot-up failing with 34")
    net.wait_operating([2])
    window(0.5, "node 1's failure not to stop the card (no auto-clear)")
    diag = net.diag()
    assert diag.can_state_name == "OPERATE" and not diag.global_bits & GlobalBits.ACLR
    assert diag.operating() == [2]


# --- silent nodes do not hold up the boot-up of the others -----------------------------


def test_a_node_boots_while_32_silent_nodes_wait_for_their_answers(
        make_net: Callable[..., Net]) -> None:
    """Each node's boot-up goes on when its node answers, whatever the others do (issue 22):
    32 nodes that never answer (each fails with 34 after some 3 s of reset, boot-up wait and
    reading 1000h) do not keep node 40, configured after them, from data exchange. A card
    that boots in a pool of 32 waiting threads boots node 40 only after a silent node's
    boot-up has ended, with its 34."""
    silent = "".join(f"[[node]]\nid = {n}\n[node.sim]\nsilent = true\n" for n in range(1, 33))
    net = make_net(silent + "[[node]]\nid = 40\n")
    net.configure()
    seen: list[ComDiagnostics] = []

    def node_40_operating() -> bool:
        seen[:] = [net.diag()]
        return 40 in seen[0].operating()

    wait_until(node_40_operating, 15, "node 40 in data exchange")
    assert seen[0].bErr_event == 0, f"Err_Event {seen[0].bErr_event} came first"
    wait_until(lambda: net.diag().bErr_event == 34, 15, "the silent nodes' 34")
