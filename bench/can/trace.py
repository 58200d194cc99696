"""The card's candump trace, read back: every frame's time stamp and identifier."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

TRACE_RECORD = re.compile(rb"\((\d+\.\d{6})\) \S+ ([0-9A-F]{3,8})#")
"""One candump record's time stamp and identifier, wherever it starts in a line."""
TRACE_LINE = re.compile(rb"\(\d+\.\d{6}\) \S+ [0-9A-F]{3,8}#[0-9A-FR]*( [RT])?")


@dataclass(slots=True)
class Trace:
    """The frames of a candump-format trace, sorted by time."""

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

