"""Phase 1, ``pdo_loop_latency``: output -> RPDO -> node -> TPDO -> input, one node.

One generic node, card in the uncontrolled handshake
(bMode 2 by DevPutTaskParameter + WARMSTART, then the on-line configuration).
The host writes a new output value with DevExchangeIO and polls the input
until it reads the same value back: output -> RPDO -> node -> TPDO -> input.
Baseline: a canopen ``RemoteNode`` sends RPDO1 and waits for TPDO1.
Both sides are timed by ``bench.common.measure``: the warm-up, then ``count`` round
trips with a clock read around each (latencies), then ``count`` more for the rate.
The ``recording`` entry runs the same loop on a plain card and on one that records a
session (``--record``, issue 25: at most 10 % dearer), side by side in alternating
batches, as the mailbox and exchange benchmarks measure it (docs/recording.md).
"""

from __future__ import annotations

import itertools
import tempfile
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import canopen

from bench.can.baseline import in_process, start_all
from bench.can.card import (
    TIMEOUT_MS,
    io_offsets,
    network_toml,
    simulated_card,
    start_uncontrolled,
)
from bench.common import (
    Measured,
    Step,
    latency_stats,
    measure,
    measure_recording_pair,
    progress,
    ratio,
    recording_entry,
    scratch_root,
)
from dbm_tools.network import parse_network
from firmware.sim.generic import IO_BYTES, generic_object_dictionary
from host_api.driver import (
    DevExchangeIO,
)

ECHO_TIMEOUT_S = 1.0
"""A PDO loop round trip not back within this is a failure."""


LOST = 1
"""[bench] status of a round trip whose value was not back within ECHO_TIMEOUT_S."""
RECORDING_BATCH = 200
"""Round trips per batch when a plain and a recording card take turns: a batch of the
mailbox's 2000 would be half a second here, and the turns would see less of the same
machine."""


def _summary(measured: Measured, firmware_log: dict[str, Any] | None = None) -> dict[str, Any]:
    result: dict[str, Any] = {
        "latency_us": latency_stats(measured.latencies_ns),
        "round_trips": measured.count,
        "round_trips_per_s": round(measured.per_second, 1),
        "failures": measured.failures,
    }
    if firmware_log is not None:
        result["firmware_log"] = firmware_log
    return result


def image_values(nodes: int) -> list[bytes]:
    """Successive values of all ``nodes`` nodes' outputs: each differs from the one before,
    none is the inputs' initial 0."""
    return [bytes([v]) * (IO_BYTES * nodes) for v in range(1, 256)]


def image_round_trip(board: int, out_offset: int, in_offset: int, nodes: int = 1) -> Step:
    """One PDO loop round trip of ``nodes`` nodes on ``board``: write their outputs, poll
    their inputs until every one shows the value (``LOST`` after ``ECHO_TIMEOUT_S``). The
    host spins, as a control loop on DevExchangeIO does."""
    exchange, clock = DevExchangeIO, time.perf_counter_ns
    values = itertools.cycle(image_values(nodes))
    size = IO_BYTES * nodes
    give_up_ns = int(ECHO_TIMEOUT_S * 1e9)

    def round_trip() -> int:
        value = next(values)
        start = clock()
        exchange(board, out_offset, value, 0, 0, TIMEOUT_MS)
        while exchange(board, 0, b"", in_offset, size, TIMEOUT_MS)[1] != value:
            if clock() - start > give_up_ns:
                return LOST
        return 0

    return round_trip


def card_pdo_latency(count: int, warmup: int) -> dict[str, Any]:
    network = parse_network(network_toml([1]))
    with simulated_card(network_toml([1])) as card:
        board, _, _ = start_uncontrolled(card, network)
        round_trip = image_round_trip(board.number, *io_offsets(network))
        progress(f"pdo latency (card): {warmup} warm-up + 2 x {count} round trips")
        measured = measure(round_trip, count, warmup, frozenset({0}))
        return _summary(measured, card.log())


@contextmanager
def _pdo_pair(records: tuple[bool, bool]) -> Iterator[list[tuple[int, Step]]]:
    """Boards 0 and 1 in one image directory, each a card with its one node, configured as
    ``card_pdo_latency``'s; ``records[n]``: board n records a session."""
    description = network_toml([1])
    network = parse_network(description)
    offsets = io_offsets(network)
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-pdo-", dir=scratch_root()) as tmp, \
            ExitStack() as stack:
        pair = []
        for number, record in enumerate(records):
            card = stack.enter_context(simulated_card(description, board=number,
                                                      dpm_dir=Path(tmp), record=record))
            board, _, _ = start_uncontrolled(card, network)
            pair.append((card.pid, image_round_trip(board.number, *offsets)))
        yield pair


def card_pdo_recording(count: int, warmup: int) -> dict[str, Any]:
    """The PDO loop on a plain card and on a recording one, in turn (``measure_recording_pair``,
    in batches of ``RECORDING_BATCH`` round trips)."""
    progress(f"pdo latency, plain and recording card in turn: {warmup} warm-up + {count} "
             "round trips each")
    run = measure_recording_pair(_pdo_pair, count, warmup, frozenset({0}), RECORDING_BATCH)
    return recording_entry("the PDO loop on a card recording a session (cifemu firmware "
                           "--simulate --record)", run, "round_trips_per_s")


def baseline_pdo_latency(count: int, warmup: int) -> dict[str, Any]:
    network = parse_network(network_toml([1]))
    with in_process(network) as (sim, client):
        node = canopen.RemoteNode(1, generic_object_dictionary(network.nodes[0]))
        client.add_node(node)
        node.rpdo.read(from_od=True)  # type: ignore[no-untyped-call]
        node.tpdo.read(from_od=True)  # type: ignore[no-untyped-call]
        start_all(sim, client)
        rpdo, tpdo = node.rpdo[1], node.tpdo[1]
        condition = tpdo.receive_condition
        values = itertools.cycle(image_values(1))

        def round_trip() -> int:
            value = next(values)
            with condition:  # taken before the send: the TPDO cannot slip past the wait
                rpdo.data = bytearray(value)
                rpdo.transmit()
                while bytes(tpdo.data) != value:
                    if not condition.wait(ECHO_TIMEOUT_S):
                        return LOST
            return 0

        progress(f"pdo latency (baseline): {warmup} warm-up + 2 x {count} round trips")
        return _summary(measure(round_trip, count, warmup, frozenset({0})))


def pdo_latency(count: int, warmup: int) -> dict[str, Any]:
    baseline = baseline_pdo_latency(count, warmup)
    card = card_pdo_latency(count, warmup)
    recording = card_pdo_recording(count, warmup)
    return {
        "description": "DevExchangeIO writes a new 8-byte output, the host polls the input "
                       "until it shows the value: output -> RPDO1 -> generic node -> TPDO1 -> "
                       "input; card in the uncontrolled handshake (exchange mode 3), 1 node",
        "cif": card,
        "baseline": {"name": "canopen RemoteNode: RPDO1 transmit, wait for TPDO1 with the value "
                             "(same simulated node, virtual bus, this process)", **baseline},
        "ratio_to_baseline": {
            "definition": "cif / baseline",
            "p50": ratio(card["latency_us"].get("p50", 0.0),
                         baseline["latency_us"].get("p50", 0.0)),
            "p99": ratio(card["latency_us"].get("p99", 0.0),
                         baseline["latency_us"].get("p99", 0.0)),
        },
        "recording": recording,
    }

