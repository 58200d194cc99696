"""Scaling by nodes: the PDO loop and expedited SDO with N active nodes (issue 22, item 4).

N generic nodes run as ``cifemu sim`` on a fresh ``shm`` channel; the card is in the
uncontrolled handshake and configured on line, every node in Nd_state. *Active* means
that every node takes part in each PDO loop round trip: the host writes a new value
into all N nodes' outputs with one DevExchangeIO and polls the inputs until all N show
it, so a round trip is N RPDOs and N TPDOs, the process image a hardware-in-the-loop
host closes its control loop through. The SDO figure is expedited uploads of 1000h
through the mailbox (COM_SDO_Up_Download), one transfer at a time, to nodes 1..N in
turn.

Baselines, in the same run: python ``canopen`` on the same N simulated nodes in this
process (``bench.can.baseline``), as the one-node phases of ``bench.can`` measure it: a
``RemoteNode`` per node transmits RPDO1 and the loop waits for every node's TPDO1 to
show the value; ``SdoClient`` uploads 1000h from nodes 1..N in turn. Both sides are up
together and are timed in alternating slices, so a change of the machine's load (by the
minute on a shared machine) hits both.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import canopen
from canopen.sdo.exceptions import SdoError

from bench.can.baseline import in_process, sdo_client, start_all
from bench.can.card import (
    DEVICE_TYPE_BYTES,
    SimCard,
    io_offsets,
    network_toml,
    simulated_card,
    start_uncontrolled,
)
from bench.can.pdo_loop import ECHO_TIMEOUT_S, LOST, image_round_trip, image_values
from bench.can.sdo import interleaved, sdo_message
from bench.common import Measured, Rate, Step, latency_stats, measure, progress, ratio
from dbm_tools.network import Network, parse_network
from firmware.sim.generic import generic_object_dictionary
from host_api.board import CifError

NODE_COUNTS = (1, 16, 126)
COUNTS = {1: 2_000, 16: 1_000, 126: 500}
"""PDO loop round trips timed per node count (twice: latencies, then the rate): a round
trip with more nodes takes longer, and the run must stay within minutes."""
QUICK_COUNTS = {1: 300, 16: 200, 126: 60}
OTHER_COUNT = 200
"""Round trips for a node count not in ``COUNTS`` (``--nodes``)."""
WARMUP = 20
SDO_SECONDS = 2.0
QUICK_SDO_SECONDS = 0.5
SDO_WARMUP = 20
ROUNDS = 4
"""Alternating slices of card and baseline, as ``bench.can.sdo`` takes its SDO figures."""


def loop_count(nodes: int, quick: bool) -> int:
    return (QUICK_COUNTS if quick else COUNTS).get(nodes, OTHER_COUNT // (4 if quick else 1))


@dataclass(frozen=True, slots=True)
class Steps:
    """One side's PDO loop round trip and expedited SDO upload."""

    round_trip: Step
    expedited: Callable[[], bool]


@contextmanager
def baseline_steps(network: Network) -> Iterator[Steps]:
    """canopen straight to the same simulated nodes in this process: a ``RemoteNode`` per
    node sends RPDO1, the loop waits for every node's TPDO1; ``SdoClient`` per node."""
    with in_process(network) as (sim, client):
        remotes = []
        for node in network.nodes:
            remote = canopen.RemoteNode(node.id, generic_object_dictionary(node))
            client.add_node(remote)
            remote.rpdo.read(from_od=True)  # type: ignore[no-untyped-call]
            remote.tpdo.read(from_od=True)  # type: ignore[no-untyped-call]
            remotes.append((remote.rpdo[1], remote.tpdo[1]))
        start_all(sim, client)
        values = itertools.cycle(image_values(1))

        def round_trip() -> int:
            value = next(values)
            for rpdo, _ in remotes:
                rpdo.data = bytearray(value)
                rpdo.transmit()
            for _, tpdo in remotes:
                with tpdo.receive_condition:  # data is set under it: no TPDO slips past
                    while bytes(tpdo.data) != value:
                        if not tpdo.receive_condition.wait(ECHO_TIMEOUT_S):
                            return LOST
            return 0

        clients = itertools.cycle([sdo_client(client, node.id) for node in network.nodes])

        def expedited() -> bool:
            try:
                return bytes(next(clients).upload(0x1000, 0)) == DEVICE_TYPE_BYTES
            except SdoError:
                return False

        yield Steps(round_trip, expedited)


@contextmanager
def card_steps(network: Network, description: str) -> Iterator[tuple[Steps, SimCard]]:
    """The card with the nodes in ``cifemu sim`` on ``shm``: the same loop through the
    process image, the same uploads by COM_SDO_Up_Download."""
    out_offset, in_offset = io_offsets(network)
    with simulated_card(description, separate=True) as sim_card:
        progress(f"active nodes (card): on-line configuration of {len(network.nodes)} node(s)")
        board, _, _ = start_uncontrolled(sim_card, network)
        requests = itertools.cycle([node.id for node in network.nodes])

        def expedited() -> bool:
            try:
                answer = board.transact(sdo_message(next(requests), 0x1000, 0))
            except CifError:
                return False
            return answer.f == 0 and answer.data[8:12] == DEVICE_TYPE_BYTES

        yield Steps(image_round_trip(board.number, out_offset, in_offset, len(network.nodes)),
                    expedited), sim_card


def interleaved_loops(card: Step, base: Step, count: int,
                      warmup: int) -> tuple[Measured, Measured]:
    """``measure`` of card and baseline in ``ROUNDS`` alternating slices of ``count`` round
    trips in all, so a change of the machine's load hits both."""
    totals = (Measured(0, [], 0, 0), Measured(0, [], 0, 0))
    for step in (card, base):
        for _ in range(warmup):
            step()
    for _ in range(ROUNDS):
        for total, step in zip(totals, (card, base), strict=True):
            part = measure(step, max(1, count // ROUNDS), 0, frozenset({0}))
            total.count += part.count
            total.latencies_ns.extend(part.latencies_ns)
            total.elapsed_ns += part.elapsed_ns
            total.failures += part.failures
    return totals


def _loop_figures(measured: Measured) -> dict[str, Any]:
    return {"latency_us": latency_stats(measured.latencies_ns), "round_trips": measured.count,
            "round_trips_per_s": round(measured.per_second, 1), "failures": measured.failures}


def _sdo_figures(rate: Rate) -> dict[str, Any]:
    return {"expedited_uploads_per_s": round(rate.per_s(), 1), "failures": rate.failures,
            "seconds": round(rate.elapsed_s, 2)}


def active_nodes(nodes: int, quick: bool = False, count: int | None = None,
                 warmup: int | None = None) -> dict[str, Any]:
    """Card and baseline with ``nodes`` active nodes; ``count`` overrides ``loop_count``,
    ``warmup`` the round trips before the timed ones (``WARMUP``)."""
    description = network_toml(range(1, nodes + 1))
    network = parse_network(description)
    count = count or loop_count(nodes, quick)
    warmup = WARMUP if warmup is None else warmup
    sdo_seconds = QUICK_SDO_SECONDS if quick else SDO_SECONDS
    progress(f"active nodes: {nodes} in canopen's network in this process, and on the card")
    with baseline_steps(network) as base_side, card_steps(network, description) as (
            card_side, sim_card):
        progress(f"active nodes: {nodes} node(s), {warmup} warm-up + 2 x {count} PDO loop "
                 f"round trips each side, in {ROUNDS} alternating slices")
        card_loop, base_loop_measured = interleaved_loops(card_side.round_trip,
                                                          base_side.round_trip, count, warmup)
        progress(f"active nodes: expedited SDO uploads, {sdo_seconds} s each side, "
                 "alternating")
        card_sdo, base_sdo = interleaved(card_side.expedited, base_side.expedited, SDO_WARMUP,
                                         len(DEVICE_TYPE_BYTES), sdo_seconds)
        firmware_log = sim_card.log()
    cif = {"pdo_loop": _loop_figures(card_loop), "sdo": _sdo_figures(card_sdo),
           "firmware_log": firmware_log}
    base = {"pdo_loop": _loop_figures(base_loop_measured), "sdo": _sdo_figures(base_sdo)}
    cif_loop, base_loop = cif["pdo_loop"]["latency_us"], base["pdo_loop"]["latency_us"]
    return {
        "nodes": nodes,
        "round_trips": count,
        "warmup": warmup,
        "sdo_seconds": sdo_seconds,
        "pdo_frames_per_round_trip": 2 * nodes,
        "cif": cif,
        "baseline": base,
        "ratio_to_baseline": {
            "definition": "cif / baseline",
            "pdo_loop_p50": ratio(cif_loop.get("p50", 0.0), base_loop.get("p50", 0.0)),
            "pdo_loop_p99": ratio(cif_loop.get("p99", 0.0), base_loop.get("p99", 0.0)),
            "sdo_expedited": ratio(cif["sdo"]["expedited_uploads_per_s"],
                                   base["sdo"]["expedited_uploads_per_s"]),
        },
    }
