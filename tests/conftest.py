"""Shared fixtures: real firmware processes on real image files."""

from __future__ import annotations

import mmap
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, TypeVar

import pytest
import pytest_timeout

from bench.cpu import descendants, runqueue_wait_ns
from host_api import driver
from host_api.ready import START_CPU_S, START_STALL_S, StartError, wait_ready
from tests.selection import HELPER_MODULES, forbid_processes, marks_of_test

if TYPE_CHECKING:
    from host_api.cia309.events import EventStream
    from host_api.cia309.model import Event

T = TypeVar("T")

REQUIRE_SOCKETCAN = "CIFEMU_REQUIRE_SOCKETCAN"
"""Set by ``make test-vcan``: there a SocketCAN test that skips is a failure."""

# The helper modules hold asserts and fixtures; test modules import them, and some also load
# them as plugins: registered here, they are rewritten on the first import, whichever it is.
pytest.register_assert_rewrite(*HELPER_MODULES)

ROOT = Path(__file__).resolve().parents[1]
IMAGE_SIZE = 8192
HOST_FLAGS = 0x1FFE
DEV_FLAGS = 0x1FFF
READY = 0x80


TIME_SCALE = 4.0 if os.environ.get("VCAN_VM_BACKEND") == "qemu" else 1.0
"""Under tools/vcan-vm's qemu backend (no KVM) Python runs about 20 times slower: the
waits for the card's own work (a start, a condition) get four times longer there. What the
card must do in a given time (supervision, SYNC) is not scaled."""


STRETCH_LIMIT = 20.0
"""How far load may stretch a wait's deadline (``wait_until``): 20 times its time-out.
Beyond it the test's processes had less than a twentieth of the time they waited for."""


GUEST_STALL_PERIOD = 0.01
"""How often ``GuestStalls``'s thread looks at the clock while a wait runs (seconds)."""
GUEST_STALL_MIN = 0.02
"""Lateness of that look, beyond its own run-queue wait, that counts as a stall (seconds):
more than the interpreter's switch interval (5 ms) a busy main thread may hold it back."""


class GuestStalls:
    """Seconds the whole virtual machine stood still while a wait ran (``tools/vcan-vm``).

    User-Mode Linux's guest has one CPU, one host thread pinned to one host CPU, and on the
    shared machine it stalls as a whole for 0.2 to 1.3 s a few times a minute (the host runs
    something else). The guest's clocks jump over such a stall, /proc/stat books it as idle,
    UML has no steal time, and ``runqueue_wait_ns`` shows it only when the guest books it as
    run-queue wait of the thread it wakes first afterwards, which may be none of the test's
    (measured with the guest stopped from the host for 2 s: CLOCK_MONOTONIC moved 2.012 s,
    a sleeping probe's CPU time and run-queue wait not at all, 201 idle ticks). So a thread
    looks at the clock every ``GUEST_STALL_PERIOD`` while a wait runs; a look later than
    ``GUEST_STALL_MIN``, less the thread's own run-queue wait since its last late look, is a
    stall of the machine, not of the test's processes. (A stall the guest also booked as a
    test thread's run-queue wait counts twice: the deadline moves by up to twice the stall.)
    Runs only under ``tools/vcan-vm`` (``VCAN_VM_BACKEND``): on a host, a late look is the
    run-queue wait that ``LoadClock`` counts already."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._waits = 0
        self._stalled = 0.0
        self._waiting = threading.Event()
        self._thread: threading.Thread | None = None

    def watch(self) -> Callable[[], float]:
        """Measure from now while the returned function lives; it gives the seconds of
        stall since this call."""
        with self._lock:
            self._waits += 1
            self._waiting.set()
            if self._thread is None:
                self._thread = threading.Thread(target=self._measure, name="guest-stalls",
                                                daemon=True)
                self._thread.start()
            at = self._stalled

        def since() -> float:
            with self._lock:
                return self._stalled - at

        weakref.finalize(since, self._end)
        return since

    def _end(self) -> None:
        with self._lock:
            self._waits -= 1
            if not self._waits:
                self._waiting.clear()

    def _measure(self) -> None:
        schedstat = Path(f"/proc/self/task/{threading.get_native_id()}/schedstat")

        def queued() -> float:
            return int(schedstat.read_text().split()[1]) / 1e9

        while True:
            self._waiting.wait()
            waited = queued()
            last = time.monotonic()
            while self._waiting.is_set():
                time.sleep(GUEST_STALL_PERIOD)
                now = time.monotonic()
                late = now - last - GUEST_STALL_PERIOD
                last = now
                if late > GUEST_STALL_MIN:  # read /proc only then: a read costs here
                    before, waited = waited, queued()
                    stall = late - (waited - before)
                    if stall > 0:
                        with self._lock:
                            self._stalled += stall


GUEST_STALLS = GuestStalls() if os.environ.get("VCAN_VM_BACKEND") else None
"""The virtual machine's stalls (``GuestStalls``); None outside ``tools/vcan-vm``."""


class LoadClock:
    """Seconds the test's processes could run: wall time minus the time their threads
    waited for a CPU (``bench.cpu.runqueue_wait_ns``), summed over this test process and
    the firmwares, ``cifemu sim`` and commands it started, and theirs, and under
    ``tools/vcan-vm`` minus the time the whole guest stood still (``GuestStalls``). On an
    idle machine it runs with the wall clock; with two busy processes and other workers on
    two cores, a card's every step waits in the run queue, and a deadline in wall time
    failed where the card had done nothing wrong (at a load of 15 a runnable process gets
    about a seventh of a core)."""

    def __init__(self, start: float, stalls: Callable[[], float] | None = None) -> None:
        """``stalls``: a ``GuestStalls.watch`` started with the wait (one is started here
        when the guest has none given)."""
        self._start = start
        self._waited = self._sample()
        self._seen = dict(self._waited)
        """Each thread's run-queue wait at its last look, also of threads that have ended
        since: a command's compilers and children, which each waited their share."""
        if stalls is None and GUEST_STALLS is not None:
            stalls = GUEST_STALLS.watch()
        self._stalls = stalls

    @staticmethod
    def _sample() -> dict[int, int]:
        return runqueue_wait_ns([os.getpid(), *descendants(os.getpid())])

    def elapsed(self) -> float:
        """Wall seconds since ``start``, less the time load took from the test's processes
        (and stalls of the guest) since the clock was made, but never less than a
        ``STRETCH_LIMIT``-th of them. A thread that ended keeps what it had waited when
        last seen here."""
        wall = time.monotonic() - self._start
        self._seen.update(self._sample())
        stolen = sum(ns - self._waited.get(tid, 0) for tid, ns in self._seen.items()) / 1e9
        if self._stalls is not None:
            stolen += self._stalls()
        return max(wall - stolen, wall / STRETCH_LIMIT)


def wait_until(condition: Callable[[], object], timeout: float = 5.0, what: str = "") -> None:
    """Poll ``condition`` until true; fail the test with ``what`` at the deadline.

    ``timeout`` counts the time the test's processes could run (``LoadClock``): wall time
    on an idle machine; on a loaded one (or in a stalled virtual machine) the deadline moves
    by the time load took from them.
    """
    timeout *= TIME_SCALE
    start = time.monotonic()
    deadline = start + timeout  # when the load clock is first read
    # In the guest, stalls count from the start: the first look may block through one (a
    # DevExchangeIO waiting for the card's answer).
    stalls = GUEST_STALLS.watch() if GUEST_STALLS is not None else None
    clock: LoadClock | None = None
    while not condition():
        if clock is None:  # a wait not over at once: /proc is read for its baseline
            clock = LoadClock(start, stalls)
        now = time.monotonic()
        if now > deadline:
            elapsed = clock.elapsed()
            if elapsed > timeout:
                pytest.fail(f"timed out after {timeout} s waiting for {what or condition}"
                            + (f" ({now - start:.1f} s of wall time on a loaded machine)"
                               if now - start > timeout + 0.5 else ""))
            deadline = now + min(timeout - elapsed, 0.05)  # the next look at the clock
        time.sleep(0.001)



LOOK_S = 0.25
"""How often a blocking wait past its wall-clock time-out reads the load clock again."""


class LoadDeadline:
    """A time-out on the load clock (``LoadClock``) for a wait that blocks, not polls: an
    event, a condition variable, a queue, a process, a socket. ``left()`` says how long to
    block before looking again: the wall time to the time-out first; past it, no more than
    ``LOOK_S`` at a time while the load clock has not passed the time-out; then 0. Scaled
    by ``TIME_SCALE``, as ``wait_until``'s."""

    def __init__(self, timeout: float) -> None:
        self.timeout = timeout * TIME_SCALE
        self._start = time.monotonic()
        self._wall = self._start + self.timeout
        self._clock: LoadClock | None = None

    def left(self) -> float:
        """Seconds to block before looking again; 0 once the time-out has passed."""
        now = time.monotonic()
        if self._clock is None:  # a wait not over at once: /proc is read for its baseline
            self._clock = LoadClock(self._start)
        if now < self._wall:
            return self._wall - now
        elapsed = self._clock.elapsed()
        if elapsed >= self.timeout:
            return 0.0
        self._wall = now + min(self.timeout - elapsed, LOOK_S)
        return self._wall - now

    def wall(self) -> float:
        """Wall seconds since the wait began (for a message)."""
        return time.monotonic() - self._start


def on_load_clock(attempt: Callable[[float], T], timeout: float,
                  expired: type[Exception] | tuple[type[Exception], ...] = TimeoutError) -> T:
    """``attempt(seconds)``, a wait that blocks up to ``seconds`` and raises ``expired`` when
    its condition did not come, again until it returns; ``timeout`` counts on the load clock
    (``LoadDeadline``). The last ``expired`` is raised once the time-out has passed."""
    deadline = LoadDeadline(timeout)
    seconds = deadline.left()
    while True:
        try:
            return attempt(seconds)
        except expired:
            seconds = deadline.left()
            if seconds <= 0:
                raise


def within(wait: Callable[[float], bool], timeout: float) -> bool:
    """Whether ``wait(seconds)`` (``threading.Event.wait``, a doorbell's ``wait``: True once
    its condition came) comes true within ``timeout`` on the load clock. A test that expects
    nothing within a window asserts ``not within(...)``: the window, too, is the time the
    test's processes could run, so load cannot pass the check for a card that had no CPU to
    do the wrong thing in."""
    def attempt(seconds: float) -> bool:
        if not wait(seconds):
            raise TimeoutError
        return True

    try:
        return on_load_clock(attempt, timeout)
    except TimeoutError:
        return False


def taken(source: queue.Queue[T] | queue.SimpleQueue[T], timeout: float) -> T:
    """``source.get`` with ``timeout`` on the load clock; ``queue.Empty`` past it."""
    return on_load_clock(lambda seconds: source.get(timeout=seconds), timeout, queue.Empty)


def ended(thread: threading.Thread, timeout: float) -> bool:
    """Whether ``thread`` ends within ``timeout`` on the load clock (``Thread.join``'s)."""
    def wait(seconds: float) -> bool:
        thread.join(seconds)
        return not thread.is_alive()

    return within(wait, timeout)


def expect(stream: EventStream, predicate: Callable[[Event], bool], timeout: float,
           what: str = "a matching event") -> Event:
    """The first event of a CiA 309 gateway's stream that ``predicate`` accepts, waited for
    ``timeout`` seconds on the load clock: ``EventStream.wait_for`` counts wall time, and an
    event of a busy machine's card came later than 5 s of it (CI of 2026-12-04 00:33)."""
    deadline = LoadDeadline(timeout)
    while (seconds := deadline.left()) > 0:
        try:
            return stream.wait_for(predicate, seconds)
        except TimeoutError:
            pass
    pytest.fail(f"timed out after {deadline.timeout} s waiting for {what} "
                f"({deadline.wall():.1f} s of wall time)")


def silent(stream: EventStream, predicate: Callable[[Event], bool], window: float,
           what: str = "an event") -> None:
    """Fail when ``stream`` shows an event ``predicate`` accepts within ``window`` seconds on
    the load clock (``within``'s windows)."""
    deadline = LoadDeadline(window)
    while (seconds := deadline.left()) > 0:
        try:
            event = stream.wait_for(predicate, seconds)
        except TimeoutError:
            continue
        pytest.fail(f"{what}: {event}")


TEST_STRETCH_LIMIT = 10.0
"""How far load may stretch a test's own time-out (pytest-timeout's 120 s,
``pytest_timeout_set_timer``): 10 times, 20 minutes of wall time, about what a test gets at
a load of 20-30 on two cores (a fifteenth of a core for each runnable process). A test's
waits stretch up to ``STRETCH_LIMIT`` times each, but a test that hangs busy on a loaded
machine must still end within a run."""


@pytest.hookimpl(tryfirst=True)
def pytest_timeout_set_timer(item: pytest.Item, settings: Any) -> bool | None:
    """pytest-timeout's time-out of a whole test (120 s, pyproject.toml) on the load clock.

    It is there to end a test that hangs. Counted in wall time it ended tests that were
    getting on under load: ``test_dbm_cli``'s card commands, a 10 s wait of
    ``test_node_handlers[shm]`` that the load clock had rightly stretched, and the mailbox
    fuzz's thousand exchanges (runs of 2026-12-03). Here the alarm comes after the time-out
    in wall time, as before; then the test fails only once its processes could have run for
    the time-out (``LoadClock``) or ``TEST_STRETCH_LIMIT`` times it has passed on the wall
    clock, and otherwise the alarm is set again for what is left. A test whose processes
    hang blocked gets no run-queue wait: it ends at the time-out, as before. Only the
    ``signal`` method (a test in the main thread, the default here) is taken over."""
    if (settings.method != "signal"
            or threading.current_thread() is not threading.main_thread()):
        return None  # pytest-timeout's own timer
    start = time.monotonic()
    clock = LoadClock(start)

    def handler(signum: int, frame: object) -> None:
        __tracebackhide__ = True
        left = min(settings.timeout - clock.elapsed(),
                   settings.timeout * TEST_STRETCH_LIMIT - (time.monotonic() - start))
        if left > 0:
            signal.setitimer(signal.ITIMER_REAL, max(left, 0.1))
            return
        pytest_timeout.timeout_sigalrm(item, settings)

    def cancel() -> None:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, signal.SIG_DFL)

    item.cancel_timeout = cancel  # type: ignore[attr-defined]  # read by pytest-timeout
    signal.signal(signal.SIGALRM, handler)
    signal.setitimer(signal.ITIMER_REAL, settings.timeout)
    return True


LOG_SHOWN = 4000
"""The last characters of each live card's log that a failed test's report shows."""


@dataclass(eq=False)
class Card:
    """A firmware process serving board ``board`` in ``directory``; its stderr (the log)
    goes to ``stderr``, an unnamed file (``log``).

    Not a pipe: nobody reads a card's pipe while it runs, and a card that had logged 64 KiB
    (a pipe's buffer) into one would block in its next log line, whichever of its threads
    wrote it, and stop serving mid-test."""

    directory: Path
    board: int
    proc: subprocess.Popen[bytes]
    stderr: IO[bytes]

    def log(self) -> str:
        """What the card has logged so far."""
        self.stderr.seek(0)
        return self.stderr.read().decode(errors="replace")

    @property
    def path(self) -> Path:
        return self.directory / f"board{self.board}.dpm"

    def map(self) -> mmap.mmap:
        """A raw map of the image, as a program that never imports host_api has."""
        fd = os.open(self.path, os.O_RDWR)
        try:
            return mmap.mmap(fd, IMAGE_SIZE)
        finally:
            os.close(fd)

    def freeze(self) -> None:
        """Stop the firmware process (SIGSTOP): the image stays, nobody answers."""
        self.proc.send_signal(signal.SIGSTOP)

    def thaw(self) -> None:
        self.proc.send_signal(signal.SIGCONT)

    def stop(self) -> int:
        """SIGTERM, and its end within 10 s on the load clock (``tests.commands.wait``): a
        card that ends its threads and unmaps its image on a loaded machine is not hung."""
        from tests import commands  # imports this module: not at the top

        if self.proc.poll() is None:
            self.thaw()
            self.proc.terminate()
        return commands.wait(self.proc, 10)


_CARDS: weakref.WeakSet[Card] = weakref.WeakSet()
"""The cards a test or its fixtures still hold: a failed test's report shows their logs."""


def start_card(directory: Path, board: int = 0, *extra: str) -> Card:
    """Start a firmware and wait until it serves (``host_api.ready.wait_ready``: READY from
    this process, for as long as its start advances); a firmware that exits first fails
    with its stderr, one whose start stops advancing is stopped. The bounds scale with
    ``TIME_SCALE``, as every wait of the suite does."""
    stderr = tempfile.TemporaryFile()  # noqa: SIM115 (read after the card stops: Card.log)
    proc = subprocess.Popen(
        [sys.executable, "-m", "cifemu", "firmware", "--board", str(board),
         "--dpm-dir", str(directory), "--log-level", "WARNING", *extra],
        stderr=stderr,
    )
    card = Card(directory, board, proc, stderr)
    _CARDS.add(card)
    try:
        wait_ready(proc, directory, board, START_STALL_S * TIME_SCALE, START_CPU_S * TIME_SCALE)
    except StartError as exc:
        if exc.status is None:
            card.stop()
            raise RuntimeError(str(exc)) from None
        raise RuntimeError(f"{exc}: {card.log()}") from None
    return card


def pytest_configure(config: pytest.Config) -> None:
    # A shell starts a background job (`make test &`, CI scripts) with SIGINT ignored, and
    # children inherit an ignored signal: the demo, `cifemu record` and the other commands
    # that the tests end with Ctrl-C would never see it. A handler is not inherited: the
    # children start with Ctrl-C's default again.
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    config.addinivalue_line("markers", "vcan: needs SocketCAN with vcan0 (make test-vcan)")
    config.addinivalue_line("markers", "fast: starts no process and opens no socket: a codec, "
                            "parser or source check (make test-fast; tests/selection.py)")
    config.addinivalue_line("markers", "vcan_vm: starts a virtual machine through "
                            "tools/vcan-vm (make test-vcan, not make test)")
    config.addinivalue_line("markers", "serial: measures time; make test runs it after the "
                            "parallel pass, alone on the machine")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The markers by module and test (tests/selection.py), and ``vcan`` on the
    ``socketcan`` variants of the back-to-back fixtures, so that ``-m vcan`` selects them
    (``test_vcan_tools.py``, SocketCAN only, marks itself)."""
    for item in items:
        for mark in marks_of_test(item.path.stem, getattr(item, "originalname", item.name)):
            item.add_marker(mark)
        callspec = getattr(item, "callspec", None)
        if callspec is not None and "socketcan" in callspec.params.values():
            item.add_marker(pytest.mark.vcan)


@pytest.fixture(scope="session", autouse=True)
def fast_stays_fast(request: pytest.FixtureRequest) -> None:
    """Under ``-m fast`` (make test-fast) starting a process or opening a socket fails the
    test that does it: the selection cannot grow a firmware unnoticed."""
    if request.config.option.markexpr.strip() == "fast":
        forbid_processes()


@pytest.fixture(scope="session", autouse=True)
def private_image_directory(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """$CIF_DPM_DIR of this test process (each pytest-xdist worker has its own): a test or
    a command it runs that takes the default image directory never meets another worker's
    card, nor the user's in /dev/shm/cif."""
    directory = tmp_path_factory.mktemp("default-images")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("CIF_DPM_DIR", str(directory))
        yield directory


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]
                              ) -> Iterator[None]:
    """Under ``make test-vcan`` a skipped ``vcan`` test fails: the run exists to prove them."""
    del call
    outcome = yield
    report: pytest.TestReport = outcome.get_result()  # type: ignore[attr-defined]
    if report.failed:
        for card in list(_CARDS):
            report.sections.append((f"log of the card of board {card.board} in "
                                    f"{card.directory}", card.log()[-LOG_SHOWN:]))
    if (report.skipped and not hasattr(report, "wasxfail")  # an expected failure stays one
            and os.environ.get(REQUIRE_SOCKETCAN) and item.get_closest_marker("vcan") is not None):
        report.outcome = "failed"
        report.longrepr = f"skipped under {REQUIRE_SOCKETCAN}: {report.longrepr}"


@pytest.fixture(autouse=True)
def private_flash(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Every firmware a test starts keeps its database in the test's own flash root
    ($CIFEMU_FLASH_DIR), never in the user's data directory."""
    root = tmp_path / "flash"
    monkeypatch.setenv("CIFEMU_FLASH_DIR", str(root))
    return root


@pytest.fixture
def card(tmp_path: Path) -> Iterator[Card]:
    c = start_card(tmp_path)
    yield c
    c.stop()


@pytest.fixture
def board(card: Card) -> Iterator[int]:
    """Board 0 opened through the driver API against a running card."""
    assert driver.DevOpenDriver(card.directory) == 0
    assert driver.DevInitBoard(0) == 0
    yield 0
    while driver.DevCloseDriver() == 0:
        pass
