"""The host program under test: a stand-in for the user's own.

It sets a node's outputs through the classic driver API and confirms them by the node's
inputs: the generic I/O module of a cifemu network (a CiA 401-style node) sends back on
its TPDO what it received on its RPDO. It opens the board without naming a directory,
as a program written for the real card does; the ``cif_card`` fixture has set
``$CIF_DPM_DIR`` to the test's card.
"""

from __future__ import annotations

import time

from host_api.board import Board


def write_and_confirm(board: int, offset: int, outputs: bytes, timeout_s: float = 10.0) -> bytes:
    """Write ``outputs`` at ``offset`` of the output area until the same bytes come back
    at ``offset`` of the input area; the inputs then. TimeoutError when they never do."""
    with Board(board) as card:
        deadline = time.monotonic() + timeout_s
        while True:
            inputs = card.exchange_io(outputs, send_offset=offset,
                                      receive_size=len(outputs), receive_offset=offset)
            if inputs == outputs:
                return inputs
            if time.monotonic() > deadline:
                raise TimeoutError(f"wrote {outputs.hex()} at {offset}, read {inputs.hex()}")
