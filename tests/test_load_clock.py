"""The suite's time-outs on the load clock: a command's (``tests/commands.py``), a blocking
wait's (``within`` and the helpers on ``LoadDeadline``) and a whole test's (pytest-timeout's,
``pytest_timeout_set_timer`` in ``tests/conftest.py``).

Load is made here, not hoped for: the process under test shares one CPU with ``RIVALS``
busy processes of its own (all pinned to it), so it gets at most a quarter of that CPU and
needs four times its CPU time in wall time or more. A time-out on the wall clock fails
there; one on the load clock passes. A process that hangs blocked waits in no run queue:
its time-out still ends it, in about its time-out.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from tests.commands import CommandTimeout, run
from tests.conftest import ROOT, TEST_STRETCH_LIMIT, LoadClock, within

CPU = min(os.sched_getaffinity(0))

RIVALS = 3
"""Busy processes beside the starved one: with three, its CPU time is a quarter of its wall
time or less, so a time-out of twice its CPU time passes on the wall clock, on a quiet
machine as on a loaded one, while a loaded one (the suite's, load 15-20) does not yet
stretch that wall time past ``TEST_STRETCH_LIMIT`` times the time-out (with one rival and
a time-out of 1.4 times its CPU time it did: 0.7 s of CPU took 10 s)."""

STARVED = textwrap.dedent(f"""
    import os, subprocess, sys, time
    os.sched_setaffinity(0, {{{CPU}}})
    rivals = [subprocess.Popen([sys.executable, "-c", "import os\\n"
                                "os.sched_setaffinity(0, {{{CPU}}})\\n"
                                "parent = os.getppid()\\n"
                                "while os.getppid() == parent: pass"])
              for _ in range(RIVALS)]
    try:
        begun = time.process_time()
        while time.process_time() - begun < WORK_S:
            pass
    finally:
        for rival in rivals:
            rival.kill()
            rival.wait()
""")
"""A program that spends ``WORK_S`` of CPU on a CPU it shares with ``RIVALS`` busy ones
(both set before it). A rival spins only while its parent lives: a time-out kills the
starved program with SIGKILL, which skips its ``finally``, and rivals that looped forever
were left behind, busy on that CPU for the rest of the suite."""

WORK_S = 1.0
TIMEOUT_S = 2.0


def starved_command() -> list[str]:
    return [sys.executable, "-c", f"WORK_S = {WORK_S}\nRIVALS = {RIVALS}\n{STARVED}"]


def test_a_starved_command_runs_past_its_wall_clock_time_out() -> None:
    begun = time.monotonic()
    done = run(starved_command(), TIMEOUT_S, capture_output=True, text=True)
    wall = time.monotonic() - begun
    assert done.returncode == 0, done.stderr
    assert wall > TIMEOUT_S, f"{wall:.1f} s: not starved, the test shows nothing"


def test_a_wall_clock_time_out_fails_the_same_command() -> None:
    """What the suite did before: ``subprocess.run``'s time-out fails the starved command
    the load clock lets finish (the pair shows the load is real)."""
    with pytest.raises(subprocess.TimeoutExpired):
        subprocess.run(starved_command(), capture_output=True, timeout=TIMEOUT_S)


def test_a_command_that_hangs_is_ended_at_its_time_out() -> None:
    clock = LoadClock(time.monotonic())
    with pytest.raises(CommandTimeout) as failed:
        run([sys.executable, "-c", "import time; print('begun', flush=True); time.sleep(60)"],
            1.0, capture_output=True, text=True)
    assert clock.elapsed() < 5  # not its 60 s of sleep
    assert failed.value.output == "begun\n"  # what it said before it was killed
    assert "wall time" in str(failed.value)


def test_a_starved_program_s_event_comes_within_its_time_out_on_the_load_clock() -> None:
    """``within`` (``Event.wait`` on the load clock; ``ended``, ``taken`` and ``expect`` wait
    the same way): the event set when the starved program ends comes past the wall-clock
    time-out and within the load clock's. ``Event.wait`` with the same time-out, the
    suite's wait before, gives up first: the load is real."""
    proc = subprocess.Popen(starved_command())
    done = threading.Event()

    def reap() -> None:
        proc.wait()
        done.set()

    threading.Thread(target=reap, daemon=True).start()
    try:
        assert not done.wait(TIMEOUT_S), "not starved: the test shows nothing"
        assert within(done.wait, TIMEOUT_S), "no end within the load clock's time-out"
        assert proc.returncode == 0
    finally:
        proc.kill()


def test_a_window_in_which_nothing_may_happen_lasts_at_least_its_time() -> None:
    """A check that nothing happens (``not within(...)``, ``silent``) looks for its whole
    window: never less than the time-out in wall time, and more when load took time from
    the test's processes, so a starved card cannot pass it for want of CPU."""
    begun = time.monotonic()
    assert not within(threading.Event().wait, 0.5)
    assert time.monotonic() - begun >= 0.5


TEST_WORK_S = 0.2
TEST_TIMEOUT_S = 1.0
TEST_RIVALS = 7
"""A test's time-out, the CPU it spends starved and its rivals: with seven, the starved
test needs only a fifth of its time-out in CPU to run past it on a quiet machine, as a
test's time-out stretches only ``TEST_STRETCH_LIMIT`` times in wall time (with three and
0.4 s of CPU it ran into that bound at load 22: 10 s)."""

TIMED_TESTS = textwrap.dedent(f"""
    import subprocess, sys, time
    import pytest

    STARVED = {STARVED!r}

    @pytest.mark.timeout({TEST_TIMEOUT_S})
    def test_starved():
        exec("WORK_S = {TEST_WORK_S}\\nRIVALS = {TEST_RIVALS}\\n" + STARVED)

    @pytest.mark.timeout(1)
    def test_hangs():
        time.sleep(60)
""")


def test_a_starved_test_passes_and_one_that_hangs_fails(tmp_path: Path) -> None:
    """pytest-timeout's time-out of a test on the load clock: the starved test (it runs
    ``STARVED`` in the test process itself) passes past its wall-clock time-out; the hung
    one fails at its time-out. On the old conftest both failed: "Timeout (>1.0s)"."""
    (tmp_path / "test_timed.py").write_text(TIMED_TESTS)
    done = run([sys.executable, "-m", "pytest", "-p", "tests.conftest", "-p", "no:randomly",
                "-p", "no:cacheprovider", "-q", "-rA", "--rootdir", str(tmp_path),
                "--durations=0", str(tmp_path / "test_timed.py")], 120, cwd=ROOT,
               capture_output=True, text=True)
    lines = done.stdout.splitlines()
    # -rA's lines are "OUTCOME path::test" and, where the terminal is wide enough for it,
    # " - reason": the test's name is what comes before that.
    outcomes = {line.split(" - ")[0].rsplit("::", 1)[-1]: line.split(" ", 1)[0]
                for line in lines if line.startswith(("PASSED ", "FAILED "))}
    assert outcomes.get("test_starved") == "PASSED", done.stdout
    assert outcomes.get("test_hangs") == "FAILED", done.stdout
    assert "Failed: Timeout (>1.0s) from pytest-timeout" in done.stdout
    def duration(test: str) -> float:
        return next(float(line.split("s")[0]) for line in lines
                    if " call " in line and line.endswith(f"::{test}"))

    assert duration("test_starved") > TEST_TIMEOUT_S, done.stdout
    assert duration("test_hangs") < TEST_STRETCH_LIMIT, done.stdout  # not its 60 s of sleep
