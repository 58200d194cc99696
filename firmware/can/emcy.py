"""EMCY consumption for one node: its emergency frames into its diagnosis (seed 5.2.7).

Why a module of its own: EMCY is a service of its own in CiA 301 (7.2.7), as in
canopen's ``canopen/emcy.py``, with a COB-ID the host may move or switch off at run time
(COM_Set_Emcy_Consumer) while the node runs. It shares with the node handler only the
diagnosis it writes into and the Nd_diag bit it raises; it never changes the node's state.
"""

from __future__ import annotations

from collections.abc import Callable

import can

from dpm.com import EMCY_ENTRIES, NodeDiagnosis, NodeStatus
from firmware.can.bus import CanBus


class EmcyConsumer:
    """The EMCY frames of one COB-ID, collected for COM_Node_Diag."""

    def __init__(self, diag: NodeDiagnosis, cob_id: int | None,
                 raise_diag: Callable[[], None]) -> None:
        self._diag = diag
        self.cob_id = cob_id
        """EMCY COB-ID collected for COM_Node_Diag; None while the EMCY consumer is off."""
        self._raise_diag = raise_diag
        """Sets the node's Nd_diag bit: a new entry waits for the host."""

    def attach(self, bus: CanBus) -> None:
        if self.cob_id is not None:
            bus.subscribe(self.cob_id, self._on_emcy)

    def detach(self, bus: CanBus) -> None:
        if self.cob_id is not None:
            bus.unsubscribe(self.cob_id, self._on_emcy)

    def move(self, bus: CanBus | None, cob_id: int | None) -> None:
        """COM_Set_Emcy_Consumer: collect EMCY frames of ``cob_id``, or none."""
        if bus is not None:
            self.detach(bus)
        self.cob_id = cob_id
        if bus is not None:
            self.attach(bus)

    def _on_emcy(self, msg: can.Message) -> None:
        if msg.is_remote_frame:
            return
        if len(self._diag.emcy) == EMCY_ENTRIES:
            self._diag.status |= NodeStatus.EMCY_BUFFER_OVERFLOW
        self._diag.emcy.append(bytes(msg.data).ljust(8, b"\0")[:8])
        self._raise_diag()
