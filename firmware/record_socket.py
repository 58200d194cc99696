"""The card's side of the record socket: a recording attached while the card runs [ours].

The contract (``board<N>.record``, ATTACH with two descriptors, the answers) is
``dpm.record_socket``. Here one thread serves it: it accepts a connection, checks the
three descriptors (regular files, open for writing: the writer must never block on a pipe
nobody reads, or the card's queue would grow without bound), starts a ``Recorder`` on
them and hands it to the device loop (``Device.record``). When the recording side
detaches, goes away, or the card stops, it takes the recorder out of the loop again,
lets the writer write everything and answers ``detached``. A second ATTACH meanwhile is
refused with the pid of the one that runs.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import selectors
import socket
import stat
import threading
from typing import TYPE_CHECKING

from dpm.record_socket import (
    ATTACH,
    DETACH,
    MAX_MESSAGE,
    encode_answer,
    peer_pid,
    record_address,
)
from firmware.recorder import Recorder

if TYPE_CHECKING:
    from firmware.device import Device

log = logging.getLogger(__name__)

REQUEST_TIMEOUT_S = 5.0
"""How long the card waits for a connected recording side's ATTACH."""


def _writable_file(fd: int) -> bool:
    return (stat.S_ISREG(os.fstat(fd).st_mode)
            and fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_ACCMODE in (os.O_WRONLY, os.O_RDWR))


class RecordSocket:
    """``board<N>.record`` of ``device``, served by a thread of its own.

    Made while the firmware holds the board's lock: a socket file already there is a
    killed firmware's and is replaced. A socket that cannot be offered costs the card
    its attached recordings, never its service: one line in the log."""

    def __init__(self, device: Device) -> None:
        self._device = device
        self._path = record_address(device.path)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)
        self._wake_r, self._wake_w = socket.socketpair()
        self._attached: socket.socket | None = None
        self._recorder: Recorder | None = None
        self._peer = 0
        self._thread: threading.Thread | None = None
        try:
            device.files.bind(self._sock, self._path)
            self._sock.listen(4)
        except OSError as exc:
            log.error("record socket not offered, `cifemu record` cannot attach: %s", exc)
            self._sock.close()
            return
        self._thread = threading.Thread(target=self._serve, name="record-socket", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """End an attached recording (its session complete) and stop serving."""
        if self._thread is not None:
            self._wake_w.send(b"x")
            self._thread.join()
            self._sock.close()
            self._device.files.unlink(self._path.name)
        self._wake_r.close()
        self._wake_w.close()

    def _serve(self) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self._sock, selectors.EVENT_READ)
            selector.register(self._wake_r, selectors.EVENT_READ)
            while True:
                for key, _ in selector.select():
                    if key.fileobj is self._wake_r:
                        self._detach(card_stopped=True)
                        return
                    if key.fileobj is self._sock:
                        self._accept(selector)
                    elif key.fileobj is self._attached:
                        try:
                            request = self._attached.recv(MAX_MESSAGE)
                        except OSError:
                            request = b""
                        if request in (DETACH, b""):  # b"": the recording side went away
                            selector.unregister(self._attached)
                            self._detach(card_stopped=False)

    def _accept(self, selector: selectors.BaseSelector) -> None:
        try:
            conn, _ = self._sock.accept()
        except OSError:
            return
        conn.settimeout(REQUEST_TIMEOUT_S)
        fds: list[int] = []
        try:
            request, fds, flags, _ = socket.recv_fds(conn, MAX_MESSAGE, 3)
            refusal = self._refusal(request, fds, flags)
            if refusal is None:
                try:
                    recorder = self._start(fds)
                except Exception as exc:  # whatever starting the writer raised: its reason
                    log.exception("a recording could not start")
                    refusal = f"the card could not start a recording: {exc}"
            if refusal is not None:
                conn.send(encode_answer("refused", refusal))
                conn.close()
                return
        except OSError as exc:
            log.warning("an attach to the record socket failed: %s", exc)
            conn.close()
            return
        finally:
            for fd in fds:
                os.close(fd)  # the writer holds its own copies
        self._attached, self._recorder, self._peer = conn, recorder, peer_pid(conn)
        conn.settimeout(None)
        selector.register(conn, selectors.EVENT_READ)
        log.info("recording attached by pid %d", self._peer)
        with contextlib.suppress(OSError):  # gone already: its hang-up ends the recording
            conn.send(encode_answer("attached", {
                "board": recorder.board, "firmware_pid": os.getpid(),
                "started_t": recorder.started_t, "started_wall": recorder.started_wall,
                "channel": self._device.can.master.config.channel}))

    def _refusal(self, request: bytes, fds: list[int], flags: int) -> str | None:
        if (request != ATTACH or len(fds) != 3 or flags & socket.MSG_CTRUNC
                or not all(_writable_file(fd) for fd in fds)
                or fcntl.fcntl(fds[2], fcntl.F_GETFL) & os.O_ACCMODE != os.O_RDWR):
            return ("an ATTACH takes three regular files open for writing, the last also for "
                    "reading (dpm/record_socket.py)")
        if self._recorder is not None:
            return (f"it is being recorded already (attached by pid {self._peer}); end that "
                    "recording first")
        if self._device.recorder is not None:
            return "it records from its start already (cifemu firmware --record)"
        return None

    def _start(self, fds: list[int]) -> Recorder:
        device = self._device
        recorder = Recorder(device.board, fds[0], fds[1], fds[2],
                            device.can.master.config.channel)
        recorder.start(device.files, device.mm, device.plc.image)
        device.record(recorder)
        return recorder

    def _detach(self, card_stopped: bool) -> None:
        recorder, conn = self._recorder, self._attached
        if recorder is None or conn is None:
            return
        self._recorder = self._attached = None
        self._device.record(None)
        recorder.close()
        log.info("recording of pid %d detached: %d events, %d frames", self._peer,
                 recorder.events, recorder.frames)
        with contextlib.suppress(OSError):
            conn.send(encode_answer("detached", {
                "events": recorder.events, "frames": recorder.frames,
                "complete": recorder.complete, "card_stopped": card_stopped}))
        conn.close()
