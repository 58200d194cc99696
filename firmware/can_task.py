"""The CAN task (msg.rx 3): every CAN-task message of the seed manual.

This module is the task itself: its life cycle, FAT when the controller cannot be opened,
the data sets it runs (one entry point each, which the on-line download and the stored
database share), and the table of its messages. The messages live by what they do, one
module each: the download area (``can_download``), diagnosis (``can_diagnosis``), the
host's SDO transfers (``can_host_sdo``), the host's own frames (``can_bus_access``) and the
commands of our own for the CiA 309 gateway (``can_gateway``). The CANopen services they
drive live in ``firmware.can`` (the master, one handler per node, the controller).
Handlers that must wait on the bus (SDO) run in a worker and post their answer later, so
the device loop never blocks on the network.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from dbm_tools.parameters import BusParameterSet, ExtendedBusParameterSet, NodeParameterSet
from dbm_tools.validate import (
    check_bus_parameters,
    check_extended_bus_parameters,
    check_node_parameters,
)
from dpm import message
from dpm.errors import CanF
from dpm.message import Message
from dpm.task2 import CanState, GlobalBits
from firmware import card_info
from firmware.can.bus import INTERFACE_ERRORS, BusConfig
from firmware.can.master import Master
from firmware.can.pdo import await_numpy
from firmware.can_bus_access import BusAccess
from firmware.can_diagnosis import Diagnosis
from firmware.can_download import OnlineDownload
from firmware.can_gateway import GatewayCommands
from firmware.can_host_sdo import HostSdo
from firmware.task import Task

if TYPE_CHECKING:
    from firmware.whole_card import WholeCard

log = logging.getLogger(__name__)


NUMPY_WAIT_S = 1.0
"""[ours] How long a start waits, before it shows READY, for the numpy import that a network
of more than ``FEW_NODES`` nodes began (``CanTask.before_ready``): 0.1-0.2 s on a quiet
machine; under load the start goes on without it rather than keep a host's DevReset."""


class CanTask(Task):
    number = message.Task.CAN
    name = "CAN"

    def __init__(self, device: WholeCard, config: BusConfig | None = None) -> None:
        """``device`` is the whole card only for the facts the controller publishes beside
        the image (``card_info``); the master and the handlers see a ``Card``."""
        super().__init__(device)
        self.master = Master(device, config or BusConfig(), lambda: card_info.publish(device))
        self.node_data: dict[int, bytes] = {}
        self.bus_data: bytes | None = None
        self.from_flash = False
        """The running configuration came from the database in flash (``StoredDatabase``)."""
        self.run_withdrawn = False
        """[ours] "delete database" took RUN away until the next start or bus parameter set
        (``RcsTask._withdraw_run``)."""
        self.fatal: str | None = None
        """Why the controller could not be opened: the card runs with FAT (``open``)."""
        self.extended_data: bytes | None = None
        self.download = OnlineDownload(self)
        self.host_sdo = HostSdo(device, self.master)
        for commands in (self.download, Diagnosis(device, self.master), self.host_sdo,
                         BusAccess(self.master), GatewayCommands(device, self.master)):
            self.handlers.update(commands.handlers())

    # --- life cycle ---------------------------------------------------------------------------

    def open(self) -> None:
        """Connect the controller; one that cannot be opened leaves the card up with FAT.

        Seed 4.3: FAT, "because of heavy internal error, no further bus communication is
        possible". A host then sees a faulty card, not a dead one: READY without RUN, FAT in
        Task2State's global bits after every start, and [ours] f 200 ("DEVICE is not
        configured") for every CAN-task command.
        """
        try:
            self.master.open()
        except INTERFACE_ERRORS as exc:
            if self.master.config.exit_on_error:
                raise
            cfg = self.master.config
            self.fatal = (f"cannot open CAN interface {cfg.interface!r} channel "
                          f"{cfg.channel!r}: {exc}")
            log.error("%s; the card stays up with FAT set (no bus communication)", self.fatal)

    def close(self) -> None:
        self.master.close()

    def handle(self, msg: Message) -> Message | None:
        if self.fatal is not None:
            return msg.answer(f=CanF.NOT_CONFIGURED)  # FAT: no bus to configure or use
        return super().handle(msg)

    def reset(self, cold: bool) -> None:
        del cold
        if self.fatal is not None:
            self.device.set_global_bit(GlobalBits.FAT, True)  # after every start's clear
        self.master.reset()
        self.node_data.clear()
        self.bus_data = None
        self.extended_data = None
        self.from_flash = False
        self.run_withdrawn = False
        self.download.reset()
        self.host_sdo.reset()

    @property
    def configured(self) -> bool:
        return self.master.nmt.running

    def can_state(self) -> CanState:
        return self.master.can_state()

    def next_indication(self) -> Message | None:
        return self.master.layer2.next_indication()

    def indication_waiting(self) -> bool:
        """An indication waits for the host mailbox (read without the queue's lock: a hint
        for the device loop's poll and rings, which look again)."""
        return bool(self.master.layer2.indications)

    # --- the configuration entry points (also used at start-up from flash) ---------------------

    def download_node(self, address: int, data: bytes) -> int:
        """Check and take one node parameter data set; 0 or the seed's msg.f."""
        errors = [f for f in check_node_parameters(data, address) if f.severity == "error"]
        if errors:
            return errors[0].number
        return self.take_node(address, data, NodeParameterSet.decode(data))

    def take_node(self, address: int, data: bytes, params: NodeParameterSet) -> int:
        """Take a node parameter data set that passed ``check_node_parameters`` already, with
        ``params`` decoded from it: the stored database's, which ``check_dbm`` checked at
        the start (checking the 127 sets of a full database again cost each start another
        2 ms of CPU, issue 22); 0 or the seed's msg.f."""
        if address in self.node_data or (address == self.master.ext.bNodeID and address):
            return CanF.DOUBLE_ADDRESS  # a second data set never replaces the first unseen
        self.node_data[address] = bytes(data)
        self.master.configure_node(address, params)
        return 0

    def download_extended(self, data: bytes) -> int:
        errors = [f for f in check_extended_bus_parameters(data) if f.severity == "error"]
        if errors:
            return errors[0].number
        ext = ExtendedBusParameterSet.decode(data)
        if ext.bNodeID and ext.bNodeID in self.node_data:
            return CanF.DOUBLE_ADDRESS
        self.extended_data = bytes(data)
        self.master.ext = ext
        return 0

    def before_ready(self) -> None:
        """What a start with a stored database finishes before READY: the master's numpy
        import, begun when its network passed ``FEW_NODES`` nodes, at most ``NUMPY_WAIT_S``.
        Why: its 0.3 s of CPU ran on in a thread after READY, in the first boot of a host
        that cold-starts at once, as the spare SYNC timer's start had (issue 22, note 5);
        the card pays it once per process, before READY as a card on ``shm`` did while its
        stations imported numpy."""
        await_numpy(NUMPY_WAIT_S)

    def download_bus(self, data: bytes) -> int:
        """The bus parameter data set; a good one starts the network."""
        errors = [f for f in check_bus_parameters(data) if f.severity == "error"]
        if errors:
            return errors[0].number
        self.bus_data = bytes(data)
        self.run_withdrawn = False
        self.master.start_network(BusParameterSet.decode(data))
        return 0
