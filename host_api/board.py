"""A Pythonic face on the driver API: ``Board`` raises instead of returning codes.

::

    with Board(0) as card:
        answer = card.transact(Message(rx=2, tx=16, b=17, data=header))
        inputs = card.exchange_io(outputs, receive_size=8)

Every failure is a ``CifError`` carrying the driver's code, its CIFUSER.H
name and its meaning; RCS errors (1000 + msg.f) read with the task's text.
"""

from __future__ import annotations

import itertools
import secrets
from pathlib import Path
from types import TracebackType

from dpm import flags as fl
from dpm.errors import Drv, drv_name, drv_text
from dpm.layout import HOST_FLAGS
from dpm.message import Message, MessageError
from dpm.task2 import ComDiagnostics, ComPlcParameter
from host_api import driver as d
from host_api.errors import HostApiError
from host_api.registry import registry


class CifError(HostApiError):
    """A driver call failed: ``code``, ``name`` (e.g. DRV_DEV_NOT_READY) and ``text``."""

    def __init__(self, code: int, call: str = "", detail: str = "") -> None:
        self.code = int(code)
        self.name = drv_name(code)
        self.text = drv_text(code)
        where = f"{call}: " if call else ""
        after = f"; {detail}" if detail else ""
        super().__init__(f"{where}{self.name} ({self.code}): {self.text}{after}")


def _check(code: int, call: str) -> None:
    if code != Drv.DRV_NO_ERROR:
        raise CifError(code, call)


class Board:
    """One board of the emulated card, opened on enter and closed on exit.

    Every method that calls the driver raises ``CifError`` with the driver's code when
    the call does not return DRV_NO_ERROR; ``close`` never raises.
    """

    def __init__(self, number: int = 0, directory: str | Path | None = None,
                 timeout: int = 1000) -> None:
        self.number = number
        self.directory = directory
        self.timeout = timeout
        """Default timeout in milliseconds for calls that wait."""
        self._nr = itertools.count(secrets.randbelow(255))
        """[ours] From a random start: a process's first request rarely has the number of
        another process's, which only a host outside the transaction discipline needs
        (the ledger discards a dead host's answers, whatever their numbers)."""

    def open(self) -> Board:
        _check(d.DevOpenDriver(self.directory), "DevOpenDriver")
        code = d.DevInitBoard(self.number)
        if code != Drv.DRV_NO_ERROR:
            d.DevCloseDriver()
            raise CifError(code, "DevInitBoard")
        return self

    def close(self) -> None:
        d.DevExitBoard(self.number)
        d.DevCloseDriver()

    def __enter__(self) -> Board:
        return self.open()

    def __exit__(
        self, t: type[BaseException] | None, v: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _timeout(self, timeout: int | None) -> int:
        return self.timeout if timeout is None else timeout

    # --- mailboxes -----------------------------------------------------------------------

    def put_message(self, msg: Message, timeout: int | None = None) -> None:
        _check(d.DevPutMessage(self.number, msg, self._timeout(timeout)), "DevPutMessage")

    def get_message(self, timeout: int | None = None) -> Message:
        code, msg = d.DevGetMessage(self.number, d.MSG_BUFFER_SIZE, self._timeout(timeout))
        _check(code, "DevGetMessage")
        assert msg is not None
        return msg

    def transact(self, msg: Message, timeout: int | None = None) -> Message:
        """Send a command and return its answer, atomically against other hosts and
        this process's other threads.

        A message number is assigned when ``msg.nr`` is 0; answers with another
        number (indications) are skipped. An answer to another host's request, or to
        an earlier request that timed out, is never returned, even with this number:
        the driver discards it (``host_api.locks.Transaction``).
        """
        if msg.nr == 0:
            msg.nr = next(self._nr) % 255 + 1
        board = registry.boards.get(self.number)
        if board is None:
            raise CifError(Drv.DRV_USR_NOT_INITIALIZED, "transact")
        lock = board.transaction
        wait = self.timeout if timeout is None else timeout
        if not lock.acquire(wait / 1000.0):
            raise CifError(Drv.DRV_CMD_ACTIVE, "transact",
                           lock.holder.advice() if lock.holder is not None else "")
        # The driver's insides with the session held, not DevPutMessage and DevGetMessage:
        # the board looked up once, and neither the transaction lock's ``enter`` and ``leave``
        # nor the driver's checks of its arguments per call, on the way of every host SDO
        # (issue 22). The codes are theirs: READY is looked at before each call.
        try:
            mm = board.mm
            if not mm[HOST_FLAGS] & fl.READY:
                raise CifError(Drv.DRV_DEV_NOT_READY, "DevPutMessage")
            try:
                raw = msg.encode()
            except MessageError:
                raise CifError(Drv.DRV_USR_SIZE_INVALID, "DevPutMessage") from None
            code = d.put_inside(board, msg, raw, wait, d.call_deadline(wait))
            if code:
                raise CifError(code, "DevPutMessage")
            while True:
                if not mm[HOST_FLAGS] & fl.READY:
                    raise CifError(Drv.DRV_DEV_NOT_READY, "DevGetMessage")
                code, answer = d.get_inside(board, d.MSG_BUFFER_SIZE, wait,
                                            d.call_deadline(wait))
                if code:
                    raise CifError(code, "DevGetMessage")
                assert answer is not None
                if answer.nr == msg.nr and answer.a == msg.b:
                    return answer
        finally:
            lock.release()

    # --- process data ------------------------------------------------------------------------

    def exchange_io(self, send: bytes = b"", send_offset: int = 0, receive_size: int = 0,
                    receive_offset: int = 0, timeout: int | None = None) -> bytes:
        code, data = d.DevExchangeIO(self.number, send_offset, send, receive_offset,
                                     receive_size, self._timeout(timeout))
        _check(code, "DevExchangeIO")
        return data

    # --- control and state -------------------------------------------------------------------

    def reset(self, mode: int = d.WARMSTART, timeout: int = 5000) -> None:
        _check(d.DevReset(self.number, mode, timeout), "DevReset")

    def set_host_ready(self, ready: bool = True, timeout: int = 0) -> None:
        mode = d.HOST_READY if ready else d.HOST_NOT_READY
        _check(d.DevSetHostState(self.number, mode, timeout), "DevSetHostState")

    def trigger_watchdog(self) -> int:
        code, value = d.DevTriggerWatchDog(self.number, d.WATCHDOG_START)
        _check(code, "DevTriggerWatchDog")
        return value

    def diagnostics(self) -> ComDiagnostics:
        """Task2State decoded (COM_DIAGNOSTICS)."""
        code, raw = d.DevGetTaskState(self.number, 2, 64)
        _check(code, "DevGetTaskState")
        return ComDiagnostics.decode(raw)

    def protocol_parameters(self) -> ComPlcParameter:
        code, raw = d.DevGetTaskParameter(self.number, 2, 64)
        _check(code, "DevGetTaskParameter")
        return ComPlcParameter.decode(raw)

    def warm_start(self, parameters: ComPlcParameter, timeout: int = 5000) -> None:
        """Write the protocol parameters, then warm-start so they take effect."""
        _check(d.DevPutTaskParameter(self.number, 2, parameters.encode()[:16]),
               "DevPutTaskParameter")
        self.reset(d.WARMSTART, timeout)

    def info(self, area: int, size: int) -> bytes:
        code, data = d.DevGetInfo(self.number, area, size)
        _check(code, "DevGetInfo")
        return data
