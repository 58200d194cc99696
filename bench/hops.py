"""``python -m bench hops``: where each microsecond of a round trip goes (issue 22).

Every hop gets a time stamp on CLOCK_MONOTONIC, which is one clock for every process
on Linux: the host's own marks (``time.monotonic_ns`` around each driver call, and
while it watches the image's flag byte or input bytes spinning, so it sees a change
within a microsecond or two of the card's write), and the bus frames' time stamps.
The nodes run as ``cifemu sim`` on a fresh ``shm`` channel; this process opens one
more station on it and reads, after each round trip, the frames with the time stamp
their sender gave them (``time.time()`` at the send, turned into the monotonic clock
with the offset of the two clocks measured here). No firmware change is needed.

Paths: ``pdo_loop`` (DevExchangeIO output -> RPDO -> node -> TPDO -> input in the
image, uncontrolled handshake), ``mailbox`` (a COM_Shared_Memory read), ``sdo`` (an
expedited SDO upload by COM_SDO_Up_Download), ``cia309`` (the same upload as a 309-3
line over TCP to the server, which runs in this process as in ``bench.cia309``). Hop by
hop:

- host write: the driver call that writes the output or the message (DevExchangeIO,
  DevPutMessage); in the PDO loop one hop with the card's until the RPDO, since the
  driver's ring wakes the card, which may send before the call returns;
- card notices: until the card shows it took the message (DEVACK toggles);
- frame sent: until the card's frame is on the bus (its time stamp);
- node: the simulated node's answer frame after the card's;
- frame received -> image written: until the input bytes or HOSTCOM change in the image;
- host notices: the driver call that reads the answer (DevGetMessage), once it is there.

Each path also runs its plain round trip (the driver waiting on the doorbell, no
spinning), whose p50 against the sum of the hops is the cost of the host's wake-up. The
mailbox path also says what each plain round trip cost the host's thread and the card's
device loop (``plain_round_trip_scheduling``: CPU, waits for a CPU, wake-ups and
preemptions, from ``/proc``); ``--load`` runs the paths beside two busy processes, as
``python -m bench --load`` does, where those waits show which side the load delays.
With ``--profile`` py-spy samples the firmware's GIL holder during each path
(``bench.can.profile.summarise_profile``): the share of the device loop, the CAN
master's thread, the controller's receive thread.
"""

from __future__ import annotations

import argparse
import bisect
import contextlib
import itertools
import mmap
import os
import socket
import subprocess
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Any

import can

from bench.can.card import (
    SeparateBus,
    SimCard,
    board_of,
    configure,
    io_offsets,
    network_toml,
    simulated_card,
    start_uncontrolled,
    wait_operating,
)
from bench.can.profile import _py_spy, summarise_profile
from bench.can.sdo import sdo_message
from bench.common import (
    emit,
    help_text,
    latency_stats,
    machine_info,
    percentile,
    progress,
    source_fingerprint,
)
from bench.cpu import CpuSample, ThreadSched, share
from bench.load import busy_load, describe
from bench.mailbox import READ_TELEGRAM
from dbm_tools.network import parse_network
from dpm import flags as fl
from dpm.commands import COM_SHARED_MEMORY
from dpm.layout import DPM_SIZE, HOST_FLAGS, RCV_PD
from dpm.message import Message, Task
from firmware.device import HOP_TRACE_ENV
from host_api.cia309.gateway import Gateway
from host_api.cia309.server import BackgroundServer, ServerConfig
from host_api.driver import MSG_BUFFER_SIZE, DevExchangeIO, DevGetMessage, DevPutMessage

NAME = "hops"
DEFAULT_COUNT = 2000
DEFAULT_WARMUP = 200
TIMEOUT_MS = 1000
GIVE_UP_NS = 1_000_000_000
PROFILE_S = 6
PROFILE_RATE = 500
RPDO1, TPDO1, SDO_RX, SDO_TX = 0x201, 0x181, 0x601, 0x581
"""Node 1's RPDO1 and TPDO1, and its SDO request and answer identifiers (CiA 301)."""

Marks = list[int]
"""One round trip's monotonic time stamps in ns, in the order of the path's hops."""


class Lost(Exception):
    """A round trip whose next step did not come within GIVE_UP_NS."""


def wall_to_monotonic_ns() -> int:
    """What to add to a ``time.time()`` stamp (ns) to put it on the monotonic clock."""
    best = None
    for _ in range(20):
        before = time.monotonic_ns()
        wall = time.time_ns()
        after = time.monotonic_ns()
        if best is None or after - before < best[0]:
            best = (after - before, (before + after) // 2 - wall)
    assert best is not None
    return best[1]


def spin(condition: Callable[[], bool]) -> int:
    """Spin until ``condition``; its monotonic time stamp (Lost after GIVE_UP_NS)."""
    clock = time.monotonic_ns
    start = clock()
    while not condition():
        if clock() - start > GIVE_UP_NS:
            raise Lost
    return clock()


class BusTap:
    """One more ``shm`` station on the card's channel: the frames with their senders' stamps."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="shm", channel=channel)
        self.offset = wall_to_monotonic_ns()

    def stamp(self, ident: int, data: bytes | None = None) -> int:
        """The monotonic time stamp of the next frame ``ident`` (with ``data``), in ns."""
        deadline = time.monotonic() + GIVE_UP_NS / 1e9
        while time.monotonic() < deadline:
            msg = self.bus.recv(0.05)
            if msg is not None and msg.arbitration_id == ident and (
                    data is None or bytes(msg.data) == data):
                return int(msg.timestamp * 1e9) + self.offset
        raise Lost

    def drain(self) -> None:
        while self.bus.recv(0) is not None:
            pass

    def close(self) -> None:
        self.bus.shutdown()


def _image(card: SimCard) -> mmap.mmap:
    fd = os.open(card.directory / "board0.dpm", os.O_RDWR)
    try:
        return mmap.mmap(fd, DPM_SIZE)
    finally:
        os.close(fd)


def _hop(marks: Marks, index: int) -> int:
    """Nanoseconds of hop ``index`` in one round trip."""
    return marks[index + 1] - marks[index]


def breakdown(names: list[str], rounds: list[Marks]) -> dict[str, Any]:
    """Per hop: p50, p90, p99 (µs) and the hop's share of the summed p50s."""
    table: list[dict[str, Any]] = []
    for index, name in enumerate(names):
        spans = sorted(r[index + 1] - r[index] for r in rounds)
        table.append({"hop": name, "p50_us": round(percentile(spans, 50) / 1000, 1),
                      "p90_us": round(percentile(spans, 90) / 1000, 1),
                      "p99_us": round(percentile(spans, 99) / 1000, 1)})
    total = sum(row["p50_us"] for row in table)
    for row in table:
        row["share"] = round(row["p50_us"] / total, 3) if total else None
    return {"hops": table, "sum_of_p50_us": round(total, 1),
            "end_to_end_us": latency_stats([r[-1] - r[0] for r in rounds]),
            "round_trips": len(rounds), "tail": tail(names, rounds)}


def tail(names: list[str], rounds: list[Marks]) -> dict[str, Any]:
    """Where the slowest round trips lose their time: for those at or above the end-to-end
    p99, each hop's mean and how often it was the round trip's longest hop.

    The p99 of each hop alone does not say that: the slowest round trips need not be made
    of any one hop's slowest spans. A tail spread over the hops that are wake-ups of a
    thread or process, while the hops that only compute stay short, is the scheduler's
    (a woken thread waiting for a CPU), not the card's work."""
    if not rounds:
        return {}
    ends = sorted(r[-1] - r[0] for r in rounds)
    threshold = percentile(ends, 99)
    slow = [r for r in rounds if r[-1] - r[0] >= threshold]
    longest = [max(range(len(names)), key=partial(_hop, r)) for r in slow]
    return {"round_trips": len(slow), "from_us": round(threshold / 1000, 1),
            "hops": [{"hop": name,
                      "mean_us": round(sum(r[i + 1] - r[i] for r in slow) / len(slow) / 1000, 1),
                      "longest_in": longest.count(i)} for i, name in enumerate(names)]}


def run_rounds(step: Callable[[], Marks], count: int, warmup: int) -> tuple[list[Marks], int]:
    rounds, lost = [], 0
    for i in range(warmup + count):
        try:
            marks = step()
        except Lost:
            lost += 1
            continue
        if i >= warmup:
            rounds.append(marks)
    return rounds, lost


def plain_p50(step: Callable[[], object], count: int) -> float:
    """p50 in µs of the unspun round trip (the driver waits on its doorbell)."""
    spans = []
    for _ in range(count):
        start = time.monotonic_ns()
        step()
        spans.append(time.monotonic_ns() - start)
    return round(percentile(sorted(spans), 50) / 1000, 1)


@contextmanager
def profiled(pid: int, enabled: bool) -> Iterator[dict[str, Any]]:
    """py-spy on ``pid`` (GIL holder, by thread) and its CPU time, while the block runs."""
    result: dict[str, Any] = {}
    spy = _py_spy() if enabled else None
    recorder = None
    output = Path(f"/tmp/cifemu-hops-{uuid.uuid4().hex[:8]}.txt")
    if spy is not None:
        recorder = subprocess.Popen(
            [spy, "record", "--pid", str(pid), "--duration", str(PROFILE_S), "--rate",
             str(PROFILE_RATE), "--format", "raw", "--output", str(output), "--threads",
             "--gil", "--nonblocking"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        time.sleep(0.3)  # py-spy attaches
    before = CpuSample.take(pid)
    try:
        yield result
    finally:
        result["firmware_cpu"] = share(before, CpuSample.take(pid), pid)
        if recorder is not None:
            try:
                recorder.communicate(timeout=PROFILE_S + 30)
            except subprocess.TimeoutExpired:
                recorder.kill()
                recorder.communicate()
            if output.exists():
                result["py_spy_gil"] = summarise_profile(output.read_text(),
                                                         PROFILE_S * PROFILE_RATE)
                output.unlink()
            else:
                result["py_spy_gil"] = {"error": f"py-spy failed ({recorder.returncode})"}


def _card(nodes: list[int]) -> tuple[str, SeparateBus, str]:
    channel = f"hops-{uuid.uuid4().hex[:10]}"
    return network_toml(nodes), SeparateBus("shm", channel), channel


def _window(step: Callable[[], Any], seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        with contextlib.suppress(Lost):
            step()


# --- the paths --------------------------------------------------------------------------------


PDO_HOPS = ["host writes, rings -> card notices (device loop) -> RPDO sent (CAN master)",
            "node: RPDO -> TPDO", "card receives TPDO -> input in image (host spinning)"]
"""The host's write is one hop with the card's: DevExchangeIO rings the card, which often
sends the RPDO before the call has returned. How long the call takes is reported beside
(``host_write_call_us``)."""


def pdo_loop(count: int, warmup: int, profile: bool) -> dict[str, Any]:
    description, bus, channel = _card([1])
    network = parse_network(description)
    with simulated_card(description, separate=True, bus=bus) as card:
        board, _, _ = start_uncontrolled(card, network)
        out_offset, in_offset = io_offsets(network)
        tap, image = BusTap(channel), _image(card)
        inputs = RCV_PD + in_offset
        values = itertools.cycle(bytes([v]) * 8 for v in range(1, 256))
        number = board.number
        calls: list[int] = []

        def step() -> Marks:
            value = next(values)
            tap.drain()
            t0 = time.monotonic_ns()
            DevExchangeIO(number, out_offset, value, 0, 0, TIMEOUT_MS)
            calls.append(time.monotonic_ns() - t0)
            t4 = spin(lambda: image[inputs : inputs + 8] == value)
            return [t0, tap.stamp(RPDO1, value), tap.stamp(TPDO1, value), t4]

        def plain() -> None:
            value = next(values)
            DevExchangeIO(number, out_offset, value, 0, 0, TIMEOUT_MS)
            start = time.monotonic_ns()
            while DevExchangeIO(number, 0, b"", in_offset, 8, TIMEOUT_MS)[1] != value:
                if time.monotonic_ns() - start > GIVE_UP_NS:
                    return

        try:
            progress(f"{NAME} pdo_loop: {warmup} + {count} round trips")
            rounds, lost = run_rounds(step, count, warmup)
            result = breakdown(PDO_HOPS, rounds)
            result["host_write_call_us"] = latency_stats(calls[warmup:])
            result["lost"] = lost
            result["plain_round_trip_p50_us"] = plain_p50(plain, count)
            with profiled(card.pid, profile) as prof:
                _window(plain, PROFILE_S)
            result["profile"] = prof
            return result
        finally:
            image.close()
            tap.close()


MAILBOX_HOPS = ["host: DevPutMessage writes, rings -> card loop awake",
                "card: awake -> takes the message (DEVACK)",
                "card: handles it -> answer in the mailbox (HOSTCOM)",
                "host: answer there -> DevGetMessage returns (host spinning)"]
SDO_HOPS = ["host: DevPutMessage writes, rings -> card loop awake",
            "card: awake -> takes the message (DEVACK)",
            "card: -> SDO request frame sent", "node: request -> answer frame",
            "card: answer frame -> answer in the mailbox (HOSTCOM)",
            "host: answer there -> DevGetMessage returns (host spinning)"]


@contextmanager
def hop_trace() -> Iterator[Path]:
    """The firmware started inside the block stamps its loop (``HOP_TRACE_ENV``) into the
    yielded file, written when the firmware ends."""
    with tempfile.TemporaryDirectory(prefix="cifemu-hops-") as tmp:
        path = Path(tmp) / "trace.txt"
        os.environ[HOP_TRACE_ENV] = str(path)
        try:
            yield path
        finally:
            del os.environ[HOP_TRACE_ENV]


def read_trace(path: Path) -> dict[str, list[int]]:
    """The firmware's stamps by event (woke, took, delivered), sorted."""
    events: dict[str, list[int]] = {}
    for line in path.read_text().splitlines():
        name, _, ns = line.partition(" ")
        events.setdefault(name, []).append(int(ns))
    return {name: sorted(stamps) for name, stamps in events.items()}


def _first_after(stamps: list[int], after: int) -> int | None:
    index = bisect.bisect_left(stamps, after)
    return stamps[index] if index < len(stamps) else None


def with_trace(rounds: list[Marks], trace: dict[str, list[int]]) -> list[Marks]:
    """Each round trip's host marks [put, (request, answer frame,) get returned] with the
    card's first wake-up, take and delivery after the put in between."""
    merged = []
    for marks in rounds:
        put, frames, got = marks[0], marks[1:-1], marks[-1]
        woke = _first_after(trace.get("woke", []), put)
        took = _first_after(trace.get("took", []), put)
        delivered = _first_after(trace.get("delivered", []), frames[-1] if frames else put)
        if woke is None or took is None or delivered is None or not woke <= took <= got:
            continue
        merged.append([put, woke, took, *frames, delivered, got])
    return merged


def _mailbox_step(number: int, image: mmap.mmap, request: Message, tap: BusTap | None,
                  frames: tuple[int, int] = (SDO_RX, SDO_TX)) -> Marks:
    """One put-spin-get round trip: the host's stamps (with ``tap``: and the two frames')."""
    if tap is not None:
        tap.drain()
    host = image[HOST_FLAGS]
    t0 = time.monotonic_ns()
    if DevPutMessage(number, request, TIMEOUT_MS) != 0:
        raise Lost
    spin(lambda: bool((image[HOST_FLAGS] ^ host) & fl.HOSTCOM))
    rc, answer = DevGetMessage(number, MSG_BUFFER_SIZE, TIMEOUT_MS)
    t4 = time.monotonic_ns()
    if rc != 0 or answer is None or answer.f != 0:
        raise Lost
    if tap is None:
        return [t0, t4]
    return [t0, tap.stamp(frames[0]), tap.stamp(frames[1]), t4]


def scheduling(step: Callable[[], object], count: int, card_pid: int) -> dict[str, Any]:
    """``count`` plain round trips, and what each cost the host's thread and the card's
    device loop (its main thread) in CPU, waits for a CPU, wake-ups and preemptions: on a
    loaded machine the waits say which side the load delays (issue 22)."""
    pid, tid = os.getpid(), threading.get_native_id()
    host, card = ThreadSched.take(pid, tid), ThreadSched.take(card_pid, card_pid)
    for _ in range(count):
        step()
    return {"round_trips": count,
            "host_thread": ThreadSched.take(pid, tid).per_call(host, count),
            "card_device_loop": ThreadSched.take(card_pid, card_pid).per_call(card, count)}


def _plain_mailbox(number: int, request: Message) -> Callable[[], None]:
    def plain() -> None:
        DevPutMessage(number, request, TIMEOUT_MS)
        DevGetMessage(number, MSG_BUFFER_SIZE, TIMEOUT_MS)
    return plain


def mailbox(count: int, warmup: int, profile: bool) -> dict[str, Any]:
    description, bus, _ = _card([1])
    with hop_trace() as trace_path:
        with simulated_card(description, separate=True, bus=bus) as card:
            number, image = board_of(card).number, _image(card)
            request = Message(rx=Task.PLC, tx=Task.USER, b=COM_SHARED_MEMORY, nr=1,
                              data=READ_TELEGRAM)
            try:
                progress(f"{NAME} mailbox: {warmup} + {count} round trips")
                rounds, lost = run_rounds(lambda: _mailbox_step(number, image, request, None),
                                          count, warmup)
                plain = _plain_mailbox(number, request)
                plain_us = plain_p50(plain, count)
                per_round_trip = scheduling(plain, count, card.pid)
                with profiled(card.pid, profile) as prof:
                    _window(plain, PROFILE_S)
            finally:
                image.close()
        result = breakdown(MAILBOX_HOPS, with_trace(rounds, read_trace(trace_path)))
    result.update(lost=lost, plain_round_trip_p50_us=plain_us,
                  plain_round_trip_scheduling=per_round_trip, profile=prof)
    return result


def sdo(count: int, warmup: int, profile: bool) -> dict[str, Any]:
    description, bus, channel = _card([1])
    with hop_trace() as trace_path:
        with simulated_card(description, separate=True, bus=bus) as card:
            board = board_of(card)
            configure(card, parse_network(description))
            wait_operating(board.number, 1)
            tap, image = BusTap(channel), _image(card)
            request = sdo_message(1, 0x1000, 0)
            request.nr = 1
            try:
                progress(f"{NAME} sdo: {warmup} + {count} expedited uploads")
                rounds, lost = run_rounds(
                    lambda: _mailbox_step(board.number, image, request, tap), count, warmup)
                plain = _plain_mailbox(board.number, request)
                plain_us = plain_p50(plain, count)
                with profiled(card.pid, profile) as prof:
                    _window(plain, PROFILE_S)
            finally:
                image.close()
                tap.close()
        result = breakdown(SDO_HOPS, with_trace(rounds, read_trace(trace_path)))
    result.update(lost=lost, plain_round_trip_p50_us=plain_us, profile=prof)
    return result


CIA309_HOPS = ["client line sent -> 309-3 server -> gateway -> DevPutMessage -> card awake",
               "card: awake -> takes the message (DEVACK)",
               "card: -> SDO request frame sent", "node: request -> answer frame",
               "card: answer frame -> answer in the mailbox (HOSTCOM)",
               "gateway: DevGetMessage -> answer line -> client has it"]


def cia309(count: int, warmup: int, profile: bool) -> dict[str, Any]:
    """``[n] 1 read 0x1000 0 u32`` over TCP to the 309-3 server (in this process, as in
    ``bench.cia309``) on the card: the client's stamps, the frames', the device loop's."""
    description, bus, channel = _card([1])
    with hop_trace() as trace_path:
        with simulated_card(description, separate=True, bus=bus) as card:
            configure(card, parse_network(description))
            wait_operating(board_of(card).number, 1)
            tap = BusTap(channel)
            with Gateway([0], card.directory) as gateway:
                gateway.set_default_node_id(1)
                server = BackgroundServer(gateway, ServerConfig(port=0))
                client = socket.create_connection(("127.0.0.1", server.port), timeout=10)
                client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                sequence = itertools.count(1)

                def line() -> int:
                    client.sendall(f"[{next(sequence)}] 1 read 0x1000 0 u32\n".encode())
                    answer = b""
                    while not answer.endswith(b"\r\n"):
                        chunk = client.recv(256)
                        if not chunk:
                            raise Lost
                        answer += chunk
                    return time.monotonic_ns()

                def step() -> Marks:
                    tap.drain()
                    t0 = time.monotonic_ns()
                    t_end = line()
                    return [t0, tap.stamp(SDO_RX), tap.stamp(SDO_TX), t_end]

                try:
                    progress(f"{NAME} cia309: {warmup} + {count} TCP SDO reads")
                    rounds, lost = run_rounds(step, count, warmup)
                    plain_us = plain_p50(line, count)
                    with profiled(card.pid, profile) as prof:
                        _window(line, PROFILE_S)
                finally:
                    client.close()
                    server.close()
                    tap.close()
        result = breakdown(CIA309_HOPS, with_trace(rounds, read_trace(trace_path)))
    result.update(lost=lost, plain_round_trip_p50_us=plain_us, profile=prof)
    return result


PATHS: dict[str, Callable[[int, int, bool], dict[str, Any]]] = {
    "pdo_loop": pdo_loop, "mailbox": mailbox, "sdo": sdo, "cia309": cia309,
}


def measure_hops(count: int, warmup: int, paths: list[str], profile: bool) -> dict[str, Any]:
    return {
        "benchmark": NAME,
        "clock": "CLOCK_MONOTONIC (time.monotonic_ns), system-wide; bus frames by their "
                 "senders' time.time() stamps moved onto it",
        "paths": {name: PATHS[name](count, warmup, profile) for name in paths},
        "machine": machine_info(),
        "source": source_fingerprint(),
    }


def run(count: int | None = None, warmup: int | None = None) -> dict[str, Any]:
    """``python -m bench hops``: every path, with py-spy when it is installed."""
    return measure_hops(count or DEFAULT_COUNT, DEFAULT_WARMUP if warmup is None else warmup,
                        list(PATHS), _py_spy() is not None)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.hops", description=help_text(__doc__),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=DEFAULT_COUNT)
    parser.add_argument("--warmup", type=int, default=DEFAULT_WARMUP)
    parser.add_argument("--only", nargs="*", choices=list(PATHS), default=list(PATHS))
    parser.add_argument("--profile", action="store_true", help="py-spy the firmware per path")
    parser.add_argument("--load", action="store_true",
                        help="beside two busy processes, as python -m bench --load")
    args = parser.parse_args(argv)
    if not args.load:
        emit(measure_hops(args.count, args.warmup, args.only, args.profile))
        return 0
    with busy_load() as pids:
        result = measure_hops(args.count, args.warmup, args.only, args.profile)
    emit({**result, "load": describe(pids)})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
