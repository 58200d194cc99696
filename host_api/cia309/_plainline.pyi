from collections.abc import Callable, Mapping
from typing import TypeVar

_Request = TypeVar("_Request")
_Type = TypeVar("_Type", bound=str)

def read_line(upload: Callable[..., _Request], types: Mapping[str, _Type], max_node: int,
              data: bytes, max_line: int, /) -> _Request | None:
    """The SDO upload ``data`` makes when it is one whole line in the plain form of a read
    with no white space around it: ``upload(sequence=, net=, node=, index=, subindex=,
    dtype=)``, ``dtype`` ``types[name]`` or None; None otherwise."""

def format_upload(lely: bool, line_end: str, sequence: int, dtype: str | None, data: bytes,
                  /) -> str | None:
    """``formatters.format_upload``'s answer for no type, HEX or an integer type of the
    data's size; None otherwise."""
