"""The frame tap's contract: every frame the card sends or receives, for a monitor [ours].

python-can's ``virtual`` bus lives inside one process, so on it nothing outside
the firmware could see the card's traffic. The controller therefore offers its
frames on a Unix datagram socket, ``board<N>.tap`` beside the image: a file
system socket, so the directory's permissions (docs/security.md) decide who may
subscribe. On an abstract name, any local user could take the name first (the
card had no bus) or hold every subscription (the owner's monitor got nothing
while that user read every frame). A monitor binds an automatic abstract
name and sends ``SUBSCRIBE`` at least every ``RENEW_S``; the card sends each
frame to every subscriber heard from within ``EXPIRE_S``, and drops one whose
socket is gone. Sending never blocks: a subscriber that does not keep up loses
frames, the card never waits for it. A new subscriber first gets the last EMCY of
each node again, marked as a replay, so a state view started after a node's
emergency still shows it; a trace drops replays.

A frame datagram is ``FRAME_HEAD`` (time stamp, identifier, flags, DLC) and the
data bytes. The codec (``encode_frame`` / ``decode_frame``) is apart from the
socket so both sides and the tests share it. Like the doorbell, the tap is a
contract between the firmware and the host tools, so it lives here: the card's
serving side is ``firmware.can.tap.TapPublisher``, a monitor's receiving side is
``TapSubscriber`` below.
"""

from __future__ import annotations

import os
import socket
import struct
import time
from pathlib import Path

import can

from dpm.image import socket_path

SUBSCRIBE = b"S"
RENEW_S = 1.0
EXPIRE_S = 5.0

FRAME_HEAD = struct.Struct("<dIBB")
FLAG_EXTENDED = 0x01
FLAG_REMOTE = 0x02
FLAG_ERROR = 0x04
FLAG_RX = 0x08
"""Set for a frame the card received, clear for one it sent."""
FLAG_FD = 0x10
FLAG_REPLAY = 0x20
"""A frame sent again to a new subscriber: the last EMCY of each node, so a view
started after a node's emergency still shows it [ours]."""


def tap_address(image_path: Path) -> bytes:
    """The socket of the tap of the card serving ``image_path``: ``board<N>.tap`` beside it."""
    return os.fsencode(socket_path(image_path, "tap"))


def encode_frame(msg: can.Message, received: bool, replay: bool = False) -> bytes:
    flags = ((FLAG_EXTENDED if msg.is_extended_id else 0) | (FLAG_REMOTE if msg.is_remote_frame
             else 0) | (FLAG_ERROR if msg.is_error_frame else 0) | (FLAG_RX if received else 0)
             | (FLAG_FD if msg.is_fd else 0) | (FLAG_REPLAY if replay else 0))
    return FRAME_HEAD.pack(msg.timestamp, msg.arbitration_id, flags, msg.dlc) + bytes(msg.data)


def decode_frame(datagram: bytes, channel: str | None = None) -> tuple[can.Message, bool]:
    """A frame datagram back into a python-can message and whether it is a replay;
    ValueError when it is malformed."""
    if len(datagram) < FRAME_HEAD.size:
        raise ValueError(f"tap datagram of {len(datagram)} bytes is shorter than its head")
    timestamp, ident, flags, dlc = FRAME_HEAD.unpack_from(datagram)
    msg = can.Message(
        timestamp=timestamp, arbitration_id=ident, is_extended_id=bool(flags & FLAG_EXTENDED),
        is_remote_frame=bool(flags & FLAG_REMOTE), is_error_frame=bool(flags & FLAG_ERROR),
        is_rx=bool(flags & FLAG_RX), is_fd=bool(flags & FLAG_FD), dlc=dlc,
        data=datagram[FRAME_HEAD.size:], channel=channel, check=False)
    return msg, bool(flags & FLAG_REPLAY)


class TapSubscriber:
    """A monitor's side: receives the frames of the card serving ``image_path``."""

    def __init__(self, image_path: Path) -> None:
        self.address = tap_address(image_path)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self._sock.bind(b"")  # an automatic abstract name
        self._renew_due = 0.0

    def subscribe(self) -> str | None:
        """Renew the subscription; None when sent, else why no card's tap takes it
        (none listens, or the directory's permissions keep this user out)."""
        try:
            self._sock.sendto(SUBSCRIBE, socket.MSG_DONTWAIT, self.address)
        except (ConnectionRefusedError, FileNotFoundError):
            return f"no card's frame tap at {os.fsdecode(self.address)}"
        except PermissionError:
            return (f"no permission to reach the card's frame tap at "
                    f"{os.fsdecode(self.address)} (docs/security.md: join the directory's group)")
        except OSError:
            pass  # the card's queue is full: it drains it while frames flow, renew later
        return None

    def recv(self, timeout: float | None) -> bytes | None:
        """One frame datagram, renewing the subscription as time passes; None on time-out."""
        now = time.monotonic()
        if now >= self._renew_due:
            self._renew_due = now + RENEW_S
            self.subscribe()
        wait = RENEW_S if timeout is None else min(timeout, max(0.0, self._renew_due - now))
        self._sock.settimeout(wait)
        try:
            return self._sock.recv(128)
        except TimeoutError:
            return None

    def close(self) -> None:
        self._sock.close()
