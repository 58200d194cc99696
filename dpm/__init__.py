"""The card's header: the dual-port memory's layout, flags, messages and numbers.

One module per part of the seed manual's header: ``layout`` (every offset, as numpy
dtypes), ``flags`` (HostFlags/DevFlags and the handshakes), ``message`` (MSG_STRUC, the
telegram header, task numbers), ``commands`` (command codes and message sizes),
``errors`` (driver codes, ``msg.f`` and Err_Event numbers and texts), ``task2``
(Task2Parameter/Task2State), ``image`` (the image file) and ``doorbell`` (the event
channel). Every other package takes the card's numbers from here. ``DpmError`` is the root of
what this package raises.

The names below are the ones nearly every user of the card needs; the rest are imported
from their modules.
"""

from importlib.metadata import version

from dpm.commands import Com, LoadMode, Nmt, Plc, Rcs
from dpm.errors import DpmError, Drv
from dpm.flags import DevFlag, HostFlag
from dpm.message import Ext, Message, MessageError, Task, TelegramHeader, Tfc
from dpm.task2 import ComDiagnostics, ComPlcParameter

__version__ = version("cifemu")

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
