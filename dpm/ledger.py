"""The transaction ledger's line format, shared by every host and by the card [ours].

A host holds a board's transaction lock (``board<N>.transaction.lock``) from a request until
its answer; the lock file lists the requests whose answers are awaited, one line each:
``pid owner nr b rx tx multi sent_ms`` (decimal, space-separated; owner a random number per
process and board, multi 0 to 2, sent_ms CLOCK_MONOTONIC in milliseconds). host_api and libcif
(libcif/src/chanlock.c) write it; the card's recorder reads it to name a message's host.
The format lives here, apart from the locking (``host_api.locks``), so both sides read one
definition.

[ours] The ledger ends at the file's end or at its first NUL byte (``END``), whichever comes
first. host_api and libcif end it with a NUL, in the same write as the lines, instead of
truncating the file: on the tmpfs under the image, emptying a file frees its page and the
next request allocates one again, twice the cost of the write itself, and the truncation
is a system call more, on every mailbox round trip. Every reader stops at the NUL
(``ledger_text``).
"""

from __future__ import annotations

from typing import NamedTuple


class LedgerLine(NamedTuple):
    pid: int
    owner: int
    nr: int
    b: int
    rx: int
    tx: int
    multi: int
    """0: one answer ends it; 1 before a long upload's first part, 2 after it."""
    sent_ms: int

    def encode(self) -> str:
        return LINE % self


LINE = "%d %d %d %d %d %d %d %d\n"
"""One ledger line, formatted from its eight fields in ``LedgerLine``'s order."""

END = b"\0"
"""Where the ledger ends when the file goes on: what follows is left from a longer one."""


def ledger_text(raw: bytes) -> bytes:
    """The ledger's lines in the file's bytes ``raw``: up to ``END`` or the end."""
    return raw.partition(END)[0]


def decode_line(line: str | bytes) -> LedgerLine | None:
    """One ledger line, or None when it is malformed: a host may die mid-write, and any
    local user who may take the lock may write the file, so nothing in it is trusted."""
    text = line.decode("ascii", "replace") if isinstance(line, bytes) else line
    fields = text.split()
    if len(fields) != 8 or not all(f.lstrip("-").isdigit() for f in fields):
        return None
    entry = LedgerLine(*(int(f) for f in fields))
    if not all(0 <= v <= 255 for v in (entry.nr, entry.b, entry.rx, entry.tx)):
        return None
    if entry.multi not in (0, 1, 2):
        return None
    return entry
