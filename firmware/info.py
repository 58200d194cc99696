"""What the card says about itself: VERSIONINFO, FIRMWAREINFO, TASKINFO, RCSINFO, DEVINFO."""

from __future__ import annotations

from typing import Any

from dpm.identity import (
    DEV_MODEL,
    DEV_TYPE,
    DEVICE_NUMBER,
    FIRMWARE_NAME,
    FIRMWARE_VERSION,
    RCS_VERSION,
    TASKS,
)


def _bcd(value: int) -> int:
    out = 0
    for shift, digit in enumerate(reversed(str(value))):
        out |= int(digit) << (4 * shift)
    return out


def fill(view: Any, board: int) -> None:
    """Write the identification areas into the image (at power-on and every start)."""
    version = view["VersionInfo"]
    version["ulDate"] = _bcd(20261122)
    version["ulDeviceNo"] = DEVICE_NUMBER
    version["ulSerialNo"] = _bcd(board + 1)
    version["ulReserved"] = 0
    version["abPcOsName0"] = b"RCS "
    version["abPcOsName1"] = b"CAN "
    version["abPcOsName2"] = b"    "
    version["abOemIdentifier"] = b"    "
    firmware = view["FirmwareInfo"]
    firmware["abFirmwareName"] = FIRMWARE_NAME.ljust(16)
    firmware["abFirmwareVersion"] = FIRMWARE_VERSION.ljust(16)
    for index in range(7):
        entry = view["TaskInfo"][index]
        name, task_version = TASKS.get(index, (b"", 0))
        entry["abTaskName"] = name.ljust(8)
        entry["usVersion"] = task_version
        entry["bCondition"] = 1 if name else 0
    rcs = view["RcsInfo"]
    rcs["usRcsVersion"] = RCS_VERSION
    rcs["bRcsError"] = 0
    rcs["bSegmentCount"] = 8
    rcs["bDeviceAdress"] = 0
    dev = view["DevInfo"]
    dev["bDpmSize"] = 8
    dev["bDevType"] = DEV_TYPE
    dev["bDevModel"] = DEV_MODEL
    dev["abDevIdentifier"] = b"CIF"
