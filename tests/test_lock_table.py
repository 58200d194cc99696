"""A running card is alive while other processes churn the kernel's lock table.

Liveness asks /proc/locks whether the firmware holds its lock (host_api/liveness.py,
libcif's firmware_alive). The kernel hands that table out a page per read: when locks
listed before the firmware's go between two pages, the firmware's falls out of the read.
A loaded CI run met it as a DevInitBoard of a freshly started card answering
DRV_DEV_NOT_READY (-11). The churners are real processes taking and dropping real flocks;
nothing is mocked.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from host_api.liveness import firmware_liveness
from tests.conftest import Card
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
