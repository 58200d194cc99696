"""The spool between the recording card and its writer (dpm.session's SPOOL_* layouts) reads
back as written: every event kind, cut into pieces anywhere (firmware/session_writer.py).

The events are packed here by the documented layout, as firmware/recorder.py packs them, and
come out as session.jsonl lines, which dpm.session's codec reads back: the test holds the
spool's format and the lines' format, not the writer's inner tuples.
"""

from __future__ import annotations

import io
import itertools
from dataclasses import dataclass

from hypothesis import given, settings
from hypothesis import strategies as st

from dpm import session as s
from dpm.layout import IO_AREA_SIZE, TASK_STATE_SIZE
from dpm.message import Message
from firmware.session_writer import Events, batches

WALL_OFFSET = 1_700_000_000.0
"""Unix time minus CLOCK_MONOTONIC: the writer adds it to each event's ``t``."""


@dataclass(frozen=True)
class Spooled:
    """One event: its spool bytes and what its lines must say."""

    kind: str
    t: float
    before: int
    after: int
    msg: Message | None = None
    state: bytes = b""
    parameter: bytes = b""
    io: bytes | None = None
    """EXCHANGE: SndPd and RcvPd, or None when the card saw them unchanged."""

    def pack(self) -> bytes:
        code = s.SPOOL_CODES[self.kind]
        head = (code, self.t, self.before, self.after)
        if self.kind == s.PUT:
            assert self.msg is not None
            raw = self.msg.encode()
            return s.SPOOL_PUT.pack(*head, len(raw), 0) + raw  # no ledger lines
        if self.kind == s.ANSWER:
            assert self.msg is not None
            raw = self.msg.encode()
            return s.SPOOL_ANSWER.pack(*head, len(raw)) + raw + self.state
        if self.kind == s.HOST_FLAGS:
            return s.SPOOL_HOST_FLAGS.pack(*head)
        if self.kind == s.DEV_FLAGS:
            return s.SPOOL_DEV_FLAGS.pack(*head, 1 if self.parameter else 0) + self.parameter
        changed = self.io is not None
        return (s.SPOOL_EXCHANGE.pack(*head, changed) + (self.io or b"") + self.state)


def _image(runs: list[tuple[int, bytes]]) -> bytes:
    image = bytearray(2 * IO_AREA_SIZE)
    for offset, data in runs:
        image[offset : offset + len(data)] = data[: len(image) - offset]
    return bytes(image)


_byte = st.integers(0, 255)
_t = st.integers(0, 10**12).map(lambda us: us / 1e6)  # what the lines' 6 decimals keep
_message = st.builds(Message, rx=_byte, tx=_byte, b=_byte, data=st.binary(max_size=255),
                     nr=_byte, a=_byte, f=_byte, e=_byte)
_state = st.binary(min_size=TASK_STATE_SIZE, max_size=TASK_STATE_SIZE)
_io = st.lists(st.tuples(st.integers(0, 2 * IO_AREA_SIZE - 1), st.binary(min_size=1,
                                                                        max_size=8)),
               max_size=4).map(_image)


_event = st.one_of(
    st.builds(Spooled, st.just(s.PUT), _t, _byte, _byte, msg=_message),
    st.builds(Spooled, st.just(s.ANSWER), _t, _byte, _byte, msg=_message, state=_state),
    st.builds(Spooled, st.just(s.HOST_FLAGS), _t, _byte, _byte),
    st.builds(Spooled, st.just(s.DEV_FLAGS), _t, _byte, _byte,
              parameter=st.one_of(st.just(b""), st.binary(min_size=s.PARAMETER_SIZE,
                                                          max_size=s.PARAMETER_SIZE))),
    st.builds(Spooled, st.just(s.EXCHANGE), _t, _byte, _byte, state=_state,
              io=st.one_of(st.none(), _io)),
)


def _spool(stream: bytes, cuts: list[int], frames: list[bytes]) -> bytes:
    """The events' byte stream in pieces cut at ``cuts``, a frames' piece after the first."""
    bounds = [0, *sorted({c % (len(stream) + 1) for c in cuts}), len(stream)]
    out = b""
    for number, (start, end) in enumerate(itertools.pairwise(bounds)):
        out += s.SPOOL_PIECE.pack(s.SPOOL_EVENTS, end - start) + stream[start:end]
        if number == 0 and frames:
            data = b"".join(s.SPOOL_FRAME_LENGTH.pack(len(f)) + f for f in frames)
            out += s.SPOOL_PIECE.pack(s.SPOOL_FRAMES, len(data)) + data
    return out


def _expected(event: Spooled, io: bytearray) -> list[s.Record]:
    """The records of one event's lines, in the writer's order."""
    wall = round(event.t + WALL_OFFSET, 6)
    flags = s.Record(s.HOST_FLAGS, event.t, wall, before=event.before, after=event.after)
    if event.kind == s.PUT:
        return [flags, s.Record(s.PUT, event.t, wall, msg=event.msg)]
    if event.kind == s.ANSWER:
        return [s.Record(s.ANSWER, event.t, wall, msg=event.msg, state=event.state), flags]
    if event.kind in (s.HOST_FLAGS, s.DEV_FLAGS):
        return [s.Record(event.kind, event.t, wall, before=event.before, after=event.after,
                         parameter=event.parameter)]
    changes: dict[str, s.Runs] = {}
    if event.io is not None:
        for area, start in zip(s.AREAS, (0, IO_AREA_SIZE), strict=True):
            runs = s.changed_runs(bytes(io[start : start + IO_AREA_SIZE]),
                                  event.io[start : start + IO_AREA_SIZE])
            if runs:
                changes[area] = runs
        io[:] = event.io
    return [flags, s.Record(s.EXCHANGE, event.t, wall, changes=changes, state=event.state)]


@settings(max_examples=300, deadline=None)
@given(st.lists(_event, min_size=1, max_size=12), st.lists(st.integers(0, 10**6), max_size=6),
       st.lists(st.binary(min_size=1, max_size=16), max_size=2))
def test_every_event_kind_reads_back_as_written_in_pieces_cut_anywhere(
        spooled: list[Spooled], cuts: list[int], frames: list[bytes]) -> None:
    stream = b"".join(event.pack() for event in spooled)
    events = Events(WALL_OFFSET)
    lines, got_frames = [], []
    for batch in batches(io.BytesIO(_spool(stream, cuts, frames))):
        for item in batch:
            if item[0] == s.CAN_FRAME:
                got_frames.append(item[1])
            else:
                lines += events.lines(item)
    image = bytearray(2 * IO_AREA_SIZE)
    expected = [record for event in spooled for record in _expected(event, image)]
    got = [s.decode_record(line) for line in lines]
    for record in got:
        record.wall = round(record.wall, 6)
    assert got == expected
    assert got_frames == frames


def test_a_spool_cut_inside_an_event_keeps_the_whole_events_before_it() -> None:
    """A firmware killed in the middle of a write: the events before the cut count, the
    one it cut is the loss docs/recording.md names."""
    whole = Spooled(s.HOST_FLAGS, 1.0, 0, 8).pack()
    cut = Spooled(s.ANSWER, 2.0, 8, 9, msg=Message(3, 16, 74, b"abc"), state=bytes(64)).pack()
    data = whole + cut[:-1]
    spool = s.SPOOL_PIECE.pack(s.SPOOL_EVENTS, len(data) + 10) + data  # the piece is short
    assert [len(batch) for batch in batches(io.BytesIO(spool))] == [1]
