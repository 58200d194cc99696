"""What the card says about itself: VERSIONINFO, FIRMWAREINFO, TASKINFO, RCSINFO, DEVINFO.

Written field by field through the layout's tables (``dpm.layout.pack_field``), not a
numpy view: a card that is never configured does not import numpy (docs/testing.md,
*Start-up*).
"""

from __future__ import annotations

import mmap

from dpm.identity import (
    DEV_MODEL,
    DEV_TYPE,
    DEVICE_NUMBER,
    FIRMWARE_NAME,
    FIRMWARE_VERSION,
    RCS_VERSION,
    TASKS,
)
from dpm.layout import pack_field, size_of

TASK_INFO_ENTRIES = 7


def _bcd(value: int) -> int:
    out = 0
    for shift, digit in enumerate(reversed(str(value))):
        out |= int(digit) << (4 * shift)
    return out


def _put(mm: mmap.mmap, path: str, value: int | bytes, index: int = 0) -> None:
    """Write a field; ``index``: of that entry of an array of records (TaskInfo)."""
    offset, packing = pack_field(path)
    if index:
        top = path.split(".")[0]
        offset += index * size_of(top) // TASK_INFO_ENTRIES
    packing.pack_into(mm, offset, value)


def fill(mm: mmap.mmap, board: int) -> None:
    """Write the identification areas into the image (at power-on and every start)."""
    _put(mm, "VersionInfo.ulDate", _bcd(20261122))
    _put(mm, "VersionInfo.ulDeviceNo", DEVICE_NUMBER)
    _put(mm, "VersionInfo.ulSerialNo", _bcd(board + 1))
    _put(mm, "VersionInfo.ulReserved", 0)
    _put(mm, "VersionInfo.abPcOsName0", b"RCS ")
    _put(mm, "VersionInfo.abPcOsName1", b"CAN ")
    _put(mm, "VersionInfo.abPcOsName2", b"    ")
    _put(mm, "VersionInfo.abOemIdentifier", b"    ")
    _put(mm, "FirmwareInfo.abFirmwareName", FIRMWARE_NAME.ljust(16))
    _put(mm, "FirmwareInfo.abFirmwareVersion", FIRMWARE_VERSION.ljust(16))
    for index in range(TASK_INFO_ENTRIES):
        name, task_version = TASKS.get(index, (b"", 0))
        _put(mm, "TaskInfo.abTaskName", name.ljust(8), index)
        _put(mm, "TaskInfo.usVersion", task_version, index)
        _put(mm, "TaskInfo.bCondition", 1 if name else 0, index)
    _put(mm, "RcsInfo.usRcsVersion", RCS_VERSION)
    _put(mm, "RcsInfo.bRcsError", 0)
    _put(mm, "RcsInfo.bSegmentCount", 8)
    _put(mm, "RcsInfo.bDeviceAdress", 0)
    _put(mm, "DevInfo.bDpmSize", 8)
    _put(mm, "DevInfo.bDevType", DEV_TYPE)
    _put(mm, "DevInfo.bDevModel", DEV_MODEL)
    _put(mm, "DevInfo.abDevIdentifier", b"CIF")
