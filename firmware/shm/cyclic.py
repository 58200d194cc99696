"""Cyclic sending on ``shm`` from a timer process of its own [ours].

Why not python-can's generic cyclic task: it is a thread, and in a busy
multi-threaded process such as the firmware it waits for CPython's
interpreter lock behind the receive and tick threads, so a 1 ms SYNC comes
milliseconds late. SocketCAN hands the same job to the kernel (the broadcast
manager); the ``shm`` equivalent is a small process that does nothing but
sleep to each deadline and write the frame into its own station's ring.

It imports neither python-can nor numpy (its station is ``firmware.shm.station``'s, its
frames records made from the job's line), so its start costs about 0.05 s of CPU where it
cost 0.45-0.55 s with ``ShmBus``: a card starts one with its controller and one more each
time SYNC starts, and a network that booted meanwhile paid for it (issue 22).

It asks Linux for ``SCHED_FIFO`` at the lowest real-time priority, so a
normal process never keeps it from waking. Measured on this project's 2-core
VM with three busy processes beside it, a 1 ms sleep loop woke with a p99
error of 19 µs under SCHED_FIFO and 999 µs without. Where the process may
not (no CAP_SYS_NICE), it runs as a normal process and ``realtime`` says so.
It sleeps rather than spinning to the deadline: spinning measured worse,
because the hypervisor takes the vCPU of a spinning guest.

A bus opened with ``timer_process`` keeps one such process started ahead
(``firmware.shm.tasks.SpareTimer``, which also holds the python-can task that
feeds it), so a task starts sending at once rather than an interpreter start later.
The child ends when the task stops, after ``duration``, or when the parent dies: it
reads its standard input, and the end of that pipe is the parent going away. Like
python-can's cyclic tasks, a task with several frames sends one per period, in turn.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

from firmware.shm.station import EXTENDED, RECORD, REMOTE, ChannelError, Station

REALTIME_PRIORITY = 1
"""SCHED_FIFO's lowest priority: above every normal process, below the kernel's IRQ threads."""


def _realtime() -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(REALTIME_PRIORITY))
    except OSError:  # PermissionError without CAP_SYS_NICE
        return False
    return True


def decode_frames(line: str) -> tuple[tuple[int, int, int, bytes], ...]:
    """The frames of one ``firmware.shm.tasks.encode_frames`` line, as the identifier, the
    record's flags, the DLC and the data that ``RECORD`` packs."""
    return tuple((ident, (EXTENDED if extended else 0) | (REMOTE if remote else 0), dlc,
                  bytes.fromhex(data))
                 for ident, extended, remote, dlc, data in json.loads(line))


def main() -> None:
    """Wait for a job, then send its frames until standard input closes (the parent's end)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C is for the parent, which stops us
    line = sys.stdin.readline()
    if not line:
        return  # a spare that was not needed
    job = json.loads(line)
    path, period, duration = str(job["path"]), float(job["period"]), float(job["duration"])
    realtime = _realtime()
    frames = decode_frames(sys.stdin.readline())
    done = threading.Event()

    def follow_input() -> None:
        nonlocal frames
        for line in sys.stdin:
            frames = decode_frames(line)
        done.set()

    try:
        station = Station(Path(path))
    except (ChannelError, OSError) as exc:  # e.g. every station taken: the parent says why
        print("failed", exc, flush=True)
        return
    try:
        threading.Thread(target=follow_input, daemon=True).start()
        print("ready", "realtime" if realtime else "normal", flush=True)
        start = due = time.perf_counter()
        index = 0
        while not done.is_set() and not (duration and due - start >= duration):
            now = time.perf_counter()
            if due - now > 0:
                time.sleep(due - now)
            elif now - due > period:  # the machine stalled: skip the lost periods, no burst
                due = now
            current = frames
            ident, flags, dlc, data = current[index % len(current)]
            station.write(RECORD.pack(time.time(), ident, flags, dlc, 0, data))
            index += 1
            due += period
    finally:
        station.leave()
        station.release()


if __name__ == "__main__":
    main()
