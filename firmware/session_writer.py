"""The recorder's child process: turns the card's event batches into session.jsonl [ours].

``firmware.recorder`` hands it batches through its stdin, each a 4-byte little-endian
length and a pickled list of event tuples; pickle, because both ends are the same
firmware and the pipe is theirs alone (nothing else can write to it). Here, out of the
firmware's process, each event becomes a ``dpm.session.Record``: the pid of a put's
host from the ledger bytes the card read, an answer's pid from its request, an
exchange's changed bytes from the snapshots, each line encoded and written to the
file descriptor given as the one argument. At the end of its stdin it exits.

    python -m firmware.session_writer FD
"""

from __future__ import annotations

import os
import pickle
import sys
from typing import Any, BinaryIO

from dpm import session as s
from dpm.layout import IO_AREA_SIZE, RCV_PD, SND_PD
from dpm.message import Ext, Message

_IO_END = RCV_PD + IO_AREA_SIZE

NICE = 10
"""The writer yields the processor to the card and its hosts: on a busy machine it falls
behind (the firmware's queue grows), it never slows the card's answers down."""


class Events:
    """What the card's event tuples become; state carried from one event to the next."""

    def __init__(self) -> None:
        self._io = bytes(_IO_END - SND_PD)
        self._pending: dict[tuple[int, int, int, int], int] = {}
        """Puts awaiting their answers: (nr, b, rx, tx) -> pid."""

    def record(self, item: tuple[Any, ...]) -> s.Record:
        kind, t, wall = item[0], item[1], item[2]
        if kind == s.PUT:
            msg = Message.decode(item[3])
            pid = s.ledger_pid(item[4], msg)
            if pid is not None:
                self._pending[(msg.nr, msg.b, msg.rx, msg.tx)] = pid
            return s.Record(kind, t, wall, pid, msg=msg)
        if kind == s.ANSWER:
            msg = Message.decode(item[3])
            key = (msg.nr, msg.a, msg.tx, msg.rx)
            pid = self._pending.get(key)
            more = msg.f == 0 and msg.e & Ext.SEQ_MASK in (Ext.FIRST, Ext.CONT)
            if pid is not None and not more:  # a long upload's parts share their request
                del self._pending[key]
            return s.Record(kind, t, wall, pid, msg=msg, state=bytes(item[4]))
        if kind == s.EXCHANGE:
            io: bytes | None = item[3]
            if io is None:  # the card saw the areas unchanged
                return s.Record(kind, t, wall, state=bytes(item[4]))
            old = self._io
            self._io = io
            changes = {area: s.changed_runs(old[start : start + IO_AREA_SIZE],
                                            io[start : start + IO_AREA_SIZE])
                       for area, start in zip(s.AREAS, (SND_PD, RCV_PD - SND_PD), strict=True)}
            return s.Record(kind, t, wall, changes={a: r for a, r in changes.items() if r},
                            state=bytes(item[4]))
        if kind == s.DEV_FLAGS:
            return s.Record(kind, t, wall, before=max(item[3], 0), after=item[4],
                            parameter=bytes(item[5]))
        return s.Record(kind, t, wall, before=item[3], after=item[4])


def batches(stream: BinaryIO) -> Any:
    """Each batch of the stream until its end."""
    while True:
        head = stream.read(s.BATCH_FRAME.size)
        if len(head) < s.BATCH_FRAME.size:
            return
        (size,) = s.BATCH_FRAME.unpack(head)
        yield pickle.loads(stream.read(size))


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    os.nice(NICE)
    events = Events()
    with os.fdopen(int(args[0]), "w", encoding="ascii") as out:
        for batch in batches(sys.stdin.buffer):
            out.writelines(s.encode_record(events.record(item)) + "\n" for item in batch)
            out.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
