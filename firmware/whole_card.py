"""The card as a start sees it: ``Card`` plus the flash, the database and every task.

Two parts of the firmware reach further than a task's own work: the RCS task's start
sequence (it resets every task, loads the database from flash, hands it to the CAN task)
and the facts a start publishes beside the image (``firmware.card_info``: the database,
the flash, the controller). ``WholeCard`` names what those two use; ``Device``
implements it structurally. It lives apart from ``firmware.card`` because it names the
flash's types, and the flash's start-up configuration takes a plain ``Card``: in one
module the two would import each other.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from firmware.card import Answer, Card, Configurable, HasImage

if TYPE_CHECKING:
    from dbm_tools.parameters import BusParameterSet
    from dpm.image import CardDirectory
    from dpm.task2 import ComPlcParameter
    from firmware.can.bus import BusConfig, CanBus
    from firmware.flash import FlashStore, StoredDatabase


class Resettable(Protocol):
    """A task as a start sees it: reset during every cold and warm start."""

    def reset(self, cold: bool) -> None: ...


class PlcSetup(HasImage, Protocol):
    """The PLC task as a start sees it: it takes the protocol parameters (bMode)."""

    def apply_parameters(self, parameter: ComPlcParameter) -> bool: ...


class ControllerFacts(Protocol):
    """The CAN master's controller as ``card.json`` reports it."""

    @property
    def config(self) -> BusConfig: ...

    @property
    def bus(self) -> CanBus | None: ...

    @property
    def bus_params(self) -> BusParameterSet | None: ...


class CanSetup(Configurable, Protocol):
    """The CAN task as a start and ``card.json`` see it."""

    run_withdrawn: bool

    @property
    def fatal(self) -> str | None: ...

    @property
    def master(self) -> ControllerFacts: ...

    def before_ready(self) -> None: ...


class WholeCard(Card, Protocol):
    """What the start sequence and the card's facts use; see the module's docstring."""

    database: StoredDatabase | None

    @property
    def board(self) -> int: ...

    @property
    def path(self) -> Path: ...

    @property
    def directory(self) -> Path: ...

    @property
    def files(self) -> CardDirectory:
        """The checked image directory: files beside the image are written through it."""

    @property
    def flash(self) -> FlashStore: ...

    @property
    def outbox(self) -> deque[Answer]: ...

    @property
    def tasks(self) -> Mapping[int, Resettable]: ...

    @property
    def plc(self) -> PlcSetup: ...

    @property
    def can(self) -> CanSetup: ...

    def clear_state(self) -> None: ...

    def fill_info(self) -> None: ...

    def level_flags(self) -> int: ...

    def update_driving(self) -> None: ...
