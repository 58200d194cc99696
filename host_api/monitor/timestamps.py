"""candump's time stamps for ``cifemu monitor -t``: absolute, delta, zero-based, with date.

The four forms of can-utils' candump (``-t a|d|z|A``), so a trace reads and diffs like
one: ``(1345212884.318850)``, ``(000.001234)`` since the previous frame, ``(012.345678)``
since the first, ``(2012-08-17 16:14:44.318850)`` in local time. The first frame's delta
is 0, as candump's is.
"""

from __future__ import annotations

import time

FORMATS = ("a", "d", "z", "A")
"""absolute, delta, zero-based, absolute with date (candump -t)."""


class Stamps:
    """The time stamp of each frame in one of ``FORMATS``, frame after frame."""

    def __init__(self, form: str) -> None:
        if form not in FORMATS:
            raise ValueError(f"time stamp format {form!r}: one of {', '.join(FORMATS)}")
        self.form = form
        self._first: float | None = None
        self._previous: float | None = None

    def stamp(self, when: float) -> str:
        first = self._first = when if self._first is None else self._first
        previous = when if self._previous is None else self._previous
        self._previous = when
        if self.form == "a":
            return f"({when:.6f})"
        if self.form == "A":
            seconds, micro = divmod(round(when * 1e6), 1_000_000)
            return f"({time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(seconds))}.{micro:06d})"
        span = max(0.0, when - (previous if self.form == "d" else first))
        seconds, micro = divmod(round(span * 1e6), 1_000_000)
        return f"({seconds:03d}.{micro:06d})"
