"""DevExchangeIO calls per second in each process-data handshake mode.

Each call writes 32 bytes of outputs and reads 32 bytes of inputs. The card is
switched between the modes by a warm start with the protocol parameter bMode
(Task2Parameter byte 0): uncontrolled (exchange mode 3), buffered host-controlled
(mode 4), buffered device-controlled (mode 2). The baseline, measured in the same
run, is the bare work of an uncontrolled exchange: a 32-byte slice store and a
32-byte slice load on an anonymous mmap of the image's size.

Without a configured CAN bus the card never sets COM, so DevExchangeIO answers
DRV_DEV_NO_COM_FLAG (-21) after exchanging the data: 0 and -21 both count as a
completed exchange, any other code as a failure.

    python -m bench.exchange_io [--count N] [--warmup N]
"""

from __future__ import annotations

import mmap
from dataclasses import dataclass
from typing import Any

from bench.common import (
    Measured,
    Step,
    host_session,
    machine_info,
    measure,
    measure_recording,
    progress,
    ratio,
    recording_entry,
    running_card,
    sized_main,
    source_fingerprint,
)
from dpm.errors import Drv
from dpm.layout import DPM_SIZE, RCV_PD, SND_PD
from dpm.task2 import BMODE_TO_EXCHANGE_MODE, PlcMode
from host_api.driver import (
    GET_IO_INFO,
    WARMSTART,
    DevExchangeIO,
    DevGetInfo,
    DevPutTaskParameter,
    DevReset,
)

NAME = "exchange_io"
DEFAULT_COUNT = 20_000
DEFAULT_WARMUP = 1_000
IO_BYTES = 32
TIMEOUT_MS = 1000
RESET_TIMEOUT_MS = 5000

COMPLETED = frozenset({int(Drv.DRV_NO_ERROR), int(Drv.DRV_DEV_NO_COM_FLAG)})
SHORT_READ = -1000
"""[bench] status of a call that returned fewer input bytes than asked for."""

RECORDED_MODE = BMODE_TO_EXCHANGE_MODE[PlcMode.BUFFERED_HOST_CONTROLLED]
"""The mode measured again on a recording card: a handshake per call, so each call is a
recorded exchange (the PDO loop a host runs)."""


@dataclass(frozen=True, slots=True)
class Mode:
    exchange_mode: int
    """High nibble of bDriverType, as DevGetInfo(GET_IO_INFO) reports it."""
    b_mode: int
    """The protocol parameter that selects it at a warm start."""
    name: str
    target_calls_per_s: float | None


MODES = tuple(
    Mode(BMODE_TO_EXCHANGE_MODE[b_mode], b_mode, name, target)
    for b_mode, name, target in (
        (PlcMode.UNCONTROLLED, "uncontrolled", 100_000.0),
        (PlcMode.BUFFERED_HOST_CONTROLLED, "buffered_host_controlled", 5_000.0),
        (PlcMode.BUFFERED_DEVICE_CONTROLLED, "buffered_device_controlled", None),
    )
)


def measure_baseline(count: int, warmup: int) -> Measured:
    image = mmap.mmap(-1, DPM_SIZE)
    outputs = bytes(range(IO_BYTES))
    send_end, recv_end = SND_PD + IO_BYTES, RCV_PD + IO_BYTES

    def copy() -> int:
        image[SND_PD:send_end] = outputs
        return 0 if len(image[RCV_PD:recv_end]) == IO_BYTES else SHORT_READ

    try:
        progress(f"mmap baseline: {warmup} warm-up + 2 x {count} calls")
        return measure(copy, count, warmup, frozenset({0}))
    finally:
        image.close()


def _select_mode(board: int, mode: Mode) -> None:
    """Warm start with ``mode``'s bMode and check the card took it."""
    rc = DevPutTaskParameter(board, 2, bytes([mode.b_mode, 0, 0]))
    if rc != 0:
        raise RuntimeError(f"DevPutTaskParameter returned {rc}")
    rc = DevReset(board, WARMSTART, RESET_TIMEOUT_MS)
    if rc != 0:
        raise RuntimeError(f"DevReset(WARMSTART) returned {rc}")
    rc, io_info = DevGetInfo(board, GET_IO_INFO, 6)
    if rc != 0 or io_info[1] != mode.exchange_mode:
        raise RuntimeError(
            f"bMode {mode.b_mode}: card reports exchange mode {io_info[1:2].hex() or '?'} "
            f"(rc {rc}), expected {mode.exchange_mode}"
        )


def _exchange(board: int) -> Step:
    outputs = bytes(range(IO_BYTES))

    def exchange() -> int:
        rc, inputs = DevExchangeIO(board, 0, outputs, 0, IO_BYTES, TIMEOUT_MS)
        return int(rc) if len(inputs) == IO_BYTES else SHORT_READ

    return exchange


def measure_mode(board: int, mode: Mode, count: int, warmup: int) -> Measured:
    _select_mode(board, mode)
    progress(f"mode {mode.exchange_mode} ({mode.name}): {warmup} warm-up + 2 x {count} calls")
    return measure(_exchange(board), count, warmup, COMPLETED)




def run(count: int | None = None, warmup: int | None = None) -> dict[str, Any]:
    """The exchange benchmark's JSON document."""
    count = DEFAULT_COUNT if count is None else count
    warmup = DEFAULT_WARMUP if warmup is None else warmup
    machine = machine_info()
    source = source_fingerprint()
    baseline = measure_baseline(count, warmup).summary("calls_per_s")
    modes: list[dict[str, Any]] = []
    with running_card() as card, host_session(card) as board:
        for mode in MODES:
            result = measure_mode(board, mode, count, warmup).summary("calls_per_s")
            rate = result["calls_per_s"]
            target = mode.target_calls_per_s
            modes.append({
                "exchange_mode": mode.exchange_mode,
                "bMode": mode.b_mode,
                "name": mode.name,
                **result,
                "target_calls_per_s_min": target,
                "meets_target": None if target is None else rate >= target,
                "ratio_to_baseline": {
                    "calls_per_s": ratio(rate, baseline["calls_per_s"]),
                    "p50": ratio(result["latency_us"]["p50"], baseline["latency_us"]["p50"]),
                },
            })
    host_controlled = next(m for m in MODES if m.exchange_mode == RECORDED_MODE)
    progress(f"mode {RECORDED_MODE}, plain and recording card in turn: {warmup} warm-up + "
             f"{count} calls each")
    recording = measure_recording(_exchange, count, warmup, COMPLETED,
                                  lambda board: _select_mode(board, host_controlled))
    return {
        "benchmark": NAME,
        "description": f"DevExchangeIO with {IO_BYTES} bytes out and {IO_BYTES} bytes in, "
                       "per process-data handshake mode, against a running firmware process",
        "machine": machine,
        "source": source,
        "params": {
            "count": count,
            "warmup": warmup,
            "send_bytes": IO_BYTES,
            "receive_bytes": IO_BYTES,
            "timeout_ms": TIMEOUT_MS,
            "completed_return_codes": sorted(COMPLETED),
        },
        "targets": {m.name: {"calls_per_s_min": m.target_calls_per_s} for m in MODES},
        "meets_target": {m["name"]: m["meets_target"] for m in modes},
        "modes": modes,
        "recording": recording_entry(f"mode {RECORDED_MODE} on a card recording a session "
                                     "(cifemu firmware --record)", recording, "calls_per_s"),
        "baseline": {"name": f"mmap slice store + load of {IO_BYTES} bytes", **baseline},
        "ratio_definition": "mode / baseline",
    }


def main(argv: list[str] | None = None) -> int:
    return sized_main("python -m bench.exchange_io", __doc__, run, (DEFAULT_COUNT, DEFAULT_WARMUP),
                      argv)


if __name__ == "__main__":
    raise SystemExit(main())
