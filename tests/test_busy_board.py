"""A board whose mailbox a CiA 309 gateway holds: the others fail at once and name it.

Both drivers, Python and libcif (in this process through ctypes, and a C host under
AddressSanitizer and UBSan), refuse at once; a holder that is no gateway is still waited
for. libcif's readers of /proc/locks and /proc/PID/cmdline are fed malformed files under
the sanitizers (tests/c/holder_fuzz.c).
"""

from __future__ import annotations

import queue
import re
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cifemu import libcif
from dbm_tools.builder import build_dbm
from dbm_tools.container import save_dbm
from dbm_tools.network import load_network
from dpm.commands import COM_NODE_DIAG
from dpm.errors import Drv
from dpm.image import lock_path
from dpm.message import Message, Task
from host_api.board import Board, CifError
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload
from host_api.driver import DevCloseDriver, DevExitBoard, DevInitBoard, DevOpenDriver
from tests import commands
from tests.cia309_clients import serving
from tests.conftest import ROOT, Card, start_card, taken
from tests.libcif_host import (
    C_TESTS,
    CC,
    PYTHON_DRIVER,
    SANITIZE,
    STRICT,
    CDriver,
    build_libcif,
    compile_program,
    run,
)

SHM_READ = Message(rx=2, tx=16, b=17, nr=1, data=bytes([0, 1, 0, 0, 0, 2, 5, 1]))
"""COM_Shared_Memory: 2 bytes of the receive area at 0."""
LONG_WAIT_MS = 5000
AT_ONCE_S = 1.0


def cifemu(*args: str) -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "cifemu", *args], capture_output=True,
                        text=True, timeout=60, cwd=ROOT)


def test_a_gateway_holding_the_mailbox_is_named_within_a_second(tmp_path: Path) -> None:
    network = tmp_path / "net.toml"
    network.write_text("[[node]]\nid = 2\n")
    dbm = tmp_path / "plant.dbm"
    assert cifemu("dbm", "build", str(network), "-o", str(dbm)).returncode == 0
    card = start_card(tmp_path)
    serve = subprocess.Popen([sys.executable, "-m", "cifemu", "309", "serve", "--dpm-dir",
                              str(tmp_path), "--port", "0"], cwd=ROOT, stderr=subprocess.PIPE,
                             text=True)
    where = ("--dpm-dir", str(tmp_path))
    try:
        stderr = serve.stderr
        assert stderr is not None
        lines: queue.SimpleQueue[str] = queue.SimpleQueue()

        def pump() -> None:
            for line in stderr:
                lines.put(line)

        threading.Thread(target=pump, daemon=True).start()
        match = re.search(r"listening on 127\.0\.0\.1:(\d+)", taken(lines, 30))
        assert match is not None
        port = match.group(1)
        # the gateway listens once it holds the board's mailbox (host_api.cia309.link)
        assert DevOpenDriver(tmp_path) == 0 and DevInitBoard(0) == 0
        try:
            started = time.monotonic()
            rc = DevDownload(0, CONFIGURATION_DOWNLOAD, dbm)
            download_s = time.monotonic() - started
        finally:
            DevExitBoard(0)
            DevCloseDriver()
        with Board(0, tmp_path, timeout=5000) as board:
            started = time.monotonic()
            with pytest.raises(CifError) as refused:
                board.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_NODE_DIAG,
                                       data=bytes([2])))
            transact_s = time.monotonic() - started
        download = cifemu("dbm", "download", str(dbm), *where)
        direct = cifemu("309", "exec", "--direct", "1 read 0x1000 0 u32", *where)
    finally:
        serve.terminate()
        commands.wait(serve, 20)
        card.stop()
    assert rc == Drv.DRV_CMD_ACTIVE and download_s < 1.0
    assert refused.value.code == Drv.DRV_CMD_ACTIVE and transact_s < 1.0
    named = f"(cifemu 309 serve --dpm-dir {tmp_path} --port 0) holds this board's mailbox"
    advice = f"`cifemu 309 exec --port {port} '1 read 0x1000 0 u32'`"
    for text in (str(refused.value), download.stderr, direct.stdout + direct.stderr):
        assert f"the CiA 309 gateway pid {serve.pid} " + named in text, text
        assert advice in text, text
    assert download.returncode == 1 and direct.returncode != 0



# --- the raw driver calls, in both drivers -------------------------------------------------


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, Path]]:
    """A ``cifemu 309 serve`` on board 0 of a card, and a DBM of that card's network."""
    directory = tmp_path_factory.mktemp("busy")
    with serving(directory):
        dbm = directory / "plant.dbm"
        save_dbm(dbm, build_dbm(load_network(directory / "network0.toml")))
        yield directory, dbm


def driver(kind: str) -> Any:
    return PYTHON_DRIVER if kind == "python" else CDriver()


def timed(call: Any, *args: Any) -> tuple[int, float]:
    """A driver call's code and the seconds it took."""
    started = time.monotonic()
    result = call(*args)
    return (result[0] if isinstance(result, tuple) else result), time.monotonic() - started


@pytest.mark.parametrize("kind", ["python", "c"])
def test_mailbox_calls_fail_at_once_while_a_gateway_holds_the_mailbox(
        gateway: tuple[Path, Path], kind: str) -> None:
    """The gateway never lets go: a DevPutMessage or DevGetMessage that waited its 5 s
    time-out, or a DevDownload its 30 s, would end in -4 all the same."""
    directory, dbm = gateway
    d = driver(kind)
    assert d.DevOpenDriver(directory) == 0 and d.DevInitBoard(0) == 0
    try:
        put = timed(d.DevPutMessage, 0, SHM_READ, LONG_WAIT_MS)
        get = timed(d.DevGetMessage, 0, 288, LONG_WAIT_MS)
        download = timed(d.DevDownload, 0, CONFIGURATION_DOWNLOAD, dbm)
    finally:
        d.DevExitBoard(0)
        d.DevCloseDriver()
    for name, (rc, seconds) in {"put": put, "get": get, "download": download}.items():
        assert rc == Drv.DRV_CMD_ACTIVE, name
        assert seconds < AT_ONCE_S, f"{name} took {seconds:.2f} s"


def test_a_sanitized_c_host_fails_at_once_while_a_gateway_holds_the_mailbox(
        gateway: tuple[Path, Path], tmp_path: Path) -> None:
    if CC is None:
        pytest.skip("no C compiler")
    directory, dbm = gateway
    build_libcif("sanitize")
    program = compile_program(C_TESTS / "busy_board.c", tmp_path / "busy_board", "sanitized")
    lines = run(program, directory, str(LONG_WAIT_MS), str(dbm)).split()
    results = {lines[i]: (int(lines[i + 1]), int(lines[i + 2])) for i in range(0, len(lines), 3)}
    assert set(results) == {"put", "get", "download"}
    for name, (rc, ms) in results.items():
        assert rc == Drv.DRV_CMD_ACTIVE, name
        assert ms < AT_ONCE_S * 1000, f"{name} took {ms} ms"


HOLD = ("import fcntl, sys\n"
        "lock = open(sys.argv[1], 'a')\n"
        "fcntl.flock(lock, fcntl.LOCK_EX)\n"
        "print('held', flush=True)\n"
        "sys.stdin.readline()\n")
"""A process that holds the board's transaction lock until its stdin has a line."""


@pytest.mark.parametrize("kind", ["python", "c"])
def test_a_holder_that_is_no_gateway_is_waited_for(card: Card, kind: str) -> None:
    """Only a gateway is refused at once: another holder may let go, and is waited for up
    to the call's time-out."""
    d = driver(kind)
    assert d.DevOpenDriver(card.directory) == 0 and d.DevInitBoard(0) == 0
    holder = subprocess.Popen([sys.executable, "-c", HOLD,
                               str(lock_path(card.directory, 0, "transaction"))],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        put = timed(d.DevPutMessage, 0, SHM_READ, 300)
        get = timed(d.DevGetMessage, 0, 288, 300)
    finally:
        holder.communicate("\n", timeout=20)
        d.DevExitBoard(0)
        d.DevCloseDriver()
    for name, (rc, seconds) in {"put": put, "get": get}.items():
        assert rc == Drv.DRV_CMD_ACTIVE, name
        assert seconds >= 0.3, f"{name} gave up after {seconds:.3f} s"


def test_libcifs_lock_table_reader_stays_in_bounds_under_the_sanitizers(tmp_path: Path) -> None:
    """Kernel lines, waiters, other files, pids 0 and this process's, lines longer than the
    reader's buffer or across its chunks, command lines with and without "309 serve", then
    random files: every answer as expected, no read outside a buffer."""
    if CC is None:
        pytest.skip("no C compiler")
    build_libcif("sanitize")
    program = tmp_path / "holder_fuzz"
    subprocess.run([CC, *STRICT, *SANITIZE, str(C_TESTS / "holder_fuzz.c"),
                    f"-I{libcif.SOURCE / 'src'}", str(libcif.BUILD / "asan" / "libcif.a"),
                    "-pthread", "-o", str(program)], check=True)
    done = commands.run([str(program), str(tmp_path), "2000", "7"], capture_output=True,
                        text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.startswith("ok ")
