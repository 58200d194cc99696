"""Recording a session from inside the card [ours] (docs/recording.md).

The device loop calls a ``Recorder`` at the points where it already looks: a message
taken from DevMbx, an answer put into PcMbx, a HostFlags write, the DevFlags it read
for its turn. Each call appends a tuple to a deque (atomic, never blocking) and
returns. A thread drains the deque every ``DRAIN_S`` and hands the batch, pickled in
one piece, through a pipe to a child process (``firmware.session_writer``) that
computes what changed and writes ``session.jsonl``. Encoding lines in the firmware's
own process, even by hand, cost the loop a third of its mailbox round trips on a
loaded two-core machine (the writer held the interpreter lock the loop waits for);
pickling a batch costs it a fraction of a microsecond per event. So recording costs
the loop a few attribute lookups, two clock reads per event and, at a process-data
handshake, one copy of the two I/O areas; never a write or a lock.

The pid of a message's host is read from the transaction ledger at the moment the
card takes the message: the ledger line is gone once the host took the answer.
"""

from __future__ import annotations

import logging
import os
import pickle
import subprocess
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

from dpm import flags as fl
from dpm import session as s
from dpm.image import CardDirectory, lock_path
from dpm.layout import IO_AREA_SIZE, RCV_PD, SND_PD, TASK2_PARAMETER, TASK2_STATE, TASK_STATE_SIZE

log = logging.getLogger(__name__)

DRAIN_S = 0.05
"""How often the writer drains the queue: the loop never wakes it."""
LEDGER_BYTES = 128 * 96
"""The ledger's largest size (host_api.locks.LEDGER_MAX lines of libcif's longest)."""

_IO_END = RCV_PD + IO_AREA_SIZE


class SessionExistsError(FileExistsError):
    """The directory already holds a session: a recording never overwrites one."""


class Recorder:
    """One session being written; the hooks are called by the device loop's threads."""

    def __init__(self, session: Path, board: int, can_log: bool) -> None:
        """Create the session's files (before the card powers on: a refusal leaves no
        card up); ``start`` then connects it to the card."""
        self.path = session
        self._files = CardDirectory(session, create=True)
        try:
            fd = self._files.open(s.EVENTS, os.O_WRONLY | os.O_CREAT | os.O_EXCL)
        except FileExistsError:
            self._files.close()
            raise SessionExistsError(f"{session} already holds a session") from None
        try:
            self._child = subprocess.Popen(
                [sys.executable, "-m", "firmware.session_writer", str(fd)], pass_fds=(fd,),
                stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                start_new_session=True)  # a terminal's Ctrl-C is the firmware's to handle:
            # the writer ends at the end of its stdin, after the last batch
        finally:
            os.close(fd)
        assert self._child.stdin is not None
        self._pipe = self._child.stdin
        self._files.replace(s.META, s.encode_meta(board, time.time(), time.monotonic(),
                                                  os.getpid(), can_log).encode())
        self._board = board
        self._image_files: CardDirectory | None = None
        self._ledger_name = ""
        self._ledger = -1
        self._mm: Any = None
        self._queue: deque[tuple[Any, ...]] = deque()
        self._dev = -1
        self._io = bytes(_IO_END - SND_PD)
        """SndPd and RcvPd as the last exchange left them."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._write_loop, name="recorder", daemon=True)

    def start(self, image_files: CardDirectory, mm: Any) -> None:
        """Record the card of ``mm``, whose directory ``image_files`` holds the ledger."""
        self._image_files = image_files
        self._ledger_name = lock_path(image_files.path, self._board, "transaction").name
        self._mm = mm
        self._thread.start()

    # --- hooks (device loop and ``post`` threads) -------------------------------------

    def put(self, raw: bytes) -> None:
        """``raw``: the message slot as the card copied it (the writer decodes it: a
        Message object costs microseconds to pickle, bytes nothing)."""
        self._queue.append((s.PUT, time.monotonic(), time.time(), raw, self._read_ledger()))

    def answer(self, raw: bytes) -> None:
        """``raw``: the encoded answer, as the card writes it into PcMbx."""
        mm = self._mm
        self._queue.append((s.ANSWER, time.monotonic(), time.time(), raw,
                            mm[TASK2_STATE : TASK2_STATE + TASK_STATE_SIZE]))

    def host_flags(self, before: int, after: int) -> None:
        if before == after:
            return
        now, wall = time.monotonic(), time.time()
        self._queue.append((s.HOST_FLAGS, now, wall, before, after))
        if (before ^ after) & fl.PDACK and before & after & fl.READY:  # not a (re)start's
            mm = self._mm
            io = mm[SND_PD:_IO_END]
            if io == self._io:
                io = None  # unchanged: the writer gets no 7 KiB to compare
            else:
                self._io = io
            self._queue.append((s.EXCHANGE, now, wall, io,
                                mm[TASK2_STATE : TASK2_STATE + TASK_STATE_SIZE]))

    def dev_flags(self, value: int) -> None:
        if value != self._dev:
            starting = value & ~max(self._dev, 0) & (fl.RESET | fl.INIT)
            parameter = (self._mm[TASK2_PARAMETER : TASK2_PARAMETER + s.PARAMETER_SIZE]
                         if starting else b"")
            self._queue.append((s.DEV_FLAGS, time.monotonic(), time.time(), self._dev, value,
                                parameter))
            self._dev = value

    def _read_ledger(self) -> bytes:
        if self._ledger < 0:
            assert self._image_files is not None  # hooks run only after start
            try:
                self._ledger = self._image_files.open(self._ledger_name, os.O_RDONLY, own=False)
            except OSError:
                return b""  # no host has locked the board yet: nobody to name
        return os.pread(self._ledger, LEDGER_BYTES, 0)

    # --- the writer --------------------------------------------------------------------

    def close(self) -> None:
        """Write what is queued and close the session (after the loop's last turn)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        self._drain()
        self._pipe.close()
        if self._child.wait() != 0:
            log.error("the session writer ended with status %d: %s is incomplete",
                      self._child.returncode, self.path / s.EVENTS)
        self._files.close()
        if self._ledger >= 0:
            os.close(self._ledger)

    def _write_loop(self) -> None:
        while not self._stop.wait(DRAIN_S):
            self._drain()

    def _drain(self) -> None:
        queue = self._queue
        batch = []
        while queue:
            batch.append(queue.popleft())
        if batch:
            data = pickle.dumps(batch, protocol=pickle.HIGHEST_PROTOCOL)
            self._pipe.write(s.BATCH_FRAME.pack(len(data)) + data)
            self._pipe.flush()

def recording_can_log(session: Path) -> Path:
    """Where the controller's trace of a recorded session goes."""
    return session / s.CAN_LOG
