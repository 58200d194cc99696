"""libcif as C programs use it: compiled with a real compiler, run against real firmware.

- the link forms a legacy program uses: pkg-config's line, libcif.a, cif_api.o by path, C++;
- tests/c/bad_input.c: every mistake gets its code and nothing crashes;
- tests/c/operative.c: the seed's chapter 7.2 procedure against simulated nodes;
- tests/c/cross_host.c: a C host and a Python host on one card never read each other's answers.

The C programs run twice: linked with the library as built, and with the library and the
program built with AddressSanitizer and UndefinedBehaviorSanitizer (``make -C libcif
sanitize``), where any memory or undefined-behaviour error fails the run.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from cifemu import libcif
from dbm_tools.builder import build_dbm
from dbm_tools.container import save_dbm
from dbm_tools.network import parse_network
from dpm.errors import Drv
from dpm.message import Message
from host_api import driver as d
from tests.conftest import Card, wait_until
from tests.libcif_host import (
    C_NETWORK,
    C_TESTS,
    CC,
    CDriver,
    build_libcif,
    compile_program,
    needs_toolchain,
    run,
)

pytestmark = needs_toolchain
pytest_plugins = ["tests.libcif_host"]
"""simulated_card: a card with C_NETWORK's nodes."""


@pytest.fixture(scope="module")
def built() -> None:
    build_libcif("all")
    build_libcif("sanitize")


# --- link forms ----------------------------------------------------------------------------

SMOKE = """
#include <stdio.h>
#include <string.h>
#include "cif_user.h"
#include "rcs_user.h"
#include "COM_USER.H"
int main(void) {
  FIRMWAREINFO fw;
  short rc = DevOpenDriver();
  if (rc == DRV_NO_ERROR) rc = DevInitBoard(0);
  if (rc == DRV_NO_ERROR) rc = DevGetInfo(0, GET_FIRMWARE_INFO, sizeof fw, &fw);
  printf("%d %.14s\\n", rc, (const char *)fw.abFirmwareName);
  DevCloseDriver();
  return rc;
}
"""


@pytest.mark.parametrize("form", ["pkg-config", "cifemu", "static", "cif_api.o", "c++",
                                  "include cif_api.c", "c++ include cif_api.c"])
def test_a_program_links_in_every_form(built: None, card: Card, tmp_path: Path,
                                       form: str) -> None:
    assert CC is not None
    source = tmp_path / "app.c"
    source.write_text(SMOKE)
    include = f"-I{libcif.INCLUDE}"
    if form == "pkg-config":
        if shutil.which("pkg-config") is None:
            pytest.skip("no pkg-config")
        flags = subprocess.run(
            ["pkg-config", "--cflags", "--libs", "libcif"], capture_output=True, text=True,
            check=True, env={**os.environ, "PKG_CONFIG_PATH": str(libcif.BUILD)}).stdout.split()
        command = [CC, str(source), *flags]
    elif form == "cifemu":
        command = [CC, str(source), *libcif.flags(True, True).split()]
    elif form == "static":
        command = [CC, str(source), include, str(libcif.BUILD / "libcif.a"), "-pthread"]
    elif form == "cif_api.o":
        command = [CC, str(source), include, str(libcif.BUILD / "cif_api.o"), "-pthread"]
    elif form == "include cif_api.c":  # the API compiled into the program itself
        source.write_text(SMOKE.replace('"cif_user.h"\n', '"cif_user.h"\n#include "cif_api.c"\n'))
        command = [CC, str(source), include, f"-I{libcif.BUILD}", "-pthread"]
    else:
        cxx = shutil.which("c++")
        if cxx is None:
            pytest.skip("no C++ compiler")
        text = SMOKE
        if form == "c++ include cif_api.c":
            text = SMOKE.replace('"cif_user.h"\n', '"cif_user.h"\n#include "cif_api.c"\n')
            flags = [include, f"-I{libcif.BUILD}", "-pthread"]
        else:
            flags = libcif.flags(True, True).split()
        (tmp_path / "app.cpp").write_text(text)
        command = [cxx, "-Wall", "-Wextra", "-Werror", str(tmp_path / "app.cpp"), *flags]
    subprocess.run([*command, "-Wall", "-Wextra", "-Werror", "-o", str(tmp_path / "app")],
                   check=True)
    assert run(tmp_path / "app", card.directory) == "0 CANopen Master\n"


def test_the_installed_library_compiles_a_program(built: None, card: Card, tmp_path: Path) -> None:
    """make install into a prefix, then pkg-config from there, as the README says."""
    assert CC is not None
    if shutil.which("pkg-config") is None:
        pytest.skip("no pkg-config")
    prefix = tmp_path / "prefix"
    subprocess.run(["make", "-s", "-C", str(libcif.SOURCE), "install", f"PREFIX={prefix}"],
                   check=True, capture_output=True)
    for name in ("cif_user.h", "rcs_user.h", "rcsdef.h", "com_user.h", "COM_USER.H",
                 "dbm_embd.h", "cif_api.c"):
        assert (prefix / "include" / name).exists(), name
    for name in ("libcif.so.1", "libcif.a", "cif_api.o", "pkgconfig/libcif.pc"):
        assert (prefix / "lib" / name).exists(), name
    flags = subprocess.run(
        ["pkg-config", "--cflags", "--libs", "libcif"], capture_output=True, text=True,
        check=True, env={**os.environ, "PKG_CONFIG_PATH": str(prefix / "lib" / "pkgconfig")},
    ).stdout.split()
    assert f"-I{prefix}/include" in flags
    (tmp_path / "app.c").write_text(SMOKE)
    subprocess.run([CC, str(tmp_path / "app.c"), *flags, "-Wall", "-Wextra", "-Werror",
                    "-o", str(tmp_path / "app")], check=True)
    assert run(tmp_path / "app", card.directory) == "0 CANopen Master\n"


def test_cifemu_libcif_prints_the_flags(built: None, capsys: pytest.CaptureFixture[str]) -> None:
    from cifemu.cli import main

    assert main(["libcif", "--cflags", "--libs"]) == 0
    assert capsys.readouterr().out.split() == [
        f"-I{libcif.INCLUDE}", f"-L{libcif.BUILD}", f"-Wl,-rpath,{libcif.BUILD}", "-lcif",
        "-pthread"]
    assert main(["libcif", "--cflags"]) == 0
    assert capsys.readouterr().out == f"-I{libcif.INCLUDE}\n"


def test_the_shared_library_has_its_soname(built: None) -> None:
    readelf = shutil.which("readelf")
    if readelf is None:
        pytest.skip("no readelf")
    dynamic = subprocess.run([readelf, "-d", str(libcif.SHARED)], capture_output=True,
                             text=True, check=True).stdout
    assert "Library soname: [libcif.so.1]" in dynamic
    assert (libcif.BUILD / "libcif.so.1").resolve() == libcif.SHARED.resolve()


# --- the C programs --------------------------------------------------------------------------


@pytest.mark.parametrize("variant", ["plain", "sanitized"])
def test_bad_input_gets_its_code_and_never_a_crash(built: None, card: Card, tmp_path: Path,
                                                  variant: str) -> None:
    program = compile_program(C_TESTS / "bad_input.c", tmp_path / "bad_input", variant)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    assert "every mistake got its code" in run(program, card.directory, str(scratch))


@pytest.mark.parametrize("variant", ["plain", "sanitized"])
def test_chapter_7_2_makes_the_card_operative(built: None, simulated_card: Card, tmp_path: Path,
                                              variant: str) -> None:
    """A SyCon-style database goes into the card first (DevDownload, a cold start), so the
    procedure's step 1 has one to delete; then on-line configuration, process data, SDO,
    node diagnostics and NMT."""
    dbm = tmp_path / "sycon.dbm"
    save_dbm(dbm, build_dbm(parse_network(C_NETWORK)))
    program = compile_program(C_TESTS / "operative.c", tmp_path / "operative", variant)
    out = run(program, simulated_card.directory, str(dbm))
    assert f"step 0: {dbm.stat().st_size - 44} bytes of database downloaded" in out
    assert "step 1: the card ran from a database: deleted" in out
    assert out.endswith("operative: all steps done\n")


def test_a_c_host_and_a_python_host_never_read_each_others_answers(
        built: None, card: Card, tmp_path: Path) -> None:
    program = compile_program(C_TESTS / "cross_host.c", tmp_path / "cross_host", "plain")
    count = 300
    assert d.DevOpenDriver(card.directory) == 0 and d.DevInitBoard(0) == 0
    wrong: list[str] = []

    def python_host() -> None:
        """Board.transact's procedure, but an answer that is not ours is an error here."""
        lock = d._driver.boards[0].transaction
        for i in range(count):
            msg = Message(rx=2, tx=16, b=17, nr=i % 255 + 1,
                          data=bytes([0, 1, 200, 0, 0, 2, 5, 1]))
            assert lock.acquire(5.0)
            try:
                assert d.DevPutMessage(0, msg, 5000) == 0
                rc, answer = d.DevGetMessage(0, 288, 5000)
            finally:
                lock.release()
            if rc != 0 or answer is None or answer.nr != msg.nr or answer.data[2] != 200:
                wrong.append(f"request {i}: rc {rc}, {answer}")

    try:
        thread = threading.Thread(target=python_host)
        thread.start()
        out = run(program, card.directory, str(count), "100")
        thread.join()
    finally:
        while d.DevCloseDriver() == 0:
            pass
    assert out == f"cross_host: {count} answers, all this host's own\n"
    assert wrong == []


def test_c_and_python_hosts_take_the_same_channel_locks(card: Card) -> None:
    """While a Python host holds a channel, libcif's call on it gets -4, and the reverse."""
    c = CDriver()
    assert d.DevOpenDriver(card.directory) == 0 and d.DevInitBoard(0) == 0
    assert c.DevOpenDriver(card.directory) == 0 and c.DevInitBoard(0) == 0
    try:
        assert c.DevPutTaskParameter(0, 2, bytes([3])) == 0  # bMode 3: handshake mode 4
        assert c.DevReset(0, d.WARMSTART, 5000) == 0
        board = d._driver.boards[0]
        request = Message(rx=2, tx=16, b=17, nr=1, data=bytes([0, 1, 0, 0, 0, 2, 5, 1]))
        # a Python host's put or get holds the transaction lock (its put and get channels
        # are thread locks inside it)
        calls: list[tuple[Any, Callable[[], int]]] = [
            (board.transaction, lambda: c.DevPutMessage(0, request, 30)),
            (board.transaction, lambda: c.DevGetMessage(0, 288, 30)[0]),
            (board.io_lock, lambda: c.DevExchangeIO(0, 0, b"x", 0, 1, 30)[0])]
        for lock, call in calls:
            assert lock.acquire(1.0)
            try:
                assert call() == Drv.DRV_CMD_ACTIVE
            finally:
                lock.release()
        # the reverse: a C host waits in DevPutMessage on a full mailbox of a frozen card
        card.freeze()
        try:
            assert c.DevPutMessage(0, request, 0) == 0
            waiter = threading.Thread(target=lambda: c.DevPutMessage(0, request, 500))
            waiter.start()
            wait_until(lambda: d.DevPutMessage(0, request, 0) == Drv.DRV_CMD_ACTIVE, 5,
                       "the C host's wait to hold the channel")
            waiter.join()
        finally:
            card.thaw()
    finally:
        c.DevCloseDriver()
        d.DevCloseDriver()
