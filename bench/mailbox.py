"""Mailbox round trip: DevPutMessage + DevGetMessage of a COM_Shared_Memory read.

One round trip sends a 16-byte message (8 header + 8 telegram-header bytes asking
the PLC task for 8 bytes of the receive area) and takes the 24-byte answer. The
baseline, measured in the same run before the card starts, is a
``multiprocessing.Pipe`` ping-pong of the same sizes between two processes: the
cost of the cheapest Python IPC round trip on this machine.

    python -m bench.mailbox [--count N] [--warmup N]
"""

from __future__ import annotations

import multiprocessing
from typing import Any

from bench.common import (
    Measured,
    Step,
    host_session,
    machine_info,
    measure,
    measure_recording,
    pipe_echo,
    progress,
    ratio,
    recording_entry,
    running_card,
    sized_main,
    source_fingerprint,
)
from dpm.commands import COM_SHARED_MEMORY
from dpm.message import Message, Task, Tdt, TelegramHeader, Tfc
from host_api.driver import MSG_BUFFER_SIZE, DevGetMessage, DevPutMessage

NAME = "mailbox"
DEFAULT_COUNT = 20_000
DEFAULT_WARMUP = 1_000
TIMEOUT_MS = 1000

TARGET_P50_US = 100.0
TARGET_ROUND_TRIPS_PER_S = 10_000.0

PLC_TASK, USER_TASK = Task.PLC, Task.USER
READ_TELEGRAM = TelegramHeader(data_area=1, data_cnt=8, data_type=Tdt.UINT8,
                               function=Tfc.READ).encode()
"""device_adr 0, data_area 1 (receive), data_adr 0, data_idx 0, data_cnt 8, uint8, read."""
REQUEST_BYTES = 8 + len(READ_TELEGRAM)
ANSWER_BYTES = 8 + len(READ_TELEGRAM) + 8

BAD_ANSWER = -1000
"""[bench] status of a round trip whose answer is not the one asked for."""


def _requests() -> list[Message]:
    """One request per msg.nr value, built once so the loop times only the driver."""
    return [
        Message(rx=PLC_TASK, tx=USER_TASK, b=COM_SHARED_MEMORY, nr=nr, data=READ_TELEGRAM)
        for nr in range(256)
    ]


def _drain(board: int) -> None:
    """After a failed round trip, drop late answers so the next ones match again."""
    while DevGetMessage(board, MSG_BUFFER_SIZE, 50)[0] == 0:
        pass


def _round_trip(board: int) -> Step:
    requests = _requests()
    sequence = 0

    def round_trip() -> int:
        nonlocal sequence
        sequence = (sequence + 1) & 0xFF
        rc = DevPutMessage(board, requests[sequence], TIMEOUT_MS)
        if rc != 0:
            return int(rc)
        rc, answer = DevGetMessage(board, MSG_BUFFER_SIZE, TIMEOUT_MS)
        if rc != 0:
            _drain(board)
            return int(rc)
        if (answer is None or answer.nr != sequence or answer.f != 0
                or answer.ln + 8 != ANSWER_BYTES):
            _drain(board)
            return BAD_ANSWER
        return 0

    return round_trip


def measure_card(count: int, warmup: int) -> Measured:
    with running_card() as card, host_session(card) as board:
        progress(f"mailbox: {warmup} warm-up + 2 x {count} round trips")
        return measure(_round_trip(board), count, warmup, frozenset({0}))




def measure_pipe(count: int, warmup: int) -> Measured:
    context = multiprocessing.get_context("spawn")
    parent, child = context.Pipe(duplex=True)
    echo = context.Process(target=pipe_echo, args=(child, ANSWER_BYTES), daemon=True)
    echo.start()
    child.close()
    request = bytes(range(REQUEST_BYTES))
    send, recv = parent.send_bytes, parent.recv_bytes

    def ping_pong() -> int:
        send(request)
        return 0 if len(recv()) == ANSWER_BYTES else BAD_ANSWER

    try:
        progress(f"pipe baseline: {warmup} warm-up + 2 x {count} round trips")
        return measure(ping_pong, count, warmup, frozenset({0}))
    finally:
        parent.send_bytes(b"")
        echo.join(5.0)
        if echo.is_alive():
            echo.terminate()
            echo.join()
        parent.close()


def run(count: int | None = None, warmup: int | None = None) -> dict[str, Any]:
    """The mailbox benchmark's JSON document."""
    count = DEFAULT_COUNT if count is None else count
    warmup = DEFAULT_WARMUP if warmup is None else warmup
    machine = machine_info()
    source = source_fingerprint()
    pipe = measure_pipe(count, warmup)
    card = measure_card(count, warmup)
    progress(f"mailbox, plain and recording card in turn: {warmup} warm-up + {count} "
             "round trips each")
    recording = measure_recording(_round_trip, count, warmup, frozenset({0}))
    card_result = card.summary("round_trips_per_s")
    pipe_result = pipe.summary("round_trips_per_s")
    p50 = card_result["latency_us"]["p50"]
    rate = card_result["round_trips_per_s"]
    return {
        "benchmark": NAME,
        "description": "DevPutMessage + DevGetMessage of a COM_Shared_Memory read "
                       "(16 bytes out, 24 back) against a running firmware process",
        "machine": machine,
        "source": source,
        "params": {
            "count": count,
            "warmup": warmup,
            "request_bytes": REQUEST_BYTES,
            "answer_bytes": ANSWER_BYTES,
            "timeout_ms": TIMEOUT_MS,
        },
        "targets": {"p50_us_max": TARGET_P50_US, "round_trips_per_s_min": TARGET_ROUND_TRIPS_PER_S},
        "meets_target": {
            "p50": p50 <= TARGET_P50_US,
            "round_trips_per_s": rate >= TARGET_ROUND_TRIPS_PER_S,
        },
        "cif_mailbox": card_result,
        "recording": recording_entry("a card recording a session (cifemu firmware --record)",
                                     recording, "round_trips_per_s"),
        "baseline": {"name": "multiprocessing.Pipe send_bytes/recv_bytes ping-pong", **pipe_result},
        "ratio_to_baseline": {
            "definition": "cif_mailbox / baseline",
            "p50": ratio(p50, pipe_result["latency_us"]["p50"]),
            "p99": ratio(card_result["latency_us"]["p99"], pipe_result["latency_us"]["p99"]),
            "round_trips_per_s": ratio(rate, pipe_result["round_trips_per_s"]),
        },
    }


def main(argv: list[str] | None = None) -> int:
    return sized_main("python -m bench.mailbox", __doc__, run, (DEFAULT_COUNT, DEFAULT_WARMUP),
                      argv)


if __name__ == "__main__":
    raise SystemExit(main())
