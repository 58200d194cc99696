"""The recorder's child process: turns the card's event batches into session.jsonl [ours].

``firmware.recorder`` hands it the events through its stdin, packed (``dpm.session``'s
spool layout: pieces of the events' byte stream and of the frames), and the pipe is
theirs alone (nothing else can write to it).

While the card records, the writer only moves what comes into the spool, a file without
a name in the session's directory (``os.splice``: the kernel copies, the writer hardly
runs), in a bare interpreter (``SPOOLER``, ``python -S``: it starts in milliseconds,
where importing this module and numpy took a third of a second of the processor the card
needed right then). At the end of its stdin, when the recording ends, that process
becomes this module (``os.execv``), which reads the spool back and encodes: each event
becomes a line of ``session.jsonl`` (``dpm.session``'s codec), or two where the card
queued a HostFlags change with its message or exchange, the pid of a put's host
from the ledger bytes the card read, an answer's pid from its request, an exchange's
changed bytes from the snapshots, the Unix time from the monotonic one; frames go to
``can.log`` in candump's format (python-can's ``CanutilsLogWriter``). Then it prints how
many lines and frames it wrote, and exits.
Encoding as the events came cost a third of a core on a mailbox loop, taken from the
card and its hosts on a two-core machine; after the recording it costs the same, but
nobody waits for an answer meanwhile.

The messages of the firmware's own host (``cifemu firmware --configure``, whose ledger
lines carry the firmware's pid) are left out [ours]: it stands for a card that comes
configured, not for a host, and a replay against a card started the same way must not
configure it a second time.

    python -S -c SPOOLER EVENTS_FD CAN_LOG_FD SPOOL_FD WALL_OFFSET CHANNEL FIRMWARE_PID
    (then) python -m firmware.session_writer EVENTS_FD ... FIRMWARE_PID

The descriptors are open files (CAN_LOG_FD -1: no frames recorded; SPOOL_FD open for
reading and writing): the firmware's own, or the ones a user's ``cifemu record`` opened
and passed to the card (firmware/record_socket.py).
"""

from __future__ import annotations

import os
import sys
from typing import Any, BinaryIO, TextIO

from dpm import session as s
from dpm.layout import IO_AREA_SIZE, RCV_PD, SND_PD
from dpm.message import HEADER, Ext

_IO_END = RCV_PD + IO_AREA_SIZE
_MORE = (Ext.FIRST, Ext.CONT)

NICE = 10
"""The writer yields the processor to the card and its hosts: on a busy machine it falls
behind (the firmware's queue grows), it never slows the card's answers down."""


class Events:
    """What the card's event tuples become; state carried from one event to the next."""

    def __init__(self, wall_offset: float, firmware_pid: int = 0) -> None:
        self._firmware = firmware_pid
        self._wall = wall_offset
        """Unix time minus CLOCK_MONOTONIC when the recording started: the card reads one
        clock per event, the writer derives the other."""
        self._io = bytes(_IO_END - SND_PD)
        self._pending: dict[tuple[int, int, int, int], int] = {}
        """Puts awaiting their answers: (nr, b, rx, tx) -> pid."""

    def lines(self, item: tuple[Any, ...]) -> list[str]:
        """The ``session.jsonl`` lines (without their newlines) of one event tuple: none
        for a message of the firmware's own host, two for an exchange."""
        kind, t, before, after, *tails = item
        wall = t + self._wall
        if kind == s.PUT:
            raw, ledger = tails
            rx, tx, _, nr, _, _, b, _ = HEADER.unpack_from(raw)
            pid = s.request_pid(ledger, nr, b, rx, tx) if ledger else None
            if pid is not None:
                self._pending[(nr, b, rx, tx)] = pid
            taken = s.encode_flags(s.HOST_FLAGS, t, wall, before, after)  # DEVACK
            if pid == self._firmware:
                return [taken]
            return [taken, s.encode_message(kind, t, wall, pid, raw)]
        if kind == s.ANSWER:
            raw, state = tails
            rx, tx, _, nr, a, f, _, e = HEADER.unpack_from(raw)
            key = (nr, a, tx, rx)
            pid = self._pending.get(key)
            more = f == 0 and e & Ext.SEQ_MASK in _MORE
            if pid is not None and not more:  # a long upload's parts share their request
                del self._pending[key]
            handed = s.encode_flags(s.HOST_FLAGS, t, wall, before, after)  # HOSTCOM
            if pid == self._firmware:
                return [handed]
            return [s.encode_message(kind, t, wall, pid, raw, state), handed]
        if kind in (s.HOST_FLAGS, s.DEV_FLAGS):  # DEV_FLAGS: Task2Parameter, or b""
            return [s.encode_flags(kind, t, wall, before, after, *tails)]
        # the HostFlags change that made the exchange, then the exchange
        return [s.encode_flags(s.HOST_FLAGS, t, wall, before, after),
                s.encode_record(self._exchange(t, wall, *tails))]

    def _exchange(self, t: float, wall: float, io: bytes, state: bytes) -> s.Record:
        if not io:  # the card saw the areas unchanged
            return s.Record(s.EXCHANGE, t, wall, state=state)
        old = self._io
        self._io = io
        changes = {area: s.changed_runs(old[start : start + IO_AREA_SIZE],
                                        io[start : start + IO_AREA_SIZE])
                   for area, start in zip(s.AREAS, (SND_PD, RCV_PD - SND_PD), strict=True)}
        return s.Record(s.EXCHANGE, t, wall, changes={a: r for a, r in changes.items() if r},
                        state=state)


class Frames:
    """``can.log``: the frames in candump's log format, as python-can writes it."""

    def __init__(self, out: TextIO, channel: str) -> None:
        from can.io import CanutilsLogWriter  # here: a session without frames needs no can

        from dpm.tap import decode_frame

        self._decode = decode_frame
        self._channel = channel
        self._writer = CanutilsLogWriter(out, channel=channel)
        self.written = 0

    def write(self, datagram: bytes) -> None:
        msg, _ = self._decode(datagram, self._channel)
        self._writer.on_message_received(msg)
        self.written += 1


def events(data: bytes) -> tuple[list[tuple[Any, ...]], int]:
    """The whole events at the start of the spooled stream ``data`` as the tuples ``Events``
    takes, ``(kind, t, before, after, *tails)`` (``dpm.session.SPOOL_LAYOUTS``), and how many
    bytes they were (the rest begins an event the next piece ends)."""
    items: list[tuple[Any, ...]] = []
    at, end = 0, len(data)
    while at < end:
        layout = s.SPOOL_LAYOUTS.get(data[at])
        if layout is None:
            raise ValueError(f"spool: unknown event code {data[at]} at byte {at} of a piece")
        stop = at + layout.head.size
        if stop > end:
            break
        _, t, before, after, *fields = layout.head.unpack_from(data, at)
        tails = []
        for length in layout.tails(*fields):
            tails.append(data[stop : stop + length])
            stop += length
        if stop > end:
            break
        items.append((layout.kind, t, before, after, *tails))
        at = stop
    return items, at


def batches(stream: BinaryIO) -> Any:
    """The spool's events and frames, piece by piece until its end: lists of ``Events``'
    tuples and of ``(CAN_FRAME, datagram)``. A firmware killed in the middle of a write
    leaves a piece cut short: its whole events and frames count, the rest is the loss
    docs/recording.md names (what the card had queued)."""
    carried = b""
    length_size = s.SPOOL_FRAME_LENGTH.size
    while True:
        head = stream.read(s.SPOOL_PIECE.size)
        if len(head) < s.SPOOL_PIECE.size:
            return
        what, size = s.SPOOL_PIECE.unpack(head)
        data = stream.read(size)
        short = len(data) < size
        if what == s.SPOOL_EVENTS:
            data = carried + data
            items, used = events(data)
            carried = data[used:]
            yield items
        else:
            frames, at = [], 0
            while at + length_size <= len(data):
                (length,) = s.SPOOL_FRAME_LENGTH.unpack_from(data, at)
                at += length_size + length
                if at > len(data):
                    break
                frames.append((s.CAN_FRAME, data[at - length : at]))
            yield frames
        if short:
            return


SPOOLER = f"""import os, sys
os.nice({NICE})
while os.splice(0, int(sys.argv[3]), 1 << 20):
    pass
os.execv(sys.executable, [sys.executable, "-m", "firmware.session_writer", *sys.argv[1:]])
"""
"""The writer's first part: stdin (the card's batches) to the spool until its end, then
this module. Every descriptor stays open across the exec."""


def command(events: int, can_log: int | None, spool: int, wall_offset: float, channel: str,
            firmware_pid: int) -> list[str]:
    """The writer's command line (``firmware.recorder`` starts it)."""
    return [sys.executable, "-S", "-c", SPOOLER, str(events),
            str(-1 if can_log is None else can_log), str(spool), repr(wall_offset), channel,
            str(firmware_pid)]


def main(argv: list[str] | None = None) -> int:
    events_fd, can_fd, spool_fd, wall_offset, channel, firmware_pid = (
        sys.argv[1:] if argv is None else argv)
    events = Events(float(wall_offset), int(firmware_pid))
    can_out = os.fdopen(int(can_fd), "w", encoding="ascii") if int(can_fd) >= 0 else None
    frames = Frames(can_out, channel) if can_out is not None else None
    os.lseek(int(spool_fd), 0, os.SEEK_SET)
    written = 0
    with os.fdopen(int(spool_fd), "rb") as stored, \
            os.fdopen(int(events_fd), "w", encoding="ascii") as out:
        for batch in batches(stored):
            lines = []
            for item in batch:
                if item[0] == s.CAN_FRAME:
                    if frames is not None:
                        frames.write(item[1])
                else:
                    lines += [line + "\n" for line in events.lines(item)]
            out.writelines(lines)
            written += len(lines)
    if can_out is not None:
        can_out.close()
    print(written, frames.written if frames is not None else 0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
