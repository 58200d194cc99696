import mmap
from typing import Any

def change(image: mmap.mmap, offset: int, set_bits: int, clear_bits: int, toggle: int, /) -> int:
    """Set, clear, then toggle bits of the byte at ``offset``, atomically; the new value."""

def change_ring(image: mmap.mmap, offset: int, set_bits: int, clear_bits: int, toggle: int,
                fd: int, address: bytes, payload: int, /) -> int:
    """``change``, then a one-byte datagram from socket ``fd`` to ``address``; the new value."""

def wait_ring(fd: int, timeout: float, wake: int = -1, /) -> int:
    """Every ring queued once ``fd`` is readable within ``timeout`` s: -1 none came in time,
    0 another thread took it, else the last ring's byte; -2 when only the pipe ``wake``
    became readable (it is emptied). ``timeout`` 0 without ``wake``: the rings queued now,
    without asking ppoll first (-1: none)."""

def setup(host_flags: int, dev_flags: int, dev_mbx: int, pc_mbx: int, devcom: int,
          hostack: int, dev_pending: int, host_pending: int, nak: int, seq_mask: int,
          first: int, cont: int, last: int, ring: int, ledger_max: int,
          unanswered: frozenset[tuple[int, int]], request_type: type, message_type: type,
          /) -> None:
    """The layout's offsets and bits, the ledger's Request and dpm's Message types, for
    ``put_request`` and ``take_answer`` (once, by ``host_api.driver``)."""

def put_request(transaction: object, image: mmap.mmap, message: object, raw: bytes, fd: int,
                address: bytes, /) -> bool:
    """``put_inside``'s work when nothing waits: ``raw`` in the device mailbox, the request
    in the ledger (``Transaction.sent``), DEVCOM toggled, the device rung. False, with
    nothing done, when the Python path must do it."""

def take_answer(transaction: object, image: mmap.mmap, size: int, fd: int, address: bytes,
                ring: bool, /) -> Any:
    """``get_inside``'s work when nothing waits: the host mailbox's message (a
    ``dpm.message.Message``), HOSTACK toggled (the device rung when ``ring``), its request
    settled (``Transaction.answered``). None, with nothing done, when the Python path must
    do it."""
