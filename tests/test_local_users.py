"""Another local user against root's card: planted files, squatted sockets, tap subscriptions.

docs/security.md. The tests run as root and make the other user real: a forked child
becomes ``nobody`` (os.setgid/os.setuid) and creates its directories, symlinks and
sockets itself. The card's files live in a directory under /dev/shm (world-writable and
sticky, as the default /dev/shm/cif's parent is); the victims are root's 0600 files with
known bytes in a directory only root enters, and must come out byte for byte and mode
for mode unchanged. tests/c/bell_ring.c shows that libcif (x86-64 and i386) rings the
doorbell where the firmware now binds it.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pwd
import select
import shutil
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

import host_api as d
from dbm_tools.builder import build_dbm
from dbm_tools.container import data_area
from dbm_tools.network import parse_network
from dpm.doorbell import device_address
from dpm.image import CardDirectory
from dpm.tap import SUBSCRIBE, tap_address
from host_api.board import Board
from host_api.download import CONFIGURATION_DOWNLOAD
from host_api.network_view import remember_network
from host_api.ready import START_CPU_S, START_STALL_S, StartError, wait_ready
from tests import commands
from tests.conftest import IMAGE_SIZE, ROOT, TIME_SCALE, start_card, wait_until

pytestmark = pytest.mark.skipif(os.geteuid() != 0, reason="becoming another user needs root")

NOBODY = pwd.getpwnam("nobody")
DEMO = ROOT / "cifemu" / "examples" / "demo.toml"


@pytest.fixture
def shm() -> Iterator[Path]:
    """A fresh world-writable sticky directory in /dev/shm: the place every user may
    create the card's directory first."""
    place = Path(tempfile.mkdtemp(dir="/dev/shm", prefix="cifemu-test-"))
    os.chmod(place, 0o1777)
    yield place
    shutil.rmtree(place, ignore_errors=True)


@pytest.fixture
def victims(tmp_path: Path) -> dict[str, Path]:
    """Root's files, mode 0600, in a directory only root enters."""
    home = tmp_path / "root-only"
    home.mkdir(mode=0o700)
    files = {}
    for name in ("image", "lock", "card", "card-tmp", "note", "flash"):
        path = home / name
        path.write_bytes(f"root's {name} file, keep out\n".encode())
        path.chmod(0o600)
        files[name] = path
    return files


def assert_unchanged(victims: dict[str, Path]) -> None:
    for name, path in victims.items():
        st = os.lstat(path)
        assert (path.read_bytes(), stat.S_IMODE(st.st_mode), st.st_uid) == (
            f"root's {name} file, keep out\n".encode(), 0o600, 0), f"{path} was changed"


def as_nobody(where: Path, action: Callable[[], None]) -> None:
    """Run ``action`` in a forked child that is the user nobody, in directory ``where``."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child reports through its exit status
        code = 1
        try:
            os.chdir(where)
            os.setgroups([])
            os.setgid(NOBODY.pw_gid)
            os.setuid(NOBODY.pw_uid)
            action()
            code = 0
        except BaseException:
            traceback.print_exc()
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, "the child as nobody failed"


def firmware(directory: Path, *extra: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", "cifemu", "firmware", "--dpm-dir",
                             str(directory), "--log-level", "WARNING", *extra],
                            stderr=subprocess.PIPE, cwd=ROOT)


def serving(proc: subprocess.Popen[bytes], directory: Path) -> bool:
    """Wait until the firmware ends (False) or serves board 0 (True), by the suite's one wait
    for a start (``host_api.ready``); a start that stops advancing gives True: it still runs."""
    try:
        wait_ready(proc, directory, 0, START_STALL_S * TIME_SCALE, START_CPU_S * TIME_SCALE)
    except StartError as exc:
        return exc.status is None
    return True


def ended(proc: subprocess.Popen[bytes]) -> str:
    """What the firmware wrote to stderr; killed if it still runs."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
    return proc.communicate(timeout=30)[1].decode()


def refusal(proc: subprocess.Popen[bytes], err: str) -> str:
    """The firmware's one line on stderr, as it ended with status 1."""
    assert proc.returncode == 1, f"the firmware served instead of refusing: {err}"
    lines = err.splitlines()
    assert len(lines) == 1, err
    return lines[0]


def test_a_card_directory_another_user_made_first_is_refused(
        shm: Path, victims: dict[str, Path], tmp_path: Path) -> None:
    def plant() -> None:
        os.mkdir("cif")
        os.chmod("cif", 0o777)
        for name, victim in (("board0.dpm", "image"), ("board0.firmware.lock", "lock"),
                             ("board0.card.json", "card"), ("board0.card.tmp", "card-tmp")):
            os.symlink(victims[victim], f"cif/{name}")

    as_nobody(shm, plant)
    proc = firmware(shm / "cif", "--flash", str(tmp_path / "flash"))
    serving(proc, shm / "cif")
    err = ended(proc)
    assert_unchanged(victims)
    line = refusal(proc, err)
    assert line.startswith("cifemu firmware: board 0 refused: directory ")
    assert str(shm / "cif") in line
    assert "lets every user write to it" in line


def group_directory(shm: Path) -> Path:
    """A directory of root's whose group (nogroup) is the host group: nobody writes to it."""
    directory = shm / "cif"
    directory.mkdir()
    os.chown(directory, 0, NOBODY.pw_gid)
    directory.chmod(0o2770)
    return directory


@pytest.mark.parametrize(("name", "victim"), [("board0.dpm", "image"),
                                              ("board0.firmware.lock", "lock")])
def test_a_symlink_planted_by_a_host_group_member_is_refused(
        shm: Path, victims: dict[str, Path], tmp_path: Path, name: str, victim: str) -> None:
    directory = group_directory(shm)
    as_nobody(directory, lambda: os.symlink(victims[victim], name))
    proc = firmware(directory, "--flash", str(tmp_path / "flash"))
    serving(proc, directory)
    err = ended(proc)
    assert_unchanged(victims)
    line = refusal(proc, err)
    assert line == f"cifemu firmware: board 0 refused: {directory / name} refused: a symbolic link"


def test_planted_temporary_files_and_notes_are_not_followed(
        shm: Path, victims: dict[str, Path], tmp_path: Path) -> None:
    directory = group_directory(shm)

    def plant() -> None:
        os.symlink(victims["card-tmp"], "board0.card.tmp")  # today's fixed temporary name
        os.symlink(victims["card"], "board0.card.json")
        os.symlink(victims["note"], "board0.network")

    as_nobody(directory, plant)
    card = start_card(directory, 0, "--flash", str(tmp_path / "flash"))
    try:
        remember_network(directory, 0, DEMO)  # as `cifemu configure` run by root does
    finally:
        card.stop()
    assert_unchanged(victims)
    for name in ("board0.card.json", "board0.network"):
        st = os.lstat(directory / name)
        assert stat.S_ISREG(st.st_mode) and st.st_uid == 0, name
    assert (directory / "board0.network").read_text() == f"{DEMO}\n"


def test_a_flash_directory_another_user_can_write_to_is_refused(
        shm: Path, victims: dict[str, Path]) -> None:
    cards = shm / "cards"
    flash = group_directory(shm)
    proc = firmware(cards, "--flash", str(flash))
    try:
        if serving(proc, cards):  # today: the user plants the store's temporary file
            as_nobody(flash, lambda: os.symlink(victims["flash"], f".database.bin.{proc.pid}.tmp"))
            area = data_area(build_dbm(parse_network('[[node]]\nid = 3\nboot = ["start"]\n')))
            assert d.DevOpenDriver(cards) == 0 and d.DevInitBoard(0) == 0
            d.DevDownload(0, CONFIGURATION_DOWNLOAD, area)
    finally:
        while d.DevCloseDriver() == 0:
            pass
        err = ended(proc)
    assert_unchanged(victims)
    assert refusal(proc, err) == (f"cifemu firmware: board 0 refused: directory {flash} "
                                  f"refused: mode 2770 lets group {NOBODY.pw_gid} write to it")


def test_directories_and_files_keep_their_modes_under_umask_000(tmp_path: Path) -> None:
    cards = tmp_path / "run" / "cif"
    flash = tmp_path / "data" / "board0"
    old = os.umask(0)
    try:
        card = start_card(cards, 0, "--flash", str(flash))
    finally:
        os.umask(old)
    try:
        modes = {path.relative_to(tmp_path).as_posix(): stat.S_IMODE(os.lstat(path).st_mode)
                 for path in (cards.parent, cards, flash.parent, flash, *cards.iterdir())}
    finally:
        card.stop()
    assert modes == {"run": 0o2750, "run/cif": 0o2770, "data": 0o750, "data/board0": 0o750,
                     "run/cif/board0.dpm": 0o660, "run/cif/board0.firmware.lock": 0o660,
                     "run/cif/board0.card.json": 0o660, "run/cif/board0.bell": 0o660,
                     "run/cif/board0.tap": 0o660, "run/cif/board0.fault": 0o660,
                     "run/cif/board0.record": 0o660}


def hold(action: Callable[[socket.socket], None]) -> tuple[int, socket.socket]:
    """A child that is nobody runs ``action`` and then waits until the returned socket
    closes, sending one byte when ready; returns its pid and our end."""
    ours, theirs = socket.socketpair()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child reports through its exit status
        code = 1
        try:
            ours.close()
            os.setgroups([])
            os.setgid(NOBODY.pw_gid)
            os.setuid(NOBODY.pw_uid)
            action(theirs)
            code = 0
        except BaseException:
            traceback.print_exc()
        finally:
            os._exit(code)
    theirs.close()
    ours.settimeout(20 * TIME_SCALE)
    assert ours.recv(1) == b"+", "the child as nobody did not get ready"
    return pid, ours


def release(pid: int, ours: socket.socket) -> bytes:
    """Tell the child to end; what it sent after its ready byte."""
    ours.shutdown(socket.SHUT_WR)
    rest = b""
    while chunk := ours.recv(64):
        rest += chunk
    ours.close()
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, "the child as nobody failed"
    return rest


def test_squatted_socket_names_do_not_stop_the_card(shm: Path) -> None:
    cards = shm / "cif"
    image = str((cards / "board0.dpm").resolve()).encode()
    digest = hashlib.sha1(image).hexdigest()[:20].encode()  # the names cifemu used to take

    def squat(report: socket.socket) -> None:
        taken = []
        for name in (b"\0cifemu-dpm-" + digest, b"\0cifemu-tap-" + digest):
            taken.append(socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM))
            taken[-1].bind(name)
        report.send(b"+")
        report.recv(1)

    pid, ours = hold(squat)
    try:
        card = start_card(cards, 0, "--simulate", str(DEMO), "--configure")
        try:
            with Board(0, cards) as board:
                wait_until(lambda: board.diagnostics().can_state_name == "OPERATE", 20,
                           "the network in OPERATE")
            done = commands.run([sys.executable, "-m", "cifemu", "monitor", "--dpm-dir",
                                 str(cards), "--json", "--count", "3", "--duration", "20"],
                                capture_output=True, text=True, timeout=60, cwd=ROOT)
        finally:
            card.stop()
    finally:
        release(pid, ours)
    assert done.returncode == 0 and len(done.stdout.splitlines()) == 3, done.stderr


def test_another_user_cannot_take_the_taps_subscriptions(shm: Path) -> None:
    cards = shm / "cif"
    card = start_card(cards, 0, "--simulate", str(DEMO), "--configure")
    address = tap_address(card.path)

    def subscribe_all(report: socket.socket) -> None:
        """Hold all 8 subscriptions, renewed every 0.3 s, and count the frames read."""
        taps = [socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) for _ in range(8)]
        for tap in taps:
            tap.bind(b"")
            tap.setblocking(False)
        frames = 0
        ready = False
        while True:
            for tap in taps:
                with contextlib.suppress(OSError):  # refused: the directory keeps us out
                    tap.sendto(SUBSCRIBE, address)
            if not ready:
                report.send(b"+")
                ready = True
            readable, _, _ = select.select([report, *taps], [], [], 0.3)
            for tap in taps:
                while tap in readable:
                    try:
                        tap.recv(128)
                    except BlockingIOError:
                        break
                    frames += 1
            if report in readable:
                break
        report.send(str(frames).encode())

    try:
        pid, ours = hold(subscribe_all)
        try:
            done = commands.run([sys.executable, "-m", "cifemu", "monitor", "--dpm-dir",
                                 str(cards), "--json", "--count", "5", "--duration", "15"],
                                capture_output=True, text=True, timeout=60, cwd=ROOT)
        finally:
            stolen = release(pid, ours)
    finally:
        card.stop()
    assert done.returncode == 0 and len(done.stdout.splitlines()) == 5, done.stderr
    assert stolen == b"0", f"nobody read {stolen.decode()} of the card's frames"


def test_a_socket_name_a_host_group_member_took_is_one_line(
        shm: Path, tmp_path: Path) -> None:
    directory = group_directory(shm)
    as_nobody(directory, lambda: os.mkdir("board0.bell"))
    proc = firmware(directory, "--flash", str(tmp_path / "flash"))
    serving(proc, directory)
    assert refusal(proc, ended(proc)) == (
        f"cifemu firmware: board 0 refused: {directory / 'board0.bell'}: the card's socket "
        "cannot take this name: Is a directory")

    os.rmdir(directory / "board0.bell")
    as_nobody(directory, lambda: os.mkdir("board0.tap"))
    card = start_card(directory, 0, "--flash", str(tmp_path / "flash"))
    try:
        with Board(0, directory) as board:  # the card serves without its tap
            assert board.diagnostics().can_state_name == "OFFLINE"
        done = commands.run([sys.executable, "-m", "cifemu", "monitor", "--dpm-dir",
                             str(directory), "--duration", "5"],
                            capture_output=True, text=True, timeout=60, cwd=ROOT)
    finally:
        card.stop()
    err = card.log()
    assert "frame tap not offered, monitors see no frames" in err and "Traceback" not in err
    assert done.returncode == 1
    assert done.stderr == (f"cifemu monitor: no card's frame tap at {directory / 'board0.tap'}\n")


@pytest.mark.parametrize("bits", ["64", "32"])
def test_libcifs_doorbell_rings_the_socket_in_the_cards_directory(
        tmp_path: Path, bits: str) -> None:
    """The C side names the doorbell as the firmware does; i386 too (the legacy preload)."""
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("no C compiler")
    if bits == "32" and (ROOT / "libcif" / "build" / "i386" / "MISSING").exists():
        pytest.skip((ROOT / "libcif" / "build" / "i386" / "MISSING").read_text().strip())
    program = tmp_path / "bell_ring"
    subprocess.run([compiler, f"-m{bits}", "-std=c11", "-Wall", "-Wextra", "-Werror",
                    str(ROOT / "tests" / "c" / "bell_ring.c"), str(ROOT / "libcif" / "src"
                                                               / "bell.c"),
                    f"-I{ROOT / 'libcif' / 'src'}", "-o", str(program)], check=True)
    cards = tmp_path / "cards"
    files = CardDirectory(cards, create=True)
    device = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        (cards / "board0.dpm").write_bytes(bytes(IMAGE_SIZE))
        files.bind(device, Path(device_address(cards / "board0.dpm")))
        done = commands.run([str(program), str(cards / "board0.dpm")], capture_output=True,
                            text=True, timeout=30)
        assert done.returncode == 0, done.stderr
        assert done.stdout == f"{device_address(cards / 'board0.dpm')}\n"
        device.settimeout(10 * TIME_SCALE)
        assert device.recv(16) == b"\x01"
    finally:
        device.close()
        files.close()
    deep = tmp_path / ("d" * 100)
    deep.mkdir()
    (deep / "board0.dpm").write_bytes(bytes(IMAGE_SIZE))
    done = commands.run([str(program), str(deep / "board0.dpm")], capture_output=True,
                        text=True, timeout=30)
    assert (done.returncode, done.stderr) == (2, "bell_ring: File name too long\n")
