"""``cifemu``, the umbrella command: ``main`` parses ``cifemu COMMAND ...``.

``cifemu.cli.COMMANDS`` is the one table of commands: each names the module that
implements it, which is imported only when that command runs. ``__version__`` is read
from the package metadata when first asked for: importlib.metadata costs every command's
start-up a few tens of milliseconds otherwise.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from cifemu.cli import build_parser, main

if TYPE_CHECKING:
    __version__: str

__all__ = ["__version__", "build_parser", "main"]


def __getattr__(name: str) -> str:
    if name == "__version__":
        from importlib.metadata import version

        return version("cifemu")
    raise AttributeError(f"module 'cifemu' has no attribute {name!r}")
