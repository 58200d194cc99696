"""CPU time of another process and of its threads, from /proc (Linux).

CPU time, unlike wall time, hardly moves when the machine is loaded: a shared box
with a load average of 15 still gives a fair figure of what a process costs.
``/proc/PID/task/TID/schedstat`` counts nanoseconds on the CPU per thread;
``/proc/PID/stat`` (utime + stime, clock ticks) counts the whole process including
threads that have ended, at a resolution of 10 ms, as a cross-check (``stat_cpu_ns``,
``host_api.ready``'s: the wait for a firmware's start follows the same figure).
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dpm.start_progress import stat_cpu_ns


def _schedstat_ns(path: Path) -> int | None:
    try:
        return int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def _comm(task: Path) -> str:
    try:
        return (task / "comm").read_text().strip()
    except OSError:
        return "?"


def _wakeups(task: Path) -> int:
    """Voluntary context switches of a thread: each one a sleep (a wait, a poll) that ended."""
    try:
        for line in (task / "status").read_text().splitlines():
            if line.startswith("voluntary_ctxt_switches:"):
                return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


def thread_wakeups(pid: int) -> dict[int, int]:
    """Voluntary context switches of each live thread of ``pid`` (thread id -> count)."""
    return {int(task.name): _wakeups(task) for task in Path(f"/proc/{pid}/task").iterdir()}


def thread_cpu_ns(pid: int) -> dict[int, int]:
    """Nanoseconds on the CPU of each live thread of ``pid`` (thread id -> ns)."""
    threads: dict[int, int] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        ns = _schedstat_ns(task / "schedstat")
        if ns is not None:
            threads[int(task.name)] = ns
    return threads


@dataclass(frozen=True, slots=True)
class CpuSample:
    """One reading of a process: per-thread ns, the whole-process ticks, the wall clock."""

    threads: dict[int, int]
    stat_ns: int
    wall_ns: int
    wakeups: dict[int, int]

    @classmethod
    def take(cls, pid: int) -> CpuSample:
        return cls(thread_cpu_ns(pid), stat_cpu_ns(pid), time.monotonic_ns(),
                   thread_wakeups(pid))


def share(before: CpuSample, after: CpuSample, pid: int) -> dict[str, Any]:
    """Per cent of one core between two samples: the process, its main thread, the others,
    and per thread (busiest first) its share and its wake-ups a second.

    ``main_thread`` is the thread whose id is ``pid``: the firmware's device loop. The
    other threads have no names the kernel knows; their wake-up rates tell them apart (the
    controller's receive thread wakes for every frame and, idle, about once a second).
    """
    wall = after.wall_ns - before.wall_ns
    spent = {tid: ns - before.threads.get(tid, 0) for tid, ns in after.threads.items()}
    total = sum(spent.values())
    main = spent.get(pid, 0)

    def pct(ns: int) -> float:
        return round(100.0 * ns / wall, 3) if wall else 0.0

    seconds = wall / 1e9 if wall else 1.0
    per_thread = [
        {"thread": "main (device loop)" if tid == pid else f"tid {tid}", "pct": pct(ns),
         "wakeups_per_s": round((after.wakeups.get(tid, 0) - before.wakeups.get(tid, 0))
                                / seconds, 1)}
        for tid, ns in sorted(spent.items(), key=lambda item: -item[1])
    ]
    return {
        "process_pct": pct(total),
        "main_thread_pct": pct(main),
        "other_threads_pct": pct(total - main),
        "stat_process_pct": pct(after.stat_ns - before.stat_ns),
        "threads": len(after.threads),
        "per_thread": per_thread,
        "wall_s": round(wall / 1e9, 3),
    }


def runqueue_wait_ns(pids: list[int]) -> dict[int, int]:
    """Nanoseconds each live thread of ``pids`` has waited for a CPU while it could run
    (``/proc/PID/task/TID/schedstat``'s second field; thread id -> ns). On an idle machine
    it hardly moves; on a loaded one it is the time load took from the thread."""
    waited: dict[int, int] = {}
    for pid in pids:
        try:
            tasks = list(Path(f"/proc/{pid}/task").iterdir())
        except OSError:
            continue
        for task in tasks:
            try:
                waited[int(task.name)] = int((task / "schedstat").read_text().split()[1])
            except (OSError, ValueError, IndexError):
                continue
    return waited


@dataclass(frozen=True, slots=True)
class ThreadSched:
    """One thread's scheduling counters: ns on a CPU and waiting for one while it could run
    (``schedstat``), sleeps that ended (voluntary context switches, its wake-ups) and
    preemptions (involuntary ones)."""

    cpu_ns: int
    wait_ns: int
    wakeups: int
    preemptions: int

    @classmethod
    def take(cls, pid: int, tid: int) -> ThreadSched:
        task = Path(f"/proc/{pid}/task/{tid}")
        cpu, wait = (int(field) for field in (task / "schedstat").read_text().split()[:2])
        switches = {}
        for line in (task / "status").read_text().splitlines():
            name, _, value = line.partition(":")
            if name.endswith("ctxt_switches"):
                switches[name] = int(value)
        return cls(cpu, wait, switches["voluntary_ctxt_switches"],
                   switches["nonvoluntary_ctxt_switches"])

    def per_call(self, before: ThreadSched, calls: int) -> dict[str, float]:
        """What each of ``calls`` calls since ``before`` cost this thread (µs and counts):
        on a loaded machine ``wait_us`` is the time the load took from it."""
        return {"cpu_us": round((self.cpu_ns - before.cpu_ns) / calls / 1000, 1),
                "wait_us": round((self.wait_ns - before.wait_ns) / calls / 1000, 1),
                "wakeups": round((self.wakeups - before.wakeups) / calls, 2),
                "preemptions": round((self.preemptions - before.preemptions) / calls, 2)}


def descendants(pid: int) -> list[int]:
    """The live child processes of ``pid`` and theirs (a card's SYNC timer process).

    A child that ends meanwhile is skipped: its time is lost to the figures, which is why
    they are taken over processes that live as long as the card.
    """
    found: list[int] = []
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return found
    for task in tasks:
        try:
            children = [int(child) for child in (task / "children").read_text().split()]
        except (OSError, ValueError):
            continue
        for child in children:
            found += [child, *descendants(child)]
    return found


def tree_cpu_ns(pid: int) -> int:
    """utime + stime of ``pid`` and its live descendants, in ns (``stat_cpu_ns`` each)."""
    total = stat_cpu_ns(pid)
    for child in descendants(pid):
        try:
            total += stat_cpu_ns(child)
        except (OSError, ValueError, IndexError):
            continue  # ended between the listing and the reading
    return total


@dataclass(frozen=True, slots=True)
class Usage:
    """``tree_cpu_ns`` of named processes at one moment, and the wall clock."""

    ns: dict[str, int]
    wall_ns: int

    @classmethod
    def take(cls, pids: Mapping[str, int]) -> Usage:
        return cls({name: tree_cpu_ns(pid) for name, pid in pids.items()}, time.monotonic_ns())

    def pct_since(self, before: Usage) -> dict[str, float]:
        """Per cent of one core each process (with its descendants) used since ``before``."""
        wall = self.wall_ns - before.wall_ns
        return {name: round(100.0 * (ns - before.ns[name]) / wall, 3) if wall else 0.0
                for name, ns in self.ns.items()}


BLOCKED_SOURCE = (
    "import socket\n"
    "s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)\n"
    "s.bind(b'')\n"
    "print('ready', flush=True)\n"
    "s.recv(1)\n"
)
"""The baseline: a Python process asleep on its doorbell, as an idle card could be."""


@contextmanager
def blocked_process() -> Iterator[int]:
    """A Python process blocked on a Unix datagram socket; yields its pid, kills it at exit."""
    proc = subprocess.Popen([sys.executable, "-c", BLOCKED_SOURCE], stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE)
    try:
        assert proc.stdout is not None
        proc.stdout.readline()  # bound: it sleeps from here on
        yield proc.pid
    finally:
        proc.kill()
        proc.wait()
