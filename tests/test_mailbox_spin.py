"""A host whose answers outlast its watch of the flags stops watching (issue 22) [ours].

A waiting single-threaded Python host, and every libcif host, watches the flags for 100 µs
before it sleeps on the bell, because a card answers most requests sooner. A watch that
the answer outlasts costs its whole CPU time for nothing, and on a busy machine takes it
from the card that has to answer: the mailbox round trip beside two busy processes was
3-3.4 times a pipe's. After such a watch the next 1, 3, 7 ... up to 63 waits sleep at once.

Measured here on a real card that sends nothing, with waits of 1 ms: a call that watches
looks at the flags (Python) or reads the clock (libcif) hundreds of times, one that
sleeps at once a few times. Each host runs as its own process, single-threaded (a
Python host with other threads never watches).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

from dpm.errors import Drv
from tests import commands
from tests.conftest import Card
from tests.libcif_host import C_TESTS, CC, build_libcif, compile_program, run

CALLS = 32
WATCHED = 20
"""Looks (or clock readings) above which a call watched the flags: a call that sleeps at
once makes fewer than ten, a 100 µs watch hundreds to thousands."""
MOST_WATCHES = 8
"""Of ``CALLS`` waits that no answer ends, at most this many watch: 5 with the back-off
(the 1st, 3rd, 7th, 15th and 31st), every one without it."""

ROOT = Path(__file__).resolve().parents[1]
PYTHON_HOST = """
import sys
from host_api import driver as d
from host_api.registry import lookup

assert d.DevOpenDriver(sys.argv[1]) == 0 and d.DevInitBoard(0) == 0
board = lookup(0)
looks = 0

def never() -> bool:
    global looks
    looks += 1
    return False

for _ in range(int(sys.argv[2])):
    looks = 0
    board.wait_for(never, 1)
    print(looks)
d.DevCloseDriver()
"""


def assert_backs_off(counts: list[int]) -> None:
    watched = [i + 1 for i, n in enumerate(counts) if n > WATCHED]
    assert 0 < len(watched) <= MOST_WATCHES, f"calls that watched the flags: {watched} ({counts})"


def test_a_python_host_whose_answers_outlast_its_watch_sleeps_at_once(card: Card) -> None:
    done = commands.run([sys.executable, "-c", PYTHON_HOST, str(card.directory), str(CALLS)],
                        cwd=ROOT, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert_backs_off([int(line) for line in done.stdout.split()])


@pytest.mark.skipif(CC is None or shutil.which("make") is None, reason="no C compiler or make")
def test_a_c_host_whose_answers_outlast_its_watch_sleeps_at_once(card: Card,
                                                                   tmp_path: Path) -> None:
    build_libcif("all")
    program = compile_program(C_TESTS / "spin_backoff.c", tmp_path / "spin_backoff", "plain")
    lines = [line.split() for line in run(program, card.directory, str(CALLS)).splitlines()]
    assert [int(rc) for rc, _ in lines] == [Drv.DRV_DEV_GET_TIMEOUT] * CALLS
    assert_backs_off([int(readings) for _, readings in lines])
