"""A running card is alive while other processes churn the kernel's lock table.

Liveness asks /proc/locks whether the firmware holds its lock (host_api/liveness.py,
libcif's firmware_alive). The kernel hands that table out a page per read: when locks
listed before the firmware's go between two pages, the firmware's falls out of the read.
A loaded CI run met it as a DevInitBoard of a freshly started card answering
DRV_DEV_NOT_READY (-11). The churners are real processes taking and dropping real flocks;
nothing is mocked.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from dpm.image import lock_path
from host_api.liveness import FirmwareLiveness, firmware_liveness
from tests.conftest import Card, wait_until
from tests.libcif_host import C_TESTS, CC, build_libcif, compile_program, run

CHURN = """
import fcntl, os, sys
fds = [os.open(os.path.join(sys.argv[1], f"churn{sys.argv[2]}-{i}"), os.O_CREAT | os.O_RDWR)
       for i in range(1000)]
print("ready", flush=True)
while True:
    for fd in fds:
        fcntl.flock(fd, fcntl.LOCK_EX)
    for fd in fds:
        fcntl.flock(fd, fcntl.LOCK_UN)
"""
"""Two of these hold up to 2,000 flocks, about 30 pages of /proc/locks, and drop them
again and again: before the fix about one read in 40 missed the card's lock."""


@pytest.fixture
def churning(tmp_path: Path) -> Iterator[None]:
    place = tmp_path / "churn"
    place.mkdir()
    churners = [subprocess.Popen([sys.executable, "-c", CHURN, str(place), str(n)],
                                 stdout=subprocess.PIPE, text=True) for n in range(2)]
    try:
        for churner in churners:
            assert churner.stdout is not None and churner.stdout.readline() == "ready\n"
        yield
    finally:
        for churner in churners:
            churner.kill()
            churner.wait()


def test_python_hosts_see_a_running_card_alive(card: Card, churning: None) -> None:
    answers = [firmware_liveness(card.path.parent, 0) for _ in range(300)]
    assert sum(not a.alive for a in answers) == 0
    assert {a.pid for a in answers} == {card.proc.pid}


@pytest.mark.skipif(CC is None or shutil.which("make") is None, reason="no C compiler or make")
def test_c_hosts_are_never_refused_a_running_card(card: Card, churning: None,
                                                  tmp_path: Path) -> None:
    build_libcif("all")
    program = compile_program(C_TESTS / "init_loop.c", tmp_path / "init_loop", "plain")
    assert run(program, card.path.parent, "300") == "refused 0\n"


def test_a_recorded_pid_counts_only_for_the_process_that_wrote_it(tmp_path: Path) -> None:
    """With nobody holding the lock, the recorded pid decides (the table may have missed
    the holder): a process started after the file's last write is a pid used again, and a
    zombie's lock went with its files; both are a dead firmware."""
    path = lock_path(tmp_path, 0)
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        path.write_text(f"{sleeper.pid}\n")
        assert firmware_liveness(tmp_path, 0) == FirmwareLiveness(True, sleeper.pid)
        long_ago = time.time() - 3600  # the pid was written before this process started
        os.utime(path, (long_ago, long_ago))
        assert firmware_liveness(tmp_path, 0) == FirmwareLiveness(False, sleeper.pid)
        path.write_text(f"{sleeper.pid}\n")
        sleeper.kill()
        stat = Path(f"/proc/{sleeper.pid}/stat")
        wait_until(lambda: stat.read_text().rsplit(")", 1)[1].split()[0] == "Z", 5,
                   "the killed process a zombie (not yet reaped)")
        assert firmware_liveness(tmp_path, 0) == FirmwareLiveness(False, sleeper.pid)
    finally:
        sleeper.kill()
        sleeper.wait()
    assert firmware_liveness(tmp_path, 0) == FirmwareLiveness(False, sleeper.pid)
