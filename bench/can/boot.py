"""Phase 4, ``boot``: 127 nodes from a stored database, against canopen's boot sequence.

127 generic nodes from a stored database (DevDownload, then a cold
start): the time from DevReset until all 127 are in Nd_state. Node 127 cannot
be configured on line: area code 127 of COM_Download is the bus parameter
set, so the on-line figure (taken from phase 2) has 126 nodes, timed from the
bus parameter download. Baseline: canopen runs the card's boot sequence
(NMT reset node, boot-up, upload 1000h, download 1017h, 1005h, 1014h and the
node's SDO list from the database, NMT start) for the same 127 nodes, 32 nodes
in parallel in a pool of threads, since canopen's client blocks (the card's boot-up is
driven by the answering frames, 64 nodes' at once: firmware.can.boot.BOOTS_IN_FLIGHT).
Both meet the nodes in ``cifemu sim`` on a channel of the same kind (a fresh ``shm``
one each), so they ask the same of the same nodes over the same medium; the baseline's
nodes once ran in its own process on the virtual bus, and it wrote 1017h once where the
card writes it twice. Each side boots once before the measured boots (``BOOT_WARMUPS``),
timed apart: the first boot met start-up work still running (docs/benchmarks.md, note 5).
"""

from __future__ import annotations

import struct
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import canopen
from canopen.sdo.exceptions import SdoCommunicationError

from bench.can.baseline import sdo_client
from bench.can.card import (
    DEVICE_TYPE_BYTES,
    RESET_TIMEOUT_MS,
    SeparateBus,
    board_of,
    network_toml,
    separate_nodes,
    simulated_card,
    wait_operating,
)
from bench.common import (
    percentile,
    progress,
    ratio,
)
from bench.cpu import tree_cpu_ns
from dbm_tools.builder import build_dbm
from dbm_tools.container import write_dbm
from dbm_tools.network import Network, parse_network
from dbm_tools.parameters import NodeParameterSet
from dbm_tools.tables import NODES
from dpm.cia301 import COB_ID_NMT, COB_ID_SYNC, EMCY_BASE, ERROR_CONTROL_BASE
from dpm.commands import NMT_RESET_NODE, NMT_START
from dpm.start_progress import stat_cpu_ns
from firmware.can.sdo import DEFAULT_SDO_TIMEOUT
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload
from host_api.driver import (
    COLDSTART,
    DevReset,
)

BOOT_NODES = 127
BOOT_REPEATS = 3
BOOT_WARMUPS = 1
"""Boots before the measured ones, on both sides alike, timed apart (``warmup_s``; the
card's CPU in ``warmup_card_cpu_s``): the first boot met the card's start-up still running
(its spare timer process, ``firmware.shm.cyclic``, started with the controller: 0.4-0.65 s
of a core in its interpreter start) and, before ``SimulatedNetwork.start`` waited for the
power-on, the simulator's 127 boot-ups. It was the slowest in 16 of 18 sets and set the
median. Both causes are gone (the timer process's start costs 0.05-0.1 s since branch
synctimer, docs/benchmarks.md note 5); the warm-up stays, so that the medians compare
with earlier runs, and its figures show a first boot that costs more again."""
BOOT_WORKERS = 32
"""The baseline's boot threads: the card's pool until its boot-up was driven by frames."""
BOOTUP_TIMEOUT_S = 3.0
BOOT_ATTEMPTS = 3
"""How often the baseline boots a node whose SDO answer did not come in time."""


def card_boot(count: int, bus: SeparateBus | None) -> dict[str, Any]:
    nodes = list(range(1, count + 1))
    text = network_toml(nodes)
    database = write_dbm(build_dbm(parse_network(text)))
    runs: list[dict[str, float]] = []
    with simulated_card(text, separate=True, bus=bus) as card:
        board = board_of(card)
        rc = DevDownload(board.number, CONFIGURATION_DOWNLOAD, database)
        if rc != 0:
            raise RuntimeError(f"DevDownload returned {rc}")
        assert card.sim is not None  # separate=True
        cpu: list[tuple[float, float]] = []
        warmups: list[float] = []
        warmup_cpu: list[float] = []
        for attempt in range(-BOOT_WARMUPS, BOOT_REPEATS):
            what = (f"warm-up {attempt + BOOT_WARMUPS + 1}/{BOOT_WARMUPS}" if attempt < 0
                    else f"{attempt + 1}/{BOOT_REPEATS}")
            progress(f"boot (card): cold start {what} with {len(nodes)} "
                     "nodes in the stored database")
            own, theirs = tree_cpu_ns(card.pid), stat_cpu_ns(card.sim.pid)
            start = time.perf_counter()
            rc = DevReset(board.number, COLDSTART, RESET_TIMEOUT_MS)
            if rc != 0:
                raise RuntimeError(f"DevReset(COLDSTART) returned {rc}")
            ready = time.perf_counter()
            operating = wait_operating(board.number, len(nodes))
            if attempt < 0:
                warmups.append(round(operating - start, 3))
                warmup_cpu.append(round((tree_cpu_ns(card.pid) - own) / 1e9, 3))
                continue
            cpu.append((round((tree_cpu_ns(card.pid) - own) / 1e9, 3),
                        round((stat_cpu_ns(card.sim.pid) - theirs) / 1e9, 3)))
            runs.append({"all_operating_s": round(operating - start, 3),
                         "ready_s": round(ready - start, 3)})
        firmware_log = card.log()
    return {"nodes": len(nodes), "runs": runs, "warmup_s": warmups,
            "warmup_card_cpu_s": warmup_cpu,
            "median_s": round(_median([r["all_operating_s"] for r in runs]), 3),
            **_cpu_figures(cpu, "card_cpu_s", "the firmware process (and its SYNC timer)"),
            "firmware_log": firmware_log}


def _median(values: list[float]) -> float:
    return percentile(sorted(values), 50)


class NoBootUp(RuntimeError):
    """A node sent no boot-up message within ``BOOTUP_TIMEOUT_S`` of its reset: a node still
    in its power-on boot ignores the reset (its power-on boot-up came before the wait), which
    a loaded machine made happen to the first node of the first run."""


def sdo_lists(network: Network) -> dict[int, list[tuple[int, int, bytes]]]:
    """Each node's SDO list (atSdoCfgData) as the card gets it in the database: the
    writes that end its boot-up's configuration (the builder puts 1017h there again for a
    heartbeat node, so the card writes it twice)."""
    table = build_dbm(network).table(NODES)
    if table is None:
        raise RuntimeError("the network has no nodes")
    lists = {}
    for record in table.records:
        params = NodeParameterSet.decode(record[1:])
        lists[record[0]] = [(entry.usIndex, entry.bSubindex,
                             bytes(entry.abSdoValue[: entry.bLength]))
                            for entry in params.atSdoCfgData]
    return lists


def baseline_boot(count: int, bus: SeparateBus | None) -> dict[str, Any]:
    nodes = list(range(1, count + 1))
    text = network_toml(nodes)
    writes = sdo_lists(parse_network(text))
    runs: list[float] = []
    with separate_nodes(text, bus) as (station, sim):
        client = canopen.Network(station)
        client.connect()
        try:
            runs, warmups, cpu, retries = _boot_with_canopen(client, nodes, writes, sim.pid)
        finally:
            client.disconnect()
    return {
        "name": f"canopen runs the card's boot sequence for the same {len(nodes)} nodes in "
                "cifemu sim, on the same kind of channel as the card: NMT reset node, wait "
                "for the boot-up, upload 1000h, download 1017h, 1005h, 1014h and the SDO "
                "list of the database (1017h again), NMT start; "
                f"{BOOT_WORKERS} nodes in parallel (canopen's client blocks a thread each)",
        "nodes": len(nodes),
        "sdo_per_node": 4 + len(writes[nodes[0]]),
        "runs_s": [round(r, 3) for r in runs],
        "warmup_s": [round(r, 3) for r in warmups],
        "median_s": round(_median(runs), 3),
        "nodes_booted_again": retries,
        **_cpu_figures(cpu, "canopen_cpu_s", "this process (canopen and its threads)"),
    }


def _cpu_figures(cpu: list[tuple[float, float]], key: str, what: str) -> dict[str, Any]:
    """Median CPU seconds per boot of the master's side and of ``cifemu sim``: they move less
    with the machine's load than the wall-clock time does."""
    return {key: _median([c[0] for c in cpu]), "sim_cpu_s": _median([c[1] for c in cpu]),
            "cpu_note": f"median CPU seconds per boot (utime + stime, 10 ms ticks): {what}, "
                        "and the cifemu sim process"}


def _boot_with_canopen(client: canopen.Network, nodes: list[int],
                       writes: dict[int, list[tuple[int, int, bytes]]], sim: int
                       ) -> tuple[list[float], list[float], list[tuple[float, float]], int]:
    bootups = {node: threading.Event() for node in nodes}

    def on_error_control(can_id: int, data: bytearray, timestamp: float) -> None:
        del timestamp
        if data and data[0] == 0:
            bootups[can_id - ERROR_CONTROL_BASE].set()

    for node in nodes:
        client.subscribe(ERROR_CONTROL_BASE + node, on_error_control)
    clients = {node: sdo_client(client, node) for node in nodes}
    for sdo in clients.values():
        sdo.RESPONSE_TIMEOUT = DEFAULT_SDO_TIMEOUT  # the card's, not canopen's 0.3 s

    retries: list[int] = []

    def boot_node(node: int) -> None:
        """Boot the node; one whose SDO answer missed the time-out, or whose boot-up did not
        come, is booted again at once, as the card boots a failed node again (after 1 s),
        and counted: a loaded machine otherwise ended the whole phase."""
        for _ in range(BOOT_ATTEMPTS - 1):
            try:
                boot_steps(node)
                return
            except (SdoCommunicationError, NoBootUp):
                retries.append(node)
        boot_steps(node)

    def boot_steps(node: int) -> None:
        """The card's boot steps (firmware.can.boot.BootSequence._steps)."""
        sdo = clients[node]
        bootups[node].clear()
        client.send_message(COB_ID_NMT, bytes([NMT_RESET_NODE, node]))
        if not bootups[node].wait(BOOTUP_TIMEOUT_S):
            raise NoBootUp(f"node {node}: no boot-up")
        if bytes(sdo.upload(0x1000, 0)) != DEVICE_TYPE_BYTES:
            raise RuntimeError(f"node {node}: wrong device type")
        sdo.download(0x1017, 0, struct.pack("<H", 500))
        sdo.download(0x1005, 0, struct.pack("<I", COB_ID_SYNC))
        sdo.download(0x1014, 0, struct.pack("<I", EMCY_BASE + node))
        for index, subindex, value in writes[node]:
            sdo.download(index, subindex, value)
        client.send_message(COB_ID_NMT, bytes([NMT_START, node]))

    runs: list[float] = []
    warmups: list[float] = []
    cpu: list[tuple[float, float]] = []
    with ThreadPoolExecutor(max_workers=BOOT_WORKERS) as pool:
        for attempt in range(-BOOT_WARMUPS, BOOT_REPEATS):
            what = (f"warm-up {attempt + BOOT_WARMUPS + 1}/{BOOT_WARMUPS}" if attempt < 0
                    else f"run {attempt + 1}/{BOOT_REPEATS}")
            progress(f"boot (baseline): {what}, {len(nodes)} nodes")
            own, theirs = time.process_time(), stat_cpu_ns(sim)
            start = time.perf_counter()
            list(pool.map(boot_node, nodes))
            if attempt < 0:
                warmups.append(time.perf_counter() - start)
                continue
            runs.append(time.perf_counter() - start)
            cpu.append((round(time.process_time() - own, 3),
                        round((stat_cpu_ns(sim) - theirs) / 1e9, 3)))
    return runs, warmups, cpu, len(retries)


def boot(online: tuple[int, float] | None, nodes: int = BOOT_NODES,
         bus: SeparateBus | None = None) -> dict[str, Any]:
    """``online``: the pdo_throughput phase's on-line boot, (nodes, seconds)."""
    baseline = baseline_boot(nodes, bus)
    card = card_boot(nodes, bus)
    if online is not None:
        card["online_nodes"], card["online_s"] = online
        card["online_note"] = ("on-line configuration (configure_online) of the pdo_throughput "
                               "phase's network (126 nodes in the full configuration), timed "
                               "from the bus parameter download; node 127 cannot be configured "
                               "on line because area code 127 of COM_Download is the bus "
                               "parameter set")
    return {
        "description": f"{nodes} generic nodes stored in the card's flash (DevDownload), "
                       "then DevReset(COLDSTART): seconds from the reset call until all "
                       f"nodes are in Nd_state, after {BOOT_WARMUPS} warm-up boot(s) on each "
                       "side (warmup_s, not in the median; the start downloads nodes, then "
                       "the bus parameters, which start the network)",
        "cif": card,
        "baseline": baseline,
        "ratio_to_baseline": {"definition": "cif median / baseline median",
                              "median": ratio(card["median_s"], baseline["median_s"])},
    }

