"""What every benchmark shares: a card to talk to, a timing loop, statistics, JSON.

A benchmark starts its own firmware process on a fresh image directory
(``running_card``), opens the driver on it (``host_session``), times a step
function with ``measure`` and prints one JSON document with ``emit``. Progress
goes to stderr, so stdout carries nothing but the JSON.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from bench.cpu import thread_cpu_ns
from dpm.image import image_path
from host_api.driver import DevCloseDriver, DevExitBoard, DevInitBoard, DevOpenDriver
from host_api.ready import START_STALL_S, wait_ready

STARTUP_TIMEOUT = START_STALL_S
"""Seconds a starting firmware may go without CPU time before its start counts as stuck
(``host_api.ready.wait_ready``); how long the start takes on a loaded machine is not
bounded here."""

STOP_TIMEOUT = 5.0
"""Seconds a firmware may take to end after SIGTERM before it is killed."""


class BenchError(RuntimeError):
    """A run that cannot give its figures for a reason the user can act on (a machine too
    loaded for a time-out the benchmark measures with): ``python -m bench`` and a
    benchmark's own command line print it as one line and end with status 1, no traceback."""


def load_text() -> str:
    """The load average, for a message that blames the machine."""
    try:
        return "load average " + " ".join(f"{n:.1f}" for n in os.getloadavg())
    except OSError:
        return "load average unknown"


def progress(text: str) -> None:
    """A progress line for the person watching: stderr, never stdout."""
    print(f"[bench] {text}", file=sys.stderr, flush=True)


# --- the card -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Card:
    """A running firmware process: where its image lives and who serves it."""

    directory: Path
    board: int
    pid: int

    @property
    def image(self) -> Path:
        return image_path(self.directory, self.board)


def scratch_root() -> str | None:
    """/dev/shm (where real images live, docs/dpm.md 3) when usable, else the default temp dir."""
    shm = "/dev/shm"
    return shm if os.path.isdir(shm) and os.access(shm, os.W_OK) else None


def stop_process(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM, and SIGKILL when the process has not ended ``STOP_TIMEOUT`` seconds later."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(STOP_TIMEOUT)
    except subprocess.TimeoutExpired:
        progress(f"firmware {proc.pid} ignored SIGTERM; killing it")
        proc.kill()
        proc.wait()


def _start_firmware(directory: Path, board: int, record: bool,
                    extra: Sequence[str] = ()) -> subprocess.Popen[bytes]:
    """A firmware process for ``board`` in ``directory``; ``record``: recording a session
    there (``--record``); ``extra``: more options of ``cifemu firmware`` (its interface,
    say). Its stdout is discarded (it must not mix with the JSON); its
    stderr (log lines at WARNING and above) goes to ours."""
    command = [sys.executable, "-m", "cifemu", "firmware", "--board", str(board),
               "--dpm-dir", str(directory), "--flash", str(directory / f"flash{board}"),
               "--log-level", "WARNING"]
    if record:
        command += ["--record", str(directory / f"session{board}")]
    command += extra
    return subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)


@contextmanager
def running_cards(records: tuple[bool, ...], *, startup_timeout: float = STARTUP_TIMEOUT,
                  extra: Sequence[str] = ()) -> Iterator[list[Card]]:
    """Firmware processes serving boards 0, 1, ... in one temporary directory, READY on
    entry; ``records[n]``: board n records a session (to measure what that costs). On
    exit each gets SIGTERM, and is killed if it has not ended ``STOP_TIMEOUT`` seconds
    later."""
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-", dir=scratch_root()) as tmp:
        directory = Path(tmp)
        procs: list[subprocess.Popen[bytes]] = []
        try:
            cards = []
            for board, record in enumerate(records):
                proc = _start_firmware(directory, board, record, extra)
                procs.append(proc)
                card = Card(directory, board, proc.pid)
                wait_ready(proc, card.directory, card.board, startup_timeout)
                progress(f"firmware pid {proc.pid} READY on {card.image}"
                         + (" (recording)" if record else ""))
                cards.append(card)
            yield cards
        finally:
            for proc in procs:
                stop_process(proc)


@contextmanager
def running_card(board: int = 0, *, startup_timeout: float = STARTUP_TIMEOUT,
                 extra: Sequence[str] = ()) -> Iterator[Card]:
    """A firmware subprocess serving ``board`` in a temporary directory, READY on entry
    (``running_cards``)."""
    if board == 0:
        with running_cards((False,), startup_timeout=startup_timeout, extra=extra) as cards:
            yield cards[0]
        return
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-", dir=scratch_root()) as tmp:
        proc = _start_firmware(Path(tmp), board, False, extra)
        try:
            card = Card(Path(tmp), board, proc.pid)
            wait_ready(proc, card.directory, card.board, startup_timeout)
            progress(f"firmware pid {proc.pid} READY on {card.image}")
            yield card
        finally:
            stop_process(proc)


@contextmanager
def host_session(card: Card) -> Iterator[int]:
    """DevOpenDriver + DevInitBoard on ``card``; yields the board number."""
    rc = DevOpenDriver(card.directory)
    if rc != 0:
        raise RuntimeError(f"DevOpenDriver({card.directory}) returned {rc}")
    try:
        rc = DevInitBoard(card.board)
        if rc != 0:
            raise RuntimeError(f"DevInitBoard({card.board}) returned {rc}")
        try:
            yield card.board
        finally:
            DevExitBoard(card.board)
    finally:
        DevCloseDriver()


@contextmanager
def host_sessions(cards: list[Card]) -> Iterator[list[int]]:
    """DevOpenDriver on the cards' one directory, DevInitBoard on each; their numbers."""
    rc = DevOpenDriver(cards[0].directory)
    if rc != 0:
        raise RuntimeError(f"DevOpenDriver({cards[0].directory}) returned {rc}")
    opened: list[int] = []
    try:
        for card in cards:
            rc = DevInitBoard(card.board)
            if rc != 0:
                raise RuntimeError(f"DevInitBoard({card.board}) returned {rc}")
            opened.append(card.board)
        yield opened
    finally:
        for board in opened:
            DevExitBoard(board)
        DevCloseDriver()


RECORDING_BATCH = 2000
"""Calls per batch when a plain and a recording card are measured in turn."""


@dataclass(frozen=True, slots=True)
class RecordingRun:
    """A plain card and a recording one, measured in turn, and the CPU each spent per call:
    the cards' processes and the recording card's session writer (while it records: it
    encodes the session after the recording, when nobody waits)."""

    plain: Measured
    recording: Measured
    cpu_us_per_call: dict[str, float]
    batch: int
    """Calls per batch (``measure_alternating``)."""


def _cpu_ns(pid: int) -> int:
    return sum(thread_cpu_ns(pid).values())


def session_writer_of(pid: int) -> int:
    """The session writer process of the recording firmware ``pid``."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            if ppid == pid and b"firmware.session_writer" in (stat.parent / "cmdline").read_bytes():
                return int(stat.parent.name)
        except (OSError, IndexError, ValueError):
            continue
    raise RuntimeError(f"the recording firmware {pid} runs no session writer")


WRITER_END_S = 300.0
"""How long a session writer may take to encode its session after its card stopped."""


def _wait_gone(pid: int) -> None:
    """Until process ``pid`` has ended (it is no child of ours: its /proc entry goes)."""
    deadline = time.monotonic() + WRITER_END_S
    while Path(f"/proc/{pid}").exists():
        if time.monotonic() > deadline:
            raise RuntimeError(f"the session writer {pid} still runs after {WRITER_END_S} s")
        time.sleep(0.05)


def _joined(parts: list[Measured]) -> Measured:
    codes: dict[int, int] = {}
    for part in parts:
        for code, seen in part.warmup_codes.items():
            codes[code] = codes.get(code, 0) + seen
    return Measured(sum(p.count for p in parts), [ns for p in parts for ns in p.latencies_ns],
                    sum(p.elapsed_ns for p in parts), sum(p.failures for p in parts), codes,
                    timed_twice=False)


@contextmanager
def _plain_pair(records: tuple[bool, bool], make_step: Callable[[int], Step],
                prepare: Callable[[int], None]) -> Iterator[list[tuple[int, Step]]]:
    """The mailbox and exchange benchmarks' pair: two cards without a network."""
    with running_cards(records) as cards, host_sessions(cards) as boards:
        for board in boards:
            prepare(board)
        yield [(card.pid, make_step(board)) for card, board in zip(cards, boards, strict=True)]


def measure_recording(make_step: Callable[[int], Step], count: int, warmup: int,
                      accepted: frozenset[int], prepare: Callable[[int], None] = lambda b: None
                      ) -> RecordingRun:
    """``make_step(board)`` on a plain card and on a recording one (``--record``) after
    ``prepare(board)`` (``measure_recording_pair``)."""
    return measure_recording_pair(lambda records: _plain_pair(records, make_step, prepare),
                                  count, warmup, accepted)


def measure_recording_pair(pair: Pair, count: int, warmup: int, accepted: frozenset[int],
                           batch: int = RECORDING_BATCH) -> RecordingRun:
    """A plain card and a recording one of ``pair`` side by side, in alternating batches
    (``measure_alternating``): half of ``count`` with board 1 recording, half with board 0
    (two identical plain cards differed by up to a tenth on the shared machine, one board
    faster than the other).

    The CPU per call counts the warm-up calls too, and what each card spends idle while
    the other is measured (the same for both)."""
    plain: list[Measured] = []
    recording: list[Measured] = []
    spent = {"plain_card": 0, "recording_card": 0, "session_writer": 0}
    for recorder in (1, 0):
        with pair((recorder == 0, recorder == 1)) as cards:
            pids = {"plain_card": cards[1 - recorder][0], "recording_card": cards[recorder][0],
                    "session_writer": session_writer_of(cards[recorder][0])}
            before = {name: _cpu_ns(pid) for name, pid in pids.items()}
            measured = measure_alternating([step for _, step in cards], count // 2, warmup,
                                           accepted, batch)
            for name, pid in pids.items():
                spent[name] += _cpu_ns(pid) - before[name]
        _wait_gone(pids["session_writer"])  # it encodes the session now: not beside the next
        plain.append(measured[1 - recorder])
        recording.append(measured[recorder])
    calls = 2 * (count // 2 + warmup)
    return RecordingRun(_joined(plain), _joined(recording),
                        {name: round(ns / calls / 1000, 2) for name, ns in spent.items()},
                        batch)


def recording_entry(name: str, run: RecordingRun, rate_name: str) -> dict[str, Any]:
    """The ``recording`` entry of a benchmark: the recording card's figures, the plain
    card's beside it, and what recording a session costs in percent of the plain card's
    (issue 25 allows 10 %): the p50 latency's rise and the rate's fall, and the CPU per
    call (``measure_recording``)."""
    plain_summary = run.plain.summary(rate_name)
    summary = run.recording.summary(rate_name)
    p50, rate = plain_summary["latency_us"]["p50"], plain_summary[rate_name]
    cpu = run.cpu_us_per_call
    return {"name": name, **summary, "plain": plain_summary,
            "method": f"a plain card and a recording one side by side, batches of "
                      f"{run.batch} calls alternating between them; half of the calls "
                      "with board 1 recording, half with board 0",
            "cpu_us_per_call": cpu,
            "cost_pct": {
                "p50": round(100.0 * (summary["latency_us"]["p50"] - p50) / p50, 1)
                if p50 else None,
                rate_name: round(100.0 * (rate - summary[rate_name]) / rate, 1)
                if rate else None,
                "card_cpu": round(100.0 * (cpu["recording_card"] - cpu["plain_card"])
                                  / cpu["plain_card"], 1) if cpu["plain_card"] else None}}


# --- timing and statistics ------------------------------------------------------------------


Step = Callable[[], int]
"""One operation under test; returns a status code (the driver's rc, or 0 for success)."""

Pair = Callable[[tuple[bool, bool]], AbstractContextManager[list[tuple[int, Step]]]]
"""Two cards side by side, ``records[n]``: board n records a session; yields each card's
firmware pid and the step that is timed on it."""


@dataclass(slots=True)
class Measured:
    """The figures of one ``measure`` run."""

    count: int
    latencies_ns: list[int]
    elapsed_ns: int
    failures: int
    warmup_codes: dict[int, int] = field(default_factory=dict)
    timed_twice: bool = True
    """``measure``'s: the latency loop and the rate loop each ran ``count`` calls."""

    @property
    def per_second(self) -> float:
        return self.count / (self.elapsed_ns / 1e9) if self.elapsed_ns else math.inf

    def summary(self, rate_name: str) -> dict[str, Any]:
        """The JSON form: ``rate_name`` per second, latency statistics, failures."""
        return {
            rate_name: round(self.per_second, 1),
            "latency_us": latency_stats(self.latencies_ns),
            "calls": 2 * self.count if self.timed_twice else self.count,
            "failures": self.failures,
            "warmup_return_codes": {str(k): v for k, v in sorted(self.warmup_codes.items())},
        }


def measure(step: Step, count: int, warmup: int, accepted: frozenset[int]) -> Measured:
    """Run ``step`` ``warmup`` times, then twice ``count`` times.

    The first timed loop reads the clock around every call (latencies); the second
    reads it only around the whole loop (throughput), so the clock's own cost does
    not lower the rate. A call whose status is not in ``accepted`` is a failure;
    the warm-up tallies the statuses it saw.
    """
    codes: dict[int, int] = {}
    for _ in range(warmup):
        status = step()
        codes[status] = codes.get(status, 0) + 1
    clock = time.perf_counter_ns
    latencies = [0] * count
    failures = 0
    for i in range(count):
        start = clock()
        status = step()
        latencies[i] = clock() - start
        if status not in accepted:
            failures += 1
    start = clock()
    for _ in range(count):
        if step() not in accepted:
            failures += 1
    elapsed = clock() - start
    return Measured(count, latencies, elapsed, failures, codes)


def measure_alternating(steps: list[Step], count: int, warmup: int,
                        accepted: frozenset[int], batch: int = RECORDING_BATCH
                        ) -> list[Measured]:
    """Run each of ``steps`` ``warmup`` times, then ``count`` times each in batches of
    ``batch``, taking turns (the order reversed every round), with each call's latency.

    For two cards side by side, such as a plain and a recording one: on a shared machine
    the load changes from second to second, and two runs one after the other differed by
    as much as what was measured. Here both see the same machine. A batch's rate counts
    the clock reads around its calls, for each step alike.
    """
    codes: list[dict[int, int]] = [{} for _ in steps]
    for step, seen in zip(steps, codes, strict=True):
        for _ in range(warmup):
            status = step()
            seen[status] = seen.get(status, 0) + 1
    clock = time.perf_counter_ns
    latencies: list[list[int]] = [[] for _ in steps]
    elapsed = [0] * len(steps)
    failures = [0] * len(steps)
    order = list(range(len(steps)))
    done = 0
    while done < count:
        size = min(batch, count - done)
        for n in order:
            step, times = steps[n], latencies[n]
            started = clock()
            for _ in range(size):
                start = clock()
                status = step()
                times.append(clock() - start)
                if status not in accepted:
                    failures[n] += 1
            elapsed[n] += clock() - started
        order.reverse()
        done += size
    return [Measured(count, latencies[n], elapsed[n], failures[n], codes[n], timed_twice=False)
            for n in range(len(steps))]


@dataclass(slots=True)
class Rate:
    """The figures of one ``timed`` run: transfers, failures, seconds, payload bytes."""

    transfers: int = 0
    failures: int = 0
    elapsed_s: float = 0.0
    payload_bytes: int = 0

    def per_s(self) -> float:
        return self.transfers / self.elapsed_s if self.elapsed_s else 0.0

    def kib_per_s(self) -> float:
        return self.payload_bytes / 1024 / self.elapsed_s if self.elapsed_s else 0.0


def timed(step: Callable[[], bool], warmup: int, seconds: float, payload: int) -> Rate:
    """Run ``step`` (True = success) ``warmup`` times, then for ``seconds``.

    The time-boxed sibling of ``measure``, for steps too slow to count in advance (a
    whole SDO transfer): ``payload`` bytes count towards ``Rate.kib_per_s`` per success.
    """
    for _ in range(warmup):
        step()
    rate = Rate()
    clock = time.perf_counter
    start = clock()
    end = start + seconds
    while True:
        if step():
            rate.transfers += 1
            rate.payload_bytes += payload
        else:
            rate.failures += 1
        now = clock()
        if now >= end:
            rate.elapsed_s = now - start
            return rate


def percentile(sorted_values: list[int] | list[float], q: float) -> float:
    """The ``q``-th percentile (0..100) of sorted values, linearly interpolated."""
    if not sorted_values:
        return math.nan
    rank = (len(sorted_values) - 1) * q / 100.0
    low = math.floor(rank)
    high = min(low + 1, len(sorted_values) - 1)
    fraction = rank - low
    return float(sorted_values[low] * (1.0 - fraction) + sorted_values[high] * fraction)


def latency_stats(samples_ns: list[int]) -> dict[str, float]:
    """p50, p90, p99, p99.9, mean, min and max in microseconds."""
    ordered = sorted(samples_ns)
    if not ordered:
        return {}

    def us(value: float) -> float:
        return round(value / 1000.0, 3)

    return {
        "p50": us(percentile(ordered, 50)),
        "p90": us(percentile(ordered, 90)),
        "p99": us(percentile(ordered, 99)),
        "p99_9": us(percentile(ordered, 99.9)),
        "mean": us(sum(ordered) / len(ordered)),
        "min": us(ordered[0]),
        "max": us(ordered[-1]),
    }


def ratio(measured: float, baseline: float) -> float | None:
    """``measured / baseline``, rounded; None when the baseline is zero."""
    return round(measured / baseline, 3) if baseline else None


# --- baseline helper process ------------------------------------------------------------------


def pipe_echo(conn: Connection, reply_size: int) -> None:
    """Answer every message with ``reply_size`` bytes; an empty message or EOF ends it.

    Lives here rather than in ``bench.mailbox`` so a spawned child imports it by a
    stable module name, however the benchmark was started.
    """
    reply = bytes(range(reply_size))
    try:
        while True:
            request = conn.recv_bytes()
            if not request:
                return
            conn.send_bytes(reply)
    except EOFError:
        return
    finally:
        conn.close()


# --- output ----------------------------------------------------------------------------------


def _cpu_model() -> str | None:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def machine_info() -> dict[str, Any]:
    """What the figures depend on: CPUs, Python, OS, load when the run started."""
    try:
        usable: int | None = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = None
    try:
        load: list[float] | None = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        load = None
    return {
        "cpu_count": os.cpu_count(),
        "cpus_usable": usable,
        "cpu_model": _cpu_model(),
        "python_version": platform.python_version(),
        "python_implementation": platform.python_implementation(),
        "platform": platform.platform(),
        "loadavg": load,
    }


SOURCE_PACKAGES = ("dpm", "firmware", "host_api")
"""The code under test: its fingerprint says which version produced a figure."""


def source_fingerprint() -> dict[str, Any]:
    """A SHA-256 over the ``.py`` files of the code under test (subpackages too), and their
    newest mtime.

    Figures only compare between runs of the same fingerprint; the tree may
    have no commit to name, so the fingerprint stands in for one.
    """
    root = Path(__file__).resolve().parent.parent
    digest = hashlib.sha256()
    newest = 0.0
    for package in SOURCE_PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            digest.update(path.relative_to(root).as_posix().encode() + b"\0")
            digest.update(path.read_bytes())
            newest = max(newest, path.stat().st_mtime)
    return {
        "packages": list(SOURCE_PACKAGES),
        "sha256": digest.hexdigest()[:16],
        "newest_mtime": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(newest)),
    }


def emit(document: Any) -> None:
    """Print ``document`` as JSON on stdout (the only thing a benchmark prints there)."""
    json.dump(document, sys.stdout, indent=2)
    sys.stdout.write("\n")
    sys.stdout.flush()


def help_text(doc: str | None) -> str:
    """A module docstring as ``--help`` prints it: plain text, without reST's literal marks."""
    return (doc or "").replace("``", "")


def sized_main(prog: str, doc: str | None, run: Callable[[int | None, int | None], Any],
               defaults: tuple[int, int], argv: list[str] | None) -> int:
    """The command line of a benchmark that takes only ``--count`` and ``--warmup``."""
    parser = argparse.ArgumentParser(prog=prog, description=help_text(doc),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_size_arguments(parser, f"default {defaults[0]}", f"default {defaults[1]}")
    args = parser.parse_args(argv)
    emit(run(args.count, args.warmup))
    return 0


def add_size_arguments(
    parser: argparse.ArgumentParser, count_default: str, warmup_default: str
) -> None:
    """``--count`` and ``--warmup``; None (the default) leaves the benchmark's own."""
    parser.add_argument("--count", type=_positive, default=None, metavar="N",
                        help=f"calls per timed loop ({count_default})")
    parser.add_argument("--warmup", type=_non_negative, default=None, metavar="N",
                        help=f"untimed calls first ({warmup_default})")


def _positive(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text} is not a positive count")
    return value


def _non_negative(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} is a negative count")
    return value
