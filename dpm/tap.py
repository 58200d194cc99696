"""The frame tap's contract: every frame the card sends or receives, for a monitor [ours].

python-can's ``virtual`` bus lives inside one process, so on it nothing outside
the firmware could see the card's traffic. The controller therefore offers its
frames on a Unix datagram socket, ``board<N>.tap`` beside the image: a file
system socket, so the directory's permissions (docs/security.md) decide who may
subscribe. On an abstract name, any local user could take the name first (the
card had no bus) or hold every subscription (the owner's monitor got nothing
while that user read every frame). A monitor binds an automatic abstract
name and sends ``SUBSCRIBE`` at least every ``RENEW_S``; the card sends each
frame to every subscriber heard from within ``EXPIRE_S`` (or whose queue is full,
however long it is silent), and drops one whose socket is gone. Sending never
blocks: the card never waits for a subscriber that does not keep up; it keeps
that one's frames a while and numbers them, so what it drops is counted (below).
A new subscriber first gets the last EMCY of each node again, marked as a replay,
so a state view started after a node's emergency still shows it; a trace drops
replays.

No frame is lost unseen [ours]. A Unix datagram queue holds only
``net.unix.max_dgram_qlen`` datagrams (10 by default), so the card sends a batch:
``BATCH_HEAD`` (the version, the number of frames, the sequence number of its
first frame) and that many records, each a length byte and one frame (below).
The card numbers the frames it offers each subscriber from 0 at its
subscription, and keeps what that subscriber's queue did not take (at most
``PENDING_FRAMES``, dropping the oldest) to send as one batch once it has room.
A gap between one batch's sequence numbers and the next one's is the exact
number of frames that subscriber lost (``TapSubscriber.lost``). Since the oldest
are dropped, the batch after a gap is always sent once the reader reads again,
so a loss is reported even when no frame follows. A subscription names the
version it reads (``SUBSCRIBE``): a card ignores one of another version, so an
older monitor gets no frames rather than misread ones.

A frame is ``FRAME_HEAD`` (time stamp, identifier, flags, DLC) and the data
bytes; the card's recording (``firmware.recorder``) keeps frames in the same
codec. The codec (``encode_frame`` / ``decode_frame``) is apart from the socket
so both sides and the tests share it. Like the doorbell, the tap is a contract
between the firmware and the host tools, so it lives here: the card's serving
side is ``firmware.can.tap.TapPublisher``, a monitor's receiving side is
``TapSubscriber`` below.
"""

from __future__ import annotations

import contextlib
import os
import socket
import struct
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import can

from dpm.image import socket_path

TAP_VERSION = 2
"""The datagrams' version [ours]: 1 sent one bare frame per datagram, without a sequence
number, so a subscriber could not tell that it had lost frames."""
SUBSCRIBE = b"S" + bytes([TAP_VERSION])
RENEW_S = 1.0
EXPIRE_S = 5.0

BATCH_HEAD = struct.Struct("<BBHQ")
"""Version, 0 (reserved), the number of frames, the sequence number of the first one."""
BATCH_FRAMES = 256
"""At most this many frames in one datagram (about 6 KiB of classic frames)."""
PENDING_FRAMES = 4096
"""Per subscriber, the frames the card keeps while its queue is full [ours]."""
RECEIVE_BYTES = 1 << 16
"""A reader's receive buffer: more than the largest batch (``BATCH_FRAMES`` FD frames)."""

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


_CAN_ERR_CRTL = 0x004
_CAN_ERR_CRTL_RX_OVERFLOW = 0x01


def gap_frame(timestamp: float, channel: str | None = None) -> can.Message:
    """How a log written from the tap marks where frames are missing [ours]: the error frame
    a SocketCAN driver reports a receive overflow with (linux/can/error.h: controller
    problem, RX buffer overflow), which candump and python-can's log readers know."""
    return can.Message(timestamp=timestamp, arbitration_id=_CAN_ERR_CRTL, is_error_frame=True,
                       is_extended_id=False, dlc=8,
                       data=bytes([0, _CAN_ERR_CRTL_RX_OVERFLOW, 0, 0, 0, 0, 0, 0]),
                       channel=channel)


def encode_batch(first: int, frames: Sequence[bytes]) -> bytes:
    """One datagram of ``encode_frame`` frames, the first of them numbered ``first``."""
    return BATCH_HEAD.pack(TAP_VERSION, 0, len(frames), first) + b"".join(
        bytes([len(frame)]) + frame for frame in frames)


def decode_batch(datagram: bytes) -> tuple[int, list[bytes]]:
    """The sequence number of a batch's first frame and its frames (``decode_frame`` each);
    ValueError when it is malformed or of another version."""
    if len(datagram) < BATCH_HEAD.size:
        raise ValueError(f"tap datagram of {len(datagram)} bytes is shorter than its head")
    version, _, count, first = BATCH_HEAD.unpack_from(datagram)
    if version != TAP_VERSION:
        raise ValueError(f"tap datagram of version {version}, not {TAP_VERSION}")
    frames: list[bytes] = []
    offset = BATCH_HEAD.size
    for _ in range(count):
        if offset >= len(datagram) or offset + 1 + datagram[offset] > len(datagram):
            raise ValueError(f"tap datagram cut short in its frame {len(frames) + 1} of {count}")
        end = offset + 1 + datagram[offset]
        frames.append(datagram[offset + 1:end])
        offset = end
    return first, frames


class Batch(NamedTuple):
    """One datagram as a subscriber takes it: the frames lost right before it, its frames."""

    lost: int
    frames: list[bytes]


class TapSubscriber:
    """A monitor's side: receives the frames of the card serving ``image_path`` and counts
    the ones it lost (``lost``, from the gaps in the sequence numbers)."""

    def __init__(self, image_path: Path) -> None:
        self.address = tap_address(image_path)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self._sock.bind(b"")  # an automatic abstract name
        self._renew_due = 0.0
        self._next = 0
        """The sequence number the next frame should have."""
        self.lost = 0
        """Frames the card offered this subscriber that never reached it, so far."""
        self.restarts = 0
        """Times the numbering began anew (a new firmware, or a subscription that lapsed
        while this process was stopped for over ``EXPIRE_S``): frames may be missing
        there, their number unknown."""

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

    def recv(self, timeout: float | None) -> Batch | None:
        """The frames of one datagram and how many were lost before them, renewing the
        subscription as time passes; None on time-out or a malformed datagram."""
        now = time.monotonic()
        if now >= self._renew_due:
            self._renew_due = now + RENEW_S
            self.subscribe()
        wait = RENEW_S if timeout is None else min(timeout, max(0.0, self._renew_due - now))
        self._sock.settimeout(wait)
        try:
            first, frames = decode_batch(self._sock.recv(RECEIVE_BYTES))
        except (TimeoutError, ValueError):
            return None
        lost = first - self._next
        if lost < 0:
            self.restarts += 1
            lost = 0
        self.lost += lost
        self._next = first + len(frames)
        return Batch(lost, frames)

    def interrupt(self) -> None:
        """End a ``recv`` another thread waits in (it returns None): an empty datagram to
        this socket itself (shutting it down does not wake a Unix datagram reader)."""
        with contextlib.suppress(OSError):  # a full queue: the reader has datagrams to wake to
            self._sock.sendto(b"", socket.MSG_DONTWAIT, self._sock.getsockname())

    def close(self) -> None:
        self._sock.close()
