"""Keeps a ``CardModel`` current: the image on the caller's beat, the card's frames from its tap.

The image is read on each ``poll_image`` (a copy of a read-only map, so the
view never disturbs the card); frames come from the card's frame tap in a
thread of their own. Without a tap (the firmware is gone) the view still shows
the image, and says why the bus columns stay empty.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import can

from dpm.card_info import read_card_info
from dpm.image import image_path
from host_api.monitor.tap_bus import TapBus
from host_api.status import read_image
from host_api.top.model import CardModel

RECEIVE_TIMEOUT_S = 0.2


class CardFeed:
    def __init__(self, model: CardModel, board: int, directory: Path) -> None:
        self.model = model
        self.board = board
        self.directory = directory
        self.tap_error: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._bus: TapBus | None = None

    def start(self) -> None:
        info = read_card_info(self.directory, self.board) or {}
        channel = str((info.get("bus") or {}).get("channel") or "cifemu")
        if self.model.bitrate is None:
            self.model.bitrate = (info.get("bus") or {}).get("bitrate")
        try:
            self._bus = TapBus(image_path(self.directory, self.board), channel, replays=True,
                               log_losses=False)
        except can.CanError as exc:
            self.tap_error = str(exc)
            return
        self._thread = threading.Thread(target=self._receive, name="top-tap", daemon=True)
        self._thread.start()

    def _receive(self) -> None:
        assert self._bus is not None
        lost = 0
        while not self._stop.is_set():
            msg = self._bus.recv(RECEIVE_TIMEOUT_S)
            if self._bus.lost_frames != lost:
                self.model.on_frames_lost(self._bus.lost_frames - lost, time.time())
                lost = self._bus.lost_frames
            if msg is not None:
                self.model.on_frame(msg.arbitration_id, bytes(msg.data),
                                    remote=msg.is_remote_frame, extended=msg.is_extended_id,
                                    error=msg.is_error_frame, timestamp=msg.timestamp)

    def poll_image(self) -> bool:
        """Read the image once; False when there is none."""
        image = read_image(self.board, str(self.directory))
        if image is None:
            return False
        self.model.update_image(image, time.time())
        return True

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        if self._bus is not None:
            self._bus.shutdown()
