"""Where board N's image lives and how each side maps it [ours] (docs/dpm.md 3).

The firmware creates ``<dir>/board<N>.dpm`` (8192 bytes, mode 0660) and holds
an exclusive lock on ``<dir>/board<N>.lock`` for its whole life, so a second
firmware for the same board is refused instead of fighting over the flags.
"""

from __future__ import annotations

import errno
import fcntl
import mmap
import os
from collections.abc import Callable
from pathlib import Path

from dpm.errors import DpmError
from dpm.layout import DPM_SIZE

MAX_DEV_BOARDS = 4
DEFAULT_DPM_DIR = "/dev/shm/cif"
IMAGE_MODE = 0o660


def dpm_dir(explicit: str | os.PathLike[str] | None = None) -> Path:
    """``--dpm-dir`` if given, else ``$CIF_DPM_DIR``, else /dev/shm/cif."""
    if explicit is not None:
        return Path(explicit)
    return Path(os.environ.get("CIF_DPM_DIR", DEFAULT_DPM_DIR))


def image_path(directory: Path, board: int) -> Path:
    return directory / f"board{board}.dpm"


def lock_path(directory: Path, board: int, what: str = "firmware") -> Path:
    return directory / f"board{board}.{what}.lock"


class BoardBusyError(DpmError, RuntimeError):
    """Another firmware already serves this board."""


class ExclusiveLock:
    """A non-blocking flock held for an object's life; records the holder's pid.

    ``on_acquired`` runs the moment the flock is held, before anything else: the lock is
    what tells hosts that a firmware runs, so what must be true of a running firmware
    (no stale READY in its image) is made true first."""

    def __init__(self, path: Path, on_acquired: Callable[[], None] | None = None) -> None:
        self.path = path
        self._fd = os.open(path, os.O_RDWR | os.O_CREAT, IMAGE_MODE)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = os.pread(self._fd, 32, 0).decode(errors="replace").strip() or "?"
            os.close(self._fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise BoardBusyError(
                    f"{path} is held by process {holder}: a firmware already serves this board"
                ) from None
            raise
        if on_acquired is not None:
            on_acquired()
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, f"{os.getpid()}\n".encode(), 0)

    def release(self) -> None:
        if self._fd >= 0:
            os.ftruncate(self._fd, 0)
            os.close(self._fd)
            self._fd = -1


def create_image(path: Path) -> mmap.mmap:
    """The firmware's map: the file is created (or reused) with mode 0660."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, IMAGE_MODE)
    try:
        os.fchmod(fd, IMAGE_MODE)  # the umask must not widen or narrow the contract
        os.ftruncate(fd, DPM_SIZE)
        return mmap.mmap(fd, DPM_SIZE)
    finally:
        os.close(fd)


def open_image(path: Path, *, readonly: bool = False) -> mmap.mmap:
    """A host's map of an existing image; raises OSError when it is missing or short."""
    fd = os.open(path, os.O_RDONLY if readonly else os.O_RDWR)
    try:
        size = os.fstat(fd).st_size
        if size < DPM_SIZE:
            raise OSError(errno.EINVAL, f"{path} is {size} bytes, not a {DPM_SIZE}-byte image")
        access = mmap.ACCESS_READ if readonly else mmap.ACCESS_WRITE
        return mmap.mmap(fd, DPM_SIZE, access=access)
    finally:
        os.close(fd)
