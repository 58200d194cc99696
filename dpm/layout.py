"""The 8 KiB dual-port memory image as numpy structured dtypes.

This module is the single source of truth for every offset in the image: the
firmware, the driver API and the status tool all take their offsets from the
tables below (``offset_of``), and a test compares them with docs/dpm.md's table.
All integers are little-endian and all structures packed, as on the card.

Each structure is a table of (name, format, offset) in numpy's spelling; its numpy
dtype (``MSG_STRUC``, ``DPM_LAYOUT`` ...) is built from the table when first asked
for. The offsets, sizes and the card's own writes (``pack_field``) read the tables
themselves: numpy costs a process 0.1 s of CPU to import, and a card that is never
configured, ``cifemu configure`` or ``cifemu 309 exec`` do not need it (docs/testing.md,
*Start-up*).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from functools import cache
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
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

_SCALARS = {"u1": 1, "<u2": 2, "<u4": 4}
"""The integer formats the tables use, with their sizes; ``Sn`` is n bytes of text."""


@dataclass(frozen=True)
class Packed:
    """A packed little-endian record: (name, format, offset) fields and its size. A
    format is a scalar (``"u1"``, ``"<u2"``, ``"S4"``), another ``Packed``, or
    (either of them, count) for an array."""

    fields: tuple[tuple[str, Any, int], ...]
    itemsize: int


def _packed(fields: list[tuple[str, Any, int]], itemsize: int) -> Packed:
    return Packed(tuple(fields), itemsize)


def _element(form: Any) -> tuple[Any, int]:
    """An array's element and count; (form, 1) for anything else."""
    return (form[0], form[1]) if isinstance(form, tuple) else (form, 1)


def _size(form: Any) -> int:
    element, count = _element(form)
    if isinstance(element, Packed):
        return element.itemsize * count
    return (int(element[1:]) if element.startswith("S") else _SCALARS[element]) * count


_MSG_STRUC = _packed(
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

_VERSIONINFO = _packed(
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

_FIRMWAREINFO = _packed([("abFirmwareName", "S16", 0), ("abFirmwareVersion", "S16", 16)], 32)

_COM_PLC_PARAMETER = _packed(
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

_COM_DIAGNOSTICS = _packed(
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

_TASKINFO_ENTRY = _packed(
    [("abTaskName", "S8", 0), ("usVersion", "<u2", 8), ("bCondition", "u1", 10),
     ("abReserved", ("u1", 5), 11)],
    16,
)

_RCSINFO = _packed(
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

_DEVINFO = _packed(
    [("bDpmSize", "u1", 0), ("bDevType", "u1", 1), ("bDevModel", "u1", 2),
     ("abDevIdentifier", "S3", 3)],
    6,
)

_DPM_LAYOUT = _packed(
    [
        ("SndPd", ("u1", IO_AREA_SIZE), 0x0000),
        ("RcvPd", ("u1", IO_AREA_SIZE), 0x0E00),
        ("DevMbx", _MSG_STRUC, 0x1C00),
        ("VersionInfo", _VERSIONINFO, 0x1D20),
        ("PcMbx", _MSG_STRUC, 0x1D40),
        ("FirmwareInfo", _FIRMWAREINFO, 0x1E60),
        ("Task1Parameter", ("u1", 64), 0x1E80),
        ("Task2Parameter", _COM_PLC_PARAMETER, 0x1EC0),
        ("Task1State", ("u1", 64), 0x1F00),
        ("Task2State", _COM_DIAGNOSTICS, 0x1F40),
        ("TaskInfo", (_TASKINFO_ENTRY, 7), 0x1F80),
        ("RcsInfo", _RCSINFO, 0x1FF0),
        ("DevInfo", _DEVINFO, 0x1FF8),
        ("HostFlags", "u1", 0x1FFE),
        ("DevFlags", "u1", 0x1FFF),
    ],
    DPM_SIZE,
)


def _walk(path: str) -> tuple[int, Any]:
    """Absolute offset and format of a field; into an array of records, its first."""
    form: Any = _DPM_LAYOUT
    offset = 0
    for name in path.split("."):
        record = _element(form)[0]
        if not isinstance(record, Packed):
            raise KeyError(path)
        for field, sub, off in record.fields:
            if field == name:
                offset += off
                form = sub
                break
        else:
            raise KeyError(path)
    return offset, form


def offset_of(path: str) -> int:
    """Absolute image offset of a field, e.g. ``offset_of("Task2State.abNd_cfg")``."""
    return _walk(path)[0]


def size_of(path: str) -> int:
    """Size in bytes of a field of the image (the whole field, arrays included)."""
    return _size(_walk(path)[1])


@cache
def pack_field(path: str) -> tuple[int, struct.Struct]:
    """Where a scalar field of the image is and how it is packed, for ``pack_into`` and
    ``unpack_from``: a number little-endian, a text NUL-padded (as numpy writes it)."""
    offset, form = _walk(path)
    if not isinstance(form, str):
        raise KeyError(f"{path} is not a scalar field")
    code = f"{form[1:]}s" if form.startswith("S") else {1: "B", 2: "H", 4: "I"}[_SCALARS[form]]
    return offset, struct.Struct("<" + code)


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


def _dtype(form: Any) -> Any:
    """numpy's spelling of a format: a record becomes its dtype."""
    element, count = _element(form)
    spelled = dtype_of(element) if isinstance(element, Packed) else element
    return (spelled, count) if isinstance(form, tuple) else spelled


@cache
def dtype_of(record: Packed) -> np.dtype[Any]:
    """The numpy dtype of a record, with explicit offsets."""
    import numpy as np

    return np.dtype({"names": [f[0] for f in record.fields],
                     "formats": [_dtype(f[1]) for f in record.fields],
                     "offsets": [f[2] for f in record.fields],
                     "itemsize": record.itemsize})


_RECORDS = {"MSG_STRUC": _MSG_STRUC, "VERSIONINFO": _VERSIONINFO,
            "FIRMWAREINFO": _FIRMWAREINFO, "COM_PLC_PARAMETER": _COM_PLC_PARAMETER,
            "COM_DIAGNOSTICS": _COM_DIAGNOSTICS, "TASKINFO_ENTRY": _TASKINFO_ENTRY,
            "RCSINFO": _RCSINFO, "DEVINFO": _DEVINFO, "DPM_LAYOUT": _DPM_LAYOUT}

if TYPE_CHECKING:
    MSG_STRUC: np.dtype[Any]
    VERSIONINFO: np.dtype[Any]
    FIRMWAREINFO: np.dtype[Any]
    COM_PLC_PARAMETER: np.dtype[Any]
    COM_DIAGNOSTICS: np.dtype[Any]
    TASKINFO_ENTRY: np.dtype[Any]
    RCSINFO: np.dtype[Any]
    DEVINFO: np.dtype[Any]
    DPM_LAYOUT: np.dtype[Any]


def __getattr__(name: str) -> Any:
    """The records' numpy dtypes (``MSG_STRUC``, ``DPM_LAYOUT`` ...), built when first
    asked for."""
    if name in _RECORDS:
        return dtype_of(_RECORDS[name])
    raise AttributeError(f"module 'dpm.layout' has no attribute {name!r}")


def image_view(buffer: Any) -> npt.NDArray[Any]:
    """A 0-d structured array over an 8 KiB buffer (an mmap or a bytearray)."""
    import numpy as np

    return np.ndarray(shape=(), dtype=dtype_of(_DPM_LAYOUT), buffer=buffer)
