"""Card-side faults on demand, the firmware's side [ours] (docs/faults.md).

The contract (requests, replies, the socket's name) is ``dpm.faults``. Here the card binds
``board<N>.fault`` beside the image, and a thread of its own serves it: it takes each
request, changes what the card does, answers, and ends each fault when its time is up.
The device loop asks this object at three points only (``stalled``, ``hold``,
``before_turn``) and tells it of every start (``started``); everything else a fault
changes, it changes through the part of the card that owns it (the host watchdog in
``RcsTask``, the input bytes in ``ProcessImage``, the controller in ``CanBus``), between
two turns of the device loop (``Device.between_turns``), so that no host sees half of a
fault's beginning or end.

No fault touches the flash, and none outlives the firmware: every fault is state of this
process, and ``close`` ends the thread at power-off.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import select
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from dpm.faults import (
    BUS_OFF,
    CLEAR,
    DIE,
    FLIP,
    LIST,
    MAX_DATAGRAM,
    RCS_ERROR,
    SLOW,
    STALL,
    WATCHDOG,
    ActiveFault,
    FaultRequest,
    FaultRequestError,
    decode_request,
    encode_reply,
    fault_address,
)
from dpm.layout import RCS_ERROR as RCS_ERROR_BYTE
from firmware.rcs import Start

if TYPE_CHECKING:
    from firmware.card import Answer
    from firmware.device import Device

log = logging.getLogger(__name__)


class _Refused(Exception):
    """A well-formed request the card cannot follow now; the message is the reply's."""


@dataclass
class _Fault:
    request: FaultRequest
    ends: float | None
    """CLOCK_MONOTONIC seconds; None: until cleared (a ``flip`` once: until used)."""


class CardFaults:
    """The faults in force on one card, and the thread that takes requests for them."""

    def __init__(self, device: Device) -> None:
        self._device = device
        self._active: dict[str, _Fault] = {}
        self._lock = threading.Lock()
        """``_active`` and ``_held``, between the fault thread and the device's hooks."""
        self._held: deque[tuple[float, Answer]] = deque()
        """The slow card's answers, each with the time it is due."""
        self._delay = 0.0
        self._stalled = False
        self._hung = False
        self._reboot = False
        self.died = False
        """The fault ``die`` ended the firmware (``cifemu firmware`` exits with
        ``dpm.faults.DIE_EXIT_STATUS``)."""
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()
        """Wakes the thread from its own process. Not a datagram to the socket's own address:
        once the socket's file is gone (a demo removes its directory as it ends) nothing
        reaches that address, and power-off would wait for the thread for good."""
        os.set_blocking(self._wake_w, False)
        self.address = fault_address(device.path)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._bound = False
        try:
            device.files.bind(self._sock, Path(self.address))
            self._bound = True
        except OSError as exc:  # as the frame tap: the card runs on without it
            log.error("fault socket not offered, no fault can be injected: %s", exc)
        self._thread = threading.Thread(target=self._serve, name="faults", daemon=True)

    def start(self) -> None:
        if self._bound:
            self._thread.start()

    def close(self) -> None:
        """End the thread and remove the socket (power-off); the faults end with the process.
        The one a fault leaves in the image, bRcsError, is cleared: a host that finds the
        card stopped gets -11, not the RCS error of a fault that is over."""
        self._stop.set()
        self._wake()
        if self._thread.is_alive():
            self._thread.join()
        self._sock.close()
        os.close(self._wake_r)
        os.close(self._wake_w)
        if RCS_ERROR in self._active:
            self._device.mm[RCS_ERROR_BYTE] = 0
        if self._bound:
            self._device.files.unlink(Path(self.address).name)

    # --- what the device loop asks ------------------------------------------------------

    @property
    def stalled(self) -> bool:
        """The mailbox stalls: the card takes no message from DevMbx."""
        return self._stalled

    @property
    def idle(self) -> bool:
        """No fault is in force, none is pending and no answer is held: the device loop may
        serve a plain mailbox turn in C (``firmware.native_mailbox``); a fault that begins
        holds the loop between turns and rings it (``Device.between_turns``)."""
        return not (self._active or self._held or self._delay or self._stalled or self._hung
                    or self._reboot)

    def hold(self, msg: Answer) -> bool:
        """Keep ``msg`` back for the slow card's delay; False: hand it over now."""
        if not self._delay:
            return False
        with self._lock:
            if not self._delay:
                return False
            self._held.append((time.monotonic() + self._delay, msg))
            first = len(self._held) == 1
        if first:
            self._wake()  # the thread may sleep for a fault's end: it has a message due sooner
        return True

    def before_turn(self) -> bool:
        """Whether the device loop skips this turn: the card hangs (``die`` with ``hang``),
        or the hang has just ended and this turn is the cold start a card's watchdog reset
        brings."""
        if self._hung:
            return True
        if not self._reboot:
            return False
        self._reboot = False
        log.warning("fault die ended: the card starts again (cold start)")
        self._device.rcs.start(Start.COLD)
        with self._lock:
            self._device.rcs.stop_watchdog(WATCHDOG in self._active)
        return True

    def started(self) -> None:
        """A start: answers held from before it are gone, as the outbox is; an RCS error in
        force stays shown (the start filled RcsInfo anew)."""
        with self._lock:
            self._held.clear()
            fault = self._active.get(RCS_ERROR)
        if fault is not None:
            self._device.mm[RCS_ERROR_BYTE] = fault.request.code

    # --- the thread -----------------------------------------------------------------------

    def _wake(self) -> None:
        with contextlib.suppress(BlockingIOError):  # the pipe is full: it is awake anyway
            os.write(self._wake_w, b"w")

    def _serve(self) -> None:
        while not self._stop.is_set():
            due = self._next_due()
            timeout = None if due is None else max(0.0, due - time.monotonic())
            ready = select.select((self._sock.fileno(), self._wake_r), (), (), timeout)[0]
            if self._wake_r in ready:
                os.read(self._wake_r, 512)
            if self._sock.fileno() in ready:
                self._take_requests()
            now = time.monotonic()
            self._expire(now)
            self._release(now)

    def _take_requests(self) -> None:
        while True:
            try:
                data, peer = self._sock.recvfrom(MAX_DATAGRAM + 1)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # closed at power-off
            if not data:
                continue  # nothing asked
            reply = self._answer(data)
            if not peer:
                continue  # a sender without an address (socat, a shell) gets no answer
            try:
                self._sock.sendto(reply, peer)
            except OSError as exc:
                log.warning("fault reply not sent to %r: %s", peer, exc)

    def _answer(self, data: bytes) -> bytes:
        try:
            request = decode_request(data)
            self._apply(request)
        except (FaultRequestError, _Refused) as exc:
            log.warning("fault request refused: %s", exc)
            return encode_reply(error=str(exc))
        return encode_reply(self.active())

    def _next_due(self) -> float | None:
        with self._lock:
            times = [f.ends for f in self._active.values() if f.ends is not None]
            if self._held:
                times.append(self._held[0][0])
            if FLIP in self._active and self._active[FLIP].ends is None:
                times.append(time.monotonic() + 0.1)  # look for the exchange that used it
        return min(times) if times else None

    def active(self) -> list[ActiveFault]:
        """The faults in force now, with the milliseconds each has left."""
        now = time.monotonic()
        with self._lock:
            return [ActiveFault(f.request, None if f.ends is None
                                else max(0, math.ceil((f.ends - now) * 1000)))
                    for f in self._active.values()]

    # --- beginning and end ------------------------------------------------------------------

    def _apply(self, request: FaultRequest) -> None:
        kind = request.kind
        if kind == LIST:
            return
        if kind == CLEAR:
            for name in list(self._active):
                self._end(name)
            return
        if kind == DIE and not request.hang:
            self._die()
            return
        if kind == BUS_OFF and self._device.can.master.bus is None:
            raise _Refused("the card has no CAN controller open (FAT): it cannot go bus-off")
        ends = None if request.for_ms is None else time.monotonic() + request.for_ms / 1000
        if kind == DIE and kind in self._active:
            pass  # a hanging card hangs on: only the end moves
        else:
            if kind in self._active:
                self._end(kind)
            self._begin(request)
        with self._lock:
            self._active[kind] = _Fault(request, ends)
        log.warning("fault injected: %s", request.describe())

    def _begin(self, request: FaultRequest) -> None:
        device = self._device
        kind = request.kind
        with device.between_turns():
            if kind == WATCHDOG:
                device.rcs.stop_watchdog(True)
            elif kind == RCS_ERROR:
                device.mm[RCS_ERROR_BYTE] = request.code
            elif kind == STALL:
                self._stalled = True
            elif kind == SLOW:
                self._delay = request.delay_ms / 1000
            elif kind == FLIP:
                device.plc.image.flip_inputs(request.offset, 1 << request.bit,
                                             once=request.for_ms is None)
            elif kind == BUS_OFF:
                device.can.master.set_bus_off(True)
            elif kind == DIE:
                self._hang()

    def _end(self, kind: str) -> None:
        with self._lock:
            fault = self._active.pop(kind, None)
        if fault is None:
            return
        device = self._device
        with device.between_turns():
            if kind == WATCHDOG:
                device.rcs.stop_watchdog(self._hung)
            elif kind == RCS_ERROR:
                device.mm[RCS_ERROR_BYTE] = 0
            elif kind == STALL:
                self._stalled = False
            elif kind == SLOW:
                self._delay = 0.0
            elif kind == FLIP:
                device.plc.image.unflip_inputs()
            elif kind == BUS_OFF:
                device.can.master.set_bus_off(False)
            elif kind == DIE:
                self._hung = False
                self._reboot = True  # the device loop's next turn starts the card
        if kind == SLOW:
            self._release(math.inf)
        log.warning("fault ended: %s", kind)

    def _expire(self, now: float) -> None:
        with self._lock:
            due = [kind for kind, f in self._active.items() if f.ends is not None
                   and f.ends <= now]
            flip = self._active.get(FLIP)
            if (flip is not None and flip.ends is None
                    and not self._device.plc.image.flipping):
                del self._active[FLIP]  # the one exchange it was for has happened
                log.warning("fault ended: %s (one exchange)", FLIP)
        for kind in due:
            self._end(kind)

    def _release(self, now: float) -> None:
        """Hand over the slow card's answers that are due (``math.inf``: all of them)."""
        while True:
            with self._lock:
                if not self._held or self._held[0][0] > now:
                    return
                _, msg = self._held.popleft()
            self._device.hand_over(msg)

    def _die(self) -> None:
        """The card's own watchdog fires: READY (and RUN, COM) drop, the firmware ends."""
        log.error("fault die: the card's watchdog fired; READY drops and the firmware ends")
        with self._device.between_turns():
            self._device.write_host_flags(0)
            self.died = True
            self._hung = True  # the turns until the loop sees the stop serve nothing either
        self._device.stop()

    def _hang(self) -> None:
        """Like ``_die``, but the process stays: no flag, no answer, the bus quiet (every
        task reset, as the card's CPU is), until the fault ends."""
        device = self._device
        log.error("fault die (hang): the card's watchdog fired; READY drops, the card "
                  "serves nothing until the fault ends")
        device.write_host_flags(0)
        device.outbox.clear()
        with self._lock:
            self._held.clear()
        device.rcs.stop_watchdog(True)
        for task in device.tasks.values():
            task.reset(True)
        self._hung = True
