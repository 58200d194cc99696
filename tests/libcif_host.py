"""libcif through ctypes, shaped like host_api.driver: the same calls, the same tuples.

The driver behaviour tests take either module (``host_api.driver`` or ``CDriver()``) and
assert the same return codes and data, so the two implementations cannot drift apart.
"""

from __future__ import annotations

import ctypes
import fcntl
import functools
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cifemu import libcif
from dpm.message import Message
from host_api.driver import ComState
from tests import commands
from tests.conftest import Card, start_card

MSG_SIZE = 288

BUILD_LOCK = "build.lock"
"""Taken (in libcif's build directory) around every build: two pytest-xdist workers must not
compile into one directory."""


def toolchain_missing() -> str | None:
    """Why libcif cannot be compiled on this machine (no C compiler, no make), or None."""
    if (shutil.which("cc") or shutil.which("gcc")) is None:
        return "no C compiler (cc or gcc): install one to build and test libcif"
    if shutil.which("make") is None:
        return "no make: install it to build and test libcif"
    return None


needs_toolchain = pytest.mark.skipif(toolchain_missing() is not None,
                                     reason=str(toolchain_missing()))
"""Marks a test module that compiles C programs: skipped, saying what to install, where
the machine has no C compiler or no make."""


def build_libcif(target: str = "all") -> None:
    """``make -C libcif TARGET``: skips the calling test where the machine has no C toolchain
    (the reason says what to install), and FAILS it on a compile error, which a skip would
    hide among the machine's missing tools."""
    missing = toolchain_missing()
    if missing is not None:
        pytest.skip(missing)
    try:
        libcif.BUILD.mkdir(parents=True, exist_ok=True)
        with open(libcif.BUILD / BUILD_LOCK, "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            libcif.build(target)
    except libcif.LibcifError as exc:
        pytest.fail(str(exc), pytrace=False)


@functools.cache
def load_libcif() -> ctypes.CDLL:
    """libcif of this clone, brought up to date with its sources and loaded once per test
    process (see ``build_libcif`` for when it skips and when it fails)."""
    build_libcif("all")
    return libcif.load()


class PythonDriver:
    """host_api.driver's Dev* functions and constants, with DevDownload and its modes from
    host_api.download (the driver module does not import the download module)."""

    def __getattr__(self, name: str) -> Any:
        from host_api import download, driver

        return getattr(driver if hasattr(driver, name) else download, name)


PYTHON_DRIVER = PythonDriver()


class CDriver:
    """libcif's Dev* functions with host_api.driver's Python signatures."""

    def __init__(self) -> None:
        self.lib = load_libcif()

    def __getattr__(self, name: str) -> object:
        # the constants (GET_IO_INFO, WARMSTART, CONFIGURATION_DOWNLOAD, ...) are the
        # Python driver's
        return getattr(PYTHON_DRIVER, name)

    def DevOpenDriver(self, directory: str | Path | None = None) -> int:
        """libcif reads $CIF_DPM_DIR here: a directory given is set for this call only."""
        if directory is None:
            return int(self.lib.DevOpenDriver())
        before = os.environ.get("CIF_DPM_DIR")
        os.environ["CIF_DPM_DIR"] = str(directory)
        try:
            return int(self.lib.DevOpenDriver())
        finally:
            if before is None:
                del os.environ["CIF_DPM_DIR"]
            else:
                os.environ["CIF_DPM_DIR"] = before

    def DevCloseDriver(self) -> int:
        return int(self.lib.DevCloseDriver())

    def DevGetBoardInfo(self) -> tuple[int, bytes]:
        buf = ctypes.create_string_buffer(58)
        rc = int(self.lib.DevGetBoardInfo(buf))
        return rc, buf.raw if rc == 0 else b""

    def DevInitBoard(self, number: int) -> int:
        return int(self.lib.DevInitBoard(number))

    def DevExitBoard(self, number: int) -> int:
        return int(self.lib.DevExitBoard(number))

    def DevPutMessage(self, number: int, msg: Message | bytes, timeout: int) -> int:
        raw = msg.encode() if isinstance(msg, Message) else bytes(msg)
        buf = ctypes.create_string_buffer(raw.ljust(MSG_SIZE, b"\0"), MSG_SIZE)
        return int(self.lib.DevPutMessage(number, buf, timeout))

    def DevGetMessage(self, number: int, size: int, timeout: int) -> tuple[int, Message | None]:
        # a buffer of exactly the size given, so an overlong copy is a memory error
        buf = ctypes.create_string_buffer(size if 0 < size <= MSG_SIZE else MSG_SIZE)
        rc = int(self.lib.DevGetMessage(number, size & 0xFFFF, buf, timeout))
        return rc, Message.decode(buf.raw) if rc == 0 else None

    def DevGetMBXState(self, number: int) -> tuple[int, int, int]:
        dev, host = ctypes.c_ushort(), ctypes.c_ushort()
        rc = int(self.lib.DevGetMBXState(number, ctypes.byref(dev), ctypes.byref(host)))
        return (rc, dev.value, host.value) if rc == 0 else (rc, 0, 0)

    def _io(self, call: str, number: int, *mode: int, send_offset: int, send_data: bytes,
            recv_offset: int, recv_size: int, timeout: int,
            state: ctypes.Array[ctypes.c_char] | None = None) -> tuple[int, bytes]:
        send = ctypes.create_string_buffer(send_data, max(1, len(send_data)))
        recv = ctypes.create_string_buffer(max(1, recv_size))
        extra = (state,) if state is not None else ()
        rc = int(getattr(self.lib, call)(number, *mode, send_offset, len(send_data), send,
                                         recv_offset, recv_size, recv, *extra, timeout))
        copied = rc in (0, -21) and recv_size > 0
        return rc, recv.raw[:recv_size] if copied else b""

    def DevExchangeIO(self, number: int, send_offset: int, send_data: bytes, recv_offset: int,
                      recv_size: int, timeout: int) -> tuple[int, bytes]:
        return self._io("DevExchangeIO", number, send_offset=send_offset, send_data=send_data,
                        recv_offset=recv_offset, recv_size=recv_size, timeout=timeout)

    def DevExchangeIOEx(self, number: int, mode: int, send_offset: int, send_data: bytes,
                        recv_offset: int, recv_size: int, timeout: int) -> tuple[int, bytes]:
        return self._io("DevExchangeIOEx", number, mode, send_offset=send_offset,
                        send_data=send_data, recv_offset=recv_offset, recv_size=recv_size,
                        timeout=timeout)

    def DevExchangeIOErr(self, number: int, send_offset: int, send_data: bytes, recv_offset: int,
                         recv_size: int, timeout: int) -> tuple[int, bytes, ComState]:
        state = ctypes.create_string_buffer(68)
        rc, data = self._io("DevExchangeIOErr", number, send_offset=send_offset,
                            send_data=send_data, recv_offset=recv_offset, recv_size=recv_size,
                            timeout=timeout, state=state)
        raw = state.raw
        return rc, data, ComState(int.from_bytes(raw[0:2], "little"),
                                  int.from_bytes(raw[2:4], "little"), raw[4:68])

    def DevReadSendData(self, number: int, offset: int, size: int) -> tuple[int, bytes]:
        buf = ctypes.create_string_buffer(max(1, size))
        rc = int(self.lib.DevReadSendData(number, offset, size, buf))
        return rc, buf.raw[:size] if rc == 0 else b""

    def DevReset(self, number: int, mode: int, timeout: int) -> int:
        return int(self.lib.DevReset(number, mode, timeout))

    def DevSetHostState(self, number: int, mode: int, timeout: int) -> int:
        return int(self.lib.DevSetHostState(number, mode, timeout))

    def _value_call(self, call: str, number: int, mode: int) -> tuple[int, int]:
        value = ctypes.c_ushort()
        rc = int(getattr(self.lib, call)(number, mode, ctypes.byref(value)))
        return rc, value.value if rc == 0 else 0

    def DevTriggerWatchDog(self, number: int, function: int) -> tuple[int, int]:
        return self._value_call("DevTriggerWatchDog", number, function)

    def DevSpecialControl(self, number: int, mode: int) -> tuple[int, int]:
        return self._value_call("DevSpecialControl", number, mode)

    def DevGetInfo(self, number: int, area: int, size: int) -> tuple[int, bytes]:
        buf = ctypes.create_string_buffer(max(1, size))
        rc = int(self.lib.DevGetInfo(number, area, size, buf))
        return rc, buf.raw[:size] if rc == 0 else b""

    def _task(self, call: str, number: int, task: int, size: int) -> tuple[int, bytes]:
        buf = ctypes.create_string_buffer(max(1, size))
        rc = int(getattr(self.lib, call)(number, task, size, buf))
        return rc, buf.raw[:size] if rc == 0 else b""

    def DevGetTaskState(self, number: int, task: int, size: int) -> tuple[int, bytes]:
        return self._task("DevGetTaskState", number, task, size)

    def DevGetTaskParameter(self, number: int, task: int, size: int) -> tuple[int, bytes]:
        return self._task("DevGetTaskParameter", number, task, size)

    def DevPutTaskParameter(self, number: int, task: int, data: bytes) -> int:
        buf = ctypes.create_string_buffer(data, max(1, len(data)))
        return int(self.lib.DevPutTaskParameter(number, task, len(data), buf))

    def DevReadWriteDPMRaw(self, number: int, mode: int, offset: int, size: int,
                           data: bytes = b"") -> tuple[int, bytes]:
        buf = ctypes.create_string_buffer(data.ljust(size, b"\0"), max(1, size, len(data)))
        rc = int(self.lib.DevReadWriteDPMRaw(number, mode, offset, size, buf))
        return rc, buf.raw[:size] if rc == 0 and mode == 1 else b""

    def DevDownload(self, number: int, mode: int, source: str | Path) -> int:
        count = ctypes.c_ulong()
        return int(self.lib.DevDownload(number, mode, os.fsencode(source), ctypes.byref(count)))


# --- C programs built against libcif and run against a card ---------------------------

C_TESTS = Path(__file__).with_name("c")
CC = shutil.which("cc") or shutil.which("gcc")
STRICT = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-g"]
SANITIZE = ["-fsanitize=address,undefined", "-fno-sanitize-recover=all",
            "-fno-omit-frame-pointer"]


def compile_program(source: Path, out: Path, variant: str) -> Path:
    assert CC is not None
    if variant == "sanitized":
        command = [CC, *STRICT, *SANITIZE, str(source), f"-I{libcif.INCLUDE}",
                   str(libcif.BUILD / "asan" / "libcif.a"), "-pthread"]
    else:
        command = [CC, *STRICT, str(source), *libcif.flags(True, True).split()]
    subprocess.run([*command, "-o", str(out)], check=True)
    return out


def run(program: Path, directory: Path, *args: str, timeout: float = 120) -> str:
    env = {**os.environ, "CIF_DPM_DIR": str(directory),
           "ASAN_OPTIONS": "detect_leaks=1:abort_on_error=0",
           "UBSAN_OPTIONS": "print_stacktrace=1:halt_on_error=1"}
    done = commands.run([str(program), *args], env=env, capture_output=True, text=True,
                        timeout=timeout, check=False)
    assert done.returncode == 0, f"{program.name} failed:\n{done.stdout}\n{done.stderr}"
    stdout: str = done.stdout
    return stdout


C_NETWORK = """
[bus]
bitrate = 500000
sync_period_ms = 10

[[node]]
id = 1
name = "io 1"

[[node]]
id = 2
name = "io 2"
"""
"""The network the C programs run against: nodes 1 and 2, which tests/c/operative.c (the
seed's 7.2 procedure) configures; the legacy and libcif tests download its database."""


@pytest.fixture
def simulated_card(tmp_path: Path) -> Iterator[Card]:
    """A card with ``C_NETWORK``'s nodes simulated; a module takes it with
    ``pytest_plugins = ["tests.libcif_host"]``."""
    network = tmp_path / "net.toml"
    network.write_text(C_NETWORK)
    card = start_card(tmp_path, 0, "--simulate", str(network))
    yield card
    card.stop()
