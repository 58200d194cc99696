"""The common shape of the card's tasks: dispatch by ``msg.b``, error answers.

Like python-can's BusABC holds what every interface shares, ``Task`` holds
what every task of the card shares, so the RCS, PLC and CAN tasks only add
their command handlers.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

from dpm.errors import F_INTERNAL_ERROR, F_UNKNOWN_COMMAND
from dpm.message import Message

if TYPE_CHECKING:
    from firmware.card import Card

log = logging.getLogger(__name__)

Handler = Callable[[Message], Message | None]
"""A command handler returns the answer, or None when the answer comes later
(posted with ``Card.post``) or when the command has no answer at all."""

class Task:
    """One task of the card, addressed by ``msg.rx == number``."""

    number: int
    name: str
    version: int = 0x0100

    def __init__(self, device: Card) -> None:
        self.device = device
        self.handlers: dict[int, Handler] = {}

    def handle(self, msg: Message) -> Message | None:
        handler = self.handlers.get(msg.b)
        if handler is None:
            return msg.answer(f=F_UNKNOWN_COMMAND)
        try:
            return handler(msg)
        except Exception:
            log.exception("task %s failed on command %d", self.name, msg.b)
            return msg.answer(f=F_INTERNAL_ERROR)

    def reset(self, cold: bool) -> None:
        """Called by the RCS during a cold or warm start, before READY is raised."""
        del cold
