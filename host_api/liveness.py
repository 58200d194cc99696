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
beside a loaded suite saw one). Reading the table again while the recorded pid runs was not
enough: under load all five reads of a row missed (a loaded suite, twice on 2026-12-03). So
a "nobody holds it" is not believed while the recorded pid names the process that wrote it:
one that runs (not a zombie) and started no later than the file's last write. A pid used
again after a firmware died belongs to a process started after that write.
"""

from __future__ import annotations

import errno
import fcntl
import os
import time
from dataclasses import dataclass
from pathlib import Path

from dpm.image import lock_path, process_exists
from dpm.start_progress import stat_fields
from host_api.lock_table import flock_holders

START_SLACK_S = 0.02
"""Rounding between a process's start (clock ticks of 10 ms) and a file's time stamp (the
kernel's coarse clock); a firmware writes its pid some 100 ms after its start at the least."""


@dataclass(frozen=True)
class FirmwareLiveness:
    """``alive``: a process holds the firmware lock; ``pid``: its pid, else the last one."""

    alive: bool
    pid: int | None


def recorded_pid(path: Path) -> int | None:
    """The pid a firmware lock file names: the holder's once it has cleared what a killed
    predecessor left in the image (``dpm.image.ExclusiveLock``), else the last one."""
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


def _wrote_the_file(pid: int, path: Path) -> bool:
    """Whether ``pid`` runs (not a zombie) and started no later than ``path``'s last write,
    so that it may be the process that wrote its pid there (see the module docstring).
    Without /proc, whether the pid exists."""
    try:
        fields = stat_fields(pid)
        written = path.stat().st_mtime
    except FileNotFoundError:
        return False
    except OSError:
        return process_exists(pid)
    if fields[0] in ("Z", "X"):
        return False  # dead, not yet reaped: its lock went with its files
    age = time.clock_gettime(time.CLOCK_BOOTTIME) - int(fields[19]) / os.sysconf("SC_CLK_TCK")
    return age + START_SLACK_S >= time.time() - written


def firmware_liveness(directory: Path, board: int) -> FirmwareLiveness:
    """Whether board ``board``'s firmware in ``directory`` runs, and its (last) pid."""
    path = lock_path(directory, board)
    recorded = recorded_pid(path)
    holders = flock_holders(path)
    if holders is None:
        return FirmwareLiveness(_probe(path), recorded)
    if holders:
        # A pid of 0 is a holder in another pid namespace: trust the file's.
        return FirmwareLiveness(True, holders[0] or recorded)
    # The table can miss a held lock (module docstring): the pid that wrote the file decides.
    return FirmwareLiveness(recorded is not None and _wrote_the_file(recorded, path), recorded)


def firmware_serving(directory: Path, board: int) -> bool:
    """Whether board ``board``'s firmware runs and has written its pid into its lock, so that
    the image's READY, read after this answered True, is that firmware's.

    A starting firmware takes its lock, then clears the READY a killed predecessor left,
    then writes its pid (``dpm.image.ExclusiveLock``): between the lock and the pid it is
    alive, and the image still says READY. A host that took that READY for the new
    firmware's (DevInitBoard did: READY, then "alive?") went on with a card that was not up.
    So the lock's holder must be the pid its file names, and READY is read after this."""
    liveness = firmware_liveness(directory, board)
    return liveness.alive and liveness.pid == recorded_pid(lock_path(directory, board))
