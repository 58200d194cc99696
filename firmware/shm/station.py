"""A station on a ``shm`` channel: the file's layout, the table, one station's ring and bell [ours].

The medium itself is described in ``firmware.shm.bus``, whose python-can interface
(``ShmBus``) reads the other stations' rings on top of a ``Station``. It lives apart,
importing neither python-can nor numpy, because the card's SYNC timer process
(``firmware.shm.cyclic``) is a station that only writes: with ``ShmBus`` its start
imported both, 0.45-0.55 s of a core in an interpreter the card starts with its
controller, which a network booted right after the card's start paid for (docs/benchmarks.md,
issue 22's note 5); with this module alone about 0.05 s.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import mmap
import os
import re
import socket
import struct
import threading
import time
from pathlib import Path

from dpm.image import process_exists

MAGIC = b"CIFCANS2"
MAX_STATIONS = 64
CAPACITY = 1 << 13
"""Records per station ring: 8,192, almost a second of 1 Mbit/s at full load from one station."""

HEADER = struct.Struct("<8sIII")  # magic, stations, capacity, record size
BITRATE_AT = HEADER.size
BITRATE_SIZE = 4
"""After the header: the channel's bit rate in bit/s, a little-endian u32, 0: none given
(see ``ShmBus.bitrate``). The spare bytes of a file from before it read 0."""
SEQS_AT = 64
"""Per station: records ever written (u64, written only by the station)."""
SEQS_BYTES = 8 * MAX_STATIONS
WAITING_AT = SEQS_AT + SEQS_BYTES
"""Per station: 1 while it sleeps on its bell."""
STATIONS_AT = WAITING_AT + MAX_STATIONS
ENTRY = struct.Struct("<IIQ")  # in use, pid, opened (ns; part of the bell's name)
RINGS_AT = 4096
RECORD = struct.Struct("<dIBBH8s8x")  # time stamp, identifier, flags, dlc, (spare), data
RECORD_SIZE = RECORD.size
RING_BYTES = CAPACITY * RECORD_SIZE
FILE_SIZE = RINGS_AT + MAX_STATIONS * RING_BYTES

EXTENDED, REMOTE, ERROR = 0x01, 0x02, 0x04
"""A record's flags."""

_CLEAN_CHANNEL = re.compile(r"[A-Za-z0-9._-]{1,64}")


def channel_path(channel: str) -> Path:
    """The file behind ``channel``: a path as given, else a name in /dev/shm (or the temp dir)."""
    if "/" in channel:
        return Path(channel)
    name = channel if _CLEAN_CHANNEL.fullmatch(channel) else (
        hashlib.sha1(channel.encode()).hexdigest()[:24])
    root = Path("/dev/shm")
    if not root.is_dir():
        import tempfile  # here only: the timer process's start must not pay for it

        root = Path(tempfile.gettempdir())
    return root / f"cifemu-can-{name}"


def copy_records(mapped: mmap.mmap, ring_at: int, first: int, end: int) -> bytes:
    """Records ``first`` to ``end`` (counters) of the ring at ``ring_at``, unwrapped: what a
    reader (``ShmBus``, ``ChannelWatch``) copies of a station's new frames."""
    start = first % CAPACITY
    count = end - first
    if start + count <= CAPACITY:
        return mapped[ring_at + start * RECORD_SIZE:ring_at + (start + count) * RECORD_SIZE]
    return (mapped[ring_at + start * RECORD_SIZE:ring_at + RING_BYTES]
            + mapped[ring_at:ring_at + (start + count - CAPACITY) * RECORD_SIZE])


class ChannelError(Exception):
    """The file is no channel of this version, or every station on it is taken
    (``ShmBus`` raises python-can's ``CanInitializationError`` for it)."""


class Station:
    """This process's entry in a channel's table, its ring and its bell.

    ``write`` publishes a record and rings the stations that sleep; the rest of the file
    (the other rings, the bit rate, the waiting marks) is the owner's to read through
    ``map``. Opening and leaving take an ``flock`` on the file; ``release`` closes it all.
    """

    def __init__(self, path: Path, bitrate: int = 0) -> None:
        self.path = path
        digest = hashlib.sha1(str(path.resolve()).encode()).hexdigest()[:16]
        self._bell_prefix = f"\0cifemu-can-{digest}-"
        self._lock = threading.Lock()
        """The threads of one station take turns at its ring."""
        self._fence = threading.Lock()
        """Taking an uncontended lock is an atomic instruction: a full memory fence."""
        self._left = False
        self.fd, self.map = _open(path, bitrate)
        self._seqs = memoryview(self.map)[SEQS_AT:SEQS_AT + SEQS_BYTES].cast("Q")
        """The stations' counters; storing one is a single aligned 8-byte store (CPython
        packs a 'Q' item with an 8-byte ``memcpy``, one ``mov`` on x86-64, as numpy's view
        of them did)."""
        self.bell = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.bell.setblocking(False)
        self.ringer = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.ringer.setblocking(False)
        try:
            self.index = self._register()
        except BaseException:
            self.release()
            raise
        self._ring_at = RINGS_AT + self.index * RING_BYTES

    def _entry(self, index: int) -> tuple[int, int, int]:
        return ENTRY.unpack_from(self.map, STATIONS_AT + index * ENTRY.size)

    def _bell_name(self, index: int, opened: int) -> bytes:
        """A station's bell: unique per opening, so a reused entry never gets an old ring."""
        return f"{self._bell_prefix}{index}-{opened}".encode()

    def _register(self) -> int:
        fcntl.flock(self.fd, fcntl.LOCK_EX)
        try:
            self._reclaim_dead()
            for index in range(MAX_STATIONS):
                if not self._entry(index)[0]:
                    break
            else:
                raise ChannelError(f"{MAX_STATIONS} stations are open on {self.path} already")
            opened = time.monotonic_ns()
            self.bell.bind(self._bell_name(index, opened))
            # The ring's counter runs on from its last owner: readers' positions stay valid.
            self._set_entry(index, 1, os.getpid(), opened)
            return index
        finally:
            fcntl.flock(self.fd, fcntl.LOCK_UN)

    def _reclaim_dead(self) -> None:
        """Free the entries of stations whose process is gone (under the exclusive lock)."""
        for index in range(MAX_STATIONS):
            in_use, pid, _ = self._entry(index)
            if in_use and not process_exists(pid):
                self._set_entry(index, 0, 0, 0)

    def _set_entry(self, index: int, in_use: int, pid: int, opened: int) -> None:
        """Write a station's entry, not waiting (under the exclusive lock)."""
        ENTRY.pack_into(self.map, STATIONS_AT + index * ENTRY.size, in_use, pid, opened)
        self.map[WAITING_AT + index] = 0

    def write(self, record: bytes, ring_own: bool = False) -> bool:
        """Append ``record`` (a ``RECORD``) to the ring and ring the stations asleep; never
        waits for readers. ``ring_own``: this station's own sleeping reader too. False once
        the station has left (``leave``), with nothing written."""
        with self._lock:
            if self._left:
                return False
            mapped, seqs, index = self.map, self._seqs, self.index
            seq = seqs[index]
            at = self._ring_at + (seq % CAPACITY) * RECORD_SIZE
            mapped[at:at + RECORD_SIZE] = record
            seqs[index] = seq + 1  # publishes the record (one aligned 8-byte store)
            with self._fence:
                pass
            own = -1 if ring_own else WAITING_AT + index
            sleeper = mapped.find(b"\x01", WAITING_AT, WAITING_AT + MAX_STATIONS)
            while sleeper >= 0:
                if sleeper != own:  # its own reader would wake to find nothing (issue 22)
                    station = sleeper - WAITING_AT
                    mapped[sleeper] = 0
                    self._ring(self._bell_name(station, self._entry(station)[2]))
                sleeper = mapped.find(b"\x01", sleeper + 1, WAITING_AT + MAX_STATIONS)
        return True

    def _ring(self, bell: bytes) -> None:
        # OSError: gone (reclaimed when a station opens next), or its queue is full: awake.
        with contextlib.suppress(OSError):
            self.ringer.sendto(b"\x01", bell)

    def leave(self) -> None:
        """Free the entry, and remove the file when no station is left; ``write`` writes
        nothing after it."""
        with self._lock:
            self._left = True
            fcntl.flock(self.fd, fcntl.LOCK_EX)
            try:
                self._set_entry(self.index, 0, 0, 0)
                self._reclaim_dead()
                if not any(self._entry(index)[0] for index in range(MAX_STATIONS)):
                    self.path.unlink(missing_ok=True)
            finally:
                fcntl.flock(self.fd, fcntl.LOCK_UN)

    def release(self) -> None:
        """Close the mapping, the file and the sockets (after ``leave``, or a failed open)."""
        self._seqs.release()  # a view pins the mapping
        self.map.close()
        os.close(self.fd)
        self.bell.close()
        self.ringer.close()


def _open(path: Path, bitrate: int) -> tuple[int, mmap.mmap]:
    """The channel's file, created when missing, checked and mapped."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o660)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            if os.fstat(fd).st_nlink == 0:  # removed by its last station meanwhile
                os.close(fd)
                continue
            if os.fstat(fd).st_size == 0:
                os.fchmod(fd, 0o660)  # whatever the umask
                os.ftruncate(fd, FILE_SIZE)
                os.pwrite(fd, HEADER.pack(MAGIC, MAX_STATIONS, CAPACITY, RECORD_SIZE), 0)
            header = os.pread(fd, HEADER.size, 0)
            if (os.fstat(fd).st_size != FILE_SIZE or len(header) != HEADER.size
                    or HEADER.unpack(header) != (MAGIC, MAX_STATIONS, CAPACITY,
                                                 RECORD_SIZE)):
                raise ChannelError(
                    f"{path} is not a cifemu shared-memory CAN channel of this version")
            if bitrate and not any(os.pread(fd, BITRATE_SIZE, BITRATE_AT)):
                os.pwrite(fd, bitrate.to_bytes(BITRATE_SIZE, "little"), BITRATE_AT)
            mapped = mmap.mmap(fd, FILE_SIZE)
            fcntl.flock(fd, fcntl.LOCK_UN)
            return fd, mapped
        except BaseException:
            os.close(fd)
            raise
