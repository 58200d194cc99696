"""The card's frame tap (``dpm.tap``) as a receive-only python-can bus [ours].

With it the monitor treats the card's in-process ``virtual`` bus like ``shm``
or ``socketcan``: python-can's ``Notifier``, loggers and filters work on it
unchanged. Frames carry the card's channel name and ``is_rx`` from the card's
side (False: the card sent it).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can

from dpm.tap import TapSubscriber, decode_frame


class TapBus(can.BusABC):
    """Frames of the card serving ``image_path``; sending is refused (a tap only listens)."""

    def __init__(self, image_path: Path, channel: str = "cifemu", replays: bool = False,
                 **kwargs: Any) -> None:
        self._subscriber = TapSubscriber(image_path)
        problem = self._subscriber.subscribe()
        if problem is not None:
            self._subscriber.close()
            raise can.CanInitializationError(problem)
        self.channel_info = f"frame tap of {image_path}"
        self._channel = channel
        self._replays = replays
        """Whether the card's replay of each node's last EMCY is wanted (a state view)
        or dropped (a trace shows only what happens while it runs)."""
        super().__init__(channel=channel, **kwargs)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        datagram = self._subscriber.recv(timeout)
        if datagram is None:
            return None, False
        try:
            msg, replay = decode_frame(datagram, self._channel)
        except ValueError:
            return None, False
        return (msg if self._replays or not replay else None), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("the card's frame tap is receive-only")

    def shutdown(self) -> None:
        self._subscriber.close()
        super().shutdown()
