"""The 8 KiB dual-port memory image as numpy structured dtypes.

This module is the single source of truth for every offset in the image: the
firmware, the driver API and the status tool all take their offsets from the
dtypes below (``offset_of``), and a test compares them with docs/dpm.md's table.
All integers are little-endian and all structures packed, as on the card.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

DPM_SIZE = 8192
"""Size of the emulated card's dual-port memory (bDpmSize 8 KiB)."""

IO_AREA_SIZE = (DPM_SIZE - 1024) // 2
"""Send and receive process data areas, each (size-1024)/2 = 3584 bytes."""

LAST_KB = DPM_SIZE - 1024
"""Start of the last kilobyte (DevReadWriteDPMRaw offsets are relative to it)."""

MSG_DATA_SIZE = 255
MSG_HEADER_SIZE = 8


def _packed(fields: list[tuple[str, Any, int]], itemsize: int) -> np.dtype[Any]:
    """A packed little-endian record dtype with explicit offsets."""
    return np.dtype(
        {
            "names": [f[0] for f in fields],
            "formats": [f[1] for f in fields],
            "offsets": [f[2] for f in fields],
            "itemsize": itemsize,
        }
    )


MSG_STRUC = _packed(
    [
        ("rx", "u1", 0),
        ("tx", "u1", 1),
        ("ln", "u1", 2),
        ("nr", "u1", 3),
        ("a", "u1", 4),
        ("f", "u1", 5),
        ("b", "u1", 6),
        ("e", "u1", 7),
        ("data", ("u1", 255), 8),
        ("dummy", ("u1", 25), 263),
    ],
    288,
)

VERSIONINFO = _packed(
    [
        ("ulDate", "<u4", 0),
        ("ulDeviceNo", "<u4", 4),
        ("ulSerialNo", "<u4", 8),
        ("ulReserved", "<u4", 12),
        ("abPcOsName0", "S4", 16),
        ("abPcOsName1", "S4", 20),
        ("abPcOsName2", "S4", 24),
        ("abOemIdentifier", "S4", 28),
    ],
    32,
)

FIRMWAREINFO = _packed([("abFirmwareName", "S16", 0), ("abFirmwareVersion", "S16", 16)], 32)

COM_PLC_PARAMETER = _packed(
    [
        ("bMode", "u1", 0),
        ("usWatchDogTime", "<u2", 1),
        ("abReservedA", ("u1", 5), 3),
        ("abReservedB", ("u1", 8), 8),
        ("abReservedC", ("u1", 32), 16),
        ("abConnStatus", ("u1", 16), 48),
    ],
    64,
)
"""Task2Parameter of the CANopen card: protocol parameters plus the node
connection-status bits (seed manual 2 and 3) at 0x1EF0..0x1EFF."""

COM_DIAGNOSTICS = _packed(
    [
        ("bGlobalBits", "u1", 0),
        ("bCAN_State", "u1", 1),
        ("bErr_rem_adr", "u1", 2),
        ("bErr_event", "u1", 3),
        ("usBus_Error_Cnt", "<u2", 4),
        ("usBus_Off_Cnt", "<u2", 6),
        ("usMsg_Time_Out", "<u2", 8),
        ("usRx_Overflow", "<u2", 10),
        ("abReserved", ("u1", 4), 12),
        ("abNd_cfg", ("u1", 16), 16),
        ("abNd_state", ("u1", 16), 32),
        ("abNd_diag", ("u1", 16), 48),
    ],
    64,
)
"""Task2State of the CANopen card (seed manual 4)."""

TASKINFO_ENTRY = _packed(
    [("abTaskName", "S8", 0), ("usVersion", "<u2", 8), ("bCondition", "u1", 10),
     ("abReserved", ("u1", 5), 11)],
    16,
)

RCSINFO = _packed(
    [
        ("usRcsVersion", "<u2", 0),
        ("bRcsError", "u1", 2),
        ("bHostWatchDog", "u1", 3),
        ("bDevWatchDog", "u1", 4),
        ("bSegmentCount", "u1", 5),
        ("bDeviceAdress", "u1", 6),
        ("bDriverType", "u1", 7),
    ],
    8,
)

DEVINFO = _packed(
    [("bDpmSize", "u1", 0), ("bDevType", "u1", 1), ("bDevModel", "u1", 2),
     ("abDevIdentifier", "S3", 3)],
    6,
)

DPM_LAYOUT = _packed(
    [
        ("SndPd", ("u1", IO_AREA_SIZE), 0x0000),
        ("RcvPd", ("u1", IO_AREA_SIZE), 0x0E00),
        ("DevMbx", MSG_STRUC, 0x1C00),
        ("VersionInfo", VERSIONINFO, 0x1D20),
        ("PcMbx", MSG_STRUC, 0x1D40),
        ("FirmwareInfo", FIRMWAREINFO, 0x1E60),
        ("Task1Parameter", ("u1", 64), 0x1E80),
        ("Task2Parameter", COM_PLC_PARAMETER, 0x1EC0),
        ("Task1State", ("u1", 64), 0x1F00),
        ("Task2State", COM_DIAGNOSTICS, 0x1F40),
        ("TaskInfo", (TASKINFO_ENTRY, 7), 0x1F80),
        ("RcsInfo", RCSINFO, 0x1FF0),
        ("DevInfo", DEVINFO, 0x1FF8),
        ("HostFlags", "u1", 0x1FFE),
        ("DevFlags", "u1", 0x1FFF),
    ],
    DPM_SIZE,
)


def offset_of(path: str) -> int:
    """Absolute image offset of a field, e.g. ``offset_of("Task2State.abNd_cfg")``."""
    dtype: np.dtype[Any] = DPM_LAYOUT
    offset = 0
    for name in path.split("."):
        if dtype.fields is None or name not in dtype.fields:
            raise KeyError(path)
        sub, off = dtype.fields[name][:2]
        offset += off
        dtype = sub.base if sub.subdtype is not None else sub
    return offset


def size_of(path: str) -> int:
    """Size in bytes of a field of the image (the whole field, arrays included)."""
    parent, _, name = path.rpartition(".")
    dtype: np.dtype[Any] = DPM_LAYOUT
    for part in parent.split(".") if parent else []:
        sub = dtype.fields[part][0]  # type: ignore[index]
        dtype = sub.base if sub.subdtype is not None else sub
    return int(dtype.fields[name][0].itemsize)  # type: ignore[index]


# Hot-path offsets, derived once from the layout.
SND_PD = offset_of("SndPd")
RCV_PD = offset_of("RcvPd")
DEV_MBX = offset_of("DevMbx")
PC_MBX = offset_of("PcMbx")
TASK1_PARAMETER = offset_of("Task1Parameter")
TASK2_PARAMETER = offset_of("Task2Parameter")
CONN_STATUS = offset_of("Task2Parameter.abConnStatus")
TASK1_STATE = offset_of("Task1State")
TASK2_STATE = offset_of("Task2State")
TASK_STATE_SIZE = 64
TASK_PARAMETER_SIZE = 64
VERSION_INFO = offset_of("VersionInfo")
FIRMWARE_INFO = offset_of("FirmwareInfo")
TASK_INFO = offset_of("TaskInfo")
RCS_INFO = offset_of("RcsInfo")
DEV_INFO = offset_of("DevInfo")
HOST_WATCHDOG = offset_of("RcsInfo.bHostWatchDog")
DEV_WATCHDOG = offset_of("RcsInfo.bDevWatchDog")
RCS_ERROR = offset_of("RcsInfo.bRcsError")
DRIVER_TYPE = offset_of("RcsInfo.bDriverType")
DEV_IDENTIFIER = offset_of("DevInfo.abDevIdentifier")
HOST_FLAGS = offset_of("HostFlags")
DEV_FLAGS = offset_of("DevFlags")


def image_view(buffer: Any) -> npt.NDArray[Any]:
    """A 0-d structured array over an 8 KiB buffer (an mmap or a bytearray)."""
    return np.ndarray(shape=(), dtype=DPM_LAYOUT, buffer=buffer)
