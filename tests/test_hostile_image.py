"""A host that writes garbage into the image must never take the card down.

The card shares its dual-port memory with every program that maps the image. These tests
play such a program: one that rewrites msg.ln while handing a message over, and one that
writes random bytes into every area a host may write (the send area, DevMbx, the task
parameters) with DevFlags toggle storms. The firmware process must stay up, never write
into those areas itself, and serve a well-formed host afterwards.

CIFEMU_SOAK_SECONDS sets how long the random writer runs (default 5 s; the issue's
long form is 60), as CIFEMU_FUZZ_EXAMPLES sets the fuzz tests' example counts.
"""

from __future__ import annotations

import mmap
import os
import random
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from dbm_tools.network import load_network
from dpm import flags as fl
from dpm.layout import (
    DEV_FLAGS,
    DEV_MBX,
    HOST_FLAGS,
    IO_AREA_SIZE,
    SND_PD,
    TASK1_PARAMETER,
    TASK2_PARAMETER,
    TASK_PARAMETER_SIZE,
)
from dpm.message import MSG_MAX_SIZE, Message, Task
from host_api import driver
from host_api.board import Board
from host_api.driver import COLDSTART
from host_api.online import configure_online
from tests import commands
from tests.can_net import start_sim
from tests.conftest import Card, LoadDeadline, start_card, wait_until

SOAK_SECONDS = max(1.0, float(os.environ.get("CIFEMU_SOAK_SECONDS", "5")))
COM_SHARED_MEMORY = 17
MSG_B = DEV_MBX + 6
STORM_BITS = (fl.HOSTACK, fl.DEVCOM, fl.PDCOM, fl.STATEACK, fl.SPCCOM, fl.NOTREADY)
"""Every DevFlags bit but RESET and INIT (a start rewrites the parameters, by design)."""
NETWORK_NODES = [1, 2, 3]


@pytest.fixture
def hostile_card(tmp_path: Path) -> Iterator[Card]:
    card = start_card(tmp_path)
    yield card
    card.stop()


def _settle(mm: mmap.mmap) -> None:
    """Leave the handshake as a host that owns nothing: NOTREADY off, no message pending."""
    deadline = LoadDeadline(5)
    mm[DEV_FLAGS] = mm[DEV_FLAGS] & ~fl.NOTREADY
    while deadline.left() > 0:
        diff = mm[HOST_FLAGS] ^ mm[DEV_FLAGS]
        if diff & fl.HOST_MBX:  # an answer is waiting: take it
            mm[DEV_FLAGS] = mm[DEV_FLAGS] ^ fl.HOSTACK
        elif not diff & fl.DEV_MBX:
            time.sleep(0.05)
            if not (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & (fl.HOST_MBX | fl.DEV_MBX):
                return
        time.sleep(0.001)
    pytest.fail("the card never settled its mailboxes after the hostile writes")


def _serves_a_host(card: Card) -> None:
    """A well-formed host: a COM_Shared_Memory write and read back through the mailbox."""
    with Board(card.board, directory=card.directory) as board:
        header = bytes([0, 2, 0x10, 0, 0, 2, 5, 2]) + b"\xa5\x5a"  # UINT8 x2 at 0x10, send area
        answer = board.transact(Message(rx=Task.PLC, tx=Task.USER, b=COM_SHARED_MEMORY,
                                        data=header), timeout=2000)
        assert answer.f == 0
        read = bytes([0, 2, 0x10, 0, 0, 2, 5, 1])
        answer = board.transact(Message(rx=Task.PLC, tx=Task.USER, b=COM_SHARED_MEMORY,
                                        data=read), timeout=2000)
        assert (answer.f, answer.data[8:]) == (0, b"\xa5\x5a")


def test_rewriting_msg_ln_while_handing_over_keeps_the_card_alive(hostile_card: Card) -> None:
    """Defect 1 of issue 13: msg.ln flips between 0 and 255 while DEVCOM toggles.

    The card used to read ln, copy ln + 8 bytes and decode the copy, which reads ln
    again: a flip in between raised MessageError and the firmware exited with 1."""
    mm = hostile_card.map()
    try:
        mm[DEV_MBX : DEV_MBX + 8] = bytes([Task.RCS, Task.USER, 0, 0, 0, 0, 200, 0])
        handed_over = 0
        deadline = time.monotonic() + 3
        flip = 0
        while time.monotonic() < deadline and hostile_card.proc.poll() is None:
            flip ^= 0xFF
            mm[DEV_MBX + 2] = flip
            diff = mm[HOST_FLAGS] ^ mm[DEV_FLAGS]
            if diff & fl.HOST_MBX:
                mm[DEV_FLAGS] = mm[DEV_FLAGS] ^ fl.HOSTACK
            elif not diff & fl.DEV_MBX:
                mm[DEV_FLAGS] = mm[DEV_FLAGS] ^ fl.DEVCOM
                handed_over += 1
        assert hostile_card.proc.poll() is None, "the firmware died of a host's write"
        assert handed_over > 100
        _settle(mm)
    finally:
        mm.close()
    _serves_a_host(hostile_card)


def _random_writes(card: Card, seconds: float, seed: int) -> dict[str, int]:
    """Random bytes into the host's areas and DevFlags storms; returns what was done.

    The card never writes an area that belongs to the host (it would overwrite what the
    host wrote last), so every 100 steps each area must still hold exactly the bytes this
    host wrote there. msg.b is never 17 in DevMbx: a COM_Shared_Memory write is a host
    asking the card to write the send area.
    """
    rng = random.Random(seed)
    mm = card.map()
    counts = {"steps": 0, "writes": 0, "storms": 0, "handovers": 0}
    areas = [(SND_PD, IO_AREA_SIZE), (DEV_MBX, MSG_MAX_SIZE),
             (TASK1_PARAMETER, TASK_PARAMETER_SIZE), (TASK2_PARAMETER, TASK_PARAMETER_SIZE)]
    shadow = {start: bytearray(mm[start : start + size]) for start, size in areas}
    try:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and card.proc.poll() is None:
            counts["steps"] += 1
            choice = rng.random()
            if choice < 0.5:
                start, size = rng.choice(areas)
                at = rng.randrange(size)
                data = bytearray(rng.randbytes(min(rng.choice((1, 2, 8, 64, size)), size - at)))
                b_at = MSG_B - DEV_MBX - at
                if start == DEV_MBX and 0 <= b_at < len(data) and data[b_at] == COM_SHARED_MEMORY:
                    data[b_at] = 0
                mm[start + at : start + at + len(data)] = bytes(data)
                shadow[start][at : at + len(data)] = data
                counts["writes"] += 1
            elif choice < 0.8:
                for _ in range(rng.randrange(1, 50)):
                    mm[DEV_FLAGS] = mm[DEV_FLAGS] ^ rng.choice(STORM_BITS)
                counts["storms"] += 1
            else:
                diff = mm[HOST_FLAGS] ^ mm[DEV_FLAGS]
                if diff & fl.HOST_MBX:
                    mm[DEV_FLAGS] = mm[DEV_FLAGS] ^ fl.HOSTACK
                elif not diff & fl.DEV_MBX:
                    mm[DEV_FLAGS] = mm[DEV_FLAGS] ^ fl.DEVCOM
                    counts["handovers"] += 1
            if counts["steps"] % 100 == 0:
                for start, content in shadow.items():
                    assert mm[start : start + len(content)] == content, (
                        f"the card wrote into the host's area at {start:#x}")
                time.sleep(0)  # let the card's process have the CPU now and then
        _settle(mm)
    finally:
        mm.close()
    return counts


def test_random_writes_to_every_host_area_never_crash_the_card(hostile_card: Card) -> None:
    """Issue 13, hostile input: random bytes for SOAK_SECONDS, then a well-formed host."""
    counts = _random_writes(hostile_card, SOAK_SECONDS, seed=13)
    assert hostile_card.proc.poll() is None, "the firmware died of a host's writes"
    assert counts["writes"] > 100 and counts["storms"] > 100 and counts["handovers"] > 10
    _serves_a_host(hostile_card)
    assert driver.DevOpenDriver(hostile_card.directory) == 0
    try:
        assert driver.DevInitBoard(0) == 0
        code, state = driver.DevGetTaskState(0, 2, 64)
        assert code == 0 and len(state) == 64
    finally:
        while driver.DevCloseDriver() == 0:
            pass


def test_random_writes_while_the_bus_runs_then_a_host_restarts_it(tmp_path: Path) -> None:
    """The same writer against a card exchanging process data with simulated nodes: the
    random connection-status bits and NOTREADY toggles stop and restart nodes and the bus
    under it, and its random messages reach the nodes (layer-2 frames, NMT, SDO). Then the
    nodes are powered anew (the writer may have reconfigured them through the card, as it
    may: those are services a host has), and a well-formed host cold-starts the card (the
    writer left garbage in the parameters a warm start would take), configures it and
    exchanges data again."""
    network = tmp_path / "network.toml"
    network.write_text("".join(f"[[node]]\nid = {n}\n" for n in NETWORK_NODES))
    channel = f"hostile-{uuid.uuid4().hex}"
    card = start_card(tmp_path, 0, "--interface", "shm", "--channel", channel)
    sim = start_sim(network, "shm", channel)
    try:
        with Board(0, tmp_path, timeout=5000) as board:
            configure_online(board, load_network(network))
            wait_until(lambda: board.diagnostics().operating() == NETWORK_NODES, 10,
                       "the nodes in data exchange")
        counts = _random_writes(card, SOAK_SECONDS, seed=1313)
        assert card.proc.poll() is None, "the firmware died of a host's writes"
        assert counts["writes"] > 100 and counts["storms"] > 100
        sim.terminate()
        commands.wait(sim, 10)
        sim = start_sim(network, "shm", channel)
        with Board(0, tmp_path, timeout=5000) as board:
            board.reset(COLDSTART)
            configure_online(board, load_network(network))
            wait_until(lambda: board.diagnostics().operating() == NETWORK_NODES, 10,
                       "the nodes in data exchange again")
            wait_until(lambda: board.exchange_io(b"\x77", receive_size=1) == b"\x77", 3,
                       "node 1 to echo the outputs")
    finally:
        card.stop()
        sim.terminate()
        commands.wait(sim, 10)
