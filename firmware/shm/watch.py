"""``ChannelWatch``: every frame on a ``shm`` channel, read from its rings by a benchmark
or a test without opening a station [ours].

Apart from ``firmware.shm.bus`` because it needs numpy (a structured array of time stamps
and identifiers, sorted): imported there, numpy cost every process that opens a station
(the card, ``cifemu sim``) 0.3 s of CPU at its start, for a tool only the benchmarks and
tests use.
"""

from __future__ import annotations

import mmap
import os
from typing import Any

import numpy as np
import numpy.typing as npt

from firmware.shm.station import (
    CAPACITY,
    FILE_SIZE,
    MAX_STATIONS,
    RECORD_SIZE,
    RING_BYTES,
    RINGS_AT,
    SEQS_AT,
    channel_path,
    copy_records,
)

FRAME_STAMP_ID = np.dtype({"names": ["stamp", "ident"], "formats": ["<f8", "<u4"],
                           "offsets": [0, 8], "itemsize": RECORD_SIZE})
"""The time stamp (s, ``time.time()`` of the sender) and identifier of a ring's record."""


class ChannelWatch:
    """Every frame on a channel, copied from the rings without opening a station [ours].

    Why: a benchmark that must count a card's frames by identifier and time (a loss
    check) would otherwise trace them in the card, which costs the card CPU per frame,
    or open a station, which every writer then rings (a system call per frame in the
    processes being measured). This maps the file read-only and copies what is new
    when asked; the writers never learn it exists. Each ``poll`` must come before
    any station wrote a whole ring (``CAPACITY`` records) more: what a ring overwrote
    first is counted in ``missed``, never returned.
    """

    def __init__(self, channel: str) -> None:
        fd = os.open(channel_path(channel), os.O_RDONLY)
        try:
            self._map = mmap.mmap(fd, FILE_SIZE, access=mmap.ACCESS_READ)
        finally:
            os.close(fd)
        self._seqs: npt.NDArray[np.uint64] = np.ndarray(
            (MAX_STATIONS,), np.uint64, buffer=self._map, offset=SEQS_AT)
        self._cursors = self._seqs.copy()
        """Per station: the records copied so far; frames before the watch began are not."""
        self._raw: list[bytes] = []
        self.missed = 0
        """Records overwritten before a ``poll`` copied them."""

    def poll(self) -> int:
        """Copy every record written since the last poll; returns how many."""
        copied = 0
        seqs, cursors = self._seqs, self._cursors
        for station in np.flatnonzero(seqs != cursors).tolist():
            cursor, seq = int(cursors[station]), int(seqs[station])
            first = max(cursor, seq - CAPACITY)
            raw = copy_records(self._map, RINGS_AT + station * RING_BYTES, first, seq)
            overwritten = int(seqs[station]) - CAPACITY - first  # meanwhile, by the writer
            if overwritten > 0:
                raw = raw[overwritten * RECORD_SIZE:]
                first += overwritten
            self.missed += first - cursor
            cursors[station] = seq
            self._raw.append(raw)
            copied += seq - first
        return copied

    def frames(self) -> npt.NDArray[Any]:
        """Every frame copied so far (``FRAME_STAMP_ID`` records), sorted by time stamp."""
        frames = np.frombuffer(b"".join(self._raw), dtype=FRAME_STAMP_ID)
        return np.sort(frames, order="stamp")

    def close(self) -> None:
        del self._seqs  # a numpy view pins the mapping
        self._map.close()
