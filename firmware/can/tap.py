"""The controller's frame tap, the card's serving side [ours].

The wire format, the socket's place and a monitor's side are the contract in
``dpm.tap``; here the card binds ``board<N>.tap``, learns its subscribers and sends
each frame to them without ever blocking. What a subscriber's queue does not take
waits in its ``pending`` (the oldest dropped past ``PENDING_FRAMES``, and so counted
by the sequence numbers) and goes out as one batch when the queue has room again: a
thread, started at the first full queue, waits for that room in ``poll``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import socket
import threading
import time
from collections import deque
from itertools import islice
from pathlib import Path

import can

from dpm.cia301 import COB_ID_TIME, EMCY_BASE
from dpm.image import CardDirectory
from dpm.tap import (
    BATCH_FRAMES,
    EXPIRE_S,
    PENDING_FRAMES,
    SUBSCRIBE,
    encode_batch,
    encode_frame,
)

log = logging.getLogger(__name__)

DRAIN_INTERVAL_S = 0.1
"""How often the publisher looks for new subscribers (only while frames flow)."""
MAX_SUBSCRIBERS = 8
EMCY_IDS = range(EMCY_BASE + 1, COB_ID_TIME)
"""CiA 301's predefined EMCY identifiers (080h + node-ID 1..127, up to TIME's 100h)."""
SEND_BUFFER_BYTES = 1 << 20
"""A subscriber socket's SO_SNDBUF (the kernel doubles it, up to net.core.wmem_max). A
Unix datagram socket counts the datagrams its peer has not read against its own send
buffer, and ``poll`` calls it writable only while they fill a quarter of it or less:
with the default (208 KiB) a queue of full batches would never look writable."""
JOIN_S = 2.0


class _Subscriber:
    """One subscriber: a socket connected to it (so ``poll`` can tell when its queue has
    room), the frames offered to it so far, and the ones it has not taken yet."""

    __slots__ = ("offered", "peer", "pending", "seen", "sock", "waiting")

    def __init__(self, peer: bytes, now: float) -> None:
        self.peer = peer
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        try:
            self.sock.setblocking(False)
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)
            self.sock.connect(peer)
        except OSError:
            self.sock.close()
            raise
        self.seen = now
        self.offered = 0
        """Frames offered to this subscriber since it subscribed: the next one's number."""
        self.pending: deque[bytes] = deque(maxlen=PENDING_FRAMES)
        self.waiting = False
        """Its queue was full at the last send: only the flusher sends to it now."""


class TapPublisher:
    """The card's side: a bound socket and the subscribers it has heard from.

    Made while the firmware holds the board's lock: a socket file already at
    ``address`` is a killed firmware's and is replaced (``CardDirectory.bind``). A tap
    that cannot be offered costs the card its monitors, never its bus: one line in the
    log, and ``publish`` does nothing."""

    def __init__(self, address: bytes) -> None:
        self.address = address
        self._subscribers: dict[bytes, _Subscriber] = {}
        self._last_emcy: dict[int, bytes] = {}
        """Per EMCY identifier, the last one as a replay frame."""
        self._lock = threading.Lock()
        self._drain_due = 0.0
        """The next look for subscribers, on the frames' own time stamps (``publish``)."""
        self._flusher: threading.Thread | None = None
        self._wake_r, self._wake_w = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._closed = False
        path = Path(os.fsdecode(address))
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._requests = select.poll()
        """Whether a subscription waits on ``_sock``: asked before reading it, because an
        empty socket's ``recvfrom`` raises (2.1 us of CPU in a hot loop against 0.6 us for
        the look, more on a cold wake-up), and the drain runs with every frame of a quiet
        bus, a lone node's heartbeats (issue 22)."""
        self._requests.register(self._sock, select.POLLIN)
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
        while self._requests.poll(0):
            try:
                payload, peer = self._sock.recvfrom(16)
            except OSError:  # taken meanwhile, or the socket is closing
                break
            if payload != SUBSCRIBE or not isinstance(peer, bytes) or not peer:
                continue
            known = self._subscribers.get(peer)
            if known is not None:
                known.seen = now
            elif len(self._subscribers) < MAX_SUBSCRIBERS:
                try:
                    subscriber = _Subscriber(peer, now)
                except OSError:
                    continue  # gone again already
                self._subscribers[peer] = subscriber
                self._offer(subscriber, list(self._last_emcy.values()))
        for subscriber in list(self._subscribers.values()):
            # one whose queue is full stays, however long it is silent: a monitor stopped
            # (Ctrl-Z) is told on waking how many frames it lost, which it could not be if
            # its numbering began anew; a dead one goes at the flusher's next send
            if now - subscriber.seen > EXPIRE_S and not subscriber.waiting:
                self._remove(subscriber)

    def publish(self, msg: can.Message, received: bool) -> None:
        """Offer one frame (any thread). The subscribers are only changed under the lock; a
        look at them without it can at worst miss one that ``_drain`` is adding in this
        moment, which then gets the next frame.

        [ours] When to look for new subscribers is judged on the frame's time stamp, not on
        a clock reading of its own: the controller stamped every frame already (``send``,
        the interface on reception), and each clock reading is a system call inside
        User-Mode Linux, two per host SDO transfer here (issue 22). A frame without a stamp
        (0) is judged on the wall clock's reading; a stamp before the last look (a wall clock
        set back) makes a look too."""
        if self._directory is None:
            return
        stamp = msg.timestamp or time.time()
        due = self._drain_due
        look = not due - DRAIN_INTERVAL_S <= stamp < due
        emcy = msg.arbitration_id in EMCY_IDS and not msg.is_extended_id and not (
            msg.is_remote_frame or msg.is_error_frame)
        if not (emcy or self._subscribers or look):
            return  # nothing to keep, nobody to send it to, no look due: not even the lock
        with self._lock:
            if emcy:
                self._last_emcy[msg.arbitration_id] = encode_frame(msg, received, replay=True)
            if look:
                self._drain_due = stamp + DRAIN_INTERVAL_S
                self._drain(time.monotonic())
            if not self._subscribers:
                return
            frame = [encode_frame(msg, received)]
            for subscriber in list(self._subscribers.values()):
                self._offer(subscriber, frame)

    def _offer(self, subscriber: _Subscriber, frames: list[bytes]) -> None:
        """Number ``frames`` for ``subscriber`` and send what it can take now (under the
        lock). While its queue is full they only wait, the oldest making way."""
        subscriber.offered += len(frames)
        subscriber.pending.extend(frames)
        if not subscriber.waiting:
            self._flush(subscriber)

    def _flush(self, subscriber: _Subscriber) -> None:
        """Send ``subscriber``'s waiting frames in batches until its queue is full (then
        the flusher waits for room) or they are all sent (under the lock)."""
        pending = subscriber.pending
        while pending:
            count = min(len(pending), BATCH_FRAMES)
            datagram = encode_batch(subscriber.offered - len(pending),
                                    list(islice(pending, count)))
            try:
                subscriber.sock.send(datagram)
            except BlockingIOError:
                if not subscriber.waiting:
                    subscriber.waiting = True
                    self._wake_flusher()
                return
            except OSError:  # its socket is gone (or refuses): it subscribes anew if it lives
                self._remove(subscriber)
                return
            for _ in range(count):
                pending.popleft()
        subscriber.waiting = False

    def _remove(self, subscriber: _Subscriber) -> None:
        del self._subscribers[subscriber.peer]
        subscriber.sock.close()
        if subscriber.waiting:
            self._wake_flusher()  # its socket leaves the flusher's poll

    def _wake_flusher(self) -> None:
        """Have the flusher look at the waiting subscribers anew (under the lock), starting
        it on the first full queue: a card nobody reads slowly never has the thread."""
        if self._flusher is None:
            self._flusher = threading.Thread(target=self._flushing, name="tap-flusher",
                                             daemon=True)
            self._flusher.start()
        with contextlib.suppress(OSError):  # full: a wake-up is queued already
            self._wake_w.send(b"w")

    def _flushing(self) -> None:
        """Wait for room in the full queues, and send each its waiting frames then; no
        time-out: nothing to do until a reader reads, a subscriber goes or the card stops."""
        while True:
            with self._lock:
                if self._closed:
                    return
                waiting = {s.sock.fileno(): s for s in self._subscribers.values() if s.waiting}
            poller = select.poll()
            poller.register(self._wake_r, select.POLLIN)
            for fd in waiting:
                poller.register(fd, select.POLLOUT)
            ready = poller.poll()
            while True:
                try:
                    self._wake_r.recv(16)
                except OSError:
                    break
            with self._lock:
                for fd, _ in ready:
                    subscriber = waiting.get(fd)
                    if (subscriber is not None and subscriber.waiting
                            and self._subscribers.get(subscriber.peer) is subscriber):
                        subscriber.waiting = False
                        self._flush(subscriber)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            for subscriber in list(self._subscribers.values()):
                self._remove(subscriber)
            flusher = self._flusher
            if flusher is not None:
                self._wake_flusher()
        if flusher is not None:
            flusher.join(JOIN_S)
        self._wake_r.close()
        self._wake_w.close()
        self._sock.close()
        if self._directory is not None:
            self._directory.unlink(os.fsdecode(os.path.basename(self.address)))
            self._directory.close()
            self._directory = None
