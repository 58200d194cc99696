import mmap
import threading
from collections import deque
from typing import Any

def configure(layout: dict[str, int], types: tuple[tuple[int, int, int], ...], /) -> None:
    """The offsets, bits, numbers and msg.f of dpm/ by name; per data type its limits."""

def configure_record(spool: dict[str, int | tuple[int, str, int]], /) -> None:
    """The spool's heads by event kind (code, struct format, size), and the recorder's reads."""

def configure_exchange(numbers: dict[str, int | tuple[int, str, int]], /) -> None:
    """The exchange's flag bits, RcvPd's offset and the spool head of an exchange."""

def serve(
    image: mmap.mmap, fd: int, hosts: list[bytes], interval: float, due: float, device: object,
    calls: deque[Any], outbox: deque[Any], indications: deque[Any], turn: threading.Lock,
    image_lock: threading.RLock, inputs: bytearray, outputs: bytes, conn: bytes,
    record: tuple[object, bytearray, int, int] | None,
    sdo: object, exchange: tuple[object, bytearray] | None = None, /,
) -> tuple[list[tuple[bytes, str | bytes]], list[bytes], int, int, int, int, int]:
    """Answer the last host's COM_Shared_Memory reads until a turn needs Python."""
