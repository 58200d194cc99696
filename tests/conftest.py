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

from host_api import driver
from host_api.liveness import firmware_liveness

REQUIRE_SOCKETCAN = "CIFEMU_REQUIRE_SOCKETCAN"
"""Set by ``make test-vcan``: there a SocketCAN test that skips is a failure."""

# test_sim.py loads tests.buses as a plugin, but test_can_task.py imports it first:
# registered here, it is rewritten on that first import, as its plugin use expects.
pytest.register_assert_rewrite("tests.buses")

ROOT = Path(__file__).resolve().parents[1]
IMAGE_SIZE = 8192
HOST_FLAGS = 0x1FFE
DEV_FLAGS = 0x1FFF
READY = 0x80


TIME_SCALE = 4.0 if os.environ.get("VCAN_VM_BACKEND") == "qemu" else 1.0
"""Under tools/vcan-vm's qemu backend (no KVM) Python runs about 20 times slower: the
waits for the card's own work (a start, a condition) get four times longer there. What the
card must do in a given time (supervision, SYNC) is not scaled."""


def wait_until(condition: Callable[[], object], timeout: float = 5.0, what: str = "") -> None:
    """Poll ``condition`` until true; fail the test with ``what`` at the deadline."""
    timeout *= TIME_SCALE
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what or condition}")
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
    proc = subprocess.Popen(
        [sys.executable, "-m", "cifemu", "firmware", "--board", str(board),
         "--dpm-dir", str(directory), "--log-level", "WARNING", *extra],
        stderr=subprocess.PIPE,
    )
    card = Card(directory, board, proc)
    deadline = time.monotonic() + 15 * TIME_SCALE
    while True:
        if proc.poll() is not None:
            stderr = proc.stderr.read().decode() if proc.stderr else ""
            raise RuntimeError(f"firmware exited: {stderr}")
        if card.path.exists() and card.path.stat().st_size == IMAGE_SIZE:
            with open(card.path, "rb") as f:
                f.seek(HOST_FLAGS)
                # READY from this process, not from a killed predecessor's image
                if f.read(1)[0] & READY and firmware_liveness(directory, board).pid == proc.pid:
                    return card
        if time.monotonic() > deadline:
            card.stop()
            raise RuntimeError("firmware did not become READY")
        time.sleep(0.005)


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "vcan: needs SocketCAN with vcan0 (make test-vcan)")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Marks the ``socketcan`` variants of the back-to-back fixtures ``vcan``, so that
    ``-m vcan`` selects them (``test_vcan_tools.py``, SocketCAN only, marks itself)."""
    for item in items:
        callspec = getattr(item, "callspec", None)
        if callspec is not None and "socketcan" in callspec.params.values():
            item.add_marker(pytest.mark.vcan)


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
