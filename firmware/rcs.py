"""The RCS system task (msg.rx 0): starts, flags, the host watchdog.

It brings the card up at every cold, warm and boot start (docs/dpm.md section 3),
follows the host's NOTREADY level and supervises the host watchdog. The DBM
load function (msg.b 6) joins it with the flash store.
"""

from __future__ import annotations

import logging
from enum import Enum
from typing import TYPE_CHECKING

from dpm import errors
from dpm import flags as fl
from dpm.commands import LOAD_FUNCTION
from dpm.layout import DEV_FLAGS, DEV_WATCHDOG, HOST_WATCHDOG, TASK2_PARAMETER, TASK_PARAMETER_SIZE
from dpm.task2 import ComPlcParameter, GlobalBits
from firmware import card_info
from firmware.flash import LoadFunction, StoredDatabase
from firmware.task import Task

if TYPE_CHECKING:
    from firmware.whole_card import WholeCard

log = logging.getLogger(__name__)


class Start(Enum):
    """The three starts of DevReset; a boot start is a cold start here [ours]."""

    COLD = "cold"
    WARM = "warm"
    BOOT = "boot"

    @classmethod
    def from_flags(cls, dev_flags: int) -> Start:
        if dev_flags & fl.RESET and dev_flags & fl.INIT:
            return cls.BOOT
        return cls.COLD if dev_flags & fl.RESET else cls.WARM


class RcsTask(Task):
    number = 0
    name = "RCS"
    device: WholeCard
    """A start reaches every part of the card (``WholeCard``), not a task's ``Card`` only."""

    def __init__(self, device: WholeCard, reset_delay: float = 0.0) -> None:
        super().__init__(device)
        self.reset_delay = reset_delay
        self.watchdog_time = 0
        self.watchdog_expired = False
        self.watchdog_stopped = False
        """[ours] The fault "watchdog" (firmware/faults.py): the card's side of the host
        watchdog has stopped."""
        self._last_dev_watchdog = 0
        self._watchdog_deadline = 0.0
        self.host_not_ready = False
        self.load_function = LoadFunction(device.flash, self._withdraw_run)
        self.handlers[LOAD_FUNCTION] = self.load_function.handle

    def reset(self, cold: bool) -> None:
        del cold
        self.load_function.abort()

    def start(self, kind: Start) -> None:
        """Run one start: everything down, parameters in, READY (and RUN) up."""
        dev = self.device
        log.info("%s start", kind.value)
        dev.write_host_flags(0)  # READY first, so no host sees stale flags as ready
        dev.mm[DEV_FLAGS] = 0
        dev.outbox.clear()
        dev.clear_state()
        if self.reset_delay and dev.sleep(self.reset_delay):
            return
        cold = kind is not Start.WARM
        database = dev.database = StoredDatabase.load(dev.flash, dev.database)
        card_info.publish(dev)
        if cold:  # a warm start keeps the host's parameters: they rank above flash (seed 2)
            parameter = database.protocol_parameters() if database else ComPlcParameter()
        else:
            raw = dev.mm[TASK2_PARAMETER : TASK2_PARAMETER + TASK_PARAMETER_SIZE]
            parameter = ComPlcParameter.decode(raw)
        parameter.abConnStatus = b"\xff" * 16  # [ours] every node enabled after a start
        dev.mm[TASK2_PARAMETER : TASK2_PARAMETER + TASK_PARAMETER_SIZE] = parameter.encode()
        self.watchdog_time = parameter.usWatchDogTime
        self.watchdog_expired = False
        self._last_dev_watchdog = 0
        dev.mm[HOST_WATCHDOG] = 1
        dev.mm[DEV_WATCHDOG] = 0
        # A start ends a NOTREADY or watchdog hold-over: the outputs drive again (setting
        # the two fields alone left the bus STOP after HOST_NOT_READY and a reset).
        self._follow_not_ready(False)
        dev.fill_info()
        for task in dev.tasks.values():
            task.reset(cold)
        dev.plc.apply_parameters(parameter)
        if database is not None:
            if database.waits_for_host:  # [ours] bSystemStart: the host's HOST_READY starts it
                dev.mm[DEV_FLAGS] = fl.NOTREADY
                self._follow_not_ready(True)
            database.configure(dev)
            dev.can.before_ready()
        # READY, RUN and COM in one write: a host that saw READY also sees RUN.
        dev.write_host_flags(fl.READY | dev.level_flags())

    def _withdraw_run(self) -> None:
        """[ours] After "delete database" RUN drops at once, the network running on (seed
        7.2 step 1: a host deletes and reads bHostFlags again until it shows RDY alone;
        had RUN stayed until the next start, it would delete for ever). The next start, or
        a new bus parameter set, gives RUN back."""
        self.device.can.run_withdrawn = True

    def service(self, dev_flags: int, now: float) -> None:
        """Follow NOTREADY and the host watchdog; called every loop turn."""
        not_ready = bool(dev_flags & fl.NOTREADY)
        if not_ready != self.host_not_ready:
            self._follow_not_ready(not_ready)
        self._watchdog(now)

    def watchdog_due(self) -> float | None:
        """When the host watchdog expires unless triggered (monotonic seconds), or None
        while it is off, stopped, untriggered or expired: the device loop sleeps until then."""
        if (not self.watchdog_time or self.watchdog_expired or not self._last_dev_watchdog
                or self.watchdog_stopped):
            return None
        return self._watchdog_deadline

    def stop_watchdog(self, stopped: bool) -> None:
        """[ours] Stop or resume the card's side of the host watchdog (the fault
        "watchdog"): stopped, it answers no trigger and supervises nothing; resumed, it
        answers the trigger that waits and supervises from then on, so the time it was
        stopped never counts against the host."""
        self.watchdog_stopped = stopped
        if not stopped:
            self._last_dev_watchdog = 0

    def _follow_not_ready(self, not_ready: bool) -> None:
        self.host_not_ready = not_ready
        self.device.set_global_bit(GlobalBits.NRDY, not_ready)
        self.device.update_driving()

    def _watchdog(self, now: float) -> None:
        if self.watchdog_stopped:
            return
        mm = self.device.mm
        trigger = mm[DEV_WATCHDOG]
        if trigger == 0:
            self._last_dev_watchdog = 0
            return
        if self.watchdog_expired:
            return
        if trigger != self._last_dev_watchdog:
            self._last_dev_watchdog = trigger
            mm[HOST_WATCHDOG] = trigger % 255 + 1  # trigger + 1, skipping 0
            self._watchdog_deadline = now + self.watchdog_time / 1000.0
            return
        if self.watchdog_time and now > self._watchdog_deadline:
            log.warning("host watchdog expired after %d ms", self.watchdog_time)
            self.watchdog_expired = True
            self.device.report_error(errors.ERR_NODE_DEVICE, errors.ERR_EVENT_HOST_WATCHDOG)
            self.device.update_driving()

