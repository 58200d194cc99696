"""The card on SocketCAN, seen and driven by tools nobody here wrote: can-utils.

Everything runs on ``vcan0`` as separate processes, as on a real bus: the card
(``cifemu firmware --interface socketcan``), the simulated nodes (``cifemu sim``),
``candump`` recording every frame with the kernel's receive time stamps, and
``cansend`` injecting frames the card must react to. The host side is the
driver API. These tests need SocketCAN: ``make test-vcan`` runs them inside
``tools/vcan-vm`` on a machine whose kernel has none.
"""

from __future__ import annotations

import itertools
import shutil
import signal
import statistics
import struct
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from dbm_tools.network import load_network
from dpm.com import acceptance_long
from dpm.errors import Drv
from dpm.message import Message
from host_api import driver as d
from host_api.board import Board
from host_api.online import configure_online
from tests import commands
from tests.buses import HOW_TO_RUN, SOCKETCAN_CHANNEL, socketcan_missing
from tests.can_net import start_sim
from tests.conftest import Card, start_card, wait_until

pytestmark = pytest.mark.vcan

MARK = 0x7FF
"""The identifier of candump's readiness marks (no CANopen service uses it)."""

NODE_DIAG = bytes([0, 0, 0, 0, 0, 5, 1])
"""COM_Node_Diag (msg.b 66) after the node address: the rest of its header."""


@dataclass(frozen=True)
class Frame:
    """One line of ``candump -L``: ``(time) channel ID#DATA`` or ``ID#R``."""

    time: float
    ident: int
    extended: bool
    remote: bool
    data: bytes

    @staticmethod
    def matching(ident: int, data: bytes) -> Callable[[Frame], bool]:
        return lambda f: f.ident == ident and not f.remote and f.data == data

    @classmethod
    def parse(cls, line: str) -> Frame:
        stamp, _, text = line.split()[:3]
        ident, _, payload = text.partition("#")
        remote = payload.startswith("R")
        return cls(float(stamp.strip("()")), int(ident, 16), len(ident) == 8, remote,
                   b"" if remote else bytes.fromhex(payload))


class Candump:
    """``candump -L vcan0`` writing to a file, running from before the test's first frame."""

    def __init__(self, path: Path) -> None:
        self.path = path
        with path.open("wb") as out:
            self.proc = subprocess.Popen(["candump", "-L", SOCKETCAN_CHANNEL], stdout=out)
        # Ready once it records a frame of our own (candump has no other sign of life).
        mark = f"{MARK:03X}#C0FFEE"
        wait_until(lambda: self._sent_and_seen(mark), 10, "candump to record a first frame")
        self.start = time.time()

    def _sent_and_seen(self, mark: str) -> bool:
        cansend(mark)
        return any(f.ident == MARK for f in self._recorded())

    def _recorded(self) -> list[Frame]:
        """Whole lines only: candump may be half-way through one."""
        written = self.path.read_text()
        return [Frame.parse(line) for line in written[: written.rfind("\n") + 1].splitlines()]

    def frames(self, ident: int | None = None) -> list[Frame]:
        """What it recorded so far, without its readiness marks."""
        return [f for f in self._recorded()
                if f.ident != MARK and (ident is None or f.ident == ident)]

    def wait_for(self, match: Callable[[Frame], bool], what: str, timeout: float = 10) -> None:
        wait_until(lambda: any(match(f) for f in self.frames()), timeout, what)

    def wait(self, ident: int, what: str, count: int = 1, timeout: float = 10) -> list[Frame]:
        wait_until(lambda: len(self.frames(ident)) >= count, timeout, what)
        return self.frames(ident)

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGINT)
        commands.wait(self.proc, 10)


def cansend(frame: str) -> None:
    subprocess.run(["cansend", SOCKETCAN_CHANNEL, frame], check=True)


@dataclass
class Bench:
    card: Card
    board: Board
    candump: Candump

    def send(self, b: int, data: bytes) -> Message:
        return self.board.transact(Message(rx=3, tx=16, b=b, data=data))

    def operating(self) -> list[int]:
        return self.board.diagnostics().operating()

    def wait_operating(self, nodes: list[int], timeout: float = 15) -> None:
        wait_until(lambda: self.operating() == nodes, timeout,
                   f"nodes {nodes} in data exchange (now {self.operating()})")

    def indication(self, b: int, timeout_ms: int = 5000) -> Message:
        """The next indication of kind ``b`` in the host mailbox (others are passed over)."""
        deadline = time.monotonic() + timeout_ms / 1000
        while time.monotonic() < deadline:
            rc, msg = d.DevGetMessage(0, 288, 200)
            if rc == 0 and msg is not None and msg.b == b:
                return msg
        pytest.fail(f"no indication msg.b {b} within {timeout_ms} ms")


@pytest.fixture
def bench(tmp_path: Path) -> Iterator[Callable[..., Bench]]:
    """A factory: candump first, then the card, then (with a network) ``cifemu sim``."""
    reason = socketcan_missing()
    if reason is not None:
        pytest.skip(reason)
    for tool in ("candump", "cansend", "cangen"):
        if shutil.which(tool) is None:
            pytest.skip(f"{tool} (can-utils) is missing: {HOW_TO_RUN}")
    made: list[Bench] = []
    sims: list[subprocess.Popen[bytes]] = []

    def make(toml: str | None = None, configure: bool = True) -> Bench:
        candump = Candump(tmp_path / "candump.log")
        card = start_card(tmp_path, 0, "--interface", "socketcan", "--channel",
                          SOCKETCAN_CHANNEL)
        board = Board(0, tmp_path, timeout=5000).open()
        bench = Bench(card, board, candump)
        made.append(bench)
        if toml is not None:
            path = tmp_path / "network.toml"
            path.write_text(toml)
            sims.append(start_sim(path, "socketcan", SOCKETCAN_CHANNEL))
            if configure:
                configure_online(board, load_network(path))
        return bench

    yield make
    for bench in made:
        bench.board.close()
        bench.card.stop()
        bench.candump.stop()
    for sim in sims:
        sim.terminate()
        commands.wait(sim, 10)


# --- candump records what the card was told to do ---------------------------------------------


RECORDED = """[bus]
sync_period_ms = 20
[[node]]
id = 1
[node.sim]
emcy_burst = { after_s = 2.0, count = 1, code = 0x2310 }
[[node]]
id = 2
error_control = "guarding"
guard_time_ms = 100
life_time_factor = 3
"""


def test_candump_sees_the_cards_nmt_sdo_pdo_guarding_and_the_nodes_emcy(
        bench: Callable[..., Bench]) -> None:
    b = bench(RECORDED)
    b.wait_operating([1, 2])
    dump = b.candump
    # NMT: the boot sequence resets each node and starts it (CiA 301: 000#<cs><node>).
    for nmt in (b"\x81\x01", b"\x01\x01", b"\x81\x02", b"\x01\x02"):
        dump.wait_for(Frame.matching(0, nmt), f"NMT {nmt.hex()}")
    # SDO: what the host asked for goes out as an expedited upload; the node's answer
    # is what the mailbox returns.
    answer = b.send(74, struct.pack("<BBHBBBB", 1, 0, 0x1018, 1, 0, 0, 1))
    assert answer.f == 0
    request = bytes([0x40, 0x18, 0x10, 0x01, 0, 0, 0, 0])
    dump.wait_for(Frame.matching(0x601, request), "the SDO request")
    response = [f for f in dump.frames(0x581) if f.data[1:4] == b"\x18\x10\x01"][-1]
    assert response.data[4:8] == answer.data[8:12]
    # PDO: the host's outputs for node 1 are RPDO1's data on the bus.
    outputs = bytes([0x11, 0x22, 0x33, 0x44, 0x55, 0x66, 0x77, 0x88])
    assert d.DevExchangeIO(0, 0, outputs, 0, 8, 2000)[0] == 0
    dump.wait_for(Frame.matching(0x201, outputs), "RPDO1 of node 1")
    # Guarding: remote frames for node 2 every 100 ms, answered with alternating toggles.
    # The toggle starts at 0 again after a boot-up, so the rule holds from node 2's last
    # one: a guest stalled past the life time (300 ms) lets the node's life guarding fire,
    # and the card then boots it again (CI once saw 05 FF 00 05 85: the node gone to
    # pre-operational, reset, and guarded again).
    def since_boot_up() -> list[Frame]:
        guards = dump.frames(0x702)
        boot_ups = [n for n, f in enumerate(guards) if not f.remote and f.data[:1] == b"\0"]
        return guards[boot_ups[-1] + 1:] if boot_ups else guards

    wait_until(lambda: sum(f.remote for f in since_boot_up()) >= 10, 10,
               "ten guarding requests since node 2's last boot-up")
    guards = since_boot_up()
    first = next(n for n, f in enumerate(guards) if f.remote)
    requests = [f for f in guards[first:] if f.remote]
    answers = [f.data[0] for f in guards[first:] if not f.remote]
    assert len(requests) >= 10
    # The period's upper bound is loose: a loaded machine delays the card's ticks.
    period = statistics.median(y.time - x.time for x, y in itertools.pairwise(requests))
    assert 0.09 < period < 0.5, period
    assert all(x ^ y == 0x80 for x, y in itertools.pairwise(answers)), [hex(a) for a in answers]
    assert {a & 0x7F for a in answers[-3:]} == {0x05}  # operational
    # NMT from the host: stop node 1, then start it again.
    assert b.send(96, bytes([2, 1])).f == 0
    assert b.send(96, bytes([1, 1])).f == 0
    wait_until(lambda: [f.data for f in dump.frames(0)][-2:] == [b"\x02\x01", b"\x01\x01"],
               5, "NMT stop and start of node 1, in that order")
    b.wait_operating([1, 2])
    # EMCY: the node's emergency on the bus is the one the card collected for the host.
    emcy = dump.wait(0x081, "node 1's EMCY")[0]
    wait_until(lambda: 1 in b.board.diagnostics().diagnostic(), 5, "Nd_diag of node 1")
    diag = b.send(66, bytes([1]) + NODE_DIAG).data[8:]
    assert diag[7] == 1 and diag[8:16] == emcy.data


def test_sync_comes_from_the_kernels_broadcast_manager(bench: Callable[..., Bench]) -> None:
    """The card hands SYNC to the kernel (SocketCAN's broadcast manager): candump's time
    stamps show the period, and SYNC goes on while the card's process is stopped."""
    b = bench("[bus]\nsync_period_ms = 10\n[[node]]\nid = 1\n"  # a synchronous RPDO: the
              '[[node.pdo]]\ndirection = "output"\ncob_id = 0x201\ntransmission = 1\n'
              '[[node.pdo]]\ndirection = "input"\ncob_id = 0x181\n')  # card sends SYNC
    b.wait_operating([1])
    syncs = b.candump.wait(0x080, "50 SYNCs", count=50)
    assert all(f.data == b"" and not f.remote for f in syncs)
    periods = [y.time - x.time for x, y in itertools.pairwise(syncs)]
    assert 0.009 < statistics.median(periods) < 0.011, periods
    b.card.freeze()
    try:
        frozen = time.time()
        wait_until(lambda: sum(f.time > frozen for f in b.candump.frames(0x080)) >= 30, 5,
                   "SYNC while the card's process is stopped")
    finally:
        b.card.thaw()


# --- cansend injects what the card must react to ----------------------------------------------


def test_transparent_reception_of_29_bit_frames_from_cansend(
        bench: Callable[..., Bench]) -> None:
    b = bench()
    # SJA1000 layout: ID.28..16 compared, ID.15..0 "don't care" (mask bit 1)
    ext = struct.pack("<BIIBHB", 0x01, acceptance_long(0x1ABC0000),
                      acceptance_long(0x0000FFFF), 0, 0, 0) + bytes(28)
    assert b.send(68, bytes([0, 128, 0, 0]) + ext).f == 0
    assert b.send(68, bytes([0, 127, 0, 0, 2]) + struct.pack("<HH", 0x80, 0) + bytes(2)).f == 0
    cansend("12340000#6E6F")  # outside the acceptance filter
    cansend("1BC#0A0B")  # an 11-bit frame: never transparent
    cansend("1ABC1234#010203")
    indication = b.indication(65)
    assert indication.data[0] == 0x83  # extended frame, DLC 3
    assert int.from_bytes(indication.data[1:5], "big") >> 3 == 0x1ABC1234
    assert indication.data[5:8] == b"\x01\x02\x03"
    assert d.DevGetMessage(0, 288, 300)[0] == Drv.DRV_DEV_GET_TIMEOUT


def test_layer2_indications_of_11_bit_frames_from_cansend(bench: Callable[..., Bench]) -> None:
    b = bench()
    assert b.send(68, bytes([0, 127, 0, 0, 2]) + struct.pack("<HH", 0x80, 0) + bytes(2)).f == 0
    assert b.send(82, struct.pack("<H", 0x123)).f == 0
    cansend("124#FF")  # not registered
    cansend("123#CAFE")
    cansend("123#R")
    received = b""
    while len(received) < 6:
        received += b.indication(83).data
    second = (0x123 & 7) << 5
    assert received == bytes([0x123 >> 3, second | 2, 0xCA, 0xFE, 0x123 >> 3, second | 0x10])


def test_emcy_from_cansend_reaches_the_node_diagnosis(bench: Callable[..., Bench]) -> None:
    b = bench("[[node]]\nid = 1\n")
    b.wait_operating([1])
    cansend("081#1023AA0102030405")  # 1023h, error register AAh, five vendor bytes
    wait_until(lambda: 1 in b.board.diagnostics().diagnostic(), 5, "Nd_diag of node 1")
    diag = b.send(66, bytes([1]) + NODE_DIAG).data[8:]
    assert diag[7] == 1  # Emcy_Entries
    assert diag[8:16] == bytes.fromhex("1023AA0102030405")
    assert b.operating() == [1]  # an emergency alone does not stop the data exchange


def test_boot_up_from_cansend_is_forwarded_and_the_node_booted_again(
        bench: Callable[..., Bench]) -> None:
    b = bench("[[node]]\nid = 1\n")
    b.wait_operating([1])
    assert b.send(116, bytes([1])).f == 0  # boot-up forwarding on
    resets = len([f for f in b.candump.frames(0x000) if f.data == bytes([0x81, 1])])
    cansend("701#00")
    assert b.indication(117).data == b"\x01"
    wait_until(lambda: b.board.diagnostics().bErr_event == 31, 5, "Err_Event 31")
    assert b.board.diagnostics().bErr_rem_adr == 1
    # The card boots the node again: another NMT reset node on the bus, then data exchange.
    wait_until(lambda: len([f for f in b.candump.frames(0x000) if f.data == bytes([0x81, 1])])
               > resets, 10, "NMT reset node 1 again")
    b.wait_operating([1])


def test_heartbeat_from_cansend_going_silent(bench: Callable[..., Bench]) -> None:
    """Node 5's own heartbeat dies at once (a simulator fault); the card's heartbeat
    consumer (1 s) is fed by can-utils alone, until they stop. cangen, not a loop of
    cansend: one process sending every 100 ms, where a loaded machine could hold a
    shell's fork and exec back for longer than the consumer time."""
    b = bench("[[node]]\nid = 5\nheartbeat_ms = 1000\n[node.sim]\n"
              "heartbeat_stop_after_s = 0.0\n", configure=False)
    beating = subprocess.Popen(["cangen", SOCKETCAN_CHANNEL, "-g", "100", "-I", "705", "-L", "1",
                                "-D", "05"])
    try:
        configure_online(b.board, load_network(b.card.directory / "network.toml"))
        b.wait_operating([5])
        alive = time.monotonic() + 2.5  # well past the consumer time
        while time.monotonic() < alive:
            diag = b.board.diagnostics()
            assert diag.operating() == [5] and diag.bErr_event == 0, diag.bErr_event
            time.sleep(0.05)
    finally:
        beating.kill()
        beating.wait()
    wait_until(lambda: b.board.diagnostics().bErr_event == 30, 5, "Err_Event 30")
    assert b.board.diagnostics().bErr_rem_adr == 5 and 5 not in b.operating()


def test_the_cards_frames_on_socketcan_take_no_select_of_python_can(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 22: a frame the card sends or receives on SocketCAN is one write or one read of
    the socket after the receive thread's own ``select``; python-can's ``send`` and
    ``recv(0)`` added a ``select`` each (a system call) and two to four clock readings,
    and the receive thread read the clock once per frame for deadlines it did not have:
    each a ptrace round trip of the host inside User-Mode Linux. Counted: the ``select``
    calls and the receive thread's clock readings while the card sends 50 frames and
    receives 50 (all of them arrive, in order, with their data)."""
    reason = socketcan_missing()
    if reason is not None:
        pytest.skip(reason)
    import select

    import can

    from firmware.can.bus import CanBus

    selects = 0
    real_select = select.select

    def counting(*args: Any) -> Any:
        nonlocal selects
        selects += 1
        return real_select(*args)

    readings = 0
    real_monotonic = time.monotonic

    def clock() -> float:
        nonlocal readings
        readings += threading.current_thread().name == "can-receive"
        return real_monotonic()

    card = CanBus("socketcan", SOCKETCAN_CHANNEL)
    peer = can.Bus(interface="socketcan", channel=SOCKETCAN_CHANNEL)
    got: list[bytes] = []
    try:
        card.subscribe(0x181, lambda msg: got.append(bytes(msg.data)))
        monkeypatch.setattr(select, "select", counting)  # python-can's and the receiver's
        monkeypatch.setattr(time, "monotonic", clock)
        for n in range(50):
            assert card.send(0x201, bytes([n, 1]))
            peer.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=[n]))
            sent = peer.recv(2.0)
            assert sent is not None and bytes(sent.data) == bytes([n, 1])
        wait_until(lambda: len(got) == 50, 5.0)
        monkeypatch.undo()
    finally:
        monkeypatch.undo()
        peer.shutdown()
        card.shutdown()
    assert got == [bytes([n]) for n in range(50)]
    # the peer's own recv and send: 2 per round; the card's receive thread's own wait: at
    # most 1 per frame received; python-can's for the card's frames: none (2 a round before)
    assert selects <= 3 * 50 + 5, f"{selects} selects while the card sent 50 frames and took 50"
    # the receive thread reads no clock per frame while it keeps no deadlines (one before)
    assert readings <= 5, f"{readings} clock readings of the receive thread for 50 frames"


def test_the_cards_received_frames_on_socketcan_name_no_interface(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 22: the receive thread reads a SocketCAN frame with one ``recvmsg`` that asks
    for no sender's address. Python's ``socket.recvmsg`` (python-can's ``recv``, and the
    card's own read until 2026-12-04) names the sender's interface for every frame, an
    ``ioctl(SIOCGIFNAME)`` each, a ptrace round trip of the host inside User-Mode Linux
    (one per 309-3 read in ``strace`` of the card). Counted: the receive thread's calls of
    Python's ``recvmsg`` while the card takes 51 frames, which arrive as python-can's own
    ``recv`` gives them to a third station (identifier, data, length, flags, direction,
    channel, the kernel's time stamp)."""
    reason = socketcan_missing()
    if reason is not None:
        pytest.skip(reason)
    import socket

    import can

    from firmware.can.bus import CanBus

    calls = 0
    real_recvmsg = socket.socket.recvmsg

    def counting(self: socket.socket, *args: Any) -> Any:
        nonlocal calls
        calls += threading.current_thread().name == "can-receive"
        return real_recvmsg(self, *args)

    card = CanBus("socketcan", SOCKETCAN_CHANNEL)
    peer = can.Bus(interface="socketcan", channel=SOCKETCAN_CHANNEL)
    watcher = can.Bus(interface="socketcan", channel=SOCKETCAN_CHANNEL)
    got: list[can.Message] = []
    try:
        card.subscribe_all(got.append)
        monkeypatch.setattr(socket.socket, "recvmsg", counting)
        for n in range(50):
            peer.send(can.Message(arbitration_id=0x181 + n % 2, is_extended_id=False,
                                  data=bytes([n] * (n % 9))))
        peer.send(can.Message(arbitration_id=0x1234567, is_extended_id=True, data=b"\x07"))
        wait_until(lambda: len(got) == 51, 5.0)
        monkeypatch.undo()
        seen = [watcher.recv(2.0) for _ in range(51)]
    finally:
        monkeypatch.undo()
        watcher.shutdown()
        peer.shutdown()
        card.shutdown()

    def fields(m: can.Message | None) -> tuple[Any, ...]:
        assert m is not None
        return (m.arbitration_id, m.is_extended_id, bytes(m.data), m.dlc, m.is_rx,
                m.is_remote_frame, m.is_error_frame, m.is_fd, m.channel, m.timestamp)

    assert [fields(m)[:4] for m in got] == [
        (0x181 + n % 2, False, bytes([n] * (n % 9)), n % 9) for n in range(50)] + [
        (0x1234567, True, b"\x07", 1)]
    assert [fields(m) for m in got] == [fields(m) for m in seen]
    assert calls == 0, f"{calls} calls of Python's recvmsg for 51 frames"
