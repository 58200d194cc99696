"""Serialising host processes and threads on one board's channels.

The real driver lets one call at a time wait on a mailbox and answers a
second one with DRV_CMD_ACTIVE. Across processes sharing an image we do the
same with a lock per channel (a thread lock plus an flock on a file beside
the image): a call waits for the channel up to its own timeout and gets -4
when another caller holds it longer than that.
"""

from __future__ import annotations

import errno
import fcntl
import os
import threading
import time
from pathlib import Path
from types import TracebackType

_FLOCK_RETRY = 0.0002


class ChannelLock:
    def __init__(self, path: Path) -> None:
        self._thread = threading.Lock()
        self._fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o660)

    def acquire(self, timeout: float) -> bool:
        """Take the channel within ``timeout`` seconds (0: only if free now)."""
        if self._thread.acquire(False):  # the uncontended case, without clocks
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return True
            except BlockingIOError:
                self._thread.release()
        deadline = time.monotonic() + timeout
        got = self._thread.acquire(timeout=timeout) if timeout > 0 else self._thread.acquire(False)
        if not got:
            return False
        while True:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return True
            except OSError as exc:
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                    self._thread.release()
                    raise
            if time.monotonic() >= deadline:
                self._thread.release()
                return False
            time.sleep(_FLOCK_RETRY)

    def release(self) -> None:
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        self._thread.release()

    def __enter__(self) -> ChannelLock:
        """Block until the channel is free: for locks held only for microseconds."""
        self._thread.acquire()
        fcntl.flock(self._fd, fcntl.LOCK_EX)
        return self

    def __exit__(
        self, t: type[BaseException] | None, v: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.release()

    def close(self) -> None:
        os.close(self._fd)
