"""Whether a process just started is getting on, by its CPU time, not the wall clock [ours].

Both sides start processes and wait for a first sign of them: a host for a firmware's READY
(``host_api.ready``), the card for its cyclic timer process's first line
(``firmware.shm.tasks``). On a shared machine a fixed deadline in wall time is wrong: at a
load of 30 on two cores an interpreter's start takes 10-20 s of wall time for the same half
second of CPU. A start counts as failed when it has spent its CPU limit (busy, never ready)
or got no CPU for its stall time (stuck, stopped). Here, not in either side, because the
layers let ``firmware`` and ``host_api`` share only ``dpm`` (docs/architecture.md).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

TICK_NS = 1_000_000_000 // os.sysconf("SC_CLK_TCK")


def stat_fields(pid: int) -> list[str]:
    """/proc/PID/stat's fields from the third (the state) on, so that proc(5)'s field N is
    index N - 3: they follow the command name, which may hold spaces and parentheses.
    OSError when the process or /proc is not there."""
    raw = Path(f"/proc/{pid}/stat").read_text()
    return raw[raw.rindex(")") + 2 :].split()


def stat_cpu_ns(pid: int) -> int:
    """utime + stime of the whole process (every thread, also ended ones), in ns."""
    fields = stat_fields(pid)
    return (int(fields[11]) + int(fields[12])) * TICK_NS  # utime, stime: fields 14 and 15


class StartProgress:
    """Whether a process's start is getting on: it fails when it has spent ``cpu_limit_s``
    of CPU (busy, never ready) or got none for ``stall_s`` (stuck)."""

    def __init__(self, pid: int, stall_s: float, cpu_limit_s: float) -> None:
        self._pid = pid
        self._stall_s = stall_s
        self._cpu_limit_ns = int(cpu_limit_s * 1e9)
        self._cpu_ns = -1
        self._advanced = time.monotonic()

    def problem(self) -> str | None:
        """None while the start advances; else what went wrong, as the end of "its start
        ..." (a process that has ended gives None: its exit status says more)."""
        try:
            cpu_ns = stat_cpu_ns(self._pid)
        except (OSError, ValueError, IndexError):
            return None
        now = time.monotonic()
        if cpu_ns != self._cpu_ns:
            self._cpu_ns, self._advanced = cpu_ns, now
        if cpu_ns > self._cpu_limit_ns:
            return f"spent {cpu_ns / 1e9:.1f} s of CPU"
        if now - self._advanced > self._stall_s:
            return f"got no CPU for {self._stall_s:g} s"
        return None
