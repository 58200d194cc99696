"""The host side of the emulated card: what a host program imports.

- the classic driver API (``host_api.driver``): ``DevOpenDriver`` ... ``DevReadWriteDPMRaw``
  with the C driver's return codes, and the load-function services of
  ``host_api.download`` (``DevDownload``, ``upload_database``, ``delete_database``,
  ``flash_directory``);
- ``Board`` and ``CifError`` (``host_api.board``): the same calls, raising instead of
  returning codes; ``HostApiError`` (``host_api.errors``), the root of what host_api raises;
- ``host_api.registry``: the boards this process has initialised;
- ``host_api.online``, ``host_api.cia309``, ``host_api.status``: the on-line
  configuration, the CiA 309 gateway and the card state ``cifemu status`` shows,
  imported by their own names.

Every name here is also importable from its module. The names load on first use (as
``__version__`` does): importing ``host_api.X`` runs this file first, and a command that
needs one module (``cifemu status --help``) should not pay for the driver, numpy and the
package metadata.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from host_api.board import (
        Board,
        CifError,
    )
    from host_api.download import (
        CONFIGURATION_DOWNLOAD,
        FIRMWARE_DOWNLOAD,
        DevDownload,
        FlashEntry,
        delete_database,
        flash_directory,
        upload_database,
    )
    from host_api.driver import (
        BOOTSTART,
        COLDSTART,
        GET_DEV_INFO,
        GET_DRIVER_INFO,
        GET_FIRMWARE_INFO,
        GET_IO_INFO,
        GET_IO_SEND_DATA,
        GET_RCS_INFO,
        GET_TASK_INFO,
        GET_VERSION_INFO,
        HOST_NOT_READY,
        HOST_READY,
        MSG_BUFFER_SIZE,
        PARAMETER_READ,
        PARAMETER_WRITE,
        SPECIAL_CONTROL_CLEAR,
        SPECIAL_CONTROL_SET,
        WARMSTART,
        WATCHDOG_START,
        WATCHDOG_STOP,
        ComState,
        DevCloseDriver,
        DevExchangeIO,
        DevExchangeIOErr,
        DevExchangeIOEx,
        DevExitBoard,
        DevGetBoardInfo,
        DevGetInfo,
        DevGetMBXState,
        DevGetMessage,
        DevGetTaskParameter,
        DevGetTaskState,
        DevInitBoard,
        DevOpenDriver,
        DevPutMessage,
        DevPutTaskParameter,
        DevReadSendData,
        DevReadWriteDPMRaw,
        DevReset,
        DevSetHostState,
        DevSpecialControl,
        DevTriggerWatchDog,
    )
    from host_api.errors import (
        HostApiError,
    )

    __version__: str

_HOMES = {
    "Board": "host_api.board",
    "CifError": "host_api.board",
    "CONFIGURATION_DOWNLOAD": "host_api.download",
    "FIRMWARE_DOWNLOAD": "host_api.download",
    "DevDownload": "host_api.download",
    "FlashEntry": "host_api.download",
    "delete_database": "host_api.download",
    "flash_directory": "host_api.download",
    "upload_database": "host_api.download",
    "BOOTSTART": "host_api.driver",
    "COLDSTART": "host_api.driver",
    "GET_DEV_INFO": "host_api.driver",
    "GET_DRIVER_INFO": "host_api.driver",
    "GET_FIRMWARE_INFO": "host_api.driver",
    "GET_IO_INFO": "host_api.driver",
    "GET_IO_SEND_DATA": "host_api.driver",
    "GET_RCS_INFO": "host_api.driver",
    "GET_TASK_INFO": "host_api.driver",
    "GET_VERSION_INFO": "host_api.driver",
    "HOST_NOT_READY": "host_api.driver",
    "HOST_READY": "host_api.driver",
    "MSG_BUFFER_SIZE": "host_api.driver",
    "PARAMETER_READ": "host_api.driver",
    "PARAMETER_WRITE": "host_api.driver",
    "SPECIAL_CONTROL_CLEAR": "host_api.driver",
    "SPECIAL_CONTROL_SET": "host_api.driver",
    "WARMSTART": "host_api.driver",
    "WATCHDOG_START": "host_api.driver",
    "WATCHDOG_STOP": "host_api.driver",
    "ComState": "host_api.driver",
    "DevCloseDriver": "host_api.driver",
    "DevExchangeIO": "host_api.driver",
    "DevExchangeIOErr": "host_api.driver",
    "DevExchangeIOEx": "host_api.driver",
    "DevExitBoard": "host_api.driver",
    "DevGetBoardInfo": "host_api.driver",
    "DevGetInfo": "host_api.driver",
    "DevGetMBXState": "host_api.driver",
    "DevGetMessage": "host_api.driver",
    "DevGetTaskParameter": "host_api.driver",
    "DevGetTaskState": "host_api.driver",
    "DevInitBoard": "host_api.driver",
    "DevOpenDriver": "host_api.driver",
    "DevPutMessage": "host_api.driver",
    "DevPutTaskParameter": "host_api.driver",
    "DevReadSendData": "host_api.driver",
    "DevReadWriteDPMRaw": "host_api.driver",
    "DevReset": "host_api.driver",
    "DevSetHostState": "host_api.driver",
    "DevSpecialControl": "host_api.driver",
    "DevTriggerWatchDog": "host_api.driver",
    "HostApiError": "host_api.errors",
}
"""Where each name of ``__all__`` lives."""

__all__ = [
    "BOOTSTART",
    "COLDSTART",
    "CONFIGURATION_DOWNLOAD",
    "FIRMWARE_DOWNLOAD",
    "GET_DEV_INFO",
    "GET_DRIVER_INFO",
    "GET_FIRMWARE_INFO",
    "GET_IO_INFO",
    "GET_IO_SEND_DATA",
    "GET_RCS_INFO",
    "GET_TASK_INFO",
    "GET_VERSION_INFO",
    "HOST_NOT_READY",
    "HOST_READY",
    "MSG_BUFFER_SIZE",
    "PARAMETER_READ",
    "PARAMETER_WRITE",
    "SPECIAL_CONTROL_CLEAR",
    "SPECIAL_CONTROL_SET",
    "WARMSTART",
    "WATCHDOG_START",
    "WATCHDOG_STOP",
    "Board",
    "CifError",
    "ComState",
    "DevCloseDriver",
    "DevDownload",
    "DevExchangeIO",
    "DevExchangeIOErr",
    "DevExchangeIOEx",
    "DevExitBoard",
    "DevGetBoardInfo",
    "DevGetInfo",
    "DevGetMBXState",
    "DevGetMessage",
    "DevGetTaskParameter",
    "DevGetTaskState",
    "DevInitBoard",
    "DevOpenDriver",
    "DevPutMessage",
    "DevPutTaskParameter",
    "DevReadSendData",
    "DevReadWriteDPMRaw",
    "DevReset",
    "DevSetHostState",
    "DevSpecialControl",
    "DevTriggerWatchDog",
    "FlashEntry",
    "HostApiError",
    "__version__",
    "delete_database",
    "flash_directory",
    "upload_database",
]


def __getattr__(name: str) -> Any:
    """``host_api.Board`` and the others, imported from their module when first asked for."""
    if name == "__version__":
        from importlib.metadata import version

        return version("cifemu")
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'host_api' has no attribute {name!r}")
    return getattr(import_module(home), name)
