"""The card as its tasks see it: the narrow interface ``Device`` implements.

Why a protocol and not the device: the tasks (RCS, PLC, CAN), the CANopen master and the
flash's start-up configuration all took ``firmware.device.Device`` for their type, and
the device imports every one of them, so nine modules stood in one import circle. What
they use of the card is small: the image, the flag and Task2State bits the card writes,
the errors and counters it reports, ``post`` to answer from another thread, and
``sleep`` to wait inside the device loop. ``Card`` names just that, and ``Device``
implements it structurally, without naming it; no task imports the device.

Every member is read-only here (a property), so a device may hold a narrower type
(``plc`` is its ``PlcTask``, which has an ``image``). What a start needs beyond this, the
flash and every task, is ``firmware.whole_card.WholeCard``; it lives apart because the
flash's start-up takes a ``Card`` and ``WholeCard`` names the flash.
"""

from __future__ import annotations

import mmap
from typing import Protocol

from dbm_tools.parameters import NodeParameterSet
from dpm.doorbell import DeviceBell
from dpm.message import Message
from firmware.process_image import ProcessImage

Answer = Message | bytes
"""An answer or indication for the host mailbox: a ``Message``, or the bytes it encodes to
[ours]. The CAN task's host SDO answers are made as bytes (``firmware.can_host_sdo``): a
``Message`` decoded from them only to be encoded again at the delivery cost the thread that
ends the transfer (the receive thread on a real bus) three Python calls per transfer
(issue 22)."""


class HasImage(Protocol):
    """The PLC task as the CAN master sees it: the process data the PDOs carry."""

    @property
    def image(self) -> ProcessImage: ...


class HostReadiness(Protocol):
    """The RCS task as the CAN master sees it: whether the host's NOTREADY holds (seed 4.3)."""

    @property
    def host_not_ready(self) -> bool: ...


class Configurable(Protocol):
    """The CAN task's configuration entry points: 0 or the seed's msg.f for each data set.

    The stored database hands its data sets to the same entry points the host's downloads
    take (``StoredDatabase.configure``), so a database in flash is checked as a download is;
    its node sets go to ``take_node``, since ``check_dbm`` checked and decoded them already.
    """

    from_flash: bool

    def download_extended(self, data: bytes) -> int: ...

    def download_node(self, address: int, data: bytes) -> int: ...

    def take_node(self, address: int, data: bytes, params: NodeParameterSet) -> int: ...

    def download_bus(self, data: bytes) -> int: ...


class Card(Protocol):
    """What the card's tasks use of it; see the module's docstring for why so little."""

    @property
    def mm(self) -> mmap.mmap: ...

    @property
    def bell(self) -> DeviceBell: ...

    @property
    def plc(self) -> HasImage: ...

    @property
    def rcs(self) -> HostReadiness: ...

    @property
    def can(self) -> Configurable: ...

    def post(self, msg: Answer) -> None:
        """Answer later, from any thread (``Device.post``)."""

    def sleep(self, seconds: float) -> bool:
        """Wait inside the device loop; True when the card is told to stop."""

    def write_host_flags(self, value: int) -> None: ...

    def toggle_host_flags(self, bits: int) -> None: ...

    def set_exchange_mode(self, mode: int) -> None: ...

    def set_global_bit(self, bit: int, on: bool) -> None: ...

    def set_node_bit(self, field: str, address: int, on: bool) -> None: ...

    def report_error(self, node: int, event: int, bits: int = 0) -> None: ...

    def clear_error(self, node: int) -> None: ...

    def count(self, counter: str, by: int = 1, bit: int = 0) -> None: ...

    def can_state_changed(self) -> None:
        """The CAN master changed its state from its own thread (``Device.can_state_changed``)."""

    def reset_counters(self, bits: int) -> None: ...

    def descript_records(self) -> dict[int, bytes] | None: ...
