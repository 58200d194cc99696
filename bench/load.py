"""``python -m bench --load NAME``: the benchmarks beside busy processes (issue 22).

Issue 22's target "under load, with two busy processes on the machine's two cores":
``busy_load`` starts that many processes that spin in pure Python, each bounded in
time twice over (it ends at its own deadline, and as soon as its parent is gone), and
kills them when the benchmark ends. ``describe`` is what the JSON says about it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from bench.common import progress

DEFAULT_BUSY = 2
"""The issue's load: one busy process per core of its 2-core machine."""
LIMIT_S = 3600.0
"""A busy process ends by itself after this, whatever happens to the benchmark."""

SPIN_SOURCE = (
    "import os, sys, time\n"
    "parent, end = os.getppid(), time.monotonic() + float(sys.argv[1])\n"
    "while time.monotonic() < end and os.getppid() == parent:\n"
    "    for _ in range(100_000):\n"
    "        pass\n"
)
"""Spins; looks at its deadline and its parent about every few milliseconds."""


@contextmanager
def busy_load(count: int = DEFAULT_BUSY, limit_s: float = LIMIT_S) -> Iterator[list[int]]:
    """``count`` busy processes for the duration of the block; yields their pids."""
    procs: list[subprocess.Popen[bytes]] = []
    try:
        for _ in range(count):
            procs.append(subprocess.Popen([sys.executable, "-c", SPIN_SOURCE, str(limit_s)],
                                          stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL))
        progress(f"load: {count} busy process(es), pids {[p.pid for p in procs]}")
        yield [p.pid for p in procs]
    finally:
        for proc in procs:
            proc.kill()
        for proc in procs:
            proc.wait()


def describe(pids: list[int]) -> dict[str, Any]:
    """What a result run under ``busy_load`` carries: how many, on how many CPUs."""
    return {"busy_processes": len(pids), "kind": "pure-Python spin loop, one per process",
            "cpus": os.cpu_count()}
