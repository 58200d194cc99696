"""NMT slave and error control of a simulated node (CiA 301 7.2.8).

canopen's ``NmtSlave`` keeps the state and produces the heartbeat (a
python-can periodic task, BCM-timed on SocketCAN, restarted on 1017h writes);
``SimNmt`` keeps all of that. What it lacks, and ``SimulatedNode`` adds: a
reset command from the bus leaves canopen's slave in INITIALISING for good
(no boot-up message, no return to PRE-OPERATIONAL, parameters not restored),
and it has no node guarding at all: python-can remote frames never even reach
canopen's subscribers.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from canopen.nmt import NMT_COMMANDS, NmtSlave

from dpm.cia301 import INITIALISING
from firmware.sim.scheduler import Timer

if TYPE_CHECKING:
    from firmware.sim.node import SimulatedNode

# NMT command specifiers, as canopen names them: the simulated nodes take nothing from the
# card's modules (the card's own copy is dpm.commands.Nmt)
START = NMT_COMMANDS["OPERATIONAL"]
STOP = NMT_COMMANDS["STOPPED"]
ENTER_PRE_OPERATIONAL = NMT_COMMANDS["PRE-OPERATIONAL"]
RESET_NODE = NMT_COMMANDS["RESET"]
RESET_COMMUNICATION = NMT_COMMANDS["RESET COMMUNICATION"]
COB_ID = 0x000
"""The NMT service's identifier (CiA 301)."""

TOGGLE = 0x80
LIFE_GUARD_ERROR = 0x8130
"""EMCY code: life guard error or heartbeat error (CiA 301 table 21)."""


class SimNmt(NmtSlave):
    """canopen's NMT slave whose state the node drives, with a heartbeat that can die."""

    def __init__(self, node: SimulatedNode) -> None:
        super().__init__(node.node_id, node)
        self._node = node
        self.heartbeat_failed = False
        """Fault injection: the producer stays off until the next boot-up."""

    @property
    def code(self) -> int:
        """The state as CiA 301 encodes it in heartbeat and guarding answers."""
        return self._state

    def on_command(self, can_id: int, data: bytearray, timestamp: float) -> None:
        del can_id, timestamp
        self._node.on_nmt_command(bytes(data))

    def enter(self, state: int) -> None:
        self._state = state
        self.update_heartbeat()  # type: ignore[no-untyped-call]

    def start_heartbeat(self, heartbeat_time_ms: int) -> None:
        """Also called by canopen on a 1017h write; a node that lost its heartbeat stays mute."""
        if self.heartbeat_failed or self._state == INITIALISING:
            return
        super().start_heartbeat(heartbeat_time_ms)

    def kill_heartbeat(self) -> None:
        self.heartbeat_failed = True
        self.stop_heartbeat()  # type: ignore[no-untyped-call]


class NodeGuarding:
    """Answers guarding remote frames and watches the master's life (CiA 301 7.2.8.3.2.1).

    The answer is one byte: the toggle bit (0 in the first answer after a
    boot-up, then alternating) and the NMT state. With guard time (100Ch) and
    life time factor (100Dh) both set, the first remote frame arms life
    guarding: no further one within their product is a life guarding event.
    A node whose heartbeat producer runs (1017h != 0) does not guard: CiA 301
    lets a device use only one of the two. The fault ``guard_toggle_stuck``
    keeps the toggle bit at 0, so the master sees a guarding sequence error.
    """

    def __init__(self, node: SimulatedNode) -> None:
        self._node = node
        self.toggle = 0
        self.failed = False
        """Fault injection: remote frames go unanswered until the next boot-up."""
        self.lost = False
        self._life: Timer | None = None

    def reset(self) -> None:
        self.toggle = 0
        self.failed = False
        self.lost = False
        self.cancel()

    def cancel(self) -> None:
        if self._life is not None:
            self._life.cancel()
            self._life = None

    def on_request(self) -> None:
        node = self._node
        if node.nmt.code == INITIALISING or self.failed or node.value(0x1017, 0, 0):
            return
        node.network.send_message(node.guard_cob_id,
                                  bytes([self.toggle | node.nmt.code]))
        if not node.description.sim.guard_toggle_stuck:
            self.toggle ^= TOGGLE
        self.cancel()
        life_time_ms = node.value(0x100C, 0, 0) * node.value(0x100D, 0, 0)
        if life_time_ms:
            self._life = node.scheduler.call_later(life_time_ms / 1000, self._expired)
        if self.lost:
            self.lost = False
            node.clear_error(LIFE_GUARD_ERROR)

    def _expired(self) -> None:
        self._life = None
        self.lost = True
        self._node.communication_error(LIFE_GUARD_ERROR)
