"""Running ``python -m bench.scaling`` from a test: in a process group of its own, ended
with everything it started. Shared by the parallel module (``test_bench_scaling.py``) and
the serial one that measures frame rates (``test_bench_frame_cost.py``)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time

from tests.conftest import ROOT

STOP_S = 10.0
"""Seconds the bench's processes have after SIGTERM before they are killed: a firmware on
``shm`` stops its SYNC timer process and unmaps its image, slower on a loaded machine."""


def bench_scaling(*args: str) -> subprocess.CompletedProcess[str]:
    """``python -m bench.scaling`` in a process group of its own, ended with everything it
    started on every path out: a failure, pytest-timeout's interruption, a Ctrl-C. The
    bench stops its firmwares and ``cifemu sim`` itself when it ends normally; killed, it
    left them running, orphaned."""
    command = [sys.executable, "-m", "bench.scaling", *args]
    bench = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, start_new_session=True)
    try:
        stdout, stderr = bench.communicate()
    finally:
        end_group(bench)
    return subprocess.CompletedProcess(command, bench.returncode, stdout, stderr)


def end_group(leader: subprocess.Popen[str]) -> None:
    """SIGTERM to every process of ``leader``'s group (the firmwares stop cleanly on it),
    SIGKILL to those left after ``STOP_S``; returns once the group is empty."""
    group = leader.pid
    deadline = time.monotonic() + STOP_S
    with contextlib.suppress(ProcessLookupError):
        os.killpg(group, signal.SIGTERM)
        while True:
            leader.poll()  # reaps the leader: a zombie still counts as the group's
            os.killpg(group, 0)  # ProcessLookupError: the group is empty
            if time.monotonic() > deadline:
                os.killpg(group, signal.SIGKILL)
            time.sleep(0.05)
