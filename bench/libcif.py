"""libcif, the C driver library, beside the Python host and the baselines in one run.

- mailbox round trip (DevPutMessage + DevGetMessage of a COM_Shared_Memory read, as
  ``bench.mailbox``): a C host's p50 against the Python host's and the
  ``multiprocessing.Pipe`` ping-pong; target: the C p50 at most the Python host's;
- DevExchangeIO of 32 bytes out and 32 in, in every handshake mode (as
  ``bench.exchange_io``), C against Python and the mmap slice baseline; target:
  uncontrolled at least 2,000,000 calls/s from C.

The C figures come from ``libcif/bench/libcif_bench.c``, linked statically with libcif and
run as its own process against the same firmware: the loops and their clocks are C, so no
Python call overhead is in them.

    python -m bench.libcif [--count N] [--warmup N]
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

from bench import exchange_io, mailbox
from bench.common import (
    Card,
    Measured,
    host_session,
    machine_info,
    progress,
    ratio,
    running_card,
    sized_main,
    source_fingerprint,
)
from cifemu import libcif

NAME = "libcif"
DEFAULT_COUNT = 20_000
DEFAULT_WARMUP = 1_000
UNCONTROLLED_FACTOR = 100
"""The C uncontrolled loop runs this many times ``count`` calls: 2,000,000 by default."""
TARGET_UNCONTROLLED_CALLS_PER_S = 2_000_000.0
PROGRAM = libcif.SOURCE / "bench" / "libcif_bench.c"


def build_program(directory: Path) -> Path:
    """libcif_bench, optimised and linked with libcif.a."""
    libcif.build("all")
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        raise RuntimeError("no C compiler: the C side of this benchmark cannot be built")
    program = directory / "libcif_bench"
    subprocess.run([compiler, "-std=c11", "-O2", "-Wall", "-Wextra", "-Werror", str(PROGRAM),
                    f"-I{libcif.INCLUDE}", str(libcif.BUILD / "libcif.a"), "-pthread",
                    "-o", str(program)], check=True)
    return program


def run_c(program: Path, card: Card, *args: str) -> Measured:
    """One run of libcif_bench against ``card``, its JSON as a Measured."""
    done = subprocess.run([str(program), *args], capture_output=True, text=True, check=False,
                          env={**os.environ, "CIF_DPM_DIR": str(card.directory)}, timeout=600)
    if done.returncode != 0:
        raise RuntimeError(f"libcif_bench {' '.join(args)} failed: {done.stderr.strip()}")
    result = json.loads(done.stdout)
    return Measured(result["count"], result["latencies_ns"], result["elapsed_ns"],
                    result["failures"],
                    {int(code): n for code, n in result["warmup_codes"].items()})


def _mailbox(program: Path, count: int, warmup: int) -> dict[str, Any]:
    pipe = mailbox.measure_pipe(count, warmup).summary("round_trips_per_s")
    python = mailbox.measure_card(count, warmup).summary("round_trips_per_s")
    with running_card() as card:
        progress(f"libcif mailbox: {warmup} warm-up + {count} timed + {count} round trips")
        c = run_c(program, card, "mailbox", str(count), str(warmup)).summary("round_trips_per_s")
    c_p50, py_p50 = c["latency_us"]["p50"], python["latency_us"]["p50"]
    return {
        "c_host": c,
        "python_host": python,
        "baseline": {"name": "multiprocessing.Pipe send_bytes/recv_bytes ping-pong", **pipe},
        "target": {"c_p50_us_at_most_python_p50": True},
        "meets_target": c_p50 <= py_p50,
        "ratio": {
            "definition": "c_host / python_host and c_host / baseline",
            "p50_to_python": ratio(c_p50, py_p50),
            "round_trips_per_s_to_python": ratio(c["round_trips_per_s"],
                                                 python["round_trips_per_s"]),
            "p50_to_baseline": ratio(c_p50, pipe["latency_us"]["p50"]),
        },
    }


def _exchange(program: Path, count: int, warmup: int) -> list[dict[str, Any]]:
    baseline = exchange_io.measure_baseline(count, warmup).summary("calls_per_s")
    modes: list[dict[str, Any]] = []
    with running_card() as card:
        for mode in exchange_io.MODES:
            with host_session(card) as board:
                python = exchange_io.measure_mode(board, mode, count, warmup)
            c_count = count * UNCONTROLLED_FACTOR if mode.exchange_mode == 3 else count
            progress(f"libcif mode {mode.exchange_mode} ({mode.name}): {c_count} calls")
            c = run_c(program, card, "exchange", str(c_count), str(warmup), str(mode.b_mode))
            c_result = c.summary("calls_per_s")
            py_result = python.summary("calls_per_s")
            target = TARGET_UNCONTROLLED_CALLS_PER_S if mode.exchange_mode == 3 else None
            modes.append({
                "exchange_mode": mode.exchange_mode,
                "bMode": mode.b_mode,
                "name": mode.name,
                "c_host": c_result,
                "python_host": py_result,
                "target_c_calls_per_s_min": target,
                "meets_target": None if target is None else c_result["calls_per_s"] >= target,
                "ratio": {
                    "c_to_python_calls_per_s": ratio(c_result["calls_per_s"],
                                                     py_result["calls_per_s"]),
                    "c_to_baseline_calls_per_s": ratio(c_result["calls_per_s"],
                                                       baseline["calls_per_s"]),
                },
            })
    return [{"baseline": {"name": "Python mmap slice store + load of 32 bytes", **baseline}},
            *modes]


def run(count: int | None = None, warmup: int | None = None) -> dict[str, Any]:
    """The libcif benchmark's JSON document."""
    count = DEFAULT_COUNT if count is None else count
    warmup = DEFAULT_WARMUP if warmup is None else warmup
    machine = machine_info()
    source = source_fingerprint()
    with tempfile.TemporaryDirectory(prefix="cifemu-libcif-bench-") as tmp:
        program = build_program(Path(tmp))
        mailbox_result = _mailbox(program, count, warmup)
        baseline, *modes = _exchange(program, count, warmup)
    return {
        "benchmark": NAME,
        "description": "libcif (C) beside the Python host: mailbox round trip and DevExchangeIO "
                       "per handshake mode, against running firmware processes",
        "machine": machine,
        "source": source,
        "params": {"count": count, "warmup": warmup,
                   "c_uncontrolled_count": count * UNCONTROLLED_FACTOR},
        "meets_target": {
            "mailbox_c_p50_le_python_p50": mailbox_result["meets_target"],
            "uncontrolled_c_calls_per_s": next(m["meets_target"] for m in modes
                                               if m["exchange_mode"] == 3),
        },
        "mailbox": mailbox_result,
        "exchange_io": {"modes": modes, **baseline},
    }


def main(argv: list[str] | None = None) -> int:
    return sized_main("python -m bench.libcif", __doc__, run, (DEFAULT_COUNT, DEFAULT_WARMUP),
                      argv)


if __name__ == "__main__":
    raise SystemExit(main())
