"""One timer thread for every simulated node of a network.

Node timers (boot delay, fault injection, life guarding, PDO inhibit and event
timers, EMCY bursts) all run here rather than one ``threading.Timer`` each: a
full network would otherwise start hundreds of threads, and every callback
runs under the network's lock, so timers and bus callbacks never interleave.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

log = logging.getLogger(__name__)


@dataclass(order=True)
class Timer:
    """A pending call; ``cancel`` makes it a no-op."""

    due: float
    seq: int
    callback: Callable[[], None] = field(compare=False)
    cancelled: bool = field(default=False, compare=False)

    def cancel(self) -> None:
        self.cancelled = True


class Scheduler:
    def __init__(self, lock: threading.RLock) -> None:
        self._lock = lock
        self._queue: list[Timer] = []
        self._seq = itertools.count()
        self._wake = threading.Condition()
        self._running = False
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._running = True
        self._thread = threading.Thread(target=self._run, name="sim scheduler", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        with self._wake:
            self._running = False
            self._queue.clear()
            self._wake.notify()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)
        self._thread = None

    def call_later(self, delay: float, callback: Callable[[], None]) -> Timer:
        timer = Timer(time.monotonic() + max(delay, 0.0), next(self._seq), callback)
        with self._wake:
            heapq.heappush(self._queue, timer)
            self._wake.notify()
        return timer

    def settle(self, timeout: float) -> bool:
        """Wait until every timer due by now has run (or ``timeout`` passed): a timer called
        now comes after them in the queue, since the queue runs in due time, then call order.
        False when the timers did not run in time (or the scheduler stopped)."""
        done = threading.Event()
        self.call_later(0.0, done.set)
        return done.wait(timeout)

    def _run(self) -> None:
        while True:
            with self._wake:
                while self._running and (not self._queue
                                         or self._queue[0].due > time.monotonic()):
                    timeout = self._queue[0].due - time.monotonic() if self._queue else None
                    self._wake.wait(timeout)
                if not self._running:
                    return
                timer = heapq.heappop(self._queue)
            if timer.cancelled:
                continue
            with self._lock:
                if timer.cancelled:
                    continue
                try:
                    timer.callback()
                except Exception:
                    # A faulty node must not stop the timers of all the others.
                    log.exception("simulated node timer failed")
