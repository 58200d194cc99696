"""Bounds-checked little-endian packing shared by the container and the codecs.

All input is untrusted (a user's file, a host's COM_Download), so every access
goes through these helpers, which turn short buffers, out-of-range values and
bad strings into DbmError instead of struct.error or UnicodeError.
"""

from __future__ import annotations

import functools
import struct

from dbm_tools.errors import DbmError


@functools.cache
def _layout(fmt: str) -> struct.Struct:
    """Compiled once per format: a large database unpacks the same few layouts many times."""
    return struct.Struct("<" + fmt)


def unpack(fmt: str, data: bytes, offset: int, what: str) -> tuple[int, ...]:
    """Read a little-endian struct at `offset`, or fail naming the field."""
    layout = _layout(fmt)
    if offset < 0 or offset + layout.size > len(data):
        raise DbmError(f"data too short for {what}", field=what)
    return tuple(int(v) for v in layout.unpack_from(data, offset))


def pack(fmt: str, *values: int, what: str) -> bytes:
    """Write a little-endian struct, or fail naming the field whose value does not fit."""
    try:
        return struct.pack("<" + fmt, *values)
    except struct.error as exc:
        raise DbmError(f"value out of range for {what}: {values}", field=what) from exc


def fixed(data: bytes, size: int, what: str) -> bytes:
    """Insist on an exact length (a record, a reserved area): the codecs are lossless only then."""
    if len(data) != size:
        raise DbmError(f"{what} must be {size} bytes, got {len(data)}", field=what)
    return bytes(data)


def decode_text(raw: bytes, what: str) -> str:
    """Read a NUL-padded string field.

    Bytes after the terminator must be zero: anything else would be lost on
    re-encoding, and the files we know are clean. Latin-1 maps every byte, so
    Windows-written names never fail to decode.
    """
    text, _, rest = raw.partition(b"\0")
    if rest.strip(b"\0"):
        raise DbmError(f"{what} is not NUL padded", field=what)
    return text.decode("latin-1")


def encode_text(text: str, size: int, what: str) -> bytes:
    """Write a NUL-padded string field of `size` bytes."""
    try:
        raw = text.encode("latin-1")
    except UnicodeEncodeError as exc:
        raise DbmError(f"{what} is not Latin-1: {text!r}", field=what) from exc
    if b"\0" in raw or len(raw) > size:
        raise DbmError(f"{what} does not fit {size} bytes: {text!r}", field=what)
    return raw.ljust(size, b"\0")
