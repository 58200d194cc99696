"""The card's frame tap (``dpm.tap``) as a receive-only python-can bus [ours].

With it the monitor treats the card's in-process ``virtual`` bus like ``shm``
or ``socketcan``: python-can's ``Notifier``, loggers and filters work on it
unchanged. Frames carry the card's channel name and ``is_rx`` from the card's
side (False: the card sent it).

A thread of the bus's own reads the socket as frames come, so a caller busy for a
moment (printing, decoding) does not fill the card's queue to it; it keeps up to
``QUEUE_FRAMES`` for ``recv``. Frames lost all the same are never lost unseen: where
``recv`` reaches the place they are missing from, it adds them to ``lost_frames``
and logs a warning.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import can

from dpm.tap import EXPIRE_S, RENEW_S, TapSubscriber, decode_frame

log = logging.getLogger(__name__)

QUEUE_FRAMES = 16384
"""Frames the reader thread keeps for ``recv`` [ours]. When they are all waiting, it
stops taking the card's datagrams (it only renews the subscription): the card keeps the
next ones, then drops the oldest and counts them, so memory stays bounded and every
loss is counted in one place."""
JOIN_S = 2.0


class TapBus(can.BusABC):
    """Frames of the card serving ``image_path``; sending is refused (a tap only listens)."""

    def __init__(self, image_path: Path, channel: str = "cifemu", replays: bool = False,
                 log_losses: bool = True, **kwargs: Any) -> None:
        self._subscriber = TapSubscriber(image_path)
        problem = self._subscriber.subscribe()
        if problem is not None:
            self._subscriber.close()
            raise can.CanInitializationError(problem)
        self.channel_info = f"frame tap of {image_path}"
        self.channel = channel
        """The channel name its frames carry (the card's bus's)."""
        self._replays = replays
        """Whether the card's replay of each node's last EMCY is wanted (a state view)
        or dropped (a trace shows only what happens while it runs)."""
        self._log_losses = log_losses
        """False for a caller that shows ``lost_frames`` itself (``cifemu monitor``, ``top``)."""
        self.lost_frames = 0
        """Frames the card sent this bus that ``recv`` never returned (the reader was too
        slow), counted when ``recv`` reaches their place: before the frame it returns."""
        self._queue: deque[can.Message | int] = deque()
        """Frames for ``recv``, and where frames are missing, their number (an int)."""
        self._frames = 0
        self._ready = threading.Condition()
        self._closing = False
        super().__init__(channel=channel, **kwargs)
        self._reader = threading.Thread(target=self._read, name="tap-reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        restarts = 0
        while not self._closing:
            batch = self._subscriber.recv(RENEW_S)
            if self._subscriber.restarts != restarts:
                restarts = self._subscriber.restarts
                log.warning("the card's frame tap began its numbering anew (a new firmware, "
                            "or this process was stopped for over %g s): frames may be "
                            "missing", EXPIRE_S)
            if batch is None:
                continue
            items: list[can.Message | int] = [batch.lost] if batch.lost else []
            for frame in batch.frames:
                try:
                    msg, replay = decode_frame(frame, self.channel)
                except ValueError:
                    continue
                if self._replays or not replay:
                    items.append(msg)
            with self._ready:
                while self._frames >= QUEUE_FRAMES and not self._closing:
                    if not self._ready.wait(RENEW_S):
                        self._subscriber.subscribe()  # stay subscribed while recv catches up
                self._queue.extend(items)
                self._frames += len(items) - (1 if batch.lost else 0)
                self._ready.notify_all()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        end = None if timeout is None else time.monotonic() + timeout
        with self._ready:
            while True:
                while self._queue:
                    item = self._queue.popleft()
                    if isinstance(item, int):
                        self.lost_frames += item
                        if self._log_losses:
                            log.warning("%d frames lost (tap reader too slow); %d so far",
                                        item, self.lost_frames)
                        continue
                    self._frames -= 1
                    self._ready.notify_all()
                    return item, False
                left = None if end is None else end - time.monotonic()
                if self._closing or (left is not None and left <= 0):
                    return None, False
                self._ready.wait(left)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("the card's frame tap is receive-only")

    def shutdown(self) -> None:
        with self._ready:
            self._closing = True
            self._ready.notify_all()
        self._subscriber.interrupt()
        self._reader.join(JOIN_S)
        self._subscriber.close()
        super().shutdown()
