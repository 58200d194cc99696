"""The system calls of a mailbox round trip, Python host and C host (issue 22).

A round trip used to take three flock rounds in a Python host (the transaction lock, and
the flags lock around each DevFlags toggle) and five in a C host (the put and get channels
too): ten and six system calls of the twelve to seventeen a round trip made. DevFlags is
now changed by an atomic read-modify-write on the mapped byte, and the put and get
channels are thread locks inside the transaction lock, in both drivers: one flock round is
left, the transaction lock's, which a crashed host's kernel frees (docs/dpm.md section 2).
A user sees this as CPU per round trip; the tests count the calls, which the machine's
load does not change.
"""

from __future__ import annotations

import fcntl
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from bench.libcif import build_program
from bench.mailbox import _round_trip
from tests import commands
from tests.conftest import Card
from tests.libcif_host import needs_toolchain

ROUND_TRIPS = 200
FLOCKS_PER_ROUND_TRIP = 2
"""Take and release of the transaction lock: the put takes it, the get's answer frees it."""


def test_a_python_round_trip_takes_one_flock_round(board: int,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    round_trip = _round_trip(board)
    assert round_trip() == 0  # the first call maps and loads what later calls reuse
    calls: list[int] = []
    real: Callable[[int, int], None] = fcntl.flock

    def counted(fd: int, operation: int) -> None:
        """The real flock, counted: the test asks how often the driver makes the call."""
        calls.append(operation)
        real(fd, operation)

    monkeypatch.setattr(fcntl, "flock", counted)
    for _ in range(ROUND_TRIPS):
        assert round_trip() == 0
    monkeypatch.undo()
    assert len(calls) == FLOCKS_PER_ROUND_TRIP * ROUND_TRIPS


@needs_toolchain
@pytest.mark.skipif(shutil.which("strace") is None, reason="strace counts the C host's calls")
def test_a_c_round_trip_takes_one_flock_round(card: Card, tmp_path: Path) -> None:
    program = build_program(tmp_path)
    done = commands.run(
        ["strace", "-f", "-c", "-e", "trace=flock", "-o", str(tmp_path / "calls"),
         str(program), "mailbox", str(ROUND_TRIPS), "0"],
        env={"CIF_DPM_DIR": str(card.directory), "PATH": "/usr/bin:/bin"},
        capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    found = re.search(r"^\s*[\d.]+\s+[\d.]+\s+\d+\s+(\d+)\s+(?:\d+\s+)?flock$",
                      (tmp_path / "calls").read_text(), re.MULTILINE)
    assert found is not None, (tmp_path / "calls").read_text()
    # libcif_bench makes ROUND_TRIPS timed round trips, then as many for the rate
    assert int(found.group(1)) == FLOCKS_PER_ROUND_TRIP * 2 * ROUND_TRIPS

