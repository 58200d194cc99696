"""DBM handling: parse + check a 127-node database, and download it into a running card.

The database is built in the run from a network description of 127 generic
nodes (node-IDs 1..127, 8 bytes in and out each), so NODES and DESCRIPT use
the container's long-directory form. Two figures, each beside a baseline
measured in the same run:

- parse + check: ``read_dbm`` of the file's bytes, then ``check_dbm`` (every
  data check the card applies at reset); the file read is included. Baseline:
  reading the same file from disk. Target: p50 <= 20 ms.
- download: ``DevDownload`` of the file into a firmware process (a first
  message, then the data area in 240-byte messages, each answered, then the
  card's fsync'ed store in its flash directory); reported as time and data-area
  bytes per second. Baseline: the same number of messages of the same sizes
  sent over a ``multiprocessing.Pipe`` to a process that answers each with
  8 bytes, the cheapest ping-pong transfer Python offers.

The card's flash is a temporary directory ($CIFEMU_FLASH_DIR), never the
user's.

    python -m bench.dbm [--count N] [--warmup N]
"""

from __future__ import annotations

import multiprocessing
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from bench.common import (
    Measured,
    host_session,
    machine_info,
    measure,
    pipe_echo,
    progress,
    ratio,
    running_card,
    sized_main,
    source_fingerprint,
)
from dbm_tools.builder import build_dbm
from dbm_tools.container import read_dbm, save_dbm
from dbm_tools.network import parse_network
from dbm_tools.validate import check_dbm
from dpm.commands import LOAD_CHUNK, LOAD_FIRST_LENGTH
from dpm.layout import MSG_HEADER_SIZE
from firmware.flash import FLASH_ENV
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload

NAME = "dbm"
NODES = 127
DEFAULT_COUNT = 100
DEFAULT_WARMUP = 10
DOWNLOAD_SHARE = 5
"""Downloads take longer than a parse: they run count / DOWNLOAD_SHARE times."""
FIRST_MESSAGE_BYTES = MSG_HEADER_SIZE + LOAD_FIRST_LENGTH
ANSWER_BYTES = MSG_HEADER_SIZE
TARGET_PARSE_CHECK_P50_MS = 20.0

FAILED = 1
"""[bench] status of a parse + check that found errors (a broken benchmark database)."""


def _network_text() -> str:
    return "[bus]\nbitrate = 500000\n" + "".join(
        f'[[node]]\nid = {n}\nname = "module {n}"\n' for n in range(1, NODES + 1)
    )


@contextmanager
def _database() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-dbm-") as tmp:
        path = Path(tmp) / f"{NODES}-nodes.dbm"
        save_dbm(path, build_dbm(parse_network(_network_text()), project="bench"))
        yield path


@contextmanager
def _private_flash() -> Iterator[None]:
    """Cards started meanwhile keep their flash in a temporary directory."""
    old = os.environ.get(FLASH_ENV)
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-flash-") as tmp:
        os.environ[FLASH_ENV] = tmp
        try:
            yield
        finally:
            if old is None:
                del os.environ[FLASH_ENV]
            else:
                os.environ[FLASH_ENV] = old


def measure_parse(path: Path, count: int, warmup: int) -> tuple[Measured, Measured]:
    """(parse + check, read-only baseline)."""

    def parse_check() -> int:
        return FAILED if check_dbm(read_dbm(path.read_bytes())) else 0

    def read_only() -> int:
        return 0 if path.read_bytes() else FAILED

    progress(f"dbm: read baseline, {warmup} warm-up + 2 x {count}")
    baseline = measure(read_only, count, warmup, frozenset({0}))
    progress(f"dbm: parse + check, {warmup} warm-up + 2 x {count}")
    return measure(parse_check, count, warmup, frozenset({0})), baseline


def _message_sizes(area_bytes: int) -> list[int]:
    """The download's messages as the mailbox carries them: header + data."""
    pieces = [min(LOAD_CHUNK, area_bytes - at) for at in range(0, area_bytes, LOAD_CHUNK)]
    return [FIRST_MESSAGE_BYTES] + [8 + size for size in pieces]


def measure_download(path: Path, count: int, warmup: int) -> Measured:
    with _private_flash(), running_card() as card, host_session(card) as board:
        progress(f"dbm: DevDownload, {warmup} warm-up + 2 x {count}")
        return measure(lambda: int(DevDownload(board, CONFIGURATION_DOWNLOAD, path)),
                       count, warmup, frozenset({0}))


def measure_pipe(sizes: list[int], count: int, warmup: int) -> Measured:
    context = multiprocessing.get_context("spawn")
    parent, child = context.Pipe(duplex=True)
    echo = context.Process(target=pipe_echo, args=(child, ANSWER_BYTES), daemon=True)
    echo.start()
    child.close()
    messages = [bytes(size) for size in sizes]
    send, recv = parent.send_bytes, parent.recv_bytes

    def transfer() -> int:
        for message in messages:
            send(message)
            if len(recv()) != ANSWER_BYTES:
                return FAILED
        return 0

    try:
        progress(f"dbm: pipe baseline, {warmup} warm-up + 2 x {count} transfers")
        return measure(transfer, count, warmup, frozenset({0}))
    finally:
        parent.send_bytes(b"")
        echo.join(5.0)
        if echo.is_alive():
            echo.terminate()
            echo.join()
        parent.close()


def _ms(measured: Measured) -> dict[str, float]:
    return {k: round(v / 1000.0, 3) for k, v in measured.summary("per_s")["latency_us"].items()}


def run(count: int | None = None, warmup: int | None = None) -> dict[str, Any]:
    """The DBM benchmark's JSON document."""
    count = DEFAULT_COUNT if count is None else count
    warmup = DEFAULT_WARMUP if warmup is None else warmup
    downloads = max(1, count // DOWNLOAD_SHARE)
    download_warmup = max(1, warmup // DOWNLOAD_SHARE)
    machine = machine_info()
    source = source_fingerprint()
    with _database() as path:
        file_bytes = path.stat().st_size
        area_bytes = file_bytes - 44
        sizes = _message_sizes(area_bytes)
        parse, read = measure_parse(path, count, warmup)
        pipe = measure_pipe(sizes, downloads, download_warmup)
        download = measure_download(path, downloads, download_warmup)
    parse_ms, read_ms = _ms(parse), _ms(read)
    download_ms, pipe_ms = _ms(download), _ms(pipe)
    download_rate = area_bytes / (download_ms["p50"] / 1000.0)
    pipe_rate = area_bytes / (pipe_ms["p50"] / 1000.0)
    return {
        "benchmark": NAME,
        "description": f"parse + check a {NODES}-node DBM; DevDownload it into a running card",
        "machine": machine,
        "source": source,
        "params": {
            "count": count, "warmup": warmup, "download_count": downloads,
            "download_warmup": download_warmup, "nodes": NODES, "file_bytes": file_bytes,
            "data_area_bytes": area_bytes, "messages": len(sizes),
        },
        "targets": {"parse_check_p50_ms_max": TARGET_PARSE_CHECK_P50_MS},
        "meets_target": {"parse_check_p50": parse_ms["p50"] <= TARGET_PARSE_CHECK_P50_MS},
        "parse_check": {"latency_ms": parse_ms, "failures": parse.failures},
        "parse_check_baseline": {"name": "Path.read_bytes of the same file",
                                 "latency_ms": read_ms},
        "download": {"latency_ms": download_ms, "bytes_per_s_at_p50": round(download_rate),
                     "failures": download.failures,
                     "warmup_return_codes": download.summary("per_s")["warmup_return_codes"]},
        "download_baseline": {
            "name": f"multiprocessing.Pipe: the same {len(sizes)} messages, each answered "
                    f"with {ANSWER_BYTES} bytes",
            "latency_ms": pipe_ms, "bytes_per_s_at_p50": round(pipe_rate),
        },
        "ratio_to_baseline": {
            "definition": "cifemu / baseline, p50",
            "parse_check": ratio(parse_ms["p50"], read_ms["p50"]),
            "download": ratio(download_ms["p50"], pipe_ms["p50"]),
        },
    }


def main(argv: list[str] | None = None) -> int:
    return sized_main("python -m bench.dbm", __doc__, run, (DEFAULT_COUNT, DEFAULT_WARMUP),
                      argv)


if __name__ == "__main__":
    raise SystemExit(main())
