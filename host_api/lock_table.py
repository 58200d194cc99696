"""The kernel's table of file locks, /proc/locks: which processes hold an flock on a file [ours].

Two questions of the host side are answered there: whether a board's firmware lives
(``host_api.liveness``: the firmware lock's holder) and who keeps a board's mailbox
(``host_api.holders``: the transaction lock's holder). The table's format is read here
only; each caller keeps its own policy over the answer (liveness asks the recorded pid
when the table's paging may have hidden a holder, holders pass over pid 0 and the caller).
"""

from __future__ import annotations

import os
from pathlib import Path

PROC_LOCKS = Path("/proc/locks")


def flock_holders(path: Path) -> list[int] | None:
    """Pids holding an flock on ``path``, in the table's order (0: a holder in another pid
    namespace, which the kernel does not name); None when the file or the table cannot be
    read."""
    try:
        stat = path.stat()
        lines = PROC_LOCKS.read_text().splitlines()
    except OSError:
        return None
    device = f"{os.major(stat.st_dev):02x}:{os.minor(stat.st_dev):02x}:{stat.st_ino}"
    holders = []
    for line in lines:
        # "1: FLOCK  ADVISORY  WRITE 18121 fe:00:10004389 0 EOF"; a waiter reads
        # "1: -> FLOCK ...", so its second field is not FLOCK
        fields = line.split()
        if len(fields) >= 6 and fields[1] == "FLOCK" and fields[5] == device:
            holders.append(int(fields[4]) if fields[4].isdigit() else 0)
    return holders
