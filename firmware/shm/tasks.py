"""The parent's side of cyclic sending on ``shm``: the python-can task and the spare [ours].

The frames are sent by a timer process of their own, ``python -m firmware.shm.cyclic``,
whose docstring says why. This module starts and feeds it: ``SpareTimer`` keeps one
started ahead, ``ShmCyclicSendTask`` hands it a job (a line of JSON with the station's
path, the period and the duration, then a line of frames, ``encode_frames``) and new
data. It never imports the bus: the child does, so the two modules import no cycle.
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

import can
from can.broadcastmanager import (
    LimitedDurationCyclicSendTaskABC,
    ModifiableCyclicTaskABC,
    RestartableCyclicTaskABC,
)

from dpm.start_progress import StartProgress

START_STALL_S = 10.0
"""How long ``start`` waits for the timer process to open its station while the process gets
no CPU time (stuck or stopped). Not a bound on wall time: on a loaded machine an interpreter
start took over 10 s of it (a run at load 24), for the same CPU time."""
START_CPU_S = 10.0
"""CPU seconds the timer process may spend before it is ready (its start costs a few tenths)."""


def encode_frames(messages: Sequence[can.Message]) -> str:
    """One line of JSON that the timer process turns back into frames
    (``firmware.shm.cyclic.decode_frames``, which must not import python-can)."""
    return json.dumps([[m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.dlc,
                        bytes(m.data).hex()] for m in messages]) + "\n"


class SpareTimer:
    """A timer process started ahead of need, so that a task sends its first frame at once.

    The timer process's start costs 0.05-0.1 s of CPU here (``firmware.shm.station``
    says why no more), and under load a second or more of wall time; a card's SYNC
    should start with the network, not that much later. The spare has imported what it
    needs and waits for its job; when a task takes it, the next spare starts.
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
        """End the spare at once. It has no job and no station yet, so there is nothing to
        end cleanly; closing its input instead (``_reap``) waited until it had imported
        what it needs, an interpreter start: under load all of ``_reap``'s 2 s, in every
        stop of a card on ``shm``."""
        with self._lock:
            self._closed = True
            process, self._spare = self._spare, None
        if process is not None:
            process.kill()
            _reap(process)


def _spawn() -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "firmware.shm.cyclic"],
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
            process.stdin.write(json.dumps(job) + "\n" + encode_frames(self.messages))
            process.stdin.flush()
        except OSError as exc:  # it died before its job came (a broken pipe)
            process.kill()
            _reap(process)
            raise can.CanOperationError(f"shm timer process did not start: {exc}") from exc
        ready = _read_line(process)
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
                process.stdin.write(encode_frames(messages))
                process.stdin.flush()

    def stop(self) -> None:
        process, self._process = self._process, None
        if process is not None:
            _reap(process)


def _read_line(process: subprocess.Popen[str]) -> str:
    """The child's first line, or "" when it ends first or its start stops advancing: no CPU
    time for ``START_STALL_S``, or ``START_CPU_S`` of it spent (``StartProgress``)."""
    stdout = process.stdout
    assert stdout is not None
    lines: list[str] = []

    def read() -> None:
        lines.append(stdout.readline())

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    start = StartProgress(process.pid, START_STALL_S, START_CPU_S)
    while True:
        reader.join(0.1)
        if not reader.is_alive() or start.problem() is not None:
            break
    return lines[0].strip() if lines else ""
