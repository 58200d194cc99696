"""The record socket's contract: attaching a recording to a running card [ours].

A running firmware listens on ``board<N>.record`` beside the image, a Unix
SOCK_SEQPACKET socket: a file system socket, so the directory's permissions
(docs/security.md) decide who may attach, as for the doorbell and the tap. One
recording at a time:

1. the recording side (``cifemu record``, the pytest plugin) creates the session
   directory and its files itself, as its own user, and sends ``ATTACH`` with three open
   descriptors (SCM_RIGHTS): ``session.jsonl``, ``can.log`` and the spool, a file
   without a name in the session's directory, open for reading and writing, where the
   card's writer keeps the events until the recording ends. The firmware, often root,
   never opens a path a local user named (a path would let that user have root
   overwrite any file);
2. the card answers one JSON object: ``{"attached": {board, firmware_pid, started_t,
   started_wall, channel}}``, or ``{"refused": "one line"}`` (another recording runs,
   the descriptors are not such files);
3. the recording runs until the recording side sends ``DETACH`` or goes away (its end
   of the socket closes), or the card stops. The card then has the writer write
   everything and answers ``{"detached": {events, frames, complete, card_stopped}}``:
   the session is complete once that answer has come. After the detach, the card's
   hooks cost nothing again.

The codec and the recording side (``attach``) live here, beside the image they
describe; the card's side is ``firmware.record_socket``.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import socket
import struct
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dpm import session as s
from dpm.errors import DpmError
from dpm.image import CardDirectory, socket_path

ATTACH = b"attach"
DETACH = b"detach"
MAX_MESSAGE = 4096
ANSWER_TIMEOUT_S = 10.0
"""How long the recording side waits for the card to answer an ``ATTACH``."""
DETACH_TIMEOUT_S = 300.0
"""How long ``detach`` waits for ``detached`` by default: the card's writer encodes the
whole session when the recording ends, at a low priority (a minute of a mailbox loop
takes it several seconds); the answer comes as soon as it has written everything."""


class RecordingError(DpmError, RuntimeError):
    """A recording that cannot be attached or ended; the message is one line."""


_UCRED = struct.Struct("3i")
"""struct ucred (pid, uid, gid), as SO_PEERCRED gives it."""


def peer_pid(conn: socket.socket) -> int:
    """The pid of the process at the other end of a connected Unix socket."""
    pid, _, _ = _UCRED.unpack(conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                              _UCRED.size))
    return int(pid)


def record_address(image: Path) -> Path:
    """The record socket of the card serving ``image``: ``board<N>.record`` beside it."""
    return socket_path(image, "record")


def encode_answer(kind: str, value: Any) -> bytes:
    return json.dumps({kind: value}).encode()


def decode_answer(data: bytes) -> tuple[str, Any]:
    """``(kind, value)`` of a card's answer; RecordingError when it is none."""
    try:
        obj = json.loads(data)
    except ValueError:
        raise RecordingError("the card's record socket answered no JSON") from None
    if not isinstance(obj, dict) or len(obj) != 1:
        raise RecordingError("the card's record socket answered no single object")
    ((kind, value),) = obj.items()
    return str(kind), value


@dataclass(frozen=True)
class Summary:
    """What the card reported when the recording ended."""

    events: int
    frames: int
    complete: bool
    """Whether the writer wrote everything (False: it died; the session ends early)."""
    card_stopped: bool
    """The card powered off while it was recorded (the recording ended with it)."""


class Attachment:
    """A recording attached to a running card: ``detach`` ends it, or the card does.

    Made by ``attach``; ``fileno`` becomes readable when the card ends the recording
    itself (it stops), so a program can wait on it beside its own events."""

    def __init__(self, sock: socket.socket, session: Path, meta: dict[str, Any]) -> None:
        self._sock = sock
        self.session = session
        self.meta = meta
        self.summary: Summary | None = None

    def fileno(self) -> int:
        return self._sock.fileno()

    def detach(self, timeout: float | None = DETACH_TIMEOUT_S) -> Summary:
        """End the recording; returns once the card has written all of it (None: however
        long that takes)."""
        if self.summary is not None:
            return self.summary
        with contextlib.suppress(OSError):  # the card has gone: its answer may be there
            self._sock.send(DETACH)
        return self.wait(timeout)

    def wait(self, timeout: float | None) -> Summary:
        """Wait until the card ends the recording (after ``detach``, or when it stops)."""
        if self.summary is not None:
            return self.summary
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not select.select([self._sock], [], [], left)[0]:
                raise RecordingError(
                    f"the card did not confirm the end of the recording into {self.session} "
                    f"within {timeout:.0f} s; the session may be incomplete")
            try:
                data = self._sock.recv(MAX_MESSAGE)
            except OSError as exc:
                data, error = b"", exc.strerror
            else:
                error = "the card closed the record socket"
            if not data:
                self.close()
                raise RecordingError(f"{error} before the recording into {self.session} was "
                                     "complete: the card died? the session may end early")
            kind, value = decode_answer(data)
            if kind == "detached" and isinstance(value, dict):
                self.summary = Summary(int(value.get("events", 0)), int(value.get("frames", 0)),
                                       bool(value.get("complete")),
                                       bool(value.get("card_stopped")))
                self.close()
                return self.summary

    def close(self) -> None:
        """Let the recording go without waiting (the card ends it when it sees this)."""
        self._sock.close()


def attach(image: Path, board: int, session: Path,
           timeout: float = ANSWER_TIMEOUT_S) -> Attachment:
    """Attach a recording into the new session directory ``session`` to the card serving
    ``image`` (board ``board``); RecordingError, with one line, when it cannot be: no card
    runs there, another recording runs, ``session`` holds a session already or cannot be
    made. A refused attach leaves nothing behind that it made."""
    made = not os.path.lexists(session)
    try:
        files = CardDirectory(session, create=True)
    except OSError as exc:  # UnsafePathError included: its message names path and rule
        raise RecordingError(f"cannot record into {session}: {exc}") from None
    names = (s.EVENTS, s.CAN_LOG)
    fds: list[int] = []
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)
    try:
        try:
            for name in names:
                fds.append(files.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL))
            fds.append(files.open_unnamed())
        except FileExistsError:
            raise RecordingError(f"{session} already holds a session; a recording never "
                                 "overwrites one") from None
        except OSError as exc:
            raise RecordingError(f"cannot record into {session}: {exc}") from None
        value = _request_attach(sock, image, board, fds, timeout)
        meta = s.encode_meta(board, float(value["started_wall"]), float(value["started_t"]),
                             int(value["firmware_pid"]), True, attached_by=os.getpid())
        files.replace(s.META, meta.encode())
    except BaseException:
        sock.close()
        for name, fd in zip(names, fds, strict=False):
            if _same_file(files, name, fd):  # made by this call (O_EXCL), not since replaced
                files.unlink(name)
        files.close()
        if made:
            with contextlib.suppress(OSError):
                os.rmdir(session)
        raise
    finally:
        for fd in fds:
            os.close(fd)
    files.close()
    return Attachment(sock, session, s.decode_meta(meta))


def _request_attach(sock: socket.socket, image: Path, board: int, fds: list[int],
                    timeout: float) -> dict[str, Any]:
    """``ATTACH`` with the session's files; the card's ``attached`` answer."""
    address = record_address(image)
    where = f"board {board} in {image.parent}"
    try:
        sock.settimeout(timeout)
        sock.connect(os.fspath(address))
        socket.send_fds(sock, [ATTACH], fds)
        kind, value = decode_answer(sock.recv(MAX_MESSAGE) or b"null")
    except (FileNotFoundError, ConnectionRefusedError):
        raise RecordingError(f"no card is running as {where} (no record socket "
                             f"{address.name} there)") from None
    except PermissionError:
        raise RecordingError(f"no permission to reach {address} (docs/security.md: join "
                             "the image directory's group)") from None
    except TimeoutError:
        raise RecordingError(f"the card of {where} did not answer within {timeout:.0f} s"
                             ) from None
    except OSError as exc:
        raise RecordingError(f"cannot reach the card of {where}: {exc.strerror}") from None
    if kind == "refused":
        raise RecordingError(f"board {board} refused the recording: {value}")
    if kind != "attached" or not isinstance(value, dict):
        raise RecordingError(f"the card of {where} answered {kind!r}, not attached")
    sock.settimeout(None)
    return value


def _same_file(files: CardDirectory, name: str, fd: int) -> bool:
    """Whether ``name`` in ``files`` is the file ``fd`` holds open."""
    try:
        st = os.stat(name, dir_fd=files.fd, follow_symlinks=False)
    except OSError:
        return False
    held = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (held.st_dev, held.st_ino)
