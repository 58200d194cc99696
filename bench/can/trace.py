"""The frames a phase put on the bus, by time stamp and identifier: read from outside the card.

On ``shm`` the channel's rings are copied by a ``ChannelWatch`` in the benchmark's own
process, which costs the card nothing; elsewhere (SocketCAN) the card's candump trace is
read back, which costs the card about 2 us of CPU per frame in each direction.
"""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import numpy as np
import numpy.typing as npt

from firmware.shm.station import CAPACITY
from firmware.shm.watch import ChannelWatch

TRACE_RECORD = re.compile(rb"\((\d+\.\d{6})\) \S+ ([0-9A-F]{3,8})#")
"""One candump record's time stamp and identifier, wherever it starts in a line."""
TRACE_LINE = re.compile(rb"\(\d+\.\d{6}\) \S+ [0-9A-F]{3,8}#[0-9A-FR]*( [RT])?")


WATCH_POLL_S = 0.05
"""How often ``BusWatch`` copies the rings: a ring holds ``CAPACITY`` (8,192) frames of one
station, about 0.3 s of the card's RPDOs at 30,000 frames/s, so a poll may come 6 times
late before a frame is missed (and ``missed`` says so)."""


@dataclass(slots=True)
class Trace:
    """The frames of a candump-format trace or of a ``BusWatch``, sorted by time."""

    stamps: npt.NDArray[np.float64]
    idents: npt.NDArray[np.int64]
    lines: int
    damaged_lines: int
    """Lines that are not exactly one record (records written over each other)."""
    duplicates: int
    """Records found twice in the damage (same time stamp and identifier), counted once."""


def read_trace(path: Path) -> Trace:
    """Every record of a trace, also those inside damaged lines; exact duplicates once.

    The card writes its trace from several threads (the receive thread, and each
    thread that sends); records can land inside one another, so records are
    searched anywhere in a line rather than one per line.
    """
    raw = path.read_bytes()
    lines = raw.splitlines()
    damaged = sum(1 for line in lines if not TRACE_LINE.fullmatch(line))
    seen: set[tuple[bytes, bytes]] = set()
    records: list[tuple[float, int]] = []
    duplicates = 0
    for match in TRACE_RECORD.finditer(raw):
        key = (match.group(1), match.group(2))
        if key in seen:
            duplicates += 1
            continue
        seen.add(key)
        records.append((float(match.group(1)), int(match.group(2), 16)))
    records.sort()
    stamps = np.array([r[0] for r in records], dtype=np.float64)
    idents = np.array([r[1] for r in records], dtype=np.int64)
    return Trace(stamps, idents, len(lines), damaged, duplicates)


def count_frames(trace: Trace, low: int, high: int, since: float, until: float) -> int:
    """Frames with ``low <= identifier < high`` stamped within ``[since, until]``."""
    idents, stamps = trace.idents, trace.stamps
    mask = (idents >= low) & (idents < high) & (stamps >= since) & (stamps <= until)
    return int(np.count_nonzero(mask))



class BusWatch:
    """A thread of this process that copies an ``shm`` channel's frames, for ``Trace``.

    Nothing in the card or the nodes changes: no station is opened, so no writer rings
    it. The cost is this process's own, kept in ``summary()`` (the thread's CPU time).
    """

    def __init__(self, channel: str) -> None:
        self._watch = ChannelWatch(channel)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bus watch", daemon=True)
        self._cpu_s = 0.0
        self._polls = 0

    def __enter__(self) -> BusWatch:
        self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        start = time.thread_time()
        while not self._stop.wait(WATCH_POLL_S):
            self._watch.poll()
            self._polls += 1
        self._watch.poll()
        self._cpu_s = time.thread_time() - start

    def trace(self) -> Trace:
        """The frames copied, once the watch has ended."""
        frames = self._watch.frames()
        return Trace(frames["stamp"].astype(np.float64), frames["ident"].astype(np.int64),
                     len(frames), 0, 0)

    def summary(self) -> dict[str, float | int]:
        """What the watch copied and missed, and its cost, once it has ended."""
        return {"frames_missed": self._watch.missed, "polls": self._polls,
                "cpu_s": round(self._cpu_s, 3), "ring_frames_per_station": CAPACITY}

    def close(self) -> None:
        self._watch.close()
