"""SDO of the master: one channel per node, and host transfers driven by frames.

Each node has one SDO channel (``SdoChannels``): canopen's blocking client, which the
error-control commands of the 309 gateway use from worker threads, and a lock, which a
host transfer and a boot-up take as well, so the node's one SDO server sees one transfer
at a time.

Host transfers are driven by frames, not by a waiting thread (``HostSdoTransfer``):
canopen's SdoClient blocks its caller until each answer arrives, so a host request
would need a worker thread, and the hand-over to it costs more than the transfer
itself. This client sends a request from the caller and advances on each answer in
the bus thread, so a host's COM_SDO_Up_Download is answered from the frame that
completes it. The boot-up (``firmware.can.boot``) drives its steps with the same client.
It speaks CiA 301 expedited and segmented transfers (the seed's card has no block
transfers). Time-outs are checked by the master's thread, which wakes for the earliest
of them (``SdoChannels.watch``).
"""

from __future__ import annotations

import contextlib
import math
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import can
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo.client import SdoClient
from canopen.sdo.exceptions import SdoCommunicationError

from dpm._quicklock import Lock as QuickLock
from dpm.cia301 import (
    ABORT_GENERAL,
    ABORT_TIMEOUT,
    ABORT_TOGGLE,
    ABORT_UNKNOWN_COMMAND,
    SDO_INITIATE,
    SDO_REQUEST_BASE,
    SDO_RESPONSE_BASE,
)
from firmware import inline
from firmware.can.bus import CanBus

DEFAULT_SDO_TIMEOUT = 0.5
"""[ours] seconds an SDO request waits for its answer until COM_Set_SDO_Timeout; canopen's
0.3 s lets a busy 2-core machine abort boot-ups that would have succeeded."""

CHANNEL_WAIT_LOOK_S = 0.5
"""How often a worker waiting for a node's SDO channel looks whether the card powers off
(it waits on the channel's lock, which a power-off does not release)."""
_POWER_OFF = bytes([0x80, 0, 0, 0]) + struct.pack("<I", ABORT_GENERAL)
"""What a power-off gives a blocking client waiting for its answer (``close``): an
abort, which ends the worker's transfer at once rather than after its time-out."""

_NO_CONTEXT = contextlib.nullcontext()


@dataclass
class SdoResult:
    """``data`` after a good transfer, ``abort`` the code of an abort, or ``timed_out``;
    ``failed`` says what was wrong when the client aborted an answer it could not take
    (the boot-up reports that as an unknown SDO response, not as the node's refusal)."""

    data: bytes = b""
    abort: int | None = None
    timed_out: bool = False
    failed: str = ""


class HostSdoTransfer:
    """One upload (``data`` None) or download to ``node``; ``done`` gets the result once.

    The state a transfer starts with is the class's (``_received`` is made when a
    segmented upload begins), not set per object: a host SDO read makes one of these in
    the device loop's thread per transfer (issue 22)."""

    _sent = 0
    _toggle = 0
    _initiated = False
    _expedited = False
    """Up to four bytes go in the initiate request. An empty value cannot (CiA 301's
    expedited sizes are 1-4), so it goes as a segmented download of size 0 [ours]."""
    finished = False
    """Whether ``done`` has had its result: an attribute, not a property, read after
    every request (``SdoChannels.start_host``) and by each look of the master's thread."""
    _received: bytearray

    def __init__(self, bus: CanBus, node: int, index: int, subindex: int, data: bytes | None,
                 timeout: float, done: Callable[[SdoResult], None], *,
                 answered_here: bool = False) -> None:
        self.bus = bus
        self.answered_here = answered_here
        """Send each request inside ``firmware.inline.answered_here``: a simulated node in
        this process answers it in the sending thread (the host's transfers, sent by the
        device loop, whose ``done`` posts the answer; not a boot-up's, whose steps run
        on in the thread that sends)."""
        self.node = node
        self.index = index
        self.subindex = subindex
        self.data = data
        self.timeout = timeout
        self._done = done
        if data is not None:
            self._expedited = 0 < len(data) <= 4
        self._deadline = time.monotonic() + timeout
        """Set here for the first request, which ``start`` sends without reading the clock
        again (each reading a system call inside User-Mode Linux, issue 22); refreshed by
        every later request."""
        self._head = SDO_INITIATE.pack(0, index, subindex)[1:]
        """The object's index and subindex as a request and its initiate response carry them."""
        self._context = inline.answered_here if answered_here else _NO_CONTEXT

    def start(self) -> None:
        """Send the initiate request; its answer may be handled before this returns
        (``answered_here``). Sent here, not by ``_request``: a Python call less per
        transfer (issue 22)."""
        self.bus.lend_sdo_responses(SDO_RESPONSE_BASE + self.node, self._on_frame)
        head = self._head
        if self.data is None:
            frame = b"\x40" + head + bytes(4)
        elif self._expedited:
            command = 0x23 | ((4 - len(self.data)) << 2)
            frame = bytes([command]) + head + self.data.ljust(4, b"\0")
        else:
            frame = b"\x21" + head + struct.pack("<I", len(self.data))
        with self._context:
            self.bus.send(SDO_REQUEST_BASE + self.node, frame)

    def check(self, now: float) -> float:
        """Called from the master's thread: give up after the SDO time-out. Returns when to
        look again (inf: the transfer is over)."""
        if self.finished:
            return math.inf
        if now >= self._deadline:
            self._abort(ABORT_TIMEOUT, SdoResult(timed_out=True))
            return math.inf
        return self._deadline

    @property
    def deadline(self) -> float:
        """When the transfer gives up unless an answer comes first (monotonic seconds)."""
        return self._deadline

    def _send(self, frame: bytes) -> None:
        """A request after an answer: its own time-out from now."""
        self._deadline = time.monotonic() + self.timeout
        self._request(frame)

    def _request(self, frame: bytes) -> None:
        with self._context:
            self.bus.send(SDO_REQUEST_BASE + self.node, frame)

    def _finish(self, result: SdoResult) -> None:
        if self.finished:
            return
        self.finished = True
        self.bus.take_back_sdo_responses(SDO_RESPONSE_BASE + self.node, self._on_frame)
        self._done(result)

    def _abort(self, code: int, result: SdoResult) -> None:
        self.bus.send(SDO_REQUEST_BASE + self.node,
                      bytes([0x80]) + self._head + struct.pack("<I", code))
        self._finish(result)

    def _on_frame(self, msg: can.Message) -> None:
        if self.finished or msg.is_remote_frame or len(msg.data) < 8:
            return
        frame = bytes(msg.data)
        command = frame[0]
        if (command & 0xE3 == 0x43 and self.data is None and not self._sent
                and frame[1:4] == self._head):
            # the usual answer, an expedited upload's with its size, finished here: the
            # calls of ``_upload`` and ``_finish`` on the way of every host SDO read
            # (issue 22); what ``_upload`` does with it, and the other answers, below
            self._sent = 1
            self.finished = True
            self.bus.take_back_sdo_responses(SDO_RESPONSE_BASE + self.node, self._on_frame)
            self._done(SdoResult(data=frame[4 : 8 - ((command >> 2) & 0x03)]))
            return
        if command == 0x80:
            self._finish(SdoResult(abort=struct.unpack_from("<I", frame, 4)[0]))
            return
        if self.data is None:
            self._upload(command, frame)
        else:
            self._download(command, frame)

    def _other_object(self, frame: bytes) -> None:
        """An initiate response that names another object than this request's (``_head``)
        is no answer to it (canopen's client refuses it too): abort, unknown. Called only
        for such a response: the comparison is made by the caller, without a call on the
        way of every good answer (issue 22)."""
        index, subindex = struct.unpack_from("<HB", frame, 1)
        self._abort(ABORT_GENERAL, SdoResult(abort=ABORT_GENERAL, failed=(
            f"answer for {index:04X}h sub {subindex} instead of "
            f"{self.index:04X}h sub {self.subindex}")))

    def _upload(self, command: int, frame: bytes) -> None:
        if self._sent == 0 and command & 0xE0 == 0x40:  # initiate upload response
            if frame[1:4] != self._head:
                self._other_object(frame)
                return
            self._sent = 1
            if command & 0x02:  # expedited
                size = 4 - ((command >> 2) & 0x03) if command & 0x01 else 4
                self._finish(SdoResult(data=frame[4 : 4 + size]))
                return
            self._received = bytearray()
            self._send(bytes([0x60 | self._toggle << 4]) + bytes(7))
            return
        if self._sent and command & 0xE0 == 0x00:  # upload segment response
            if (command >> 4) & 1 != self._toggle:
                self._abort(ABORT_TOGGLE, SdoResult(abort=ABORT_TOGGLE,
                                                    failed="Toggle bit mismatch"))
                return
            self._received += frame[1 : 8 - ((command >> 1) & 0x07)]
            if command & 0x01:
                self._finish(SdoResult(data=bytes(self._received)))
                return
            self._toggle ^= 1
            self._send(bytes([0x60 | self._toggle << 4]) + bytes(7))
            return
        self._abort(ABORT_UNKNOWN_COMMAND, SdoResult(abort=ABORT_UNKNOWN_COMMAND,
                                                     failed=f"Unexpected response 0x{command:02X}"))

    def _download(self, command: int, frame: bytes) -> None:
        assert self.data is not None
        initiated = command == 0x60 and not self._initiated
        if initiated and frame[1:4] != self._head:
            self._other_object(frame)
            return
        segment_done = command & 0xEF == 0x20 and self._initiated
        if not (initiated or segment_done):
            self._abort(ABORT_UNKNOWN_COMMAND, SdoResult(
                abort=ABORT_UNKNOWN_COMMAND, failed=f"Unexpected response 0x{command:02X}"))
            return
        if segment_done:
            if (command >> 4) & 1 != self._toggle:
                self._abort(ABORT_TOGGLE, SdoResult(abort=ABORT_TOGGLE,
                                                    failed="Toggle bit mismatch"))
                return
            self._toggle ^= 1
            if self._sent >= len(self.data):
                self._finish(SdoResult())
                return
        elif self._expedited:
            self._finish(SdoResult())
            return
        self._initiated = True
        chunk = self.data[self._sent : self._sent + 7]
        self._sent += len(chunk)
        last = 1 if self._sent >= len(self.data) else 0
        header = (self._toggle << 4) | ((7 - len(chunk)) << 1) | last
        self._send(bytes([header]) + chunk.ljust(7, b"\0"))


class Deadline(Protocol):
    """What the master's thread times out (``SdoChannels.watch``): an SDO transfer, or a
    boot-up's wait for the boot-up message."""

    @property
    def finished(self) -> bool: ...

    @property
    def deadline(self) -> float: ...

    def check(self, now: float) -> float:
        """Give up when the deadline has come; when to look again (inf: over)."""


class _Client(SdoClient):
    """canopen's blocking client, which sends no request once the card powers off: the bus
    is about to close under it."""

    def __init__(self, address: int, closed: threading.Event) -> None:
        super().__init__(SDO_REQUEST_BASE + address, SDO_RESPONSE_BASE + address,
                         ObjectDictionary())  # type: ignore[no-untyped-call]
        self._closed = closed

    def send_request(self, request: bytes) -> None:
        if self._closed.is_set():
            raise SdoCommunicationError("the card powers off")
        super().send_request(request)  # type: ignore[no-untyped-call]


@dataclass
class SdoChannel:
    """A node's SDO channel: one client, taken in turn by boot-up and host transfers."""

    sdo: SdoClient
    lock: QuickLock
    """threading.Lock's semantics without its clock reading on a free acquire: a host
    transfer takes it on the device loop's thread and releases it on the receive thread,
    each clock reading a system call inside User-Mode Linux (issue 22)."""


class SdoChannels:
    """The nodes' SDO channels, created on first use and kept for the card's life, with
    the host transfers under way, whose time-outs the master's thread checks.

    ``wake_at`` asks that thread to look no later than a given time (``Master.wake_at``).
    """

    def __init__(self, wake_at: Callable[[float], None]) -> None:
        self._wake_at = wake_at
        self._bus: CanBus | None = None
        self._channels: dict[int, SdoChannel] = {}
        self._watched: set[Deadline] = set()
        """The transfers and waits under way whose time-outs the master's thread checks."""
        self._watched_lock = QuickLock()
        self._next_check = math.inf
        """No watched deadline comes before this: a look before it checks none of them (a
        boot of 127 nodes has as many under way, and the master looks at every change)."""
        self.timeout = DEFAULT_SDO_TIMEOUT
        """Seconds a new channel waits for an answer (COM_Set_SDO_Timeout node 0)."""
        self._closed = threading.Event()

    def open(self, bus: CanBus) -> None:
        self._bus = bus

    def close(self) -> None:
        """The card powers off: a worker's transfer ends now, at its next request or with
        the abort its wait gets, and a worker waiting for a channel gives up (``take``).
        A job blocked for the node's SDO time-out (up to 65 s) held the power-off."""
        self._closed.set()
        for channel in list(self._channels.values()):
            channel.sdo.on_response(SDO_RESPONSE_BASE, _POWER_OFF, 0.0)  # type: ignore[no-untyped-call]

    @property
    def closing(self) -> bool:
        return self._closed.is_set()

    def take(self, channel: SdoChannel) -> bool:
        """In a worker: take ``channel``; False when the card powers off meanwhile."""
        while not channel.lock.acquire(timeout=CHANNEL_WAIT_LOOK_S):
            if self._closed.is_set():
                return False
        return True

    def channel(self, address: int) -> SdoChannel:
        """The SDO channel to ``address``."""
        channel = self._channels.get(address)
        if channel is None:
            assert self._bus is not None
            client = _Client(address, self._closed)
            client.network = self._bus.network
            client.RESPONSE_TIMEOUT = self.timeout
            self._bus.network.subscribe(SDO_RESPONSE_BASE + address, client.on_response)
            channel = self._channels[address] = SdoChannel(client, QuickLock())
        return channel

    def set_timeout(self, node: int, seconds: float) -> None:
        """COM_Set_SDO_Timeout: one node's channel, or (node 0) every channel and the default."""
        if node == 0:
            self.timeout = seconds
            for channel in self._channels.values():
                channel.sdo.RESPONSE_TIMEOUT = seconds
        else:
            self.channel(node).sdo.RESPONSE_TIMEOUT = seconds

    def start_host(self, transfer: HostSdoTransfer) -> None:
        """An SDO transfer of the host or of a boot-up; the master's thread watches its
        time-out (``check``)."""
        transfer.start()
        if not transfer.finished:  # an answer handled in ``start`` (``answered_here``)
            self.watch(transfer)

    def watch(self, item: Deadline) -> None:
        """Time ``item`` out from the master's thread when its deadline comes."""
        deadline = item.deadline
        with self._watched_lock:
            self._watched.add(item)
            wake = deadline < self._next_check
            self._next_check = min(self._next_check, deadline)
        if wake:
            self._wake_at(deadline)

    def check(self, now: float) -> float:
        """Time out what is watched whose time has come; returns when the next may (inf:
        nothing is watched). A request's deadline moves later with each request, so the
        earliest one noted may be stale: the look it causes notes the true one."""
        with self._watched_lock:
            if now < self._next_check:
                return self._next_check
            items = set(self._watched)
        due = math.inf
        over = set()
        for item in items:
            when = item.check(now)
            if math.isinf(when):
                over.add(item)
            due = min(due, when)
        with self._watched_lock:
            self._watched.difference_update(over)
            # one watched meanwhile noted its own deadline, which may come first
            self._next_check = due = min(
                (due, *(i.deadline for i in self._watched - items)))
        return due
