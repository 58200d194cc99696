"""libcif for C programs and for Python: its build, its flags, the library loaded.

``cifemu libcif`` (``cifemu.commands.libcif``) prints the flags. The library is built
from libcif/ of this clone (make -C libcif) when it is missing. load() gives the shared
library to Python (ctypes) with every Dev* function's argument and return types set: the
tests run the driver behaviour tests through it, and the benchmarks measure it beside the
Python host.
"""

from __future__ import annotations

import ctypes
import subprocess
from pathlib import Path

SOURCE = Path(__file__).resolve().parents[1] / "libcif"
INCLUDE = SOURCE / "include"
BUILD = SOURCE / "build"
SHARED = BUILD / "libcif.so"

_US = ctypes.c_ushort
_UL = ctypes.c_ulong
_P = ctypes.c_void_p
_PUS = ctypes.POINTER(ctypes.c_ushort)
_PUL = ctypes.POINTER(ctypes.c_ulong)
SIGNATURES: dict[str, list[type]] = {
    "DevOpenDriver": [],
    "DevCloseDriver": [],
    "DevGetBoardInfo": [_P],
    "DevGetBoardInfoEx": [_P],
    "DevSetOpMode": [_US, _US, _PUS],
    "DevInitBoard": [_US],
    "DevExitBoard": [_US],
    "DevPutTaskParameter": [_US, _US, _US, _P],
    "DevGetTaskParameter": [_US, _US, _US, _P],
    "DevReset": [_US, _US, _UL],
    "DevPutMessage": [_US, _P, _UL],
    "DevGetMessage": [_US, _US, _P, _UL],
    "DevGetTaskState": [_US, _US, _US, _P],
    "DevGetMBXState": [_US, _PUS, _PUS],
    "DevTriggerWatchDog": [_US, _US, _PUS],
    "DevGetInfo": [_US, _US, _US, _P],
    "DevExchangeIO": [_US, _US, _US, _P, _US, _US, _P, _UL],
    "DevExchangeIOEx": [_US, _US, _US, _US, _P, _US, _US, _P, _UL],
    "DevExchangeIOErr": [_US, _US, _US, _P, _US, _US, _P, _P, _UL],
    "DevReadSendData": [_US, _US, _US, _P],
    "DevSetHostState": [_US, _US, _UL],
    "DevExtendedData": [_US, _US, _US, _P],
    "DevGetMBXData": [_US, _US, _P, _US, _P],
    "DevReadWriteDPMRaw": [_US, _US, _US, _US, _P],
    "DevReadWriteDPMData": [_US, _US, _US, _US, _P],
    "DevSpecialControl": [_US, _US, _PUS],
    "DevDownload": [_US, _US, ctypes.c_char_p, _PUL],
    "dbm_init": [_P],
    "dbm_init_ex": [_P, _UL],
    "dbm_get_num": [ctypes.c_char_p, ctypes.POINTER(ctypes.c_ubyte)],
    "dbm_get_num_of_set": [ctypes.c_ubyte, _PUS],
    "dbm_fast_read": [ctypes.c_ubyte, _US, _US, _P, _PUS],
}
"""The prototypes of cif_user.h and dbm_embd.h, as ctypes sees them."""


class LibcifError(RuntimeError):
    """libcif cannot be built here (no clone, no compiler, a compile error)."""


def build(target: str = "all") -> None:
    """``make -C libcif <target>``; quiet unless it fails."""
    if not (SOURCE / "Makefile").exists():
        raise LibcifError(f"{SOURCE} is missing: libcif is built from a clone of cifemu")
    done = subprocess.run(["make", "-s", "-C", str(SOURCE), target], capture_output=True,
                          text=True, check=False)
    if done.returncode != 0:
        raise LibcifError(f"building libcif failed:\n{done.stdout}{done.stderr}")


def flags(cflags: bool, libs: bool) -> str:
    """What pkg-config's --cflags/--libs say for the built library of this clone."""
    parts = []
    if cflags:
        parts.append(f"-I{INCLUDE}")
    if libs:
        parts += [f"-L{BUILD}", f"-Wl,-rpath,{BUILD}", "-lcif", "-pthread"]
    return " ".join(parts)


def load() -> ctypes.CDLL:
    """The shared library, built when missing, with every function's types set."""
    if not SHARED.exists():
        build()
    lib = ctypes.CDLL(str(SHARED))
    for name, argtypes in SIGNATURES.items():
        function = getattr(lib, name)
        function.argtypes = argtypes
        function.restype = ctypes.c_short
    return lib

