"""Serialising host processes and threads on one board's channels.

The real driver lets one call at a time wait on a mailbox and answers a
second one with DRV_CMD_ACTIVE. Across processes sharing an image we do the
same with a lock per channel (``ChannelLock``: a thread lock plus an flock on a
file beside the image, the exchange's): a call waits for the channel up to its
own timeout and gets -4 when another caller holds it longer than that. The put
and get channels are thread locks only, in libcif too: both drivers take them
inside the transaction lock, so no other process can be inside them.

[ours] The transaction lock (``Transaction``) keeps request and answer
together: a host process holds its flock from a DevPutMessage until that
request is answered. Its file is the ledger of the requests whose answers are
awaited, one line each (``dpm.ledger``), the same as libcif's (libcif/src/chanlock.c).
A request the card does not answer when all goes well (COM_Tx_CAN_Layer2,
``dpm.commands.UNANSWERED``, or one sent with msg.e NAK) awaits nothing and goes
unrecorded, so the lock goes back with its call, as the real driver keeps none.
The kernel frees the flock of a host that dies; the next holder finds the dead
host's requests in the ledger and discards their answers when they come. A host
whose DevGetMessage timed out lets the lock go when no other call of it is
inside: its late answers are its own while it holds the lock again, and
another host's to discard once that host has taken it. So a host never reads an
answer to a request it did not send, except the error answer to an unrecorded one (the
card could not execute it): no request's, it comes to whichever host reads it, as an
indication does.

After ``os.fork`` the child has lock files of its own (``reopen_after_fork``):
an inherited descriptor would share its flocks with the parent.
"""

from __future__ import annotations

import errno
import fcntl
import mmap
import os
import secrets
import threading
import time
from enum import Enum
from pathlib import Path
from types import TracebackType
from typing import NamedTuple

from dpm._quicklock import Lock as QuickLock
from dpm.commands import UNANSWERED
from dpm.ledger import END, LINE, decode_line
from dpm.message import Ext, Message
from host_api.holders import Holder, lock_holder

_FLOCK_RETRY = 0.0002
_OPEN_FLAGS = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC

LEDGER_MAX = 128
"""Requests the ledger keeps at most; beyond that the oldest goes."""
LEDGER_BYTES = LEDGER_MAX * 96 + 1
"""The ledger file's size at least (96: libcif's longest line; 1: ``END``), so that the
whole of it is mapped."""
STALE_MS = 30_000
"""A dead host's request is forgotten this long after it was sent: a card answers within
it or never (the driver's longest wait is DevDownload's 15 s)."""


_LINE = LINE.encode("ascii")
_TAIL_END = _LINE[len(b"%d %d ") :] + END
"""A ledger line after its pid and owner, followed by the ledger's end, as bytes: a request
is appended as this process's prefix (``Transaction._prefix``) and these six fields, in one
write, with no text to encode."""
_new_request = tuple.__new__
"""Builds a ``Request`` from a full tuple of its fields: on every request, without the
keyword handling of the named tuple's own constructor."""

_NAK, _SEQ_MASK = int(Ext.NAK), int(Ext.SEQ_MASK)
_FIRST, _CONT, _LAST = int(Ext.FIRST), int(Ext.CONT), int(Ext.LAST)
"""msg.e's bits as plain ints, for the ledger's work on every request and answer."""


def _open(path: Path) -> int:
    """The lock file, opened or created; a planted symbolic link is refused (ELOOP)."""
    return os.open(path, _OPEN_FLAGS, 0o660)


def _map_ledger(fd: int) -> mmap.mmap:
    """The transaction lock file mapped, grown to ``LEDGER_BYTES`` first when shorter.

    [ours] The ledger is read and written through the map, without a pread and two pwrite
    per mailbox round trip (issue 22). libcif reads and writes it with pread and pwrite:
    both reach the same page cache. Growing the file adds zeros after its end, which every
    reader takes as the ledger's end (``dpm.ledger``); the file is never cut."""
    if os.fstat(fd).st_size < LEDGER_BYTES:
        os.ftruncate(fd, LEDGER_BYTES)
    return mmap.mmap(fd, LEDGER_BYTES)


class ChannelLock:
    def __init__(self, path: Path) -> None:
        self.path = path
        self._thread = threading.Lock()
        self._fd = _open(path)

    def acquire(self, timeout: float) -> bool:
        """Take the channel within ``timeout`` seconds (0: only if free now), in all.

        The thread lock stays held while the flock is awaited: the flock belongs to the
        open file description, which every thread shares."""
        if self._thread.acquire(False):  # the uncontended case, without clocks
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return True
            except BlockingIOError:
                deadline = time.monotonic() + timeout
        else:
            deadline = time.monotonic() + timeout
            got = self._thread.acquire(timeout=timeout) if timeout > 0 else False
            if not got:
                return False
        while True:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return True
            except OSError as exc:
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                    self._thread.release()
                    raise
            if time.monotonic() >= deadline:
                self._thread.release()
                return False
            time.sleep(_FLOCK_RETRY)

    def release(self) -> None:
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        self._thread.release()

    def __enter__(self) -> ChannelLock:
        """Block until the channel is free: for locks held only for microseconds."""
        self._thread.acquire()
        fcntl.flock(self._fd, fcntl.LOCK_EX)
        return self

    def __exit__(
        self, t: type[BaseException] | None, v: BaseException | None, tb: TracebackType | None
    ) -> None:
        fcntl.flock(self._fd, fcntl.LOCK_UN)  # release's body: this runs twice a round trip
        self._thread.release()

    def reopen_after_fork(self) -> None:
        """In a forked child: a file description of its own (the parent's flocks stay the
        parent's) and a new thread lock (a parent's thread that held it is not here)."""
        self._thread = threading.Lock()
        fd = _open(self.path)
        os.dup2(fd, self._fd, inheritable=False)
        os.close(fd)

    def close(self) -> None:
        os.close(self._fd)


class Answer(Enum):
    """Whose an answer read from the host mailbox was."""

    OTHER = 0
    """No awaited request's: an indication, or a request's that nobody recorded."""
    OWN = 1
    STALE = 2
    """A dead host's, or one whose DevGetMessage gave up: to be discarded."""


class Request(NamedTuple):
    """A request whose answer is awaited, as a ledger line records it.

    A named tuple, not a frozen dataclass: one is made per request, on the path of every
    mailbox round trip, and a tuple is made in a fraction of the time."""

    pid: int
    owner: int
    nr: int
    b: int
    rx: int
    tx: int
    multi: int
    """0: one answer ends it. Sent with e FIRST, a long upload's parts may follow its
    first answer: 1 before the first part, 2 after it (then only a part marked CONT or
    LAST continues it)."""
    sent_ms: int
    """CLOCK_MONOTONIC, as every process on the machine reads it."""
    given_up: bool = False
    """In memory: a get timed out waiting for it (it keeps the lock no more)."""

    def line(self) -> bytes:
        return _LINE % self[:8]

    @classmethod
    def parse(cls, line: str, now_ms: int) -> Request | None:
        """The request of one ledger line; None when malformed or past ``STALE_MS``."""
        entry = decode_line(line)
        if entry is None or entry.sent_ms > now_ms or now_ms - entry.sent_ms > STALE_MS:
            return None
        return cls(*entry, given_up=True)

    def answered_by(self, msg: Message) -> bool:
        if self.multi == 2 and msg.e & _SEQ_MASK not in (_CONT, _LAST):
            return False
        return msg.nr == self.nr and msg.a == self.b and msg.rx == self.tx and msg.tx == self.rx

    def after(self, msg: Message) -> Request | None:
        """The request once ``msg`` answered it: None when that was its last answer, a
        long upload's part (f 0, e FIRST or CONT) has more after it."""
        if self.multi and msg.f == 0 and msg.e & _SEQ_MASK in (_FIRST, _CONT):
            return self._replace(multi=2)
        return None


def _now_ms() -> int:
    return time.monotonic_ns() // 1_000_000


class Transaction:
    """The board's transaction lock as this process holds it across calls.

    ``enter``/``leave`` bracket each DevPutMessage and DevGetMessage: the process holds
    the flock while a call is inside or an answer awaited. ``acquire``/``release`` (the
    ``ChannelLock`` face that ``Board.transact``, DevDownload's session and the CiA 309
    gateway use) make a session: one thread of the process at a time, and the flock held
    from acquire to release.

    [ours] The driver's put and get that need not wait keep this ledger in C
    (``host_api._devflags.put_request``, ``take_answer``; issue 22): they read and change
    ``_own``, ``_stale``, ``_length``, the map ``_ledger`` and the file ``_fd`` by these
    names, under ``_state``, as ``sent`` and ``answered`` do, with ``_prefix``, ``_pid``
    and ``_owner`` for a new line. Renaming one of them means changing them there too;
    tests/test_host_transaction.py compares both ways.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd = _open(path)
        try:
            self._ledger = _map_ledger(self._fd)
        except BaseException:
            os.close(self._fd)
            raise
        self._state = QuickLock()
        """Guards the fields below; held for one attempt at the flock at a time."""
        self._session = QuickLock()
        self._owner = secrets.randbits(63)
        """This process's number in the ledger (a new one after a fork)."""
        self._pid = os.getpid()
        self._prefix = b"%d %d " % (self._pid, self._owner)
        """The first two fields of this process's ledger lines."""
        self._held = False
        self._users = 0
        self._own: list[Request] = []
        self._stale: list[Request] = []
        self._length = 0
        """The ledger's length (up to its end, ``dpm.ledger.END``) as this process last read
        or wrote it (while it holds the flock: then nobody else writes it). Lets a request be
        appended and the last answer empty the ledger, one system call each, on the path of
        every mailbox round trip."""
        self.holder: Holder | None = None
        """Who held the lock when ``acquire`` last failed (None: unknown or free)."""

    # --- calls ------------------------------------------------------------------------------

    def enter(self, timeout: float) -> bool:
        """A call starts: True when the process holds the lock within ``timeout`` s.

        Another process's lock is waited for, except a CiA 309 gateway's, which it keeps
        while it runs: then False at once."""
        deadline = 0.0
        asked = False
        while True:
            with self._state:
                if not self._held:
                    try:
                        fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                        self._held = True
                        self._load()
                    except BlockingIOError:
                        pass
                if self._held:
                    self._users += 1
                    return True
            now = time.monotonic()
            if not deadline:  # the clock read only once the lock is found taken
                deadline = now + timeout
            if now >= deadline:
                return False
            if not asked:
                # [ours] Another process has it: waiting is futile when it keeps the lock
                # for its life (the CiA 309 gateway), so the caller hears at once.
                asked = True
                holder = lock_holder(self.path)
                if holder is not None and holder.long_lived:
                    return False
            time.sleep(_FLOCK_RETRY)

    def leave(self) -> None:
        """The call ends: the lock goes back when no call is inside and no answer is
        awaited (answers a timed-out get gave up on do not keep it)."""
        with self._state:
            if self._users:
                self._users -= 1
            if not self._held or self._users:
                return
            for request in self._own:  # a loop, not all() over a generator made per call
                if not request.given_up:
                    return
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            self._held = False
            self._own, self._stale = [], []  # the file keeps them for the next holder

    def sent(self, msg: Message) -> None:
        """Before the request reaches the card: recorded in the ledger, unless the card
        answers it only when it fails (``dpm.commands.UNANSWERED``, or the NAK bit): an
        answer awaited that never comes would keep the board from every other host until
        a get of this one timed out."""
        e = msg.e
        if e & _NAK or (msg.rx, msg.b) in UNANSWERED:
            return
        sequence = e & _SEQ_MASK
        request = _new_request(Request, (self._pid, self._owner, msg.nr, msg.b, msg.rx,
                                         msg.tx, int(sequence == _FIRST),
                                         time.monotonic_ns() // 1_000_000, False))
        with self._state:
            own = self._own
            changed = False
            if own and sequence in (_CONT, _LAST):
                # It continues a sequence (the load function's transfers): the first request
                # of that command, answered with a part marked FIRST, was no long upload.
                kept = [r for r in own if not (
                    r.multi == 2 and (r.b, r.rx, r.tx) == (msg.b, msg.rx, msg.tx))]
                changed = len(kept) != len(own)
                self._own = own = kept
            if len(own) + len(self._stale) >= LEDGER_MAX:
                (self._stale or own).pop(0)
                changed = True
            own.append(request)
            if changed:
                self._store()
            else:
                self._append(self._prefix + _TAIL_END % request[2:8])

    def is_stale(self, msg: Message) -> bool:
        """Whether the answer waiting in the mailbox is one to discard."""
        if not self._stale:  # read without the lock: only taking the flock (``enter``, which
            return False    # the caller has done) fills it
        with self._state:
            return any(r.answered_by(msg) for r in self._stale)

    def answered(self, msg: Message) -> Answer:
        """After the answer was taken from the mailbox: whose it was. Stale requests were
        sent first, so the card answers them first."""
        with self._state:
            if self._stale and self._settle(self._stale, msg):
                return Answer.STALE
            if self._own and self._settle(self._own, msg):
                return Answer.OWN
            return Answer.OTHER

    def _settle(self, requests: list[Request], msg: Message) -> bool:
        """Whether ``msg`` answers one of ``requests``; that one goes, or waits for its
        next part, in memory and in the file."""
        for i, request in enumerate(requests):
            if request.answered_by(msg):
                rest = request.after(msg) if request.multi else None
                if rest is None:
                    del requests[i]
                else:
                    requests[i] = rest
                self._store()
                return True
        return False

    def give_up(self) -> None:
        """A get timed out: the answers awaited keep the lock no more."""
        with self._state:
            if self._own:  # none after a session's last answer: no list made anew
                self._own = [r._replace(given_up=True) for r in self._own]

    # --- sessions ---------------------------------------------------------------------------

    def acquire(self, timeout: float) -> bool:
        """A session: this thread alone in the process, the flock held until ``release``.

        Another process's lock is waited for up to ``timeout``, except a CiA 309
        gateway's, which it keeps while it runs: then False at once. ``holder`` names
        the process that held it."""
        session = self._session
        if session.acquire(False):  # the usual case: free, and no clock read (issue 22)
            left = timeout
        else:
            deadline = time.monotonic() + timeout
            if not (timeout > 0 and session.acquire(timeout=timeout)):
                return False
            left = max(0.0, deadline - time.monotonic())
        if self.enter(left):
            self.holder = None
            return True
        self.holder = lock_holder(self.path)
        self._session.release()
        return False

    def release(self) -> None:
        """The session ends; answers it did not read keep the lock no more."""
        self.give_up()
        self.leave()
        self._session.release()

    # --- the ledger -------------------------------------------------------------------------

    def _load(self) -> None:
        """The file's requests as a new holder sees them: another owner's are stale (its
        sender died, or gave up waiting and let the lock go), this process's own ones are
        given up. Malformed and expired lines are dropped."""
        ledger = self._ledger
        end = ledger.find(END)
        text = ledger[: end if end >= 0 else LEDGER_BYTES]
        self._length = len(text)
        if not text:  # the ledger of a board nobody awaits answers from
            self._own, self._stale = [], []
            return
        lines = text.decode("ascii", "replace").splitlines()
        now = _now_ms()
        kept = [r for r in (Request.parse(line, now) for line in lines) if r is not None]
        kept = kept[:LEDGER_MAX]
        self._own = [r for r in kept if r.owner == self._owner]
        self._stale = [r for r in kept if r.owner != self._owner]
        if end < 0 or len(kept) != len(lines):  # no END: a file someone else wrote
            self._store()

    def _append(self, line: bytes) -> None:
        """A request's line and ``END`` after the ledger's last line, through the map.

        A host killed while it writes leaves the ledger as it was, or with the whole line:
        the line after its first byte goes first, then that byte over the old ``END``."""
        at = self._length
        self._ledger[at + 1 : at + len(line)] = line[1:]
        self._ledger[at] = line[0]
        self._length = at + len(line) - 1  # END is one byte

    def _store(self) -> None:
        """The ledger rewritten from memory, ended by ``END``: the file is not truncated
        (``dpm.ledger``). Emptied (an answer read, on every round trip) by one byte
        written in the map; rewritten by one pwrite, which a host killed meanwhile either
        made whole or not at all."""
        if not self._own and not self._stale:
            if self._length:
                self._ledger[0] = END[0]
                self._length = 0
            return
        text = b"".join(r.line() for r in (*self._stale, *self._own))
        os.pwrite(self._fd, text + END, 0)
        self._length = len(text)

    def reopen_after_fork(self) -> None:
        """In a forked child: its own flock and owner number, an empty ledger in memory
        (the requests in the file are the parent's)."""
        self._state = QuickLock()
        self._session = QuickLock()
        self._owner = secrets.randbits(63)
        self._pid = os.getpid()
        self._prefix = b"%d %d " % (self._pid, self._owner)
        self._held = False
        self._users = 0
        self._own = []
        self._stale = []
        fd = _open(self.path)
        os.dup2(fd, self._fd, inheritable=False)
        os.close(fd)
        self._ledger.close()  # the map of the file now at the path, as the flock's
        self._ledger = _map_ledger(self._fd)

    def close(self) -> None:
        self._ledger.close()
        os.close(self._fd)
