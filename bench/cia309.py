"""CiA 309 SDO round trips: the 309-3 TCP server, the Python gateway, and python canopen.

One round trip is an expedited SDO upload of 1000h from a generic simulated node:

1. ``tcp``: a client sends ``[n] 1 read 0x1000 0 u32`` to the 309-3 server (CANopenNode
   dialect, in this process on its own event-loop thread) and reads the answer line;
2. ``gateway``: ``Gateway.sdo_upload`` as u32 (what the server does for each line);
3. baseline: python ``canopen``'s SDO client straight to the same simulated node on a
   virtual bus in this process, with no card between them.

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
canopen's own rate swung 5,800-10,000 reads/s between runs a minute apart on a quiet
machine, and the ratio with it (0.41-0.71 for the same code).

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
        self._sequence = self._sequence % 1_000_000 + 1
        self._socket.sendall(f"[{self._sequence}] {NODE} read 0x1000 0 u32\n".encode())
        answer = self._answer()
        return 0 if answer == f"[{self._sequence}] ".encode() + ANSWER else FAILED

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


def measure_card(count: int, warmup: int, baseline: Step
                 ) -> tuple[Measured, Measured, Measured, Measured, Measured,
                            dict[str, float]]:
    """(gateway, its baseline, tcp, its baseline, tcp empty line, CPU per TCP read) against
    one card, each path in turns with ``baseline``: the server's event-loop thread (which
    serves a read whole, issue 22) and the card's process, and the loop thread's and the
    card's threads' wake-ups (voluntary context switches) per read: on this VM each costs
    50-150 us of wall time and 100-200 us of CPU, so they bound the read as much as the
    interpreter's work does. Both sleep while the baseline's batches run, so their CPU
    counts the TCP reads."""
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
            direct, direct_base = measure_alternating([upload, baseline], count, warmup,
                                                      accepted, BATCH)
            server = BackgroundServer(gateway, ServerConfig(port=0))
            client = _LineClient(server.port)
            try:
                progress("timing the 309-3 TCP server, in turns with canopen")
                loop_thread = _server_thread()
                before = _cpu_ns(loop_thread, card.proc.pid)
                woken = thread_wakeups(os.getpid()).get(loop_thread, 0)
                card_woken = sum(thread_wakeups(card.proc.pid).values())
                tcp, tcp_base = measure_alternating([client.read, baseline], count, warmup,
                                                    accepted, BATCH)
                after = _cpu_ns(loop_thread, card.proc.pid)
                woken = thread_wakeups(os.getpid()).get(loop_thread, 0) - woken
                card_woken = sum(thread_wakeups(card.proc.pid).values()) - card_woken
                calls = warmup + count
                cpu_us = {
                    "server_loop_cpu_us_per_read": round((after[0] - before[0]) / calls / 1e3, 1),
                    "server_loop_wakeups_per_read": round(woken / calls, 2),
                    "card_cpu_us_per_read": round((after[1] - before[1]) / calls / 1e3, 1),
                    "card_wakeups_per_read": round(card_woken / calls, 2)}
                progress("timing the 309-3 TCP server's empty line (no gateway)")
                empty = measure(client.empty, count, warmup, accepted)
            finally:
                client.close()
                server.close()
    return direct, direct_base, tcp, tcp_base, empty, cpu_us


def _server_thread() -> int:
    """The kernel's id of the server's event-loop thread (``BackgroundServer``'s)."""
    for thread in threading.enumerate():
        if thread.name == "cia309-server" and thread.native_id is not None:
            return thread.native_id
    raise RuntimeError("no cia309-server thread")


def _cpu_ns(thread: int, card_pid: int) -> tuple[int, int]:
    """CPU nanoseconds so far of the server's loop thread and of the card's process."""
    return thread_cpu_ns(os.getpid()).get(thread, 0), stat_cpu_ns(card_pid)


def run(count: int | None = None, warmup: int | None = None) -> dict[str, Any]:
    count = count or DEFAULT_COUNT
    warmup = DEFAULT_WARMUP if warmup is None else warmup
    network = parse_network(network_toml([NODE]))
    with in_process(network) as (sim, canopen_network):
        start_all(sim, canopen_network)
        baseline = baseline_step(sdo_client(canopen_network, NODE))
        direct, direct_base, tcp, tcp_base, empty, cpu_us = measure_card(count, warmup,
                                                                         baseline)
    rates = {name: m.per_second for name, m in
             (("tcp", tcp), ("gateway", direct), ("baseline", tcp_base),
              ("gateway_baseline", direct_base), ("empty", empty))}
    floor_us = 1e6 / rates["empty"] + 1e6 / rates["gateway"]
    return {
        "benchmark": NAME,
        "what": "expedited SDO upload of 1000h from a simulated generic node, round trips",
        "count": count,
        "warmup": warmup,
        "batch": BATCH,
        "tcp_309_3": {**tcp.summary("round_trips_per_s"), **cpu_us},
        "gateway": direct.summary("round_trips_per_s"),
        "baseline_canopen": tcp_base.summary("round_trips_per_s"),
        "baseline_canopen_beside_gateway": direct_base.summary("round_trips_per_s"),
        "tcp_empty_line": empty.summary("round_trips_per_s"),
        "ratios": {
            "tcp_to_baseline": ratio(rates["tcp"], rates["baseline"]),
            "gateway_to_baseline": ratio(rates["gateway"], rates["gateway_baseline"]),
            "tcp_to_gateway": ratio(rates["tcp"], rates["gateway"]),
            "ceiling_tcp_to_baseline": ratio(1e6 / floor_us, rates["baseline"]),
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
