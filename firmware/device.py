"""The emulated card: one image, one device loop, the tasks behind it.

The device loop is the only writer of HostFlags, as the card's firmware is the
only writer of its flag byte: it wakes on a host's ring or every poll
interval, looks at DevFlags, and serves the mailboxes, the process-data and
state handshakes, special control, NOTREADY and the watchdog. Tasks that work
in threads of their own (the CAN task) hand answers over with ``post``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dpm import flags as fl
from dpm.doorbell import POLL_INTERVAL, DeviceBell
from dpm.errors import F_UNKNOWN_TASK
from dpm.image import ExclusiveLock, create_image, dpm_dir, image_path, lock_path
from dpm.layout import (
    DEV_FLAGS,
    DEV_MBX,
    DRIVER_TYPE,
    HOST_FLAGS,
    PC_MBX,
    TASK2_STATE,
    TASK_STATE_SIZE,
    image_view,
)
from dpm.message import Ext, Message
from dpm.task2 import CanState
from firmware import info
from firmware.can_task import CanTask
from firmware.plc import PlcTask
from firmware.rcs import RcsTask, Start
from firmware.task import Task

log = logging.getLogger(__name__)

OUTBOX_LIMIT = 64
"""Answers waiting for the host; past this the device stops taking commands,
so a host that never reads its answers sees a full mailbox (-16/-17) instead
of the card silently dropping answers."""

STATE_MODE_EVENT = 4
"""[ours] low nibble of bDriverType: the state field is event driven."""


class Device:
    """Board N of one emulated card, served from the calling thread by ``run``."""

    def __init__(
        self, board: int = 0, directory: str | Path | None = None, *, reset_delay: float = 0.0
    ) -> None:
        self.board = board
        self.directory = dpm_dir(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self._instance_lock = ExclusiveLock(lock_path(self.directory, board))
        self.path = image_path(self.directory, board)
        self.mm = create_image(self.path)
        self.view: Any = image_view(self.mm)
        self.bell = DeviceBell(self.path)
        self.outbox: deque[Message] = deque()
        self._calls: deque[Callable[[], None]] = deque()
        self._stop = threading.Event()
        self._ring = False
        self._state_sent = b""
        self._can_state = -1
        self.rcs = RcsTask(self, reset_delay)
        self.plc = PlcTask(self)
        self.can = CanTask(self)
        self.tasks: dict[int, Task] = {t.number: t for t in (self.rcs, self.plc, self.can)}

    # --- life cycle -----------------------------------------------------------------

    def run(self) -> None:
        """Power on (a cold start), then serve the image until ``stop``."""
        try:
            self.rcs.start(Start.COLD)
            self._flush()
            while not self._stop.is_set():
                self.bell.wait(POLL_INTERVAL)
                self.service(time.monotonic())
        finally:
            self._power_off()

    def stop(self) -> None:
        """Ask the loop to end; safe from signal handlers and other threads."""
        self._stop.set()
        self.bell.ring_self()

    def sleep(self, seconds: float) -> bool:
        """Wait inside the loop (an emulated slow reset); True when told to stop."""
        return self._stop.wait(seconds)

    def _power_off(self) -> None:
        self.write_host_flags(0)
        self._flush()
        self.bell.close()
        del self.view
        self.mm.flush()
        self.mm.close()
        self._instance_lock.release()

    # --- cross-thread entry points ---------------------------------------------------

    def post(self, msg: Message) -> None:
        """Queue an answer or indication for the host (any thread)."""
        self._calls.append(lambda: self.outbox.append(msg))
        self.bell.ring_self()

    def call_soon(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` in the device loop (any thread)."""
        self._calls.append(fn)
        self.bell.ring_self()

    # --- flags -------------------------------------------------------------------------

    def write_host_flags(self, value: int) -> None:
        self.mm[HOST_FLAGS] = value
        self._ring = True

    def toggle_host_flags(self, bits: int) -> None:
        self.write_host_flags(self.mm[HOST_FLAGS] ^ bits)

    def _set_level(self, bit: int, on: bool) -> None:
        host = self.mm[HOST_FLAGS]
        if bool(host & bit) != on:
            self.write_host_flags(host ^ bit)

    def _flush(self) -> None:
        if self._ring:
            self._ring = False
            self.bell.ring_hosts(want_ack=bool(self.outbox))

    # --- Task2State ----------------------------------------------------------------------

    def clear_state(self) -> None:
        self.mm[TASK2_STATE : TASK2_STATE + TASK_STATE_SIZE] = bytes(TASK_STATE_SIZE)
        self._state_sent = bytes(TASK_STATE_SIZE)
        self._can_state = CanState.OFFLINE

    def set_global_bit(self, bit: int, on: bool) -> None:
        state = self.view["Task2State"]
        value = int(state["bGlobalBits"])
        state["bGlobalBits"] = value | bit if on else value & ~bit

    def set_error(self, node: int, event: int, bits: int = 0) -> None:
        """Report an error; the lowest faulty address wins (seed manual 4.3)."""
        state = self.view["Task2State"]
        if int(state["bErr_event"]) == 0 or node <= int(state["bErr_rem_adr"]):
            state["bErr_rem_adr"] = node
            state["bErr_event"] = event
        if bits:
            self.set_global_bit(bits, True)

    def set_exchange_mode(self, mode: int) -> None:
        self.mm[DRIVER_TYPE] = (mode << 4) | STATE_MODE_EVENT

    def update_driving(self) -> None:
        """Outputs reach the bus only while the host is ready and its watchdog alive."""
        self.plc.image.driving = not (self.rcs.host_not_ready or self.rcs.watchdog_expired)

    def fill_info(self) -> None:
        info.fill(self.view, self.board)

    # --- the loop's work ---------------------------------------------------------------

    def service(self, now: float) -> None:
        """One turn of the device loop."""
        while self._calls:
            self._calls.popleft()()
        mm = self.mm
        dev = mm[DEV_FLAGS]
        if dev & (fl.RESET | fl.INIT):
            self.rcs.start(Start.from_flags(dev))
            self._flush()
            return
        self.rcs.service(dev, now)
        self._levels()
        if (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.DEV_MBX and len(self.outbox) < OUTBOX_LIMIT:
            self._receive()
        if self.outbox and not (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.HOST_MBX:
            self._deliver()
        self.plc.service(mm[HOST_FLAGS], mm[DEV_FLAGS])
        self._state_field()
        self._set_level(fl.SPCACK, bool(mm[DEV_FLAGS] & fl.SPCCOM))
        self._flush()

    def _levels(self) -> None:
        """RUN follows the configuration, COM the bus communication."""
        configured = self.can.configured and self.plc.image.mode != 0
        com = configured and self.can.communicating and self.plc.image.driving
        self._set_level(fl.RUN, configured)
        self._set_level(fl.COM, com)
        state = CanState.OPERATE if com else CanState.STOP if configured else CanState.OFFLINE
        if state != self._can_state:
            self._can_state = state
            self.view["Task2State"]["bCAN_State"] = state

    def _receive(self) -> None:
        mm = self.mm
        ln = mm[DEV_MBX + 2]
        raw = mm[DEV_MBX : DEV_MBX + 8 + ln]
        self.toggle_host_flags(fl.DEVACK)
        msg = Message.decode(raw)
        task = self.tasks.get(msg.rx)
        answer = task.handle(msg) if task else msg.answer(f=F_UNKNOWN_TASK)
        if answer is not None and not (msg.e & Ext.NAK and answer.f == 0):
            self.outbox.append(answer)

    def _deliver(self) -> None:
        raw = self.outbox.popleft().encode()
        self.mm[PC_MBX : PC_MBX + len(raw)] = raw
        self.toggle_host_flags(fl.HOSTCOM)

    def _state_field(self) -> None:
        """Event-driven state field: toggle STATECOM when Task2State changed."""
        mm = self.mm
        if (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.STATE:
            return
        current = mm[TASK2_STATE : TASK2_STATE + TASK_STATE_SIZE]
        if current != self._state_sent:
            self._state_sent = current
            self.toggle_host_flags(fl.STATECOM)

