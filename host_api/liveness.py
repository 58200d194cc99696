"""Is a board's firmware alive? Asked of its lock, never of the image [ours].

A firmware holds ``board<N>.firmware.lock`` (flock, exclusive) for its whole
life and writes its pid into it; a clean stop empties the file, so a pid that is
still there while nobody holds the lock is the last pid of a firmware that died
(SIGKILL, crash). The image cannot tell: a killed firmware leaves READY set.

The lock is looked up in /proc/locks (``host_api.lock_table``) rather than probed with
``flock``: a probe holds the lock for an instant, and a firmware starting in that instant
would be refused as a second firmware. The kernel hands that table out a page at a time, and a
lock can fall between two pages when locks listed before it go meanwhile (measured: 11
misses in 434 reads beside two processes taking and dropping 1,000 flocks each; a CI run
beside a loaded suite saw one), so a "nobody holds it" while the recorded pid still runs
is read again before it is believed.
"""

from __future__ import annotations

import errno
import fcntl
import os
from dataclasses import dataclass
from pathlib import Path

from dpm.image import lock_path, process_exists
from host_api.lock_table import flock_holders

LOCK_TABLE_READS = 5
"""How often a "not held" is read while the recorded firmware pid still runs: a miss needs
locks listed before ours to go between two pages, and five in a row were never seen."""


@dataclass(frozen=True)
class FirmwareLiveness:
    """``alive``: a process holds the firmware lock; ``pid``: its pid, else the last one."""

    alive: bool
    pid: int | None


def _recorded_pid(path: Path) -> int | None:
    try:
        text = path.read_text(errors="replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _probe(path: Path) -> bool:
    """Fallback without /proc: a shared non-blocking flock fails while a firmware holds it."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError as exc:
        return exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN)
    finally:
        os.close(fd)
    return False


def firmware_liveness(directory: Path, board: int) -> FirmwareLiveness:
    """Whether board ``board``'s firmware in ``directory`` runs, and its (last) pid."""
    path = lock_path(directory, board)
    recorded = _recorded_pid(path)
    for _ in range(LOCK_TABLE_READS):
        holders = flock_holders(path)
        if holders is None:
            return FirmwareLiveness(_probe(path), recorded)
        if holders:
            # A pid of 0 is a holder in another pid namespace: trust the file's.
            return FirmwareLiveness(True, holders[0] or recorded)
        if recorded is None or not process_exists(recorded):
            break  # a clean stop or a dead firmware: the common "no", read once
    return FirmwareLiveness(False, recorded)
