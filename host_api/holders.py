"""Who holds a board's lock: the process, its command, and the way past it [ours].

A host that finds the board's transaction lock taken (``host_api.locks``: the flock on
the lock file beside the image) can only wait. Waiting makes sense for a short holder (a
download, a ``cifemu configure``), not for one that keeps the mailbox for its life, as
the CiA 309 gateway does (``host_api.cia309.link``): there every wait ends in
DRV_CMD_ACTIVE, seconds later and without a name. ``lock_holder`` names the holder from
the kernel's table of file locks (/proc/locks, ``host_api.lock_table``: an flock's pid
and the file's device and inode) and its /proc/PID/cmdline; ``Holder.long_lived`` says
whether waiting is futile, and ``Holder.advice`` what to do instead.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from dpm.image import dpm_dir, lock_path
from host_api.lock_table import flock_holders

TCP_LISTEN = "0A"
"""The state column of a listening socket in /proc/net/tcp."""
GATEWAY_WORDS = ("309", "serve")
"""How a gateway's command line reads (``cifemu 309 serve ...``): it keeps the mailbox
until it ends."""
DEFAULT_GATEWAY_PORT = 60000
"""``cifemu 309 serve``'s port when its command line gives none (host_api.cia309.server
has the same default; this module must not import the gateway to name it)."""


@dataclass(frozen=True)
class Holder:
    """A process that holds a lock: its pid and its command line's words."""

    pid: int
    argv: tuple[str, ...]

    @property
    def command(self) -> str:
        words = list(self.argv)
        if len(words) > 1 and Path(words[0]).name.startswith("python"):
            words = words[1:]  # python .../cifemu 309 serve: the program, not the interpreter
            if words[0] == "-m":
                words = words[1:]
        if words and Path(words[0]).name == "cifemu":
            words[0] = "cifemu"
        return " ".join(words) or f"pid {self.pid}"

    @property
    def long_lived(self) -> bool:
        """A CiA 309 gateway: it holds the mailbox until it ends."""
        words = self.argv
        return any(words[i : i + 2] == GATEWAY_WORDS for i in range(len(words) - 1))

    @property
    def port(self) -> int:
        """The TCP port the gateway listens on: its socket's, else its --port, else the
        default (a gateway started with --port 0 has one the kernel chose)."""
        listening = _listening_port(self.pid)
        if listening is not None:
            return listening
        words = list(self.argv)
        for i, word in enumerate(words[:-1]):
            if word == "--port" and words[i + 1].isdigit():
                return int(words[i + 1])
            if word.startswith("--port=") and word[7:].isdigit():
                return int(word[7:])
        return DEFAULT_GATEWAY_PORT

    def advice(self) -> str:
        """The holder named, and the way through it."""
        who = f"pid {self.pid} ({self.command})"
        if self.long_lived:
            return (f"the CiA 309 gateway {who} holds this board's mailbox for as long as "
                    f"it runs: send through it (`cifemu 309 exec --port {self.port} "
                    "'1 read 0x1000 0 u32'`), or end it first")
        return f"{who} holds this board's mailbox: try again when it is done"


def _cmdline(pid: int) -> tuple[str, ...]:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return ()
    return tuple(word.decode(errors="replace") for word in raw.split(b"\0") if word)


def _listening_port(pid: int) -> int | None:
    """The port of a listening TCP socket of ``pid`` (/proc/PID/fd, /proc/net/tcp{,6})."""
    try:
        inodes = {os.readlink(f"/proc/{pid}/fd/{fd}")[8:-1] for fd in os.listdir(f"/proc/{pid}/fd")
                  if os.readlink(f"/proc/{pid}/fd/{fd}").startswith("socket:[")}
    except OSError:
        return None
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            rows = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            fields = row.split()  # sl local_address rem_address st ... inode (the 10th)
            if len(fields) > 9 and fields[3] == TCP_LISTEN and fields[9] in inodes:
                return int(fields[1].rsplit(":", 1)[1], 16)
    return None


def lock_holder(path: Path) -> Holder | None:
    """The other process holding an flock on ``path``; None when none does (or the kernel's
    table cannot be read). A holder in another pid namespace (pid 0) cannot be named."""
    for pid in flock_holders(path) or ():
        if pid and pid != os.getpid():
            return Holder(pid, _cmdline(pid))
    return None


def mailbox_advice(board: int, directory: str | os.PathLike[str] | None) -> str:
    """``Holder.advice`` for the board's transaction lock, or "" when nobody holds it."""
    holder = lock_holder(lock_path(dpm_dir(directory), board, "transaction"))
    return holder.advice() if holder is not None else ""
