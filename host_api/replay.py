"""Playing the host side of a recorded session against a running card [ours].

The player does through the driver what the recorded host did (docs/recording.md):
each message it put (DevPutMessage), each answer it took (DevGetMessage), each reset
and NOTREADY change (DevReset, DevSetHostState; the Task2Parameter the host had left
for a start is written first), each exchange that changed the process image
(DevExchangeIO of the whole areas). It records what it sees as a session of its own,
which ``dpm.transcript`` then compares with the recorded one.

A recorded host waited for the card between its steps (polled Task2State, repeated an
exchange until its inputs came); the recording holds what it waited for, not how. So,
as fast as the card answers, the player waits before each exchange and after each
answer until the card shows the recorded levels and Task2State, and repeats an
exchange until its inputs are the recorded ones, each up to ``step_timeout``; what is
still different then is a difference. ``pace_recorded`` also keeps the recorded gaps.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dpm import flags as fl
from dpm import session as s
from dpm.errors import DpmError, Drv, drv_name
from dpm.image import dpm_dir, image_path, open_image
from dpm.layout import HOST_FLAGS, IO_AREA_SIZE, TASK2_STATE, TASK_STATE_SIZE
from dpm.transcript import LEVELS, state_line
from host_api import driver as d

WAIT_POLL_S = 0.002
"""How often a wait for the card's state looks at the image."""


class ReplayError(DpmError, RuntimeError):
    """The player could not do a recorded step (a driver error, not a difference)."""


@dataclass(frozen=True)
class Player:
    board: int = 0
    directory: Path | None = None
    step_timeout: float = 5.0
    pace_recorded: bool = False

    def play(self, records: list[s.Record]) -> list[s.Record]:
        """Replay ``records``; the session the host sees now."""
        directory = dpm_dir(self.directory)
        rc = d.DevOpenDriver(directory)
        if rc == 0:
            rc = d.DevInitBoard(self.board)
            if rc != 0:
                d.DevCloseDriver()
        if rc != 0:
            raise ReplayError(f"board {self.board} in {directory}: {drv_name(rc)} ({rc})")
        mm = open_image(image_path(directory, self.board), readonly=True)
        try:
            return _Run(self, mm).play(records)
        finally:
            mm.close()
            d.DevExitBoard(self.board)
            d.DevCloseDriver()


class _Run:
    def __init__(self, player: Player, mm: Any) -> None:
        self.p = player
        self.mm = mm
        self.now: list[s.Record] = []
        self.outputs = bytearray(IO_AREA_SIZE)
        self.recorded_inputs = bytearray(IO_AREA_SIZE)
        self.sent = bytes(IO_AREA_SIZE)
        self.received = bytes(IO_AREA_SIZE)
        self.timeout_ms = int(player.step_timeout * 1000)
        self.recorded_host_flags = 0
        """HostFlags as the recording had them at the step being played."""

    def play(self, records: list[s.Record]) -> list[s.Record]:
        start, first = time.monotonic(), records[0].t if records else 0.0
        for number, record in enumerate(records, 1):
            if self.p.pace_recorded:
                time.sleep(max(0.0, start + record.t - first - time.monotonic()))
            try:
                self._step(record)
            except ReplayError as exc:
                raise ReplayError(f"step {number} ({record.kind}): {exc}") from None
        return self.now

    def _record(self, kind: str, **fields: Any) -> None:
        now = time.monotonic()
        self.now.append(s.Record(kind, now, time.time(), **fields))

    def _state(self) -> bytes:
        return bytes(self.mm[TASK2_STATE : TASK2_STATE + TASK_STATE_SIZE])

    def _wait_for(self, recorded: s.Record, done: Callable[[], bool] = lambda: True) -> None:
        """Until the card shows ``recorded``'s levels and Task2State (and ``done``)."""
        levels = self.recorded_host_flags & LEVELS
        want = state_line(recorded.state) if recorded.state else None
        deadline = time.monotonic() + self.p.step_timeout
        while time.monotonic() < deadline:
            if ((want is None or state_line(self._state()) == want)
                    and self.mm[HOST_FLAGS] & LEVELS == levels and done()):
                return
            time.sleep(WAIT_POLL_S)

    def _step(self, record: s.Record) -> None:
        kind = record.kind
        if kind == s.PUT and record.msg is not None:
            rc = d.DevPutMessage(self.p.board, record.msg, self.timeout_ms)
            if rc != Drv.DRV_NO_ERROR:
                raise ReplayError(f"DevPutMessage: {drv_name(rc)} ({rc})")
            self._record(s.PUT, msg=record.msg)
        elif kind == s.ANSWER:
            rc, msg = d.DevGetMessage(self.p.board, d.MSG_BUFFER_SIZE, self.timeout_ms)
            if rc not in (Drv.DRV_NO_ERROR, Drv.DRV_DEV_GET_TIMEOUT):
                raise ReplayError(f"DevGetMessage: {drv_name(rc)} ({rc})")
            self._wait_for(record)
            self._flags()
            self._record(s.ANSWER, msg=msg, state=self._state())
        elif kind == s.EXCHANGE and record.changes:
            self._exchange(record)
        elif kind == s.DEV_FLAGS:
            self._dev_flags(record)
        elif kind == s.HOST_FLAGS:
            self.recorded_host_flags = record.after

    def _flags(self) -> None:
        self._record(s.HOST_FLAGS, before=0, after=self.mm[HOST_FLAGS])

    def _exchange(self, record: s.Record) -> None:
        s.apply_runs(self.outputs, record.changes.get("SndPd", []))
        s.apply_runs(self.recorded_inputs, record.changes.get("RcvPd", []))
        self._wait_for(record)
        outputs, wanted = bytes(self.outputs), bytes(self.recorded_inputs)
        deadline = time.monotonic() + self.p.step_timeout
        while True:
            rc, inputs = d.DevExchangeIO(self.p.board, 0, outputs, 0, IO_AREA_SIZE,
                                         self.timeout_ms)
            # -21: exchanged, but COM is clear; the transcript's levels line shows that
            if rc not in (Drv.DRV_NO_ERROR, Drv.DRV_DEV_NO_COM_FLAG):
                raise ReplayError(f"DevExchangeIO: {drv_name(rc)} ({rc})")
            if inputs == wanted or time.monotonic() > deadline:
                break
            time.sleep(WAIT_POLL_S)
        changes = {area: runs for area, runs in (
            ("SndPd", s.changed_runs(self.sent, outputs)),
            ("RcvPd", s.changed_runs(self.received, inputs))) if runs}
        self.sent, self.received = outputs, inputs
        self._flags()
        self._record(s.EXCHANGE, changes=changes, state=self._state())

    def _dev_flags(self, record: s.Record) -> None:
        rising = record.after & ~record.before
        request = rising & (fl.RESET | fl.INIT)
        if request:
            if record.parameter:
                rc = d.DevPutTaskParameter(self.p.board, 2, record.parameter)
                if rc != Drv.DRV_NO_ERROR:
                    raise ReplayError(f"DevPutTaskParameter: {drv_name(rc)} ({rc})")
            mode = {fl.RESET: d.COLDSTART, fl.INIT: d.WARMSTART}.get(request, d.BOOTSTART)
            rc = d.DevReset(self.p.board, mode, max(self.timeout_ms, 15000))
            if rc != Drv.DRV_NO_ERROR:
                raise ReplayError(f"DevReset: {drv_name(rc)} ({rc})")
        if (record.before ^ record.after) & fl.NOTREADY:
            ready = not record.after & fl.NOTREADY
            d.DevSetHostState(self.p.board, d.HOST_READY if ready else d.HOST_NOT_READY, 0)
        if request or (record.before ^ record.after) & fl.NOTREADY:
            self._record(s.DEV_FLAGS, before=record.before, after=record.after,
                         parameter=record.parameter)
