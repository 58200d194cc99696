"""Where board N's image lives and how each side maps it [ours] (docs/dpm.md 3).

The firmware creates ``<dir>/board<N>.dpm`` (8192 bytes, mode 0660) and holds
an exclusive lock on ``<dir>/board<N>.firmware.lock`` for its whole life, so a second
firmware for the same board is refused instead of fighting over the flags.

The default directory, /dev/shm/cif, sits in a place every local user can write
to, and the firmware often runs as root: whoever creates the directory first, or
plants a symlink in it, must not get root to write elsewhere. ``CardDirectory``
is the checked directory both sides use, as trusted daemons do it: the directory is
opened once without following a symlink and checked (owner, not world-writable),
files are opened relative to that descriptor with O_NOFOLLOW and checked with
fstat, new files are made with O_EXCL under unpredictable names and renamed into
place, and directories are created with their mode set explicitly, whatever the
umask. The rules, for both sides, are in docs/security.md.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import mmap
import os
import secrets
import socket
import stat
from collections.abc import Callable
from pathlib import Path

from dpm.errors import DpmError

MAX_DEV_BOARDS = 4
DEFAULT_DPM_DIR = "/dev/shm/cif"
IMAGE_MODE = 0o660
DIRECTORY_MODE = 0o2770
"""The image directory the firmware creates [ours]: the owner and the host group read
and write (hosts create their lock files beside the image), nobody else enters. The
set-group-ID bit makes every file inside take the directory's group, so ``chgrp`` of
the directory once names the host group for the image, the locks and the sockets."""
PRIVATE_DIRECTORY_MODE = 0o750
"""The flash directory the firmware creates [ours]: only the firmware writes it."""
SUN_PATH_MAX = 107
"""Bytes of a socket path that fit sockaddr_un.sun_path (108) with its NUL."""


def dpm_dir(explicit: str | os.PathLike[str] | None = None) -> Path:
    """``--dpm-dir`` if given, else ``$CIF_DPM_DIR``, else /dev/shm/cif."""
    if explicit is not None:
        return Path(explicit)
    return Path(os.environ.get("CIF_DPM_DIR", DEFAULT_DPM_DIR))


def image_path(directory: Path, board: int) -> Path:
    return directory / f"board{board}.dpm"


def lock_path(directory: Path, board: int, what: str = "firmware") -> Path:
    return directory / f"board{board}.{what}.lock"


def socket_path(image: Path, what: str) -> Path:
    """The card's socket ``what`` ("bell", "tap") beside ``image``: ``board<N>.<what>``.

    A file system socket in the card's directory, not an abstract name: an abstract
    name is open to every local user, who can take it first or talk to it; the
    directory's permissions keep both to the owner and the host group [ours].
    """
    return Path(os.path.abspath(image)).with_suffix(f".{what}")


class BoardBusyError(DpmError, RuntimeError):
    """Another firmware already serves this board."""


class UnsafePathError(DpmError, PermissionError):
    """The card's directory, or a file in it, could let another user redirect a write;
    the message is one line that names the path and the rule it breaks. A
    PermissionError, so every tool's one-line report of an OSError shows it."""


def _mode(st: os.stat_result) -> str:
    return f"{stat.S_IMODE(st.st_mode):04o}"


class CardDirectory:
    """A checked, open directory of the card: the image's or the flash's.

    Opened with O_NOFOLLOW and checked with fstat, it is refused (``UnsafePathError``)
    when it is no directory, is writable by every user (sticky or not: give the card a
    directory of its own), or belongs to another user. ``private`` also refuses one its
    group can write (the flash). ``host``: a host also accepts a directory of another
    owner whose group it is a member of (a firmware run by a service user). ``create``
    makes missing directories with ``mode``, whatever the umask.
    """

    def __init__(self, path: Path, *, create: bool = False, private: bool = False,
                 host: bool = False) -> None:
        self.path = Path(path)
        if create:
            _make_directories(self.path, PRIVATE_DIRECTORY_MODE if private else DIRECTORY_MODE)
        try:
            self.fd = os.open(self.path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW
                              | os.O_CLOEXEC)
        except OSError as exc:
            what = "a symbolic link" if self.path.is_symlink() else exc.strerror
            raise UnsafePathError(f"directory {self.path} refused: {what}") from None
        problem = _directory_problem(os.fstat(self.fd), private, host)
        if problem is not None:
            os.close(self.fd)
            raise UnsafePathError(f"directory {self.path} refused: {problem}")

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1

    def open(self, name: str, flags: int, mode: int = IMAGE_MODE, *, own: bool = True) -> int:
        """``name`` opened without following a symlink; a file that is no regular file
        with one link (``own``: owned by this process's user) is refused, so a planted
        file or hard link never receives what the card writes."""
        try:
            fd = os.open(name, flags | os.O_NOFOLLOW | os.O_CLOEXEC, mode, dir_fd=self.fd)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise UnsafePathError(f"{self.path / name} refused: a symbolic link") from None
            raise
        st = os.fstat(fd)
        problem = None
        if not stat.S_ISREG(st.st_mode):
            problem = "not a regular file"
        elif own and st.st_nlink != 1:
            problem = f"{st.st_nlink} hard links"
        elif own and st.st_uid != os.geteuid():
            problem = f"owned by uid {st.st_uid}, not by uid {os.geteuid()}"
        if problem is not None:
            os.close(fd)
            raise UnsafePathError(f"{self.path / name} refused: {problem}")
        return fd

    def read(self, name: str, *, own: bool = True) -> bytes | None:
        """A whole file's bytes; None when there is none."""
        try:
            fd = self.open(name, os.O_RDONLY, own=own)
        except FileNotFoundError:
            return None
        with os.fdopen(fd, "rb") as file:
            return file.read()

    def replace(self, name: str, data: bytes, mode: int = IMAGE_MODE, *,
                durable: bool = False) -> None:
        """Write ``name`` atomically: a new file under an unpredictable name, made with
        O_EXCL (nothing planted can be followed or reused), renamed over ``name``.
        ``durable`` also syncs the file and the directory (the flash)."""
        temporary = f".{name}.{secrets.token_hex(8)}.tmp"
        fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW
                     | os.O_CLOEXEC, mode, dir_fd=self.fd)
        try:
            try:
                os.fchmod(fd, mode)  # the umask must not widen or narrow the contract
                view = memoryview(data)
                while view:
                    view = view[os.write(fd, view):]
                if durable:
                    os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(temporary, name, src_dir_fd=self.fd, dst_dir_fd=self.fd)
        except OSError:
            self.unlink(temporary)  # a full disk keeps no half file to fill it
            raise
        if durable:
            os.fsync(self.fd)

    def open_unnamed(self) -> int:
        """A new file in this directory without a name (O_TMPFILE), open for reading and
        writing: only its descriptor reaches it, and it is gone when the last one closes,
        so nothing planted in the directory can be it. Where the file system has no
        O_TMPFILE: a file made with O_EXCL under an unpredictable name, removed at once."""
        try:
            return os.open(".", os.O_TMPFILE | os.O_RDWR | os.O_CLOEXEC, 0o600, dir_fd=self.fd)
        except OSError as exc:
            if exc.errno not in (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL):
                raise
        name = f".{secrets.token_hex(8)}.tmp"
        fd = os.open(name, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                     0o600, dir_fd=self.fd)
        self.unlink(name)
        return fd

    def unlink(self, name: str) -> None:
        """Remove ``name`` (never what a symlink points to); none there is no error."""
        with contextlib.suppress(FileNotFoundError):
            os.unlink(name, dir_fd=self.fd)

    def names(self) -> list[str]:
        return os.listdir(self.fd)

    def sync(self) -> None:
        """Make a rename or unlink itself durable."""
        os.fsync(self.fd)

    def bind(self, sock: socket.socket, path: Path) -> None:
        """Bind ``sock`` to ``path`` in this directory, mode 0660 whatever the umask.

        A socket file left by a killed firmware is removed first: callers hold the
        board's lock, so no running firmware owns it. The mode is set through a
        descriptor opened without following links (``/proc/self/fd``), so a socket
        swapped for a symlink between bind and chmod changes nothing else."""
        if len(os.fsencode(path)) > SUN_PATH_MAX:
            raise UnsafePathError(f"{path}: longer than the {SUN_PATH_MAX} bytes a Unix "
                                  "socket's path may have; use a shorter --dpm-dir")
        try:
            self.unlink(path.name)
            sock.bind(os.fspath(path))
        except OSError as exc:
            raise UnsafePathError(f"{path}: the card's socket cannot take this name: "
                                  f"{exc.strerror}") from None
        fd = os.open(path.name, os.O_PATH | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=self.fd)
        try:
            st = os.fstat(fd)
            if not stat.S_ISSOCK(st.st_mode) or st.st_uid != os.geteuid():
                raise UnsafePathError(f"{path} refused: replaced while it was bound")
            os.chmod(f"/proc/self/fd/{fd}", IMAGE_MODE)
        finally:
            os.close(fd)


def _directory_problem(st: os.stat_result, private: bool, host: bool) -> str | None:
    euid = os.geteuid()
    if not stat.S_ISDIR(st.st_mode):
        return "not a directory"
    if st.st_mode & stat.S_IWOTH:
        return f"mode {_mode(st)} lets every user write to it"
    if private and st.st_mode & stat.S_IWGRP:
        return f"mode {_mode(st)} lets group {st.st_gid} write to it"
    if st.st_uid in (0, euid):
        return None
    if host and (st.st_gid == os.getegid() or st.st_gid in os.getgroups()):
        return None
    return f"owned by uid {st.st_uid}, not by root or uid {euid}"


def _make_directories(path: Path, mode: int) -> None:
    """Create the missing components of ``path``; the last gets ``mode``, the ones
    above it ``mode`` without write for the group. Set with fchmod: the umask is not
    asked (under umask 000 os.makedirs would leave them 0777)."""
    missing: list[Path] = []
    probe = Path(os.path.abspath(path))
    while not os.path.lexists(probe):
        missing.append(probe)
        probe = probe.parent
    for directory in reversed(missing):
        want = mode if directory == missing[0] else mode & ~stat.S_IWGRP
        try:
            os.mkdir(directory, 0o700)
        except FileExistsError:
            continue  # made by someone else meanwhile: the check that follows judges it
        fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
        try:
            os.fchmod(fd, want)
        finally:
            os.close(fd)


class ExclusiveLock:
    """A non-blocking flock held for an object's life; records the holder's pid.

    ``on_acquired`` runs the moment the flock is held, before anything else: the lock is
    what tells hosts that a firmware runs, so what must be true of a running firmware
    (no stale READY in its image) is made true first."""

    def __init__(self, directory: CardDirectory, name: str,
                 on_acquired: Callable[[], None] | None = None) -> None:
        self.path = directory.path / name
        self._fd = directory.open(name, os.O_RDWR | os.O_CREAT)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = os.pread(self._fd, 32, 0).decode(errors="replace").strip() or "?"
            os.close(self._fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise BoardBusyError(
                    f"{self.path} is held by process {holder}: a firmware already serves "
                    "this board") from None
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


def create_image(directory: CardDirectory, name: str) -> mmap.mmap:
    """The firmware's map: the file is created (or reused, if it is the firmware
    user's own regular file) with mode 0660."""
    from dpm.layout import DPM_SIZE  # here: every --help reads this module, not the layout

    fd = directory.open(name, os.O_RDWR | os.O_CREAT)
    try:
        os.fchmod(fd, IMAGE_MODE)  # the umask must not widen or narrow the contract
        os.ftruncate(fd, DPM_SIZE)
        return mmap.mmap(fd, DPM_SIZE)
    finally:
        os.close(fd)


def open_image(path: Path, *, readonly: bool = False) -> mmap.mmap:
    """A host's map of an existing image; raises OSError when it is missing, short, or
    no regular file (a symlink planted there would have a host write into its target)."""
    from dpm.layout import DPM_SIZE  # here: every --help reads this module, not the layout

    fd = os.open(path, (os.O_RDONLY if readonly else os.O_RDWR) | os.O_NOFOLLOW | os.O_CLOEXEC)
    try:
        st = os.fstat(fd)
        size = st.st_size
        if not stat.S_ISREG(st.st_mode):
            raise OSError(errno.EINVAL, f"{path} is not a regular file")
        if size < DPM_SIZE:
            raise OSError(errno.EINVAL, f"{path} is {size} bytes, not a {DPM_SIZE}-byte image")
        access = mmap.ACCESS_READ if readonly else mmap.ACCESS_WRITE
        return mmap.mmap(fd, DPM_SIZE, access=access)
    finally:
        os.close(fd)


def process_exists(pid: int) -> bool:
    """Whether process ``pid`` exists (a zombie, or another user's process, counts): the pid
    a lock file or a shared segment recorded may outlive its process."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
