"""The controller's frame tap, the card's serving side [ours].

The wire format, the socket's place and a monitor's side are the contract in
``dpm.tap``; here the card binds ``board<N>.tap``, learns its subscribers and sends
each frame to them without ever blocking.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from pathlib import Path

import can

from dpm.image import CardDirectory
from dpm.tap import EXPIRE_S, SUBSCRIBE, encode_frame

log = logging.getLogger(__name__)

DRAIN_INTERVAL_S = 0.1
"""How often the publisher looks for new subscribers (only while frames flow)."""
MAX_SUBSCRIBERS = 8
EMCY_IDS = range(0x081, 0x100)
"""CiA 301's predefined EMCY identifiers (080h + node-ID)."""


class TapPublisher:
    """The card's side: a bound socket and the subscribers it has heard from.

    Made while the firmware holds the board's lock: a socket file already at
    ``address`` is a killed firmware's and is replaced (``CardDirectory.bind``). A tap
    that cannot be offered costs the card its monitors, never its bus: one line in the
    log, and ``publish`` does nothing."""

    def __init__(self, address: bytes) -> None:
        self.address = address
        self._subscribers: dict[bytes, float] = {}
        self._last_emcy: dict[int, bytes] = {}
        """Per EMCY identifier, the last one as a replay datagram."""
        self._lock = threading.Lock()
        self._drain_due = 0.0
        path = Path(os.fsdecode(address))
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._directory: CardDirectory | None = None
        try:
            self._directory = CardDirectory(path.parent)
            self._directory.bind(self._sock, path)
        except OSError as exc:
            log.error("frame tap not offered, monitors see no frames: %s", exc)
            self._sock.close()
            if self._directory is not None:
                self._directory.close()
                self._directory = None

    def _drain(self, now: float) -> None:
        while True:
            try:
                payload, peer = self._sock.recvfrom(16)
            except (BlockingIOError, OSError):
                break
            if payload == SUBSCRIBE and isinstance(peer, bytes) and peer and (
                    peer in self._subscribers or len(self._subscribers) < MAX_SUBSCRIBERS):
                if peer not in self._subscribers:
                    for datagram in self._last_emcy.values():
                        self._send(peer, datagram)
                self._subscribers[peer] = now
        for peer, seen in list(self._subscribers.items()):
            if now - seen > EXPIRE_S:
                del self._subscribers[peer]

    def publish(self, msg: can.Message, received: bool) -> None:
        """Offer one frame (any thread); costs a clock read while nobody listens. The
        subscribers are only changed under the lock; a look at them without it can at worst
        miss one that ``_drain`` is adding in this moment, which then gets the next frame."""
        if self._directory is None:
            return
        now = time.monotonic()
        emcy = msg.arbitration_id in EMCY_IDS and not msg.is_extended_id and not (
            msg.is_remote_frame or msg.is_error_frame)
        if not (emcy or self._subscribers or now >= self._drain_due):
            return  # nothing to keep, nobody to send it to, no look due: not even the lock
        with self._lock:
            if emcy:
                self._last_emcy[msg.arbitration_id] = encode_frame(msg, received, replay=True)
            if now >= self._drain_due:
                self._drain_due = now + DRAIN_INTERVAL_S
                self._drain(now)
            if not self._subscribers:
                return
            datagram = encode_frame(msg, received)
            for peer in list(self._subscribers):
                self._send(peer, datagram)

    def _send(self, peer: bytes, datagram: bytes) -> None:
        try:
            self._sock.sendto(datagram, peer)
        except (ConnectionRefusedError, FileNotFoundError):
            self._subscribers.pop(peer, None)
        except OSError:
            pass  # the subscriber's queue is full: it loses this frame

    def close(self) -> None:
        self._sock.close()
        if self._directory is not None:
            self._directory.unlink(os.fsdecode(os.path.basename(self.address)))
            self._directory.close()
            self._directory = None
