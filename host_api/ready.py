"""Waiting for a firmware just started: READY from that process, while its start advances [ours].

The test suite, the benchmarks and the pytest plugin each start ``cifemu firmware`` and
must not talk to the card before it serves: this is their one wait. Two things make it
more than a look at HostFlags:

- READY alone is not enough: a killed predecessor leaves READY set in its image. The
  card is the new process's once the firmware lock file names its pid, and READY counts
  only when read after that: a firmware clears the stale READY the moment it holds the
  lock and writes its pid after that (``dpm.image.ExclusiveLock``). Reading READY first,
  then asking who holds the lock, took the predecessor's READY for the new firmware's when
  the lock was taken between the two reads, or before the new firmware cleared it: a host
  then found its DevInitBoard refused with -11 (not ready) "right after" the start.
- A fixed deadline on the wall clock is wrong on a shared machine: at a load of 30 on two
  cores a firmware's start takes 10-20 s of wall time for the same half second of CPU, and
  a fixed 15 s failed 13 tests of a run. The wait follows the process's CPU time instead
  (``dpm.start_progress.StartProgress``): the start fails when it has spent ``START_CPU_S``
  of CPU without READY (busy, never ready) or got no CPU for ``START_STALL_S`` (stuck,
  stopped).
"""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

from dpm.flags import HostFlag
from dpm.image import image_path, lock_path
from dpm.layout import HOST_FLAGS
from dpm.start_progress import StartProgress
from host_api.errors import HostApiError
from host_api.liveness import recorded_pid

START_CPU_S = 10.0
"""CPU seconds a process may spend on its start before the start counts as failed: about
20 times what a firmware's start costs (0.4-0.6 s: the interpreter, the imports, the
flash), which load hardly changes."""
START_STALL_S = 15.0
"""Wall seconds a starting process may go without any CPU time before its start counts as
stuck (blocked, stopped): a runnable process gets its share of the cores however busy they
are, so its CPU time moves within a second even at a load of 30 on two cores."""
POLL_S = 0.005


class StartError(HostApiError, RuntimeError):
    """The firmware did not come to serve its board; ``status`` is its exit status when it
    ended first, None when its start stopped advancing (the process still runs)."""

    def __init__(self, text: str, status: int | None) -> None:
        super().__init__(text)
        self.status = status


def _host_flags(image: Path) -> int | None:
    """HostFlags of an image file, or None while the file is missing or short."""
    try:
        fd = os.open(image, os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        raw = os.pread(fd, 1, HOST_FLAGS)
    finally:
        os.close(fd)
    return raw[0] if raw else None


def wait_ready(process: subprocess.Popen[bytes], directory: Path, board: int,
               stall_s: float = START_STALL_S, cpu_limit_s: float = START_CPU_S) -> None:
    """Return once the firmware ``process`` serves board ``board`` in ``directory``: its
    image shows READY and the firmware lock names its pid. StartError when the process
    ends first or its start stops advancing (``StartProgress(stall_s, cpu_limit_s)``)."""
    image = image_path(directory, board)
    lock = lock_path(directory, board)
    start = StartProgress(process.pid, stall_s, cpu_limit_s)
    while True:
        status = process.poll()
        if status is not None:
            raise StartError(f"the firmware (pid {process.pid}) exited with status {status} "
                             "before it was READY", status)
        if recorded_pid(lock) == process.pid:  # first: READY only counts when read after it
            flags = _host_flags(image)
            if flags is not None and flags & HostFlag.READY:
                return
        problem = start.problem()
        if problem is not None:
            raise StartError(f"the firmware (pid {process.pid}) was not READY ({image}): "
                             f"its start {problem}", None)
        time.sleep(POLL_S)
