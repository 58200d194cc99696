"""CiA 309 SDO round trips: the 309-3 TCP server, the Python gateway, and python canopen.

One round trip is an expedited SDO upload of 1000h from a generic simulated node:

1. ``tcp``: a client sends ``[n] 1 read 0x1000 0 u32`` to the 309-3 server (CANopenNode
   dialect, in this process on its own event-loop thread) and reads the answer line;
2. ``gateway``: ``Gateway.sdo_upload`` as u32 (what the server does for each line);
3. baseline: python ``canopen``'s SDO client straight to the same simulated node on a
   virtual bus in this process, with no card between them.

``tcp_309_3_write`` is the write: ``[n] 1 write 0x6200 1 u8 0`` (an expedited SDO download of
an output byte of the generic I/O module, which the server sends from its event loop as it
does a read) against canopen's SdoClient download of the same object.

Two references bound what the TCP path can reach: ``tcp_empty_line``, the same client's
round trip of an empty line, which the server answers without the gateway (the TCP and
asyncio floor), and ``ceiling_tcp_to_baseline``, the ratio the TCP path would have if it
cost only that floor plus the gateway's upload (docs/benchmarks.md).

The card is ``cifemu firmware --simulate`` (``bench.can.simulated_card``): the node and
the card share a virtual bus in the firmware process, and this process reaches the card
only through its image. Ratios compare each path with the baseline and the TCP server with
the gateway below it.

Each path takes turns with the baseline in batches of ``BATCH`` reads
(``measure_alternating``), so both see the same machine: measured one after the other,
canopen's own rate swung 4,400-10,000 reads/s between runs a minute apart on a quiet
machine, and the ratio with it (0.39-0.73 for the same code).

    python -m bench.cia309 [--count N] [--warmup N]
"""

from __future__ import annotations

import argparse
import os
import socket
import threading
from typing import Any

from canopen.sdo.client import SdoClient

from bench.can import configure, in_process, network_toml, sdo_client, simulated_card, start_all
from bench.can import wait_operating as wait_nodes
from bench.common import (
    Measured,
    Step,
    add_size_arguments,
    emit,
    help_text,
    machine_info,
    measure,
    measure_alternating,
    progress,
    ratio,
    source_fingerprint,
)
from bench.cpu import thread_cpu_ns, thread_wakeups
from dbm_tools.network import parse_network
from dpm.start_progress import stat_cpu_ns
from host_api.cia309.gateway import Gateway
from host_api.cia309.model import Cia309Error, DataType
from host_api.cia309.server import BackgroundServer, ServerConfig

NAME = "cia309"
DEFAULT_COUNT = 2_000
DEFAULT_WARMUP = 100
NODE = 1
DEVICE_TYPE = (0x000F0191).to_bytes(4, "little")
ANSWER = b"983441\r\n"
"""1000h of the generic module as the CANopenNode dialect prints it (after the sequence)."""
OUTPUT = (0x6200, 1)
"""What the writes write 0 to: the generic module's first output byte, which nothing else
on the bench network depends on (a write of 1017h, the heartbeat producer time, costs the
node several times more, and 0 there ends its heartbeat: guarding fails after 2 s)."""
FAILED = 1
BATCH = 250
"""Reads per batch when a path and the baseline take turns."""


class _LineClient:
    """A 309-3 client that sends one request and reads its answer line."""

    def __init__(self, port: int) -> None:
        self._socket = socket.create_connection(("127.0.0.1", port), timeout=10)
        self._socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sequence = 0

    def read(self) -> int:
        return self._ask(f"{NODE} read 0x1000 0 u32", ANSWER)

    def write(self) -> int:
        index, subindex = OUTPUT
        return self._ask(f"{NODE} write 0x{index:04X} {subindex} u8 0", b"OK\r\n")

    def _ask(self, request: str, expected: bytes) -> int:
        """``request`` with the next sequence number; 0 when answered ``expected``."""
        self._sequence = self._sequence % 1_000_000 + 1
        self._socket.sendall(f"[{self._sequence}] {request}\n".encode())
        answer = self._answer()
        return 0 if answer == f"[{self._sequence}] ".encode() + expected else FAILED

    def empty(self) -> int:
        """An empty line; the server answers it with one (CANopenNode: cocomm -f waits)."""
        self._socket.sendall(b"\n")
        return 0 if self._answer() == b"\r\n" else FAILED

    def _answer(self) -> bytes | None:
        """The server's answer line, with its CR LF; None when the server closed."""
        answer = b""
        while not answer.endswith(b"\r\n"):
            chunk = self._socket.recv(256)
            if not chunk:
                return None
            answer += chunk
        return answer

    def close(self) -> None:
        self._socket.close()


def baseline_step(sdo: SdoClient) -> Step:
    """One expedited upload of 1000h by canopen's SDO client straight to the node."""

    def upload() -> int:
        return 0 if sdo.upload(0x1000, 0) == DEVICE_TYPE else FAILED

    return upload


def baseline_write_step(sdo: SdoClient) -> Step:
    """One expedited download of ``OUTPUT`` by canopen's SDO client straight to the node."""

    def download() -> int:
        sdo.download(*OUTPUT, b"\0")
        return 0

    return download


def measure_card(count: int, warmup: int, baseline: Step, baseline_write: Step
                 ) -> tuple[dict[str, Measured], dict[str, float]]:
    """The paths against one card, each in turns with its canopen baseline (``baseline``,
    ``baseline_write``), by name, and the CPU of TCP reads and writes: the server's
    event-loop thread (which serves a read or an expedited write whole, issue 22) and the
    card's process, and the loop thread's and the card's threads' wake-ups (voluntary
    context switches) per request: on this VM each costs 50-150 us of wall time and
    100-200 us of CPU, so they bound a request as much as the interpreter's work does.
    Both sleep while the baseline's batches run, so their CPU counts the TCP requests."""
    description = network_toml([NODE])
    accepted = frozenset({0})
    with simulated_card(description) as card:
        configure(card, parse_network(description))
        wait_nodes(0, 1)
        with Gateway([0], card.directory) as gateway:
            gateway.set_default_node_id(NODE)

            def upload() -> int:
                try:
                    data = gateway.sdo_upload(0x1000, 0, data_type=DataType.UNSIGNED32)
                    return 0 if data == DEVICE_TYPE else FAILED
                except Cia309Error:
                    return FAILED

            progress("timing the gateway, in turns with canopen")
            measured: dict[str, Measured] = {}
            measured["gateway"], measured["gateway_baseline"] = measure_alternating(
                [upload, baseline], count, warmup, accepted, BATCH)
            server = BackgroundServer(gateway, ServerConfig(port=0))
            client = _LineClient(server.port)
            try:
                progress("timing the 309-3 TCP server, in turns with canopen")
                cpu_us: dict[str, float] = {}
                for name, step, base in (("read", client.read, baseline),
                                         ("write", client.write, baseline_write)):
                    before = _server_counts(card.proc.pid)
                    measured[f"tcp_{name}"], measured[f"tcp_{name}_baseline"] = (
                        measure_alternating([step, base], count, warmup, accepted, BATCH))
                    after = _server_counts(card.proc.pid)
                    for key, total in after.items():
                        per_request = (total - before[key]) / (warmup + count)
                        if key.endswith("_ns"):
                            cpu_us[f"{key[:-3]}_us_per_{name}"] = round(per_request / 1e3, 1)
                        else:
                            cpu_us[f"{key}_per_{name}"] = round(per_request, 2)
                progress("timing the 309-3 TCP server's empty line (no gateway)")
                measured["empty"] = measure(client.empty, count, warmup, accepted)
            finally:
                client.close()
                server.close()
    return measured, cpu_us


def _server_thread() -> int:
    """The kernel's id of the server's event-loop thread (``BackgroundServer``'s)."""
    for thread in threading.enumerate():
        if thread.name == "cia309-server" and thread.native_id is not None:
            return thread.native_id
    raise RuntimeError("no cia309-server thread")


def _server_counts(card_pid: int) -> dict[str, int]:
    """So far: CPU nanoseconds and wake-ups of the server's loop thread and of the card's
    process (all its threads)."""
    loop_thread = _server_thread()
    return {"server_loop_cpu_ns": thread_cpu_ns(os.getpid()).get(loop_thread, 0),
            "server_loop_wakeups": thread_wakeups(os.getpid()).get(loop_thread, 0),
            "card_cpu_ns": stat_cpu_ns(card_pid),
            "card_wakeups": sum(thread_wakeups(card_pid).values())}


def run(count: int | None = None, warmup: int | None = None) -> dict[str, Any]:
    count = count or DEFAULT_COUNT
    warmup = DEFAULT_WARMUP if warmup is None else warmup
    network = parse_network(network_toml([NODE]))
    with in_process(network) as (sim, canopen_network):
        start_all(sim, canopen_network)
        sdo = sdo_client(canopen_network, NODE)
        measured, cpu_us = measure_card(count, warmup, baseline_step(sdo),
                                        baseline_write_step(sdo))
    rates = {name: m.per_second for name, m in measured.items()}
    floor_us = 1e6 / rates["empty"] + 1e6 / rates["gateway"]

    def cpu(name: str) -> dict[str, float]:
        return {key: value for key, value in cpu_us.items() if key.endswith(f"_per_{name}")}

    return {
        "benchmark": NAME,
        "what": "expedited SDO upload of 1000h from a simulated generic node, round trips; "
                "tcp_309_3_write: expedited SDO download of 6200h sub 1",
        "count": count,
        "warmup": warmup,
        "batch": BATCH,
        "tcp_309_3": {**measured["tcp_read"].summary("round_trips_per_s"), **cpu("read")},
        "tcp_309_3_write": {**measured["tcp_write"].summary("round_trips_per_s"),
                            **cpu("write")},
        "gateway": measured["gateway"].summary("round_trips_per_s"),
        "baseline_canopen": measured["tcp_read_baseline"].summary("round_trips_per_s"),
        "baseline_canopen_write": measured["tcp_write_baseline"].summary("round_trips_per_s"),
        "baseline_canopen_beside_gateway":
            measured["gateway_baseline"].summary("round_trips_per_s"),
        "tcp_empty_line": measured["empty"].summary("round_trips_per_s"),
        "ratios": {
            "tcp_to_baseline": ratio(rates["tcp_read"], rates["tcp_read_baseline"]),
            "tcp_write_to_baseline": ratio(rates["tcp_write"], rates["tcp_write_baseline"]),
            "tcp_write_to_tcp_read": ratio(rates["tcp_write"], rates["tcp_read"]),
            "gateway_to_baseline": ratio(rates["gateway"], rates["gateway_baseline"]),
            "tcp_to_gateway": ratio(rates["tcp_read"], rates["gateway"]),
            "ceiling_tcp_to_baseline": ratio(1e6 / floor_us, rates["tcp_read_baseline"]),
            "ceiling_definition": "tcp_to_baseline if a TCP read cost only the empty line's "
                                  "round trip plus the gateway's upload",
        },
        "machine": machine_info(),
        "source": source_fingerprint(),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.cia309", description=help_text(__doc__),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_size_arguments(parser, f"default {DEFAULT_COUNT}", f"default {DEFAULT_WARMUP}")
    args = parser.parse_args(argv)
    emit(run(args.count, args.warmup))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
