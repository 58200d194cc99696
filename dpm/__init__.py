"""The card's header: the dual-port memory's layout, flags, messages and numbers.

One module per part of the seed manual's header: ``layout`` (every offset, as numpy
dtypes), ``flags`` (HostFlags/DevFlags and the handshakes), ``message`` (MSG_STRUC, the
telegram header, task numbers), ``commands`` (command codes and message sizes),
``errors`` (driver codes, ``msg.f`` and Err_Event numbers and texts), ``task2``
(Task2Parameter/Task2State), ``image`` (the image file) and ``doorbell`` (the event
channel). Every other package takes the card's numbers from here. ``DpmError`` is the root of
what this package raises.

The names below are the ones nearly every user of the card needs; the rest are imported
from their modules. They load on first use, as does ``__version__``: a command that needs
only ``dpm.errors`` (every ``cifemu COMMAND --help``) does not pay for the other modules
nor for the package metadata. numpy is imported by none of them but when ``layout``'s
dtypes or ``image_view`` are first asked for (docs/testing.md, *Start-up*).
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from dpm.commands import Com, LoadMode, Nmt, Plc, Rcs
    from dpm.errors import DpmError, Drv
    from dpm.flags import DevFlag, HostFlag
    from dpm.message import Ext, Message, MessageError, Task, TelegramHeader, Tfc
    from dpm.task2 import ComDiagnostics, ComPlcParameter

    __version__: str

_HOMES = {
    "Com": "dpm.commands", "LoadMode": "dpm.commands", "Nmt": "dpm.commands",
    "Plc": "dpm.commands", "Rcs": "dpm.commands",
    "DpmError": "dpm.errors", "Drv": "dpm.errors",
    "DevFlag": "dpm.flags", "HostFlag": "dpm.flags",
    "Ext": "dpm.message", "Message": "dpm.message", "MessageError": "dpm.message",
    "Task": "dpm.message", "TelegramHeader": "dpm.message", "Tfc": "dpm.message",
    "ComDiagnostics": "dpm.task2", "ComPlcParameter": "dpm.task2",
}

__all__ = [
    "Com",
    "ComDiagnostics",
    "ComPlcParameter",
    "DevFlag",
    "DpmError",
    "Drv",
    "Ext",
    "HostFlag",
    "LoadMode",
    "Message",
    "MessageError",
    "Nmt",
    "Plc",
    "Rcs",
    "Task",
    "TelegramHeader",
    "Tfc",
    "__version__",
]


def __getattr__(name: str) -> Any:
    """``dpm.Message`` and the others, imported from their module when first asked for."""
    if name == "__version__":
        from importlib.metadata import version

        return version("cifemu")
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'dpm' has no attribute {name!r}")
    return getattr(import_module(home), name)
