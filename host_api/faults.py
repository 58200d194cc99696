"""Card-side faults from a test's side: ask a running card to misbehave [ours].

``inject(kind, board=0, directory=None, ...)`` sends one request (``dpm.faults``) to the
fault socket of board ``board``'s firmware and returns the faults in force afterwards;
``clear`` ends them all, ``active`` only asks. Each raises ``FaultError`` with one line a
person can act on: no card serves the board, the directory keeps this user out, the
firmware did not answer, or it refused the request (with its reason). A request that is
malformed on this side (an unknown kind, a number out of range) raises
``dpm.faults.FaultRequestError`` before anything is sent. docs/faults.md says what each
kind does and what a real card would show.

Why not through the image: a fault is what the card does of itself, not what a host asks
of it; no host message or flag could stand for it without changing the card's protocol.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

from dpm.faults import (
    CLEAR,
    LIST,
    MAX_DATAGRAM,
    REPLY_TIMEOUT_S,
    ActiveFault,
    FaultRequest,
    FaultRequestError,
    decode_reply,
    fault_address,
)
from dpm.image import dpm_dir, image_path
from host_api.errors import HostApiError
from host_api.next_steps import card_options


class FaultError(HostApiError):
    """The fault could not be injected; the message is one line that says why."""


def inject(kind: str, board: int = 0, directory: str | Path | None = None, *,
           for_ms: int | None = None, code: int = 0, delay_ms: int = 0, offset: int = 0,
           bit: int = 0, hang: bool = False, timeout: float = REPLY_TIMEOUT_S,
           ) -> list[ActiveFault]:
    """Inject a fault of ``kind`` (``dpm.faults.KINDS``) into board ``board``'s card in
    ``directory`` (default ``$CIF_DPM_DIR``, /dev/shm/cif); the faults in force after it.

    ``for_ms``: how long it lasts (None: until ``clear``; for ``flip``: one exchange);
    ``code``: the RCS error of ``rcs-error``; ``delay_ms``: the lateness of ``slow``;
    ``offset``, ``bit``: the input bit of ``flip``; ``hang``: a ``die`` that keeps the
    process. ``stall`` and ``bus-off`` need ``for_ms``."""
    return send(FaultRequest(kind, for_ms=for_ms, code=code, delay_ms=delay_ms,
                             offset=offset, bit=bit, hang=hang), board, directory, timeout)


def clear(board: int = 0, directory: str | Path | None = None,
          timeout: float = REPLY_TIMEOUT_S) -> list[ActiveFault]:
    """End every fault in force on the card (a hanging card comes back by a cold start)."""
    return send(FaultRequest(CLEAR), board, directory, timeout)


def active(board: int = 0, directory: str | Path | None = None,
           timeout: float = REPLY_TIMEOUT_S) -> list[ActiveFault]:
    """The faults in force on the card, each with the milliseconds it has left."""
    return send(FaultRequest(LIST), board, directory, timeout)


def send(request: FaultRequest, board: int = 0, directory: str | Path | None = None,
         timeout: float = REPLY_TIMEOUT_S) -> list[ActiveFault]:
    """One request to the card's fault socket and its reply."""
    folder = dpm_dir(directory)
    address = fault_address(image_path(folder, board))
    start = f"`cifemu firmware{card_options(board, directory)}`"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(b"")  # an automatic abstract name: the card answers there
        sock.settimeout(timeout)
        try:
            sock.sendto(request.encode(), address)
        except (FileNotFoundError, ConnectionRefusedError):
            raise FaultError(f"no card serves board {board} in {folder} (no fault socket "
                             f"{address}); is {start} running?") from None
        except PermissionError:
            raise FaultError(f"no permission to reach the card's fault socket {address} "
                             "(docs/security.md: join the directory's group)") from None
        except OSError as exc:
            raise FaultError(f"{address}: {os.strerror(exc.errno or 0)}") from None
        try:
            reply = sock.recv(MAX_DATAGRAM + 1)
        except TimeoutError:
            raise FaultError(f"board {board}: the card did not answer the fault request "
                             f"within {timeout:g} s") from None
    try:
        return decode_reply(reply)
    except FaultRequestError as exc:
        raise FaultError(f"board {board}: the card refused the fault: {exc}") from None
