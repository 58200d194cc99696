"""Legacy binaries unchanged: /dev/cif served by libcifdev.so (LD_PRELOAD).

tests/c/legacy_ioctl.c issues the ioctls the way Hilscher's API object does (open
/dev/cif, one ioctl per driver function with its packed DEVIO structure in the
program's ABI). It runs built for x86-64 and for i386, with the ioctl numbers of driver
2.6 and of driver 2.100, against real firmware with simulated nodes: every ioctl's
success path (a message round trip, a DBM download, resets, process data in each
handshake mode, the watchdog), the driver's error codes, and malformed structures.
The i386 runs need gcc-multilib (``make test`` installs it as root, see docs/legacy.md).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from cifemu import libcif
from cifemu.commands import legacy
from dbm_tools.builder import build_dbm
from dbm_tools.container import save_dbm
from dbm_tools.network import parse_network
from tests import commands
from tests.conftest import Card
from tests.libcif_host import C_NETWORK, CC, STRICT, build_libcif, needs_toolchain

SOURCE = Path(__file__).with_name("c") / "legacy_ioctl.c"
pytestmark = needs_toolchain
pytest_plugins = ["tests.libcif_host"]
"""simulated_card: a card with C_NETWORK's nodes."""

# What the program prints, driver code by driver code. The same for both ABIs and both
# generations: the structures differ, the answers do not.
EXPECTED = {
    # the device: any flags, fcntl, read gives 0 bytes, write fails, close of a stranger
    "close_unopened": 1, "open": 1, "fcntl": 1, "read": 0, "write_enomem": 1,
    "dup_is_device": 1, "closed_dup_is_not": 1,
    "boardinfo": 0, "boards_detected": 1, "board0_available": 1, "board1_available": 0,
    # GETINFO and DPM access reached a board before INITDRV; a message did not
    "getinfo_before_initdrv": 0, "firmware_before_initdrv": "CANopen Master",
    "rwdpm_before_initdrv": 0, "identifier_before_initdrv": "CIF", "putmsg_before_initdrv": -1,
    # INITDRV: the DPM size in kB; a board the driver does not have is -1
    "initdrv": 0, "dpm_size": 8, "initdrv_absent": -1, "initdrv_board9": -1,
    "boardinfoex": 0, "boardinfoex_firmware": "CANopen Master", "boardinfoex_opens": 1,
    "getinfo_firmware": 0, "firmware": "CANopen Master", "getinfo_driver": 0,
    "getinfo_version": 0, "getinfo_task": 0, "getinfo_rcs": 0, "getinfo_dev": 0,
    "dev_identifier": "CIF", "getinfo_io": 0, "getinfo_send": 0,
    # GETINFO answered 0 for an unknown area and a board it did not have: the API
    # object makes -33 of it; sError held -5 and -1
    "getinfo_area9": -33, "getinfo_board3": -33,
    "getinfo_too_long": -43, "getinfo_bad_pointer": -45,
    "mbxinfo": 0, "mbx_dev": 0, "mbx_host": 0, "sethost_ready": 0,
    # a message round trip, an empty mailbox at once and after a wait
    "putmsg": 0, "getmsg": 0, "answer": "16,2,1,17,0", "getmsg_empty": -19,
    "getmsg_timeout": -18, "putmsg_board7": -1,
    "getmbx": 0, "getmbx_host_nr": 1, "getmbx_too_long": -43,
    "taskstate": 0, "taskstate_too_long": -43, "getparameter": 0,
    # GETPARAMETER of task 5: the driver returned -1 (EPERM) with sError -36
    "getparameter_task5": -36, "getparameter_task5_errno": 1,
    "putparameter_task9": -36, "putparameter_too_long": -43,
    # a DBM download through PUTMSG/GETMSG, then the card cold-starts from it
    "download": 0, "reset_cold": 0, "sethost_com": 0,
    **{f"mode{m}_{step}": 0 for m in (1, 2, 3)
       for step in ("putparameter", "reset_warm", "sethost", "exio", "exioex", "exioerr",
                    "readsend")},
    **{f"mode{m}_sent": 1 for m in (1, 2, 3)},
    # bMode 1, 2, 3 give the driver's exchange modes 2, 3 (uncontrolled), 4
    "mode1_driver_mode": 2, "mode2_driver_mode": 3, "mode3_driver_mode": 4,
    "exio_send_too_long": -46, "exio_bad_send": -48, "exio_bad_receive": -49,
    # EXIO on a board not initialised: the driver returned -1, the API object -33
    "exio_board3": -33, "exio_board3_errno": 1,
    "exioex_mode0": -24, "exioex_mode6": -24, "exioerr_bad_state": -45,
    "watchdog_start": 0, "watchdog_copied": 1, "watchdog_stop": 0, "watchdog_stopped": 0,
    "spcontrol_set": 0, "spcontrol_clear": 0, "spcontrol_mode5": -37,
    "rwraw_read": 0, "rwraw_identifier": "CIF", "rwraw_too_long": -43, "rwraw_mode7": -37,
    "rwdpm_write": 0, "rwdpm_read": 0, "rwdpm_roundtrip": 1, "rwdpm_too_long": -43,
    "rwdpm_bad_pointer": -45,
    # EXTDATA was never written back by the driver; GETDPMPTR had no case (ioctl 0)
    "extdata": 0, "irq_poll_polling": 0, "irq_poll_irq": 0, "irq_poll_interrupt": 0,
    "getdpmptr": -33,
    # unknown numbers ENOTTY; a structure the driver cannot read EFAULT
    "boardinfo_bad_pointer": -45, "boardinfoex_bad_pointer": -45,
    "readsend_bad_pointer": -45, "rwraw_write_bad_pointer": -45, "null_structures": 1,
    "unknown_nr26": 1, "unknown_type": 1, "bad_structure": 1, "reset_warm": 0,
    "exitdrv": 0, "exitdrv_count": 0, "exitdrv_again": -1, "putmsg_after_exit": -1,
    "close": 0, "close_again": 1, "reopen_rdwr": 1, "close_reopened": 0,
}


@pytest.fixture(scope="module")
def preloads() -> dict[str, Path]:
    """The preload library per ABI; i386 only where gcc-multilib is installed."""
    build_libcif("preload")
    built = {"x86-64": legacy.PRELOAD_64}
    if legacy.PRELOAD_32.exists():
        built["i386"] = legacy.PRELOAD_32
    return built


def need(preloads: dict[str, Path], abi: str) -> Path:
    """The preload of the ABI (i386-time64 is i386), or a skip with the build's reason."""
    abi = "i386" if abi.startswith("i386") else abi
    if abi not in preloads:
        reason = legacy.MISSING_32.read_text().strip() if legacy.MISSING_32.exists() else ""
        pytest.skip(reason or "no i386 build of libcifdev.so")
    return preloads[abi]


@pytest.fixture(scope="module")
def programs(tmp_path_factory: pytest.TempPathFactory,
             preloads: dict[str, Path]) -> dict[str, Path]:
    """tests/c/legacy_ioctl.c compiled for each ABI with a preload."""
    assert CC is not None
    out = tmp_path_factory.mktemp("legacy")
    built = {}
    flags = {"x86-64": [], "i386": ["-m32"],
             # glibc's 64-bit time_t on i386: __ioctl_time64, __fcntl_time64, open64
             "i386-time64": ["-m32", "-D_TIME_BITS=64", "-D_FILE_OFFSET_BITS=64"]}
    for abi, abi_flags in flags.items():
        if ("i386" if abi.startswith("i386") else abi) not in preloads:
            continue
        program = out / f"legacy_ioctl-{abi}"
        done = subprocess.run([CC, *abi_flags, *STRICT, str(SOURCE), "-o", str(program)],
                              capture_output=True, text=True, check=False)
        if done.returncode == 0:
            built[abi] = program
        elif abi != "i386-time64":  # only glibc >= 2.34 has 64-bit time on i386
            raise AssertionError(done.stderr)
    return built


def run_preloaded(program: Path, preload: Path, directory: Path,
                  *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "CIF_DPM_DIR": str(directory), "LD_PRELOAD": str(preload)}
    return commands.run([str(program), *args], env=env, capture_output=True, text=True,
                        timeout=180, check=False)


def parse(output: str) -> dict[str, object]:
    """The program's name=value lines; numbers as int."""
    values: dict[str, object] = {}
    for line in output.splitlines():
        name, _, value = line.partition("=")
        values[name] = int(value) if value.lstrip("-").isdigit() else value
    return values


@pytest.mark.parametrize(("abi", "generation"), [
    ("x86-64", "26"), ("x86-64", "2100"), ("i386", "26"), ("i386", "2100"),
    ("i386-time64", "26")])
def test_every_ioctl_answers_as_the_driver(preloads: dict[str, Path],
                                           programs: dict[str, Path],
                                           simulated_card: Card, tmp_path: Path,
                                           abi: str, generation: str) -> None:
    preload = need(preloads, abi)
    if abi not in programs:
        pytest.skip("this glibc has no 64-bit time_t for i386")
    dbm = tmp_path / "sycon.dbm"
    save_dbm(dbm, build_dbm(parse_network(C_NETWORK)))
    done = run_preloaded(programs[abi], preload, simulated_card.directory, generation,
                         str(dbm))
    assert done.returncode == 0, done.stdout + done.stderr
    values = parse(done.stdout)
    assert values.pop("download_bytes") == dbm.stat().st_size - 44
    wrong = {name: (values.get(name), want) for name, want in EXPECTED.items()
             if values.get(name) != want}
    assert not wrong, f"(got, expected): {wrong}\n{done.stdout}{done.stderr}"
    # the firmware still serves its card: nothing the program did broke it
    assert simulated_card.proc.poll() is None


@pytest.mark.parametrize("abi", ["x86-64", "i386"])
def test_without_a_card_the_open_fails_with_enodev(preloads: dict[str, Path],
                                                   programs: dict[str, Path],
                                                   tmp_path: Path, abi: str) -> None:
    preload = need(preloads, abi)
    done = run_preloaded(programs[abi], preload, tmp_path, "nodevice")
    assert done.stdout == "open=-1 errno=ENODEV\n", done.stderr


def test_every_other_file_is_left_alone(preloads: dict[str, Path], tmp_path: Path) -> None:
    """A program under the preload reads, writes and ioctls its own files as before."""
    cat = shutil.which("cat")
    stty = shutil.which("stty")
    if cat is None:
        pytest.skip("no cat")
    data = tmp_path / "data.bin"
    data.write_bytes(bytes(range(256)) * 40)
    done = subprocess.run([cat, str(data)], capture_output=True, check=False,
                          env={**os.environ, "LD_PRELOAD": str(preloads["x86-64"])})
    assert done.returncode == 0 and done.stdout == data.read_bytes()
    if stty is not None:  # an ioctl on a descriptor that is not the device: libc's answer
        sized = subprocess.run([stty, "size"], stdin=subprocess.DEVNULL, capture_output=True,
                               text=True, check=False,
                               env={**os.environ, "LD_PRELOAD": str(preloads["x86-64"])})
        assert sized.returncode != 0 and "Inappropriate ioctl" in sized.stderr


# --- shutdown with calls in flight, close-all loops (docs/legacy.md "Threads and descriptors")


LIFECYCLE = Path(__file__).with_name("c") / "legacy_lifecycle.c"
# EXITDRV returns at once, later calls get -1, the waiting GETMSG its -18 after its
# time-out; then the board is unmapped and opens again
EXIT_WHILE_WAITING = {
    "open": 1, "initdrv": 0, "waiter_sleeps": 1, "exitdrv": 0, "exitdrv_returned_at_once": 1,
    "waiter_still_waiting": 1, "putmsg_after_exit": -1, "waiter": -18,
    "mapped_after_waiter": 0, "initdrv_again": 0, "round_trip": 0, "exitdrv_again": 0,
    "close": 0}
# after the close-all loop the card answers; the program's file and descriptors unchanged
CLOSE_ALL = {
    "open": 1, "initdrv": 0, "round_trip": 0, "mbxinfo": 0, "reopen": 1, "mbxinfo_after": 0,
    "round_trip_after": 0, "exitdrv": 0, "close": 0, "scratch_fds_open": 1,
    "scratch_unchanged": 1}


@pytest.fixture(scope="module")
def lifecycle(tmp_path_factory: pytest.TempPathFactory,
              preloads: dict[str, Path]) -> dict[str, Path]:
    """tests/c/legacy_lifecycle.c compiled for each ABI with a preload."""
    assert CC is not None
    out = tmp_path_factory.mktemp("lifecycle")
    built = {}
    for abi, abi_flags in {"x86-64": [], "i386": ["-m32"]}.items():
        if abi not in preloads:
            continue
        program = out / f"legacy_lifecycle-{abi}"
        subprocess.run([CC, *abi_flags, *STRICT, str(LIFECYCLE), "-o", str(program), "-pthread"],
                       check=True)
        built[abi] = program
    return built


def run_legacy(program: Path, directory: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """PROGRAM ARGS through `cifemu legacy`, as a user starts a legacy binary."""
    return cifemu_legacy("--dpm-dir", str(directory), "--", str(program), *args)


@pytest.mark.parametrize("abi", ["x86-64", "i386"])
def test_exitdrv_while_another_thread_waits_in_getmsg(preloads: dict[str, Path],
                                                      lifecycle: dict[str, Path],
                                                      simulated_card: Card, abi: str) -> None:
    """A daemon's shutdown: thread B's EXITDRV while thread A waits in GETMSG. It used to
    unmap the board under A (SIGSEGV, 5 of 5). Now EXITDRV returns at once, later calls
    get the driver's -1, A's call ends as it would have (no message: -18 after its
    time-out), the board is unmapped then, and the program exits 0."""
    need(preloads, abi)
    done = run_legacy(lifecycle[abi], simulated_card.directory, "exit_while_waiting")
    assert done.returncode == 0, f"exit status {done.returncode}\n{done.stdout}{done.stderr}"
    assert parse(done.stdout) == EXIT_WHILE_WAITING, done.stdout + done.stderr
    assert simulated_card.proc.poll() is None


@pytest.mark.parametrize("abi", ["x86-64", "i386"])
def test_a_child_forked_while_a_thread_waits_closes_its_board_at_once(
        preloads: dict[str, Path], lifecycle: dict[str, Path], simulated_card: Card,
        abi: str) -> None:
    """The child of a fork has only the forking thread: none of the parent's calls in
    flight is its own, so its EXITDRV unmaps the board at once; the parent's waiting
    GETMSG ends with its -18."""
    need(preloads, abi)
    done = run_legacy(lifecycle[abi], simulated_card.directory, "fork_while_waiting")
    assert done.returncode == 0, f"exit status {done.returncode}\n{done.stdout}{done.stderr}"
    assert parse(done.stdout) == {
        "open": 1, "initdrv": 0, "waiter_sleeps": 1, "child_exitdrv": 0,
        "child_mapped_after_exitdrv": 0, "child_status": 0, "parent_mapped": 1,
        "waiter": -18, "exitdrv": 0, "close": 0}, done.stdout + done.stderr


@pytest.mark.parametrize("how", ["close", "close_table", "closefrom", "raw"])
@pytest.mark.parametrize("abi", ["x86-64", "i386"])
def test_a_close_all_loop_never_makes_the_device_write_into_a_program_file(
        preloads: dict[str, Path], lifecycle: dict[str, Path], simulated_card: Card,
        tmp_path: Path, abi: str, how: str) -> None:
    """A daemon closes every descriptor it does not know (close() of 3..255 or of the
    whole table, closefrom, or raw close system calls), opens its own file onto the
    freed numbers (for raw: dup'ed onto every number it had open) and talks to the card
    again. The preload's hidden descriptors used to die there, and the next ioctl wrote
    its structure (7 bytes for MBXINFO) into the program's file. Now the device works,
    and the file and its descriptors are as the program left them."""
    need(preloads, abi)
    scratch = tmp_path / "scratch.log"
    content = bytes(range(256)) * 4
    scratch.write_bytes(content)
    done = run_legacy(lifecycle[abi], simulated_card.directory, "close_all", how,
                      str(scratch))
    assert done.returncode == 0, f"exit status {done.returncode}\n{done.stdout}{done.stderr}"
    assert parse(done.stdout) == CLOSE_ALL, done.stdout + done.stderr
    assert scratch.read_bytes() == content
    assert simulated_card.proc.poll() is None


CLOSE_LEDGER = {
    "open": 1, "initdrv": 0, "round_trip": 0, "waiter_inside": 1, "ledger_found": 1,
    "scratch_on_ledger_number": 1, "putmsg": 0, "waiter": 0, "waiter_read_the_answer": 1,
    "round_trip_after": 0, "exitdrv": 0, "close": 0, "scratch_fds_open": 1,
    "scratch_unchanged": 1}


@pytest.mark.parametrize("abi", ["x86-64", "i386"])
def test_a_ledger_write_never_goes_into_a_program_file_on_the_ledgers_number(
        preloads: dict[str, Path], lifecycle: dict[str, Path], simulated_card: Card,
        tmp_path: Path, abi: str) -> None:
    """The window a close-all loop leaves inside a call, made deterministic: while a
    thread waits in GETMSG (no call starts, so the preload does not check its descriptors
    before the next one), the program closes the transaction ledger's descriptor with a raw
    system call and its own file lands on that number. The PUTMSG then wrote its ledger
    line into the program's file (pwrite) and cut it to the line's length (ftruncate).
    Now every call libcif makes on a descriptor is checked: the file stays as it was,
    the waiter reads its answer, the board is opened anew after the call."""
    need(preloads, abi)
    scratch = tmp_path / "scratch.dat"
    content = bytes(range(256)) * 4
    scratch.write_bytes(content)
    done = run_legacy(lifecycle[abi], simulated_card.directory, "close_ledger", str(scratch))
    assert done.returncode == 0, f"exit status {done.returncode}\n{done.stdout}{done.stderr}"
    assert parse(done.stdout) == CLOSE_LEDGER, done.stdout + done.stderr
    assert scratch.read_bytes() == content
    assert simulated_card.proc.poll() is None


@pytest.fixture(scope="module")
def sanitized_preload() -> str:
    """LD_PRELOAD for libcif/build/asan/libcifdev.so: ASan's and UBSan's run-time
    libraries first, as ASan requires of a program not built with it."""
    assert CC is not None
    build_libcif("sanitize")
    runtimes = [subprocess.run([CC, f"-print-file-name={name}"], capture_output=True,
                               text=True, check=True).stdout.strip()
                for name in ("libasan.so", "libubsan.so")]
    if not all(Path(runtime).is_absolute() for runtime in runtimes):
        pytest.skip("no ASan/UBSan run-time libraries for this compiler")
    return " ".join([*runtimes, str(libcif.BUILD / "asan" / "libcifdev.so")])


@pytest.mark.parametrize("args", [["exit_while_waiting"], ["close_all", "close_table"],
                                  ["close_all", "raw"], ["close_ledger"]])
def test_lifecycle_under_the_sanitizers(sanitized_preload: str, lifecycle: dict[str, Path],
                                        simulated_card: Card, tmp_path: Path,
                                        args: list[str]) -> None:
    """The same shutdown and close-all runs with the preload built with AddressSanitizer
    and UBSan (x86-64): a use after unmap or free, or undefined behaviour, fails them."""
    scratch = tmp_path / "scratch.log"
    scratch.write_bytes(b"the program's own log\n")
    env = {**os.environ, "CIF_DPM_DIR": str(simulated_card.directory),
           "LD_PRELOAD": sanitized_preload, "ASAN_OPTIONS": "detect_leaks=0"}
    extra = [] if args[0] == "exit_while_waiting" else [str(scratch)]
    done = commands.run([str(lifecycle["x86-64"]), *args, *extra], env=env,
                        capture_output=True, text=True, timeout=180, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    expected = {"exit_while_waiting": EXIT_WHILE_WAITING, "close_all": CLOSE_ALL,
                "close_ledger": CLOSE_LEDGER}[args[0]]
    assert parse(done.stdout) == expected, done.stdout + done.stderr
    assert scratch.read_bytes() == b"the program's own log\n"
    assert "runtime error" not in done.stderr and "AddressSanitizer" not in done.stderr


# --- cifemu legacy ------------------------------------------------------------------------


def cifemu_legacy(*args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "cifemu", "legacy", *args], input=stdin,
                        capture_output=True, text=True, timeout=180, check=False)


@pytest.mark.parametrize("abi", ["x86-64", "i386"])
def test_cifemu_legacy_preloads_the_library_of_the_programs_class(
        preloads: dict[str, Path], programs: dict[str, Path], card: Card, abi: str) -> None:
    need(preloads, abi)
    program = programs[abi]
    elf = legacy.read_elf(program)
    assert elf.dynamic and elf.elf_class == (1 if abi == "i386" else 2)
    done = cifemu_legacy("--dpm-dir", str(card.directory), "--", str(program), "smoke")
    assert done.returncode == 0, done.stderr
    # the real driver's INITDRV on a board it does not have: -1, through the API object
    assert parse(done.stdout) == {"open": 1, "initdrv": 0, "getinfo_firmware": 0,
                                  "firmware": "CANopen Master", "initdrv_absent": -1}
    assert "wrong ELF class" not in done.stderr


def test_cifemu_legacy_refuses_a_static_program(preloads: dict[str, Path],
                                                tmp_path: Path) -> None:
    assert CC is not None
    source = tmp_path / "static.c"
    source.write_text("int main(void) { return 0; }\n")
    program = tmp_path / "static"
    built = subprocess.run([CC, "-static", str(source), "-o", str(program)],
                           capture_output=True, check=False)
    if built.returncode != 0:
        pytest.skip("no static libc to link a static program with")
    done = cifemu_legacy("--", str(program))
    assert done.returncode == 1
    assert "statically linked" in done.stderr and "CUSE" in done.stderr


def test_cifemu_legacy_refuses_what_is_not_an_elf_program(tmp_path: Path) -> None:
    script = tmp_path / "script.sh"
    script.write_text("#!/bin/sh\nexit 0\n")
    script.chmod(0o755)
    done = cifemu_legacy("--", str(script))
    assert done.returncode == 1 and "not an ELF program" in done.stderr
    done = cifemu_legacy("--", str(tmp_path / "missing"))
    assert done.returncode == 1 and "No such file" in done.stderr
    done = cifemu_legacy()
    assert done.returncode == 2 and "no program given" in done.stderr
