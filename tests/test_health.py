"""A dead firmware is seen as dead; the database of the last start is told (real processes)."""

from __future__ import annotations

import datetime
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from dbm_tools.builder import build_dbm
from dbm_tools.container import write_dbm
from dbm_tools.network import load_network
from dpm.errors import Drv
from dpm.message import Message
from host_api import driver as d
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload
from host_api.liveness import firmware_liveness
from host_api.ready import StartError, wait_ready
from tests import commands
from tests.conftest import ROOT, Card, start_card, wait_until
from tests.libcif_host import PYTHON_DRIVER, CDriver

DEMO = ROOT / "cifemu" / "examples" / "demo.toml"


def status(directory: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "cifemu", "status", "--dpm-dir", str(directory),
                         *extra], capture_output=True, text=True, timeout=60, cwd=ROOT)


def kill(card: Card) -> None:
    card.proc.send_signal(signal.SIGKILL)
    commands.wait(card.proc, 10)


def test_status_reports_a_killed_firmware_as_dead_with_its_last_pid(tmp_path: Path) -> None:
    card = start_card(tmp_path)
    try:
        alive = status(tmp_path, "--json")
        assert alive.returncode == 0
        assert json.loads(alive.stdout)["health"] == {
            "alive": True, "pid": card.proc.pid, "database": None,
            "bus": {"interface": "virtual", "channel": "cifemu", "bitrate": None,
                    "sets_bitrate": False, "baud_rate": None, "fatal": None}}
        kill(card)
        assert card.map()[0x1FFE] & 0x80  # the image still says READY
        text = status(tmp_path)
        assert text.returncode == 3
        assert "DEAD" in text.stdout and f"last pid {card.proc.pid}" in text.stdout
        as_json = status(tmp_path, "--json")
        health = json.loads(as_json.stdout)["health"]
        assert as_json.returncode == 3 and health["alive"] is False
        assert health["pid"] == card.proc.pid
    finally:
        card.stop()  # a failed assertion must not leave the firmware running


def test_a_start_takes_ready_only_from_the_process_it_started(tmp_path: Path) -> None:
    """The one wait for a start (``host_api.ready``: the suite's, the benchmarks', the
    plugin's) ignores the READY a SIGKILLed firmware left in its image: a process that
    never serves fails it, by its CPU time (none for 1 s), instead of passing it at once
    (the benchmarks' own wait did, before the three waits were one)."""
    card = start_card(tmp_path)
    kill(card)
    assert card.map()[0x1FFE] & 0x80  # the image still says READY
    stand_in = subprocess.Popen([sys.executable, "-c", "import signal; print(flush=True); "
                                 "signal.pause()"], stdout=subprocess.PIPE)
    try:
        assert stand_in.stdout is not None
        stand_in.stdout.readline()  # started: from here on it sleeps, it takes no CPU
        with pytest.raises(StartError, match="got no CPU for 1 s") as refused:
            wait_ready(stand_in, tmp_path, 0, stall_s=1.0)
        assert refused.value.status is None
    finally:
        stand_in.kill()
        stand_in.wait()


HELD_IN_THE_LOCK = """
import mmap, sys
from pathlib import Path
from dpm.flags import HostFlag
from dpm.image import CardDirectory, ExclusiveLock, image_path, lock_path
from dpm.layout import HOST_FLAGS

directory = Path(sys.argv[1])

def set_host_flags(value):
    with open(image_path(directory, 0), "r+b") as f, mmap.mmap(f.fileno(), 0) as mm:
        mm[HOST_FLAGS] = value

def held():
    print("locked", flush=True)
    sys.stdin.readline()
    set_host_flags(0)  # what Device._clear_host_flags does at this point

lock = ExclusiveLock(CardDirectory(directory), lock_path(directory, 0).name, on_acquired=held)
set_host_flags(HostFlag.READY)
print("ready", flush=True)
sys.stdin.readline()
"""
"""A firmware's start around its lock (``dpm.image.ExclusiveLock``, as ``Device`` takes it),
held where the test says: a firmware is in that instant between taking the lock and
clearing its killed predecessor's READY, which no real firmware can be made to stay in."""


def test_a_start_is_not_ready_while_the_predecessors_ready_is_still_there(
        tmp_path: Path) -> None:
    """The new firmware holds its lock before it clears the READY a SIGKILLed one left:
    the start's wait read READY, then found the lock held by the new pid, and returned; the
    host's DevInitBoard then met the image without READY: -11 right after the start (a
    loaded ``-n 3`` run of test_download's SIGKILL test). READY now counts only when read
    after the lock file names the new pid, which is written after the clearing."""
    card = start_card(tmp_path)
    kill(card)
    assert card.map()[0x1FFE] & 0x80  # the image still says READY
    stand_in = subprocess.Popen([sys.executable, "-c", HELD_IN_THE_LOCK, str(tmp_path)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, cwd=ROOT)
    try:
        assert stand_in.stdin is not None and stand_in.stdout is not None
        assert stand_in.stdout.readline() == b"locked\n"  # holds the lock, sleeps on stdin
        assert card.map()[0x1FFE] & 0x80
        with pytest.raises(StartError, match="got no CPU for 1 s"):
            wait_ready(stand_in, tmp_path, 0, stall_s=1.0)
        stand_in.stdin.write(b"\n")
        stand_in.stdin.flush()
        assert stand_in.stdout.readline() == b"ready\n"
        wait_ready(stand_in, tmp_path, 0)
        assert d.DevOpenDriver(tmp_path) == 0
        assert d.DevInitBoard(0) == 0
    finally:
        while d.DevCloseDriver() == 0:
            pass
        stand_in.kill()
        stand_in.wait()


@pytest.mark.parametrize("driver", ["python", "c"])
def test_init_board_is_not_ready_while_a_new_firmware_has_not_cleared_the_old_ready(
        tmp_path: Path, driver: str) -> None:
    """[ours] A new firmware holds its lock before it clears the READY a SIGKILLed one left
    (and writes its pid after): DevInitBoard read READY, then asked whether the lock is held,
    and took the dead firmware's READY for the new one's (0, and -11 on the next call).
    It now asks first whether the holder is the pid the lock file names, READY after:
    -11 until the new firmware has written its pid, 0 once it is READY."""
    card = start_card(tmp_path)
    kill(card)
    assert card.map()[0x1FFE] & 0x80  # the image still says READY
    impl: Any = PYTHON_DRIVER if driver == "python" else CDriver()
    stand_in = subprocess.Popen([sys.executable, "-c", HELD_IN_THE_LOCK, str(tmp_path)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, cwd=ROOT)
    try:
        assert stand_in.stdin is not None and stand_in.stdout is not None
        assert stand_in.stdout.readline() == b"locked\n"  # holds the lock, sleeps on stdin
        assert impl.DevOpenDriver(tmp_path) == 0
        assert impl.DevInitBoard(0) == Drv.DRV_DEV_NOT_READY
        stand_in.stdin.write(b"\n")
        stand_in.stdin.flush()
        assert stand_in.stdout.readline() == b"ready\n"
        assert impl.DevInitBoard(0) == 0
    finally:
        while impl.DevCloseDriver() == 0:
            pass
        stand_in.kill()
        stand_in.wait()


def test_a_cleanly_stopped_firmware_leaves_no_pid(tmp_path: Path) -> None:
    card = start_card(tmp_path)
    assert card.stop() == 0
    assert firmware_liveness(tmp_path, 0).alive is False
    assert firmware_liveness(tmp_path, 0).pid is None
    assert status(tmp_path).returncode == 3


def test_init_board_after_a_sigkill_is_not_ready(tmp_path: Path) -> None:
    card = start_card(tmp_path)
    kill(card)
    assert d.DevOpenDriver(tmp_path) == 0
    try:
        assert d.DevInitBoard(0) == Drv.DRV_DEV_NOT_READY
    finally:
        d.DevCloseDriver()


def test_a_running_host_gets_not_ready_within_its_timeout(tmp_path: Path) -> None:
    card = start_card(tmp_path)
    assert d.DevOpenDriver(tmp_path) == 0
    try:
        assert d.DevInitBoard(0) == 0
        kill(card)
        assert d.DevPutMessage(0, Message(rx=3, tx=16, b=66), 200) == 0  # the mailbox was free
        start = time.monotonic()
        assert d.DevGetMessage(0, 288, 300)[0] == Drv.DRV_DEV_NOT_READY
        assert time.monotonic() - start < 1.0
        # the device mailbox stays full: nobody takes the message
        assert d.DevPutMessage(0, Message(rx=3, tx=16, b=66), 200) == Drv.DRV_DEV_NOT_READY
        assert d.DevReset(0, d.WARMSTART, 200) == Drv.DRV_DEV_NOT_READY
    finally:
        while d.DevCloseDriver() == 0:
            pass


def test_the_database_loaded_from_flash_is_logged_and_shown(tmp_path: Path) -> None:
    flash = tmp_path / "flash0"
    card = start_card(tmp_path, 0, "--flash", str(flash))
    database = write_dbm(build_dbm(load_network(DEMO), project="plant A",
                                   date=datetime.date(2026, 11, 30)))
    assert d.DevOpenDriver(tmp_path) == 0
    try:
        assert d.DevInitBoard(0) == 0
        assert DevDownload(0, CONFIGURATION_DOWNLOAD, database) == 0
    finally:
        while d.DevCloseDriver() == 0:
            pass
    assert card.stop() == 0
    card = start_card(tmp_path, 0, "--flash", str(flash), "--log-level", "INFO")
    try:
        wait_until(lambda: (json.loads(status(tmp_path, "--json").stdout)["health"]["database"]
                            or {}).get("name") == "plant A", 10, "the database in status")
        shown = json.loads(status(tmp_path, "--json").stdout)["health"]["database"]
        assert shown["nodes"] == 4 and shown["usable"] is True and "30.11.2026" in shown["date"]
        assert "plant A" in status(tmp_path).stdout
    finally:
        assert card.stop() == 0
    log = card.log()
    assert "database from flash: 'plant A' of" in log and "4 node(s)" in log
    assert os.path.exists(tmp_path / "board0.card.json")


def test_top_once_says_a_killed_firmware_is_dead(tmp_path: Path) -> None:
    card = start_card(tmp_path)
    kill(card)
    out = commands.run([sys.executable, "-m", "cifemu", "top", "--once", "--sample", "0.2",
                        "--dpm-dir", str(tmp_path)], capture_output=True, text=True,
                       timeout=60, cwd=ROOT)
    assert out.returncode == 3
    assert f"firmware DEAD (last pid {card.proc.pid})" in out.stdout
    assert "no frames: no card's frame tap" in out.stdout
