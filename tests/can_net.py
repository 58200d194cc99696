"""A card with simulated CANopen nodes on every bus: the back-to-back network fixture.

``make_net`` starts ``cifemu firmware --simulate NETWORK.toml`` and opens it through
``Board``: on ``virtual`` the card and the simulated nodes share one python-can bus inside
the firmware process; on ``shm`` the nodes run in a ``cifemu sim`` process of their own (as on
a real bus, the card then shares nothing but the bus with them); on ``socketcan`` both are on
``vcan0``, skipped with the reason where the machine has none (``tests/buses.py``).

Use it from a test module with ``pytest_plugins = ["tests.can_net"]`` and a ``make_net``
argument: every test of the module then runs on each interface. The helpers (``Net``,
``exchange``, ``candump``, ``start_sim``, ``FrameWatch``, ``window``, the data sets
``node_set`` and ``bus_parameters``, ``actual_error``) are imported as usual.
A helper module, not a test module: no test module imports another (tests/test_suite_rules.py).
"""

from __future__ import annotations

import struct
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest

from dbm_tools.network import load_network
from dbm_tools.parameters import NdFlag, NodeParameterSet, PdoData
from dpm.errors import Drv
from dpm.message import Message
from dpm.task2 import ComDiagnostics
from host_api import driver as d
from host_api.board import Board
from host_api.monitor.tap_bus import TapBus
from host_api.online import configure_online
from tests import commands
from tests.buses import SOCKETCAN_CHANNEL, socketcan_missing
from tests.conftest import GUEST_STALLS, Card, start_card, wait_until

GENERIC = "\n".join(f"[[node]]\nid = {n}" for n in (1, 2, 3))
SYNC_ID = 0x080
"""The COB-ID of SYNC the bus parameters of ``bus_parameters`` give (CiA 301's default)."""


@pytest.fixture(params=["virtual", "shm", "socketcan"])
def interface(request: pytest.FixtureRequest) -> str:
    """The card's interface; on ``shm`` the nodes run as ``cifemu sim`` in another process."""
    if request.param == "socketcan":
        reason = socketcan_missing()
        if reason is not None:
            pytest.skip(reason)
    return str(request.param)


def window(seconds: float, why: str) -> None:
    """Let ``seconds`` pass, where no event can end the wait: a time-out the card measures
    has to run out, or a check that something does NOT happen needs a span to look at.
    ``why`` says which, for the reader and for the failure message. Every other wait ends
    on a condition (``wait_until``, ``FrameWatch.wait_for``)."""
    until = time.monotonic() + seconds
    wait_until(lambda: time.monotonic() > until, seconds + 1, why)


def node_set(address: int, output_type: int = 255) -> bytes:
    """A generic node's data set as COM_Download carries it (seed 5.2.5.1.1): heartbeat
    consumer at 1000 ms, no SDO list, one RX-PDO of transmission ``output_type`` and one
    event-driven TX-PDO."""
    return NodeParameterSet(
        bNd_Flag=NdFlag.ACTIVE | NdFlag.HRTBT, usAddTypeInfo=0x000F, usDevProfNum=0x191,
        usCobIDEmcy=0x80 + address, usCobIDGuard=0x700 + address, usGuardTime=1000,
        atPdoCfgData=[PdoData(0, 8, 0x200 + address, output_type),
                      PdoData(1, 8, 0x180 + address, 255)],
        ausInputOffsets=[0], ausOutputOffsets=[0]).encode()


def bus_parameters(baud_rate: int = 2, sync_timer: int = 0) -> bytes:
    """COM_Download of the bus parameters (seed 5.2.5.4.2): Area_Code 127, then the data set
    (by default 500 kbit/s, no SYNC). Its download starts the bus."""
    return bytes([0, 127, 0, 0, baud_rate]) + struct.pack("<HH", SYNC_ID, sync_timer) + bytes(2)


def actual_error(net: Net, node: int) -> int:
    """Octet 7 of the node's COM_Node_Diag answer (seed 5.2.7): its error now."""
    answer = net.send(66, struct.pack("<BBHBBBB", node, 0, 0, 0, 0, 0, 1))
    assert answer.f == 0
    return answer.data[8 + 6]


def frame(ident: int, data: bytes | None = None,
          remote: bool | None = None) -> Callable[[can.Message], bool]:
    """A match for ``FrameWatch``: this identifier, and these data bytes or RTR bit if given."""
    def match(msg: can.Message) -> bool:
        return (msg.arbitration_id == ident and (data is None or bytes(msg.data) == data)
                and (remote is None or msg.is_remote_frame == remote))
    return match


class FrameWatch:
    """The frames the card sees, through its frame tap (what ``cifemu monitor`` shows), so a
    wait ends on frames ("five guarding answers", "the whole EMCY burst"), not on time.

    The card's tap learns a new subscriber at most every 0.1 s, and only while it publishes
    frames (``firmware/can/tap.py``); so ``Net.watch`` returns once a first frame came
    through (a simulated node's heartbeat, before the configuration too), and from then on
    every frame is here.
    """

    def __init__(self, image: Path) -> None:
        try:
            self._bus = TapBus(image)
        except can.CanInitializationError as exc:
            pytest.fail(f"no frame tap: {exc}")
        self._frames: list[can.Message] = []
        self._lock = threading.Lock()
        self._closed = threading.Event()
        # A reader of its own: the card drops what a subscriber's socket cannot queue (a
        # few datagrams, net.unix.max_dgram_qlen), so the tap is read all the time.
        self._reader = threading.Thread(target=self._read, name="frame-watch", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while not self._closed.is_set():
            msg = self._bus.recv(0.05)
            if msg is not None:
                with self._lock:
                    self._frames.append(msg)

    def mark(self) -> int:
        """Where the frames seen so far end: ``since`` for a later wait."""
        with self._lock:
            return len(self._frames)

    def matching(self, match: Callable[[can.Message], bool], since: int = 0) -> list[can.Message]:
        """The frames since the mark ``since`` that ``match``; a frame the tap lost fails the
        test here, so that it never passes for one the card did not send (or for none)."""
        if self._bus.lost_frames:
            pytest.fail(f"the frame tap lost {self._bus.lost_frames} frames (its reader was "
                        "starved): what this watch saw is not what the card sent")
        with self._lock:
            return [msg for msg in self._frames[since:] if match(msg)]

    def wait_for(self, match: Callable[[can.Message], bool], count: int, what: str,
                 since: int = 0, timeout: float = 10) -> list[can.Message]:
        """Wait until ``count`` frames that ``match`` came since the mark ``since``."""
        wait_until(lambda: len(self.matching(match, since)) >= count, timeout, what)
        return self.matching(match, since)

    def close(self) -> None:
        self._closed.set()
        self._reader.join(5)
        self._bus.shutdown()


class Net:
    """A card with a simulated network, opened through ``Board``."""

    def __init__(self, card: Card, board: Board, toml: Path, channel: str) -> None:
        self.card = card
        self.board = board
        self.toml = toml
        self.channel = channel
        self.watches: list[FrameWatch] = []

    def watch(self) -> FrameWatch:
        """A ``FrameWatch`` on the card's frames, closed with the card, once the tap sends it
        frames (some node must produce heartbeats)."""
        watch = FrameWatch(self.card.path)
        self.watches.append(watch)
        watch.wait_for(lambda msg: True, 1, "a first frame through the card's tap")
        return watch

    def diag(self) -> ComDiagnostics:
        return self.board.diagnostics()

    def send(self, b: int, data: bytes, rx: int = 3, e: int = 0) -> Message:
        return self.board.transact(Message(rx=rx, tx=16, b=b, e=e, data=data))

    def configure(self) -> None:
        configure_online(self.board, load_network(self.toml))

    def wait_operating(self, nodes: list[int], timeout: float = 10) -> None:
        wait_until(lambda: self.diag().operating() == nodes, timeout,
                   f"nodes {nodes} in data exchange (now {self.diag().operating()})")

    def sdo(self, node: int, index: int, sub: int, data: bytes | None = None) -> Message:
        head = struct.pack("<BBHBBBB", node, 0, index, sub, len(data or b""), 0,
                           2 if data is not None else 1)
        return self.send(74, head + (data or b""))


@pytest.fixture
def make_net(tmp_path: Path, interface: str) -> Iterator[Callable[..., Net]]:
    opened: list[Net] = []
    sims: list[subprocess.Popen[bytes]] = []

    def make(toml: str = GENERIC, *extra: str) -> Net:
        path = tmp_path / "network.toml"
        path.write_text(toml)
        if interface == "shm":  # the card first: it must hear the nodes from power-on
            channel = f"test-{uuid.uuid4().hex}"
            card = start_card(tmp_path, 0, "--interface", interface, "--channel", channel,
                              *extra)
            sims.append(start_sim(path, interface, channel))
        else:
            channel = SOCKETCAN_CHANNEL if interface == "socketcan" else "card"
            card = start_card(tmp_path, 0, "--simulate", str(path), "--interface", interface,
                              "--channel", channel, *extra)
        board = Board(0, tmp_path, timeout=5000).open()
        net = Net(card, board, path, channel)
        opened.append(net)
        return net

    yield make
    for net in opened:
        for watch in net.watches:
            watch.close()
        net.board.close()
        net.card.stop()
    for sim in sims:
        sim.terminate()
        commands.wait(sim, 10)


def start_sim(network: Path, interface: str, channel: str) -> subprocess.Popen[bytes]:
    """``cifemu sim`` in a process of its own, returned once its nodes are on the bus."""
    sim = subprocess.Popen([sys.executable, "-m", "cifemu", "sim", str(network), "--interface",
                            interface, "--channel", channel, "--log-level", "WARNING"],
                           stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)
    assert sim.stdout is not None
    first = sim.stdout.readline()
    if not first.startswith(b"simulating"):
        sim.kill()
        pytest.fail(f"cifemu sim did not start: {first!r}")
    threading.Thread(target=sim.stdout.read, daemon=True).start()  # the pipe must not fill
    return sim


def exchange(net: Net, outputs: bytes, offset: int = 0, size: int = 8) -> bytes:
    """One DevExchangeIO; b"" while COM is not up yet (-21), so a wait on it tries again: the
    device loop raises COM with the network's state, a moment after the nodes' Nd_state bits
    when a loaded machine (User-Mode Linux) delays it. Also b"" for the driver's time-out
    (-23) when the guest of ``tools/vcan-vm`` stood still during the call (``GuestStalls``):
    its 2 s ran on a clock that went on while neither card nor host could run. Any other
    code fails the test."""
    stalls = GUEST_STALLS.watch() if GUEST_STALLS is not None else None
    rc, data = d.DevExchangeIO(0, offset, outputs, offset, size, 2000)
    if rc == Drv.DRV_DEV_NO_COM_FLAG:
        return b""
    if rc == Drv.DRV_DEV_EXCHANGE_TIMEOUT and stalls is not None and stalls() > 0:
        return b""
    assert rc == 0
    return data



def candump(trace: Path) -> list[tuple[float, int, str]]:
    """(time, identifier, data) of every frame in a candump-format trace.

    Whole lines only: a running card's trace may end in one half written.
    """
    frames = []
    written = trace.read_text()
    for line in written[: written.rfind("\n") + 1].splitlines():
        stamp, _, frame = line.split()[:3]
        ident, _, data = frame.partition("#")
        frames.append((float(stamp.strip("()")), int(ident, 16), data))
    return frames
