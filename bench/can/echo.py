"""The closed PDO loop the throughput and SYNC phases drive through the card."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from bench.can.card import (
    TIMEOUT_MS,
)
from bench.common import (
    latency_stats,
)
from host_api.driver import (
    DevExchangeIO,
)

HOST_IDLE_S = 0.0002
"""The host's pause after a poll that found no echo: a polling host must not take a
core from the card and the nodes (the machine has two)."""
STALL_S = 0.5
"""Echoes slower than this are counted apart (late, not lost)."""
DRAIN_S = 2.0
"""After a window, how long the values in flight may take before they count as lost."""

U64 = npt.NDArray[np.uint64]

@dataclass(slots=True)
class EchoWindow:
    """One closed-loop window: every value written is verified back at the input."""

    active: int
    seconds: float
    verified_timed: int = 0
    """Values verified before the window's end."""
    verified_total: int = 0
    """... and while the values in flight at the end drained."""
    lost: int = 0
    """Values never seen at the input, DRAIN_S after the window's end."""
    exchange_errors: int = 0
    host_loops: int = 0
    wall_start: float = 0.0
    wall_end: float = 0.0
    wall_drained: float = 0.0
    elapsed_s: float = 0.0
    echo_s: list[npt.NDArray[np.float64]] = field(default_factory=list)
    """Seconds from writing each value to seeing it at the input."""
    trace: dict[str, Any] = field(default_factory=dict)

    @property
    def echoes_per_s(self) -> float:
        return self.verified_timed / self.elapsed_s if self.elapsed_s else 0.0

    def summary(self) -> dict[str, Any]:
        echo = np.concatenate(self.echo_s) if self.echo_s else np.zeros(0)
        result: dict[str, Any] = {
            "active_nodes": self.active,
            "seconds": round(self.elapsed_s, 3),
            "verified_echoes": self.verified_timed,
            "verified_echoes_per_s": round(self.echoes_per_s, 1),
            "pdo_frames_per_s": round(2 * self.echoes_per_s, 1),
            "lost": self.lost,
            f"echoes_slower_than_{STALL_S}_s": int(np.count_nonzero(echo > STALL_S)),
            "echo_latency_us": latency_stats([int(x) for x in echo * 1e9]),
            "exchange_errors": self.exchange_errors,
            "host_polls": self.host_loops,
        }
        if self.trace:
            result["trace"] = self.trace
        return result


def echo_window(board: int, values: U64, active: int, seconds: float, out_offset: int,
                in_offset: int,
                record: Callable[[npt.NDArray[np.float64]], object] | None = None) -> EchoWindow:
    """Drive ``active`` nodes' loops for ``seconds``, then let the values in flight drain.

    ``values`` holds every node's current output value (u64, little endian) and is
    advanced in place, so the next window starts from values the nodes have not seen.
    A value never comes back twice and is never replaced before it came back, so a
    value still missing ``DRAIN_S`` after the window is lost (and its node stalled).
    ``record`` takes the loop times instead of ``EchoWindow.echo_s`` (the soak's
    histogram, which does not grow).
    """
    window = EchoWindow(active, seconds)
    size = 8 * active
    out = values[:active]
    out += np.uint64(1)
    pending = np.ones(active, dtype=bool)
    exchange, clock = DevExchangeIO, time.perf_counter
    out_bytes = out.tobytes()
    window.wall_start = time.time()
    start = clock()
    sent_at = np.full(active, start)
    end = start + seconds
    running = True
    drain_deadline = 0.0
    while True:
        rc, raw = exchange(board, out_offset, out_bytes, in_offset, size, TIMEOUT_MS)
        now = clock()
        window.host_loops += 1
        if rc != 0 or len(raw) != size:
            window.exchange_errors += 1
            continue
        done = (np.frombuffer(raw, dtype="<u8") == out) & pending
        echoed = int(np.count_nonzero(done))
        if not echoed:
            time.sleep(HOST_IDLE_S)
        else:
            window.verified_total += echoed
            (record or window.echo_s.append)(now - sent_at[done])
            if running:
                out[done] += np.uint64(1)
                sent_at[done] = now
                out_bytes = out.tobytes()
            else:
                pending &= ~done
        if running:
            if now >= end:
                running = False
                window.elapsed_s = now - start
                window.wall_end = time.time()
                window.verified_timed = window.verified_total
                drain_deadline = now + DRAIN_S
        elif not pending.any() or now > drain_deadline:
            window.lost = int(np.count_nonzero(pending))
            window.wall_drained = time.time()
            return window

