"""Commands the tests run, with their time-outs on the load clock (``LoadClock``).

A command's time-out is there to end one that hangs, not to time it; but
``subprocess.run(..., timeout=30)`` counts the wall clock, and with two busy processes
beside the suite a command gets a slice of the two cores: ``cifemu --help`` and ``cifemu
status`` (0.3-0.5 s of CPU each: the interpreter and the imports) ran out of 30 s of wall
time at a load of 25-38 (the run of 2026-12-03 16:05, docs/testing.md), the command having
done nothing wrong. Here a time-out counts the time the test's processes (the command and
its children among them) could run: wall time on an idle machine, and under load the
deadline moves by the time load took from them, up to ``STRETCH_LIMIT`` times. A command
that hangs blocked (waiting for an answer, a lock) gets no run-queue wait and is ended at
its time-out as before.
"""

from __future__ import annotations

import select
import subprocess
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol, TypeVar

from tests.conftest import on_load_clock

T = TypeVar("T")


class HasFileno(Protocol):
    """What ``select`` waits on: a pipe's file, a socket."""

    def fileno(self) -> int: ...


class CommandTimeout(subprocess.TimeoutExpired):
    """``subprocess.TimeoutExpired`` that says how much wall time the time-out took."""

    def __init__(self, expired: subprocess.TimeoutExpired, wall: float) -> None:
        super().__init__(expired.cmd, expired.timeout, expired.output, expired.stderr)
        self.wall = wall

    def __str__(self) -> str:
        return (f"{super().__str__()} of the time the test's processes could run "
                f"({self.wall:.1f} s of wall time)")


def command_wait(attempt: Callable[[float], T], timeout: float) -> T:
    """``attempt(seconds)`` until it returns rather than raise ``TimeoutExpired``, the
    ``timeout`` on the load clock (``on_load_clock``); past it ``CommandTimeout``."""
    start = time.monotonic()
    try:
        return on_load_clock(attempt, timeout, subprocess.TimeoutExpired)
    except subprocess.TimeoutExpired as expired:
        raise CommandTimeout(expired, time.monotonic() - start) from None


def finish(proc: subprocess.Popen[Any], timeout: float, input: Any = None) -> tuple[Any, Any]:
    """``proc.communicate(input)`` with ``timeout`` on the load clock; a process past it is
    killed (as ``subprocess.run`` does) and ``CommandTimeout`` raised with its output."""
    pending = [input]

    def attempt(seconds: float) -> tuple[Any, Any]:
        given, pending[0] = pending[0], None  # a repeated communicate() goes on writing it
        return proc.communicate(given, timeout=seconds)

    try:
        return command_wait(attempt, timeout)
    except CommandTimeout as expired:
        proc.kill()
        expired.output, expired.stderr = proc.communicate()
        raise


def wait(proc: subprocess.Popen[Any], timeout: float) -> int:
    """``proc.wait(timeout)`` with the time-out on the load clock (the process is left
    running when it passes, as ``Popen.wait`` leaves it); its pipes are not read."""
    return command_wait(proc.wait, timeout)


def run(args: Sequence[str | Path], timeout: float, *, input: Any = None,
        capture_output: bool = False, check: bool = False,
        **popen: Any) -> subprocess.CompletedProcess[Any]:
    """``subprocess.run`` with ``timeout`` on the load clock (``finish``)."""
    if input is not None:
        popen["stdin"] = subprocess.PIPE
    if capture_output:
        popen["stdout"] = popen["stderr"] = subprocess.PIPE
    with subprocess.Popen(args, **popen) as proc:
        out, err = finish(proc, timeout, input)
    done = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    if check:
        done.check_returncode()
    return done


def readable(stream: int | HasFileno, timeout: float) -> bool:
    """Whether ``stream`` (a command's pipe, a pseudo-terminal, a socket) has something to
    read, or its end, within ``timeout`` on the load clock: ``select``'s wait for a command's
    output."""
    def attempt(seconds: float) -> bool:
        ready, _, _ = select.select([stream], [], [], seconds)
        if not ready:
            raise subprocess.TimeoutExpired("select", seconds)
        return True

    try:
        return command_wait(attempt, timeout)
    except CommandTimeout:
        return False
