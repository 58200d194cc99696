"""Cyclic sending on ``shm`` from a timer process of its own [ours].

Why not python-can's generic cyclic task: it is a thread, and in a busy
multi-threaded process such as the firmware it waits for CPython's
interpreter lock behind the receive and tick threads, so a 1 ms SYNC comes
milliseconds late. SocketCAN hands the same job to the kernel (the broadcast
manager); the ``shm`` equivalent is a small process that does nothing but
sleep to each deadline and write the frame into its own station's ring.

It asks Linux for ``SCHED_FIFO`` at the lowest real-time priority, so a
normal process never keeps it from waking. Measured on this project's 2-core
VM with three busy processes beside it, a 1 ms sleep loop woke with a p99
error of 19 µs under SCHED_FIFO and 999 µs without. Where the process may
not (no CAP_SYS_NICE), it runs as a normal process and ``realtime`` says so.
It sleeps rather than spinning to the deadline: spinning measured worse,
because the hypervisor takes the vCPU of a spinning guest.

A bus opened with ``timer_process`` keeps one such process started ahead
(``SpareTimer``), so a task starts sending at once rather than an interpreter
start later. The child ends when the task stops, after ``duration``, or when the parent
dies: it reads its standard input, and the end of that pipe is the parent
going away. Like python-can's cyclic tasks, a task with several frames sends
one per period, in turn.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import can
from can.broadcastmanager import (
    LimitedDurationCyclicSendTaskABC,
    ModifiableCyclicTaskABC,
    RestartableCyclicTaskABC,
)

from firmware.can.shm import ShmBus

REALTIME_PRIORITY = 1
"""SCHED_FIFO's lowest priority: above every normal process, below the kernel's IRQ threads."""
START_TIMEOUT_S = 10.0
"""How long ``start`` waits for the timer process to open its station (an interpreter start)."""


def _frames(messages: Sequence[can.Message]) -> str:
    """One line of JSON that the timer process turns back into frames."""
    return json.dumps([[m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.dlc,
                        bytes(m.data).hex()] for m in messages]) + "\n"


def _messages(line: str) -> tuple[can.Message, ...]:
    return tuple(can.Message(arbitration_id=ident, is_extended_id=extended,
                             is_remote_frame=remote, dlc=dlc, data=bytes.fromhex(data))
                 for ident, extended, remote, dlc, data in json.loads(line))


class SpareTimer:
    """A timer process started ahead of need, so that a task sends its first frame at once.

    An interpreter start costs about 0.3 s here; a card's SYNC should start with
    the network, not that much later. The spare has imported what it needs and
    waits for its job; when a task takes it, the next spare starts.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._closed = False
        self._spare: subprocess.Popen[str] | None = _spawn()

    def take(self) -> subprocess.Popen[str]:
        with self._lock:
            process, self._spare = self._spare, None
            if process is None or process.poll() is not None:
                if process is not None:
                    _reap(process)
                process = _spawn()
            if not self._closed:
                self._spare = _spawn()
        return process

    def close(self) -> None:
        with self._lock:
            self._closed = True
            process, self._spare = self._spare, None
        if process is not None:
            _reap(process)


def _spawn() -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "firmware.can.shm_cyclic"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def _reap(process: subprocess.Popen[str]) -> None:
    """Close the timer process's input, which ends it; kill it if it lingers."""
    assert process.stdin is not None and process.stdout is not None
    with contextlib.suppress(BrokenPipeError):  # it had ended (its duration ran out)
        process.stdin.close()
    try:
        process.wait(timeout=2)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
    process.stdout.close()


class ShmCyclicSendTask(LimitedDurationCyclicSendTaskABC, ModifiableCyclicTaskABC,
                        RestartableCyclicTaskABC):
    """A python-can cyclic task whose frames a separate timer process sends."""

    def __init__(self, timers: SpareTimer, path: Path,
                 messages: Sequence[can.Message] | can.Message, period: float,
                 duration: float | None = None, autostart: bool = True) -> None:
        if period <= 0:  # the timer process would send without pause, at real-time priority
            raise ValueError(f"period must be positive, not {period}")
        super().__init__(messages, period, duration)
        self._timers = timers
        self._path = path
        self._process: subprocess.Popen[str] | None = None
        self.realtime: bool | None = None
        """Whether the timer process got SCHED_FIFO (None until it first started)."""
        if autostart:
            self.start()

    def start(self) -> None:
        """Hand the job to a timer process; return once its station is open and sending."""
        if self._process is not None:
            if self._process.poll() is None:
                return
            self.stop()  # its duration ran out: collect it before a new one
        job = {"path": str(self._path), "period": self.period, "duration": self.duration or 0.0}
        try:
            process = self._timers.take()  # OSError: no process to be had (fork failed)
        except OSError as exc:
            raise can.CanOperationError(f"shm timer process did not start: {exc}") from exc
        try:
            assert process.stdin is not None
            process.stdin.write(json.dumps(job) + "\n" + _frames(self.messages))
            process.stdin.flush()
        except OSError as exc:  # it died before its job came (a broken pipe)
            process.kill()
            _reap(process)
            raise can.CanOperationError(f"shm timer process did not start: {exc}") from exc
        ready = _read_line(process, START_TIMEOUT_S)
        if not ready.startswith("ready "):
            process.kill()
            _reap(process)
            raise can.CanOperationError(f"shm timer process did not start: {ready!r}")
        self.realtime = ready.split()[1] == "realtime"
        self._process = process

    @property
    def alive(self) -> bool:
        """Whether the timer process runs (not after ``stop``, its duration, or a kill)."""
        return self._process is not None and self._process.poll() is None

    @property
    def pid(self) -> int | None:
        """The sending timer process (None when not ``alive``): to watch or renice it."""
        return self._process.pid if self._process is not None and self.alive else None

    def modify_data(self, messages: Sequence[can.Message] | can.Message) -> None:
        """New data for the same frames, from the next period on."""
        messages = self._check_and_convert_messages(messages)
        self._check_modified_messages(messages)
        self.messages = messages
        process = self._process
        if process is not None and process.poll() is None:
            assert process.stdin is not None
            with contextlib.suppress(BrokenPipeError):  # it ended meanwhile: start() sends all
                process.stdin.write(_frames(messages))
                process.stdin.flush()

    def stop(self) -> None:
        process, self._process = self._process, None
        if process is not None:
            _reap(process)


def _read_line(process: subprocess.Popen[str], timeout: float) -> str:
    """The child's first line, or "" when it does not come within ``timeout``."""
    stdout = process.stdout
    assert stdout is not None
    lines: list[str] = []

    def read() -> None:
        lines.append(stdout.readline())

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(timeout)
    return lines[0].strip() if lines else ""


# --- the timer process ---------------------------------------------------------------------


def _realtime() -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(REALTIME_PRIORITY))
    except OSError:  # PermissionError without CAP_SYS_NICE
        return False
    return True


def main() -> None:
    """Wait for a job, then send its frames until standard input closes (the parent's end)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C is for the parent, which stops us
    line = sys.stdin.readline()
    if not line:
        return  # a spare that was not needed
    job = json.loads(line)
    path, period, duration = str(job["path"]), float(job["period"]), float(job["duration"])
    realtime = _realtime()
    frames = _messages(sys.stdin.readline())
    done = threading.Event()

    def follow_input() -> None:
        nonlocal frames
        for line in sys.stdin:
            frames = _messages(line)
        done.set()

    try:
        bus = ShmBus(channel=path)
    except (can.CanError, OSError) as exc:  # e.g. every station taken: the parent says why
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
            bus.send(current[index % len(current)])
            index += 1
            due += period
    finally:
        bus.shutdown()


if __name__ == "__main__":
    main()
