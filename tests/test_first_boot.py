"""A boot right after the card's start costs the card no more than a later boot (issue 22).

On ``shm`` the card starts a spare SYNC timer process with its controller, before READY
(``firmware.shm.tasks.SpareTimer``: a child interpreter, ``python -m firmware.shm.cyclic``).
Its start ran on after READY, and a host that downloaded and cold-started a network of 127
nodes at once paid 0.37-0.65 s of that child's CPU during the first boot, against a card's
0.1-0.2 s per boot (docs/benchmarks.md, issue 22's note 5). What a user notices is the card's
CPU per boot, the first against later ones of the same card: CPU time, which load hardly
moves, where the wall time of a boot swings with the nodes' share of two cores. Real parts:
``cifemu firmware`` and ``cifemu sim`` on a fresh ``shm`` channel, the database downloaded
and the cold starts made through the driver, as ``python -m bench.can``'s boot phase does.

The card starts with the database in its flash, as a card in service does: a network of
more than ``FEW_NODES`` nodes has the CAN master import numpy when it is configured
(``firmware.can.pdo.import_numpy_ahead``), which a start with a stored database does before
READY, and a download followed at once by a cold start does in the first boot, on every
interface (0.3 s of CPU, once per card process). Before numpy left ``shm``'s stations
(``firmware.shm.watch``) it came with the card's start on ``shm`` whatever its network.
"""

from __future__ import annotations

import uuid
from pathlib import Path

from bench.can.card import network_toml, wait_operating
from bench.cpu import tree_cpu_ns
from dbm_tools.builder import build_dbm
from dbm_tools.container import write_dbm
from dbm_tools.network import parse_network
from dpm.start_progress import TICK_NS, stat_fields
from host_api.board import Board
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload
from host_api.driver import COLDSTART, DevReset
from tests import commands
from tests.can_net import start_sim
from tests.conftest import on_load_clock, start_card

NODES = 127
"""The benchmark's network: a boot long enough to hold the spare's whole start."""
BOOTS = 4
BOOT_S = 30.0
"""Load-clock seconds for one boot (well under 1 s on a quiet machine)."""
EXTRA_CPU_S = 0.25
"""What the first two boots may cost the card beyond the dearer of the last two. Measured
(2026-12-04, three runs each way in turns at load 12-20): the first boots 0.11-0.16 s, the
last two 0.11-0.19 s; before, the first 0.62-0.78 s against 0.10-0.22 s."""


def card_cpu_ns(pid: int) -> int:
    """The card's CPU so far: its process and those that run under it
    (``bench.cpu.tree_cpu_ns``), and the children it has waited for (a SYNC timer that
    ended: cutime and cstime)."""
    fields = stat_fields(pid)
    waited = (int(fields[13]) + int(fields[14])) * TICK_NS  # proc(5) fields 16 and 17
    return tree_cpu_ns(pid) + waited


def test_a_boot_right_after_the_start_costs_the_card_no_more_than_later_ones(
        tmp_path: Path) -> None:
    """The card starts with a database of 127 nodes in its flash; the host cold-starts it
    four times once the card is READY; the card's CPU from each DevReset until every node is
    in Nd_state. The first two boots, where the start's leftovers would land, may cost no
    more than the dearer of the last two plus ``EXTRA_CPU_S``."""
    text = network_toml(list(range(1, NODES + 1)))
    network = tmp_path / "network.toml"
    network.write_text(text)
    channel = f"test-first-boot-{uuid.uuid4().hex}"
    sim = start_sim(network, "shm", channel)  # first, as the benchmark's: all nodes there
    try:
        options = ("--interface", "shm", "--channel", channel, "--flash", str(tmp_path / "flash"))
        card = start_card(tmp_path, 0, *options)
        try:
            with Board(0, tmp_path, timeout=5000):
                assert DevDownload(0, CONFIGURATION_DOWNLOAD,
                                   write_dbm(build_dbm(parse_network(text)))) == 0
        finally:
            assert card.stop() == 0
        card = start_card(tmp_path, 0, *options)  # with its database, as a card in service
        board = Board(0, tmp_path, timeout=5000).open()
        try:
            spent = []
            for _ in range(BOOTS):
                before = card_cpu_ns(card.proc.pid)
                assert DevReset(0, COLDSTART, 10_000) == 0
                on_load_clock(lambda seconds: wait_operating(0, NODES, seconds), BOOT_S,
                              RuntimeError)
                spent.append((card_cpu_ns(card.proc.pid) - before) / 1e9)
        finally:
            board.close()
            card.stop()
    finally:
        sim.terminate()
        commands.wait(sim, 10)
    later = max(spent[2:])
    assert max(spent[:2]) <= later + EXTRA_CPU_S, (
        f"the card's CPU per boot {spent} s: the first boots cost more than later ones")
