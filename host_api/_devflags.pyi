import mmap

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
