"""The master's worker threads: jobs that wait, ended before the card powers off.

Two jobs wait in a thread of their own: the 309 gateway's error-control writes
(COM_Set_Guarding, canopen's blocking SDO client) and a boot-up whose node's SDO channel
another transfer holds (``NodeHandler.start_boot``). Their pool was shut down without a wait:
a job still running at power-off went on on the closed bus and the unmapped image, its
exception kept in its future and never seen; one that waited for a channel's lock held the
firmware process from exiting (the interpreter joins a pool's threads at exit), for good.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import Any

log = logging.getLogger(__name__)

WORKERS_JOIN_S = 2.0
"""How long a power-off waits for the jobs under way, before the controller leaves the
bus and the image is unmapped. A job notices the power-off at once in an SDO transfer
(``SdoChannels.close``) and within ``CHANNEL_WAIT_LOOK_S`` (0.5 s) while it waits for a
channel: four of those looks on a loaded machine. A job that takes longer is left to end on
its own, as a frame handler is (``RECEIVER_JOIN_S``), so the power-off stays prompt."""


class Workers:
    """A thread pool whose running jobs a power-off waits for, and whose failures are logged."""

    def __init__(self) -> None:
        self._executor = ThreadPoolExecutor(max_workers=32, thread_name_prefix="node-boot")
        self._lock = threading.Lock()
        self._running: set[Future[object]] = set()

    def submit(self, job: Callable[..., object], *args: Any) -> None:
        """Run ``job(*args)`` in a worker thread; an exception it raises is logged."""
        future = self._executor.submit(job, *args)
        with self._lock:
            self._running.add(future)
        future.add_done_callback(self._done)

    def _done(self, future: Future[object]) -> None:
        with self._lock:
            self._running.discard(future)
        if future.cancelled():
            return
        exc = future.exception()
        if exc is not None:
            log.error("worker job failed", exc_info=exc)

    def shutdown(self) -> None:
        """Drop the jobs not begun, and wait for those under way up to ``WORKERS_JOIN_S``."""
        self._executor.shutdown(wait=False, cancel_futures=True)
        with self._lock:
            running = set(self._running)
        wait(running, WORKERS_JOIN_S)
