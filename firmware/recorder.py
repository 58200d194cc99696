"""Recording a session from inside the card [ours] (docs/recording.md).

The device loop calls a ``Recorder`` at the points where it already looks: a message
taken from DevMbx, an answer put into PcMbx, a HostFlags write, the DevFlags it read
for its turn; the controller calls it for each frame. Each event call packs the event into bytes
(``dpm.session``'s spool layout: a cached ``struct`` packer, the copied bytes behind it)
and appends them to one ``bytearray`` in a single operation, so an event is whole at any
moment another thread looks (never blocking, no lock); the controller's frames go to a
deque as python-can made them. A thread drains both every ``DRAIN_S``: it takes the bytes
there are in pieces of ``PIECE`` (one copy each) and hands them through a pipe to a child
process (``firmware.session_writer``) that computes what changed and writes
``session.jsonl`` and ``can.log``. Encoding lines in the firmware's own process, even by
hand, cost the loop a third of its mailbox round trips on a loaded two-core machine (the
writer held the interpreter lock the loop waits for). Queued as tuples (until 2026-12-03)
each event left a tuple, a float and its bytes to marshal and free in the drain thread,
about 1 us a mailbox round trip of the interpreter lock the loop needs, and a ledger read
of 512 bytes, mostly zeros, in the spool; packed, the drain copies bytes and nothing
else. So recording costs the loop a few attribute lookups and one packing per event, at
most one clock read and, at a process-data handshake, a copy of the two I/O areas when
the exchange changed them (the process image tells: ``ProcessImage.exchanged_changes``),
made after the card rang its hosts (``settle``); never a write or a lock. A message and
the HostFlags toggle that takes or hands it over are one event, as are an exchange and
its PDACK toggle: each call counts on a loop that turns every 25 us.

The writer gets open files, never a path: ``create`` makes them for ``cifemu firmware
--record``, whose user chose the path; a ``cifemu record`` that attaches to a running
card opens them itself and passes them over the card's record socket
(firmware/record_socket.py), so the firmware, often root, opens no path another user
named. The pid of a message's host is read from the transaction ledger at the moment
the card takes the message: the ledger line is gone once the host took the answer.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import struct
import subprocess
import threading
import time
from collections import deque
from itertools import repeat
from operator import call
from pathlib import Path
from typing import Any

import can

from dpm import flags as fl
from dpm import session as s
from dpm.image import CardDirectory, lock_path
from dpm.layout import (
    IO_AREA_SIZE,
    MSG_HEADER_SIZE,
    RCV_PD,
    TASK2_PARAMETER,
    TASK2_STATE,
    TASK_STATE_SIZE,
)
from dpm.ledger import END, ledger_text
from dpm.message import LN_OFFSET
from dpm.tap import encode_frame
from firmware import session_writer
from firmware.process_image import ProcessImage

log = logging.getLogger(__name__)

DRAIN_S = 0.05
"""How often the writer drains the queue: the loop never wakes it."""
PIPE_BYTES = 1 << 20
"""The pipe to the writer: half a second of a mailbox loop's events (the default 64 KiB held a
third of a drain, and the drain thread waited for the writer in between)."""
PIECE = 256 * 1024
"""Bytes the drain takes out of the queue in one copy: about 25 us of the interpreter lock
(an exchange whose areas changed is 7 KiB)."""
LEDGER_BYTES = 128 * 96
"""The ledger's largest size (host_api.locks.LEDGER_MAX lines of libcif's longest)."""
LEDGER_FIRST_READ = 512
"""What the card reads of the ledger first: a dozen requests' lines; all of it only when
that was not all (the ledger's END is not in it). The read's buffer is allocated for each
message: 12 KiB each time cost the loop half a microsecond more than this. Only the ledger's
lines are queued (hosts end them with END in a file of 12 KiB of zeros)."""

_IO_END = RCV_PD + IO_AREA_SIZE
_HEAD_SIZE, _LN = MSG_HEADER_SIZE, LN_OFFSET
_STATE_END = TASK2_STATE + TASK_STATE_SIZE
_PARAMETER_END = TASK2_PARAMETER + s.PARAMETER_SIZE
_STARTS = fl.RESET | fl.INIT
_PDACK, _READY, _PDCOM = fl.PDACK, fl.READY, fl.PDCOM
_PUT, _ANSWER, _HOST_FLAGS, _DEV_FLAGS, _EXCHANGE = (
    s.SPOOL_CODES[kind] for kind in (s.PUT, s.ANSWER, s.HOST_FLAGS, s.DEV_FLAGS, s.EXCHANGE))
_put_head, _answer_head, _host_flags_head, _dev_flags_head, _exchange_head = (
    s.SPOOL_PUT.pack, s.SPOOL_ANSWER.pack, s.SPOOL_HOST_FLAGS.pack, s.SPOOL_DEV_FLAGS.pack,
    s.SPOOL_EXCHANGE.pack)
_dev_exchange_head = struct.Struct(s.SPOOL_DEV_FLAGS.format + s.SPOOL_EXCHANGE.format[1:]).pack
"""A DevFlags event and an exchange, back to back in the spool, packed at once [ours]."""
_piece_head, _frame_length = s.SPOOL_PIECE.pack, s.SPOOL_FRAME_LENGTH.pack
_monotonic = time.monotonic
_pread = os.pread
_join = b"".join


class SessionExistsError(FileExistsError):
    """The directory already holds a session: a recording never overwrites one."""


class Recorder:
    """One session being written; the hooks are called by the device loop's threads.

    Slots, module-level packers and a bound ``append`` for frames: each hook's attribute
    lookups are part of what every message and handshake of the card costs while it
    records."""

    __slots__ = (
        "_append_frame",
        "_child",
        "_dev",
        "_dev_before",
        "_dev_t",
        "_exchange",
        "_frames",
        "_held",
        "_image",
        "_image_files",
        "_ledger",
        "_ledger_name",
        "_mm",
        "_pipe",
        "_queue",
        "_stop",
        "_thread",
        "board",
        "complete",
        "events",
        "frames",
        "started_t",
        "started_wall",
    )

    def __init__(self, board: int, events: int, can_log: int | None, spool: int,
                 channel: str) -> None:
        """Start the writer on the open files ``events`` (session.jsonl), ``can_log``
        (None: no frames) and ``spool`` (read and written: where the writer keeps the
        events until the recording ends); the writer takes copies, the caller closes its
        own. ``start`` then connects the recorder to the card."""
        self.board = board
        self.started_t = time.monotonic()
        self.started_wall = time.time()
        fds = (events, spool) if can_log is None else (events, can_log, spool)
        self._child = subprocess.Popen(
            session_writer.command(events, can_log, spool, self.started_wall - self.started_t,
                                   channel, os.getpid()),
            pass_fds=fds, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            start_new_session=True)
        # a session of its own: a terminal's Ctrl-C is the firmware's to handle; the writer
        # ends at the end of its stdin, after the last batch
        assert self._child.stdin is not None
        self._pipe = self._child.stdin
        with contextlib.suppress(OSError):  # a drain's batch in one write, never a wait
            fcntl.fcntl(self._pipe.fileno(), fcntl.F_SETPIPE_SZ, PIPE_BYTES)
        self._image_files: CardDirectory | None = None
        self._ledger_name = ""
        self._ledger = -1
        self._mm: Any = None
        self._queue = bytearray()
        """The events packed (``dpm.session``'s spool layout), until the drain takes them."""
        self._frames: deque[tuple[can.Message, bool]] = deque()
        """Frames, apart from the events: they go to a file of their own (can.log)."""
        self._append_frame = self._frames.append
        self._dev = 0
        """DevFlags as last seen; a session takes them as 0 before its first dev_flags."""
        self._image: ProcessImage | None = None
        self._exchange: tuple[int, int] | None = None
        """The HostFlags change (PDACK) of this turn's exchange, until ``settle``."""
        self._dev_before = -1
        self._dev_t = 0.0
        """The host's PD toggle held for ``settle`` (``dev_flags``): DevFlags before it
        (-1: none held; after it: ``_dev``) and the turn's clock."""
        self._held = False
        """An exchange or a PD toggle is held: the one look of every other hook."""
        self.events = 0
        self.frames = 0
        """What the writer wrote: lines of session.jsonl, frames of can.log (``close``)."""
        self.complete = False
        """Whether ``close`` saw the writer write everything."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._write_loop, name="recorder", daemon=True)

    @classmethod
    def create(cls, session: Path, board: int, channel: str) -> Recorder:
        """``cifemu firmware --record``'s: the directory ``session`` and its files made
        here, with the image directory's rules (docs/security.md), before the card powers
        on (a refusal leaves no card up)."""
        files = CardDirectory(session, create=True)
        try:
            fds: list[int] = []
            try:
                for name in (s.EVENTS, s.CAN_LOG):
                    fds.append(files.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL))
                fds.append(files.open_unnamed())
            except FileExistsError:
                raise SessionExistsError(f"{session} already holds a session") from None
            finally:
                if len(fds) < 3:
                    for fd in fds:
                        os.close(fd)
            try:
                recorder = cls(board, fds[0], fds[1], fds[2], channel)
            finally:
                for fd in fds:
                    os.close(fd)
            files.replace(s.META, s.encode_meta(board, recorder.started_wall,
                                                recorder.started_t, os.getpid(), True).encode())
        finally:
            files.close()
        return recorder

    def start(self, image_files: CardDirectory, mm: Any, image: ProcessImage) -> None:
        """Record the card of ``mm``, whose directory ``image_files`` holds the ledger;
        ``image``: its process image (the next exchange is recorded with both areas: this
        session's writer has seen neither)."""
        self._image_files = image_files
        self._image = image
        image.exchanged_changes = True  # before the device loop calls a hook
        self._ledger_name = lock_path(image_files.path, self.board, "transaction").name
        self._mm = mm
        self._thread.start()

    # --- hooks (device loop, ``post`` and the controller's threads) ---------------------

    def put(self, raw: bytes, before: int, after: int) -> None:
        """``raw``: the message slot as the card copied it (the writer decodes it: a
        Message object costs microseconds to pass, bytes nothing); kept as far as its
        msg.ln reaches, a tenth of the slot for most messages, for the queue and the
        spool. ``before``, ``after``: the HostFlags change (DEVACK) that took it, in the
        same event."""
        if self._held:  # (the loop takes messages before it exchanges)
            self.settle()
        ledger = self._ledger
        if ledger < 0 and self._open_ledger():
            ledger = self._ledger
        lines = _pread(ledger, LEDGER_FIRST_READ, 0) if ledger >= 0 else b""
        end = lines.find(END)
        if end >= 0:
            lines = lines[:end]
        elif len(lines) == LEDGER_FIRST_READ:
            lines = ledger_text(_pread(self._ledger, LEDGER_BYTES, 0))
        msg = raw[: _HEAD_SIZE + raw[_LN]]
        self._queue += (_put_head(_PUT, _monotonic(), before, after, len(msg), len(lines))
                        + msg + lines)

    def answer(self, raw: bytes, before: int, after: int) -> None:
        """``raw``: the encoded answer, as the card writes it into PcMbx; ``before``,
        ``after``: the HostFlags change (HOSTCOM) that hands it over, in the same event."""
        if self._held:
            self.settle()
        self._queue += (_answer_head(_ANSWER, _monotonic(), before, after, len(raw)) + raw
                        + self._mm[TASK2_STATE:_STATE_END])

    def host_flags(self, before: int, after: int) -> None:
        if (before ^ after) & _PDACK and before & after & _READY:  # not a (re)start's
            self._exchange = (before, after)  # ``settle`` queues it, after the ring
            self._held = True
        elif before != after:
            if self._held:  # in the order the card wrote them
                self.settle()
            self._queue += _host_flags_head(_HOST_FLAGS, _monotonic(), before, after)

    def dev_flags(self, value: int, now: float) -> None:
        """``value`` as the card read it at the start of its turn at ``now`` (the loop's
        clock read: the event needs none of its own). The host's PD toggle alone is held
        until ``settle``, which queues it with the exchange it asked for in one packing and
        one append, both events' heads as the writer reads them [ours]; any other event
        of the turn queues it first."""
        before = self._dev
        if value != before:
            if self._held:
                self.settle()
            self._dev = value
            if value ^ before == _PDCOM:
                self._dev_t, self._dev_before, self._held = now, before, True
            elif value & ~before & _STARTS:
                self._queue += (_dev_flags_head(_DEV_FLAGS, now, before, value, 1)
                                + self._mm[TASK2_PARAMETER:_PARAMETER_END])
            else:
                self._queue += _dev_flags_head(_DEV_FLAGS, now, before, value, 0)

    def settle(self) -> None:
        """The turn's exchange and its PDACK toggle, one event, queued at the end of the
        turn, after the card rang its hosts (the device loop calls this after each turn).
        The areas are as the exchange left them: SndPd as the card took it
        (``ProcessImage.outputs``: the host may write the image's SndPd again as soon as
        it sees PDACK), RcvPd as the card wrote it (only the next exchange writes it);
        copied only when the process image says they may have changed
        (``ProcessImage.exchanged_changes``), else the writer gets no 7 KiB to compare."""
        if not self._held:
            return
        self._held = False
        dev_before, self._dev_before = self._dev_before, -1
        pending, self._exchange = self._exchange, None
        if pending is None:  # the PD toggle of a turn that did not exchange
            self._queue += _dev_flags_head(_DEV_FLAGS, self._dev_t, dev_before, self._dev, 0)
            return
        before, after = pending
        mm, image = self._mm, self._image
        assert image is not None  # hooks run only after start
        changed = image.exchanged_changes
        if dev_before < 0:
            head = _exchange_head(_EXCHANGE, _monotonic(), before, after, changed)
        else:
            head = _dev_exchange_head(_DEV_FLAGS, self._dev_t, dev_before, self._dev, 0,
                                      _EXCHANGE, _monotonic(), before, after, changed)
        if changed:
            image.exchanged_changes = False
            self._queue += _join((head, image.outputs, mm[RCV_PD:_IO_END],
                                  mm[TASK2_STATE:_STATE_END]))
        else:
            self._queue += head + mm[TASK2_STATE:_STATE_END]

    def frame(self, msg: can.Message, received: bool) -> None:
        """A frame the controller sent or received (any of its threads): queued as it is,
        encoded by the drain (a frame's datagram cost the receiving thread a microsecond,
        on the way from a node's TPDO to the input image). python-can makes a message per
        frame and nobody changes one afterwards."""
        self._append_frame((msg, received))

    def _open_ledger(self) -> bool:
        """Whether the ledger is open now: it cannot be until a host has locked the board
        (nobody to name until then; ``put`` tries again at each message)."""
        assert self._image_files is not None  # hooks run only after start
        try:
            self._ledger = self._image_files.open(self._ledger_name, os.O_RDONLY, own=False)
        except OSError:
            return False
        return True

    # --- the device loop's turn in C (firmware._mailbox) -------------------------------

    def native_record(self) -> tuple[Recorder, bytearray, int, int] | None:
        """What the device loop's turn in C needs to record the turns it serves as ``put``,
        ``answer`` and ``dev_flags`` do [ours]: this recorder (the C turn records only while
        it is the device's), the queue it appends the same packed events to, the ledger's
        descriptor and DevFlags as last seen. The C turn appends to this queue, in order
        with the hooks of the card's other threads, rather than keeping a stream of its own
        that the writer would have to merge (firmware/_mailbox.c says why). None: the
        Python turn records, while the ledger cannot be opened (``put`` reads no lines then
        and tries again at each message) or an exchange waits for ``settle``."""
        if self._held or (self._ledger < 0 and not self._open_ledger()):
            return None
        return self, self._queue, self._ledger, self._dev

    def native_recorded(self, dev: int) -> None:
        """DevFlags as the turns in C recorded them last (``native_record``'s, when they
        recorded none): the next ``dev_flags`` compares with them."""
        self._dev = dev

    # --- the writer --------------------------------------------------------------------

    def close(self) -> None:
        """Write what is queued and close the session (after the hooks' last call)."""
        self.settle()
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        try:
            self._drain()
            self._pipe.close()
        except OSError as exc:  # BrokenPipeError: the writer died
            log.error("the session writer is gone (%s)", exc)
        assert self._child.stdout is not None
        told = self._child.stdout.read().split()  # "EVENTS FRAMES" at its end
        self._child.stdout.close()
        if self._child.wait() == 0 and len(told) == 2:
            self.events, self.frames = int(told[0]), int(told[1])
            self.complete = True
        else:
            log.error("the session writer ended with status %d: the session is incomplete",
                      self._child.returncode)
        if self._ledger >= 0:
            os.close(self._ledger)
            self._ledger = -1

    def _write_loop(self) -> None:
        try:
            while not self._stop.wait(DRAIN_S):
                self._drain()
        except OSError as exc:  # the writer died: keep the loop's queue from growing
            log.error("the session writer is gone (%s); recording nothing more", exc)
            self._append_frame = deque[tuple[can.Message, bool]](maxlen=0).append
            queue = self._queue
            while not self._stop.wait(DRAIN_S):
                del queue[: len(queue)]

    def _drain(self) -> None:
        # What is queued now: whole events (each hook appends one in one operation);
        # hooks append behind it meanwhile. Each piece is copied out and then deleted from
        # the front (which only moves the bytearray's start), one operation each.
        queue, pipe = self._queue, self._pipe
        left = len(queue)
        while left:
            size = min(left, PIECE)
            piece = _piece_head(s.SPOOL_EVENTS, size) + queue[:size]  # one write, not two
            del queue[:size]
            left -= size
            pipe.write(piece)
        frames = self._frames
        if frames:
            # taken in one C loop, encoded here: off the controller's threads
            data = _join([_frame_length(len(datagram)) + datagram for datagram in (
                encode_frame(msg, received)
                for msg, received in map(call, repeat(frames.popleft, len(frames))))])
            pipe.write(_piece_head(s.SPOOL_FRAMES, len(data)) + data)
        pipe.flush()
