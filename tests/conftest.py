"""Shared fixtures: real firmware processes on real image files."""

from __future__ import annotations

import mmap
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from bench.cpu import descendants, runqueue_wait_ns
from host_api import driver
from host_api.ready import START_CPU_S, START_STALL_S, StartError, wait_ready
from tests.selection import HELPER_MODULES, forbid_processes, marks_of_module

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


class LoadClock:
    """Seconds the test's processes could run: wall time minus the time their threads
    waited for a CPU (``bench.cpu.runqueue_wait_ns``), summed over this test process and
    the firmwares, ``cifemu sim`` and commands it started, and theirs. On an idle machine
    it runs with the wall clock; with two busy processes and other workers on two cores,
    a card's every step waits in the run queue, and a deadline in wall time failed where
    the card had done nothing wrong (at a load of 15 a runnable process gets about a
    seventh of a core)."""

    def __init__(self, start: float) -> None:
        self._start = start
        self._waited = self._sample()

    @staticmethod
    def _sample() -> dict[int, int]:
        return runqueue_wait_ns([os.getpid(), *descendants(os.getpid())])

    def elapsed(self) -> float:
        """Wall seconds since ``start``, less the time load took from the test's processes
        since the clock was made, but never less than a ``STRETCH_LIMIT``-th of them."""
        wall = time.monotonic() - self._start
        stolen = sum(ns - self._waited.get(tid, 0) for tid, ns in self._sample().items()) / 1e9
        return max(wall - stolen, wall / STRETCH_LIMIT)


def wait_until(condition: Callable[[], object], timeout: float = 5.0, what: str = "") -> None:
    """Poll ``condition`` until true; fail the test with ``what`` at the deadline.

    ``timeout`` counts the time the test's processes could run (``LoadClock``): wall time
    on an idle machine; on a loaded one the deadline moves by the time load took from them.
    """
    timeout *= TIME_SCALE
    start = time.monotonic()
    deadline = start + timeout  # when the load clock is first read
    clock: LoadClock | None = None
    while not condition():
        if clock is None:  # a wait not over at once: /proc is read for its baseline
            clock = LoadClock(start)
        now = time.monotonic()
        if now > deadline:
            elapsed = clock.elapsed()
            if elapsed > timeout:
                pytest.fail(f"timed out after {timeout} s waiting for {what or condition}"
                            + (f" ({now - start:.1f} s of wall time on a loaded machine)"
                               if now - start > timeout + 0.5 else ""))
            deadline = now + min(timeout - elapsed, 0.05)  # the next look at the clock
        time.sleep(0.001)


@dataclass
class Card:
    """A firmware process serving board ``board`` in ``directory``."""

    directory: Path
    board: int
    proc: subprocess.Popen[bytes]

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
        if self.proc.poll() is None:
            self.thaw()
            self.proc.terminate()
        return self.proc.wait(timeout=10)


def start_card(directory: Path, board: int = 0, *extra: str) -> Card:
    """Start a firmware and wait until it serves (``host_api.ready.wait_ready``: READY from
    this process, for as long as its start advances); a firmware that exits first fails
    with its stderr, one whose start stops advancing is stopped. The bounds scale with
    ``TIME_SCALE``, as every wait of the suite does."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "cifemu", "firmware", "--board", str(board),
         "--dpm-dir", str(directory), "--log-level", "WARNING", *extra],
        stderr=subprocess.PIPE,
    )
    card = Card(directory, board, proc)
    try:
        wait_ready(proc, directory, board, START_STALL_S * TIME_SCALE, START_CPU_S * TIME_SCALE)
    except StartError as exc:
        if exc.status is None:
            card.stop()
            raise RuntimeError(str(exc)) from None
        stderr = proc.stderr.read().decode() if proc.stderr else ""
        raise RuntimeError(f"{exc}: {stderr}") from None
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
    """The markers by module (tests/selection.py), and ``vcan`` on the ``socketcan`` variants
    of the back-to-back fixtures, so that ``-m vcan`` selects them (``test_vcan_tools.py``,
    SocketCAN only, marks itself)."""
    for item in items:
        for mark in marks_of_module(item.path.stem):
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
