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

Every name here is also importable from its module.
"""

from importlib.metadata import version

from host_api.board import Board, CifError
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
from host_api.errors import HostApiError

__version__ = version("cifemu")

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
