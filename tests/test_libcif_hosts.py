"""Hosts that share one card: threads, other processes, killed hosts, timed-out gets, forks.

Every request is a COM_Shared_Memory read tagged by its data_adr (and msg.nr = tag % 255
+ 1), which the card's answer echoes, so each answer read is attributed to the request
that asked for it: none may be lost, read twice, or read by a host that did not send it.
The C hosts are tests/c/hosts.c and tests/c/chanlock_wait.c (libcif's channel lock
compiled in), run plain, under ASan/UBSan, and under ThreadSanitizer where threads meet.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cifemu import libcif
from dpm.errors import Drv
from dpm.ledger import ledger_text
from dpm.message import Ext, Message
from host_api import driver as d
from host_api.board import Board
from host_api.locks import LEDGER_BYTES, Answer, Transaction
from tests import commands
from tests.conftest import Card
from tests.libcif_host import C_TESTS, CC, STRICT, CDriver, build_libcif, compile_program, run

pytestmark = pytest.mark.skipif(CC is None or shutil.which("make") is None,
                                reason="no C compiler or make")

LIBCIF_SOURCES = ["cif_api.c", "download.c", "bell.c", "chanlock.c", "holder.c", "dbm_embd.c"]
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def built() -> None:
    build_libcif("all")
    build_libcif("sanitize")


def compile_tsan(source: Path, out: Path, *, with_library: bool = True) -> Path:
    """``source`` and libcif's sources built with ThreadSanitizer; skips where it cannot
    run (no runtime, or a kernel whose address-space layout it refuses)."""
    assert CC is not None
    sources = [str(libcif.SOURCE / "src" / name) for name in LIBCIF_SOURCES] if with_library else []
    done = subprocess.run([CC, "-std=c11", "-Wall", "-Wextra", "-Werror", "-g", "-O1",
                           "-fsanitize=thread",
                           "-Wno-tsan",  # the fences around the process-data copy: not checked
                           str(source), *sources, f"-I{libcif.INCLUDE}",
                           f"-I{libcif.SOURCE / 'src'}", "-pthread", "-o", str(out)],
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
        pytest.skip(f"no ThreadSanitizer here: {done.stderr.strip()[:200]}")
    probe = subprocess.run([str(out)], capture_output=True, text=True, check=False)
    if "ThreadSanitizer" in probe.stderr and "FATAL" in probe.stderr:
        pytest.skip(f"ThreadSanitizer cannot run here: {probe.stderr.strip()[:200]}")
    return out


@pytest.fixture(autouse=True)
def tsan_options(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any ThreadSanitizer report fails the run (exit code 66): nothing is suppressed."""
    monkeypatch.setenv("TSAN_OPTIONS", "exitcode=66")


def build(tmp_path: Path, variant: str, source: str = "hosts.c") -> Path:
    out = tmp_path / f"{Path(source).stem}-{variant}"
    if variant == "tsan":
        return compile_tsan(C_TESTS / source, out)
    return compile_program(C_TESTS / source, out, variant)


def tagged(tag: int) -> Message:
    """A COM_Shared_Memory read of 2 bytes at data_adr ``tag``."""
    return Message(rx=2, tx=16, b=17, nr=tag % 255 + 1,
                   data=bytes([0, 1, tag & 0xFF, tag >> 8, 0, 2, 5, 1]))


def tag_of(answer: Message | None) -> int | None:
    """The tag an answer echoes; None for anything but a tagged read's answer."""
    if answer is None or answer.a != 17 or answer.f != 0 or len(answer.data) < 4:
        return None
    tag = int.from_bytes(answer.data[2:4], "little")
    return tag if answer.nr == tag % 255 + 1 else None


def python_pairs(tags: range, wrong: list[str]) -> None:
    """Raw DevPutMessage/DevGetMessage pairs, as a legacy host ported line by line."""
    for tag in tags:
        rc = d.DevPutMessage(0, tagged(tag), 5000)
        if rc != Drv.DRV_NO_ERROR:
            wrong.append(f"tag {tag}: DevPutMessage {rc}")
            continue
        rc, answer = d.DevGetMessage(0, 288, 5000)
        if rc != Drv.DRV_NO_ERROR or tag_of(answer) != tag:
            wrong.append(f"tag {tag}: rc {rc}, read {tag_of(answer)} ({answer})")


TRANSACTION_PATHS = ["native", "python"]
"""The Python host's mailbox transaction in C where nothing waits, or in its Python steps
alone (``driver.native_transaction``): both keep the ledger's promises."""


@pytest.fixture(params=TRANSACTION_PATHS)
def python_host(card: Card, request: pytest.FixtureRequest,
                monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """This test process as a Python host of the card, by either transaction path."""
    monkeypatch.setattr(d, "native_transaction", request.param == "native")
    assert d.DevOpenDriver(card.directory) == 0 and d.DevInitBoard(0) == 0
    yield None
    while d.DevCloseDriver() == 0:
        pass


# --- threads -------------------------------------------------------------------------------


@pytest.mark.parametrize("variant", ["plain", "tsan"])
def test_threads_enter_a_channel_one_at_a_time_and_wait_no_longer_than_asked(
        tmp_path: Path, variant: str) -> None:
    """While another host holds a channel's flock, four threads of one process wait for it;
    once it is free they must enter one by one (the flock is the open file description's,
    which they share). A waiter whose time-out ends while another host holds the flock
    gives up then, not a whole time-out later."""
    source = C_TESTS / "chanlock_wait.c"
    out = tmp_path / f"chanlock_wait-{variant}"
    if variant == "tsan":
        compile_tsan(source, out, with_library=False)
    else:
        assert CC is not None
        subprocess.run([CC, *STRICT, str(source), f"-I{libcif.SOURCE / 'src'}", "-pthread",
                        "-o", str(out)], check=True)
    done = commands.run([str(out), str(tmp_path / "board0.get.lock")], capture_output=True,
                        text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert "one thread inside at a time" in done.stdout


@pytest.mark.parametrize("variant", ["plain", "sanitized", "tsan"])
def test_threads_waiting_in_DevGetMessage_read_each_answer_once(
        built: None, card: Card, tmp_path: Path, variant: str) -> None:
    program = build(tmp_path, variant)
    assert run(program, card.directory, "threads", "4", "300") == \
        "threads: 300 answers, each read once\n"


def test_c_threads_and_a_python_host_pairing_raw_calls_never_read_each_others_answers(
        built: None, card: Card, tmp_path: Path, python_host: None) -> None:
    """8 threads of a C host and a Python host, all pairing raw DevPutMessage/DevGetMessage:
    the C host reads each of its answers once, the Python host only its own."""
    program = build(tmp_path, "plain")
    wrong: list[str] = []
    thread = threading.Thread(target=python_pairs, args=(range(3000, 3300), wrong))
    thread.start()
    try:
        out = run(program, card.directory, "pairs", "8", "50", "0")
    finally:
        thread.join()
    assert out == "pairs: 400 answers, each this host's own, read once\n"
    assert wrong == []


@pytest.mark.parametrize("variant", ["plain", "sanitized", "tsan"])
@pytest.mark.parametrize("waiter_gets", ["its answer", "its time-out"])
def test_DevExitBoard_while_another_thread_waits_in_DevGetMessage(
        built: None, card: Card, tmp_path: Path, variant: str, waiter_gets: str) -> None:
    """A daemon's shutdown in a direct C host: thread B calls DevExitBoard and
    DevCloseDriver while thread A waits in DevGetMessage. DevExitBoard used to unmap and
    free the board under A. Now both return 0 at once, a call after them gets -32, A's
    call ends as it would have (the answer that comes after the close, or -18 after its
    time-out), the last call out unmaps the board, and it opens again."""
    program = build(tmp_path, variant)
    if waiter_gets == "its time-out":
        assert run(program, card.directory, "exitwait", "0", "2000") == \
            "exitwait: the waiter ended with -18, the board closed under it, and opens again\n"
        return
    card.freeze()  # the answer comes after DevExitBoard and DevCloseDriver
    try:
        host = subprocess.Popen([str(program), "exitwait", "7", "30000"], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, "CIF_DPM_DIR": str(card.directory),
                                     "ASAN_OPTIONS": "detect_leaks=1"})
        assert host.stdout is not None
        said = host.stdout.readline()
    finally:
        card.thaw()
    if said != "closed\n":
        host.kill()
    out, err = host.communicate("go\n", timeout=60)
    assert said == "closed\n", err
    assert host.returncode == 0, err
    assert out == "exitwait: the waiter ended with 0, the board closed under it, and opens again\n"


# --- killed hosts and timed-out gets ---------------------------------------------------------


def killed_after_put(program: Path, card: Card, tag: int) -> None:
    """A C host that put its request and was SIGKILLed before its DevGetMessage."""
    host = subprocess.Popen([str(program), "hang", str(tag)], stdout=subprocess.PIPE,
                            env={**os.environ, "CIF_DPM_DIR": str(card.directory)})
    assert host.stdout is not None
    try:
        assert host.stdout.readline() == b"sent\n"
    finally:
        host.send_signal(signal.SIGKILL)
        commands.wait(host, 10)


@pytest.mark.parametrize("answered", ["at once", "after the next host began"])
def test_a_killed_hosts_answer_never_reaches_the_next_c_host(
        built: None, card: Card, tmp_path: Path, answered: str) -> None:
    program = build(tmp_path, "plain")
    if answered != "at once":
        card.freeze()  # the answer comes once the next host has sent its request
    try:
        killed_after_put(program, card, 7)
        if answered != "at once":
            nxt = subprocess.Popen([str(program), "pairs", "1", "20", "100"],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                   env={**os.environ, "CIF_DPM_DIR": str(card.directory)})
    finally:
        card.thaw()
    if answered == "at once":
        out = run(program, card.directory, "pairs", "1", "20", "100")
    else:
        out, err = nxt.communicate(timeout=60)
        assert nxt.returncode == 0, err
    assert out == "pairs: 20 answers, each this host's own, read once\n"


def test_a_killed_hosts_answer_never_reaches_a_python_host(
        built: None, card: Card, tmp_path: Path, python_host: None) -> None:
    """Raw pairs, and Board.transact with the dead host's very message number and command:
    the dead host's answer is discarded, not returned."""
    program = build(tmp_path, "plain")
    killed_after_put(program, card, 7)
    wrong: list[str] = []
    python_pairs(range(3000, 3010), wrong)
    assert wrong == []
    killed_after_put(program, card, 7)
    with Board(0, card.directory, timeout=5000) as board:
        request = tagged(8)
        request.nr = tagged(7).nr  # the dead host's number, the same command
        answer = board.transact(request)
        assert int.from_bytes(answer.data[2:4], "little") == 8  # the dead host's said 7


PYTHON_HOST_KILLED_AFTER_PUT = """
import signal, sys
from host_api import driver as d
from tests.test_libcif_hosts import tagged

d.native_transaction = sys.argv[2] == "native"
assert d.DevOpenDriver(sys.argv[1]) == 0 and d.DevInitBoard(0) == 0
assert d.DevPutMessage(0, tagged(7), 5000) == 0
print("sent", flush=True)
signal.pause()  # until killed
"""


@pytest.mark.parametrize("path", TRANSACTION_PATHS)
def test_a_killed_python_hosts_answer_never_reaches_the_next_c_host(
        built: None, card: Card, tmp_path: Path, path: str) -> None:
    program = build(tmp_path, "plain")
    host = subprocess.Popen([sys.executable, "-c", PYTHON_HOST_KILLED_AFTER_PUT,
                             str(card.directory), path], stdout=subprocess.PIPE, cwd=ROOT)
    assert host.stdout is not None
    try:
        assert host.stdout.readline() == b"sent\n"
    finally:
        host.send_signal(signal.SIGKILL)
        commands.wait(host, 10)
    assert run(program, card.directory, "pairs", "1", "20", "100") == \
        "pairs: 20 answers, each this host's own, read once\n"


def test_a_timed_out_gets_late_answer_reaches_no_other_host(
        built: None, card: Card, tmp_path: Path, python_host: None) -> None:
    """A C host's DevGetMessage times out on a frozen card (-18) and the host lets the
    board go; the card thaws and answers. A Python host pairing raw calls then reads only
    its own answers, and the C host, pairing again, only its own."""
    program = build(tmp_path, "plain")
    card.freeze()
    host = subprocess.Popen([str(program), "late", "7"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "CIF_DPM_DIR": str(card.directory)})
    try:
        assert host.stdout is not None and host.stdout.readline() == "timed out\n"
    finally:
        card.thaw()
    wrong: list[str] = []
    python_pairs(range(3000, 3020), wrong)
    out, err = host.communicate("go\n", timeout=60)
    assert host.returncode == 0, err
    assert out == "late: 50 answers, each this host's own; the late one discarded\n"
    assert wrong == []


# --- requests the card does not answer ------------------------------------------------------


SILENT_HOST = """
import sys
from dpm.commands import COM_TX_CAN_LAYER2
from dpm.message import Message, Task
from host_api import driver as d
from tests.libcif_host import CDriver

driver = d if sys.argv[2] == "python" else CDriver()
assert driver.DevOpenDriver(sys.argv[1]) == 0 and driver.DevInitBoard(0) == 0
frame = bytes([0x300 >> 3, 0x01, 0x77])  # identifier 300h, DLC 1, one data byte
send = Message(rx=Task.CAN, tx=Task.USER, b=COM_TX_CAN_LAYER2, nr=7, data=frame)
print(driver.DevPutMessage(0, send, 5000), flush=True)
sys.stdin.readline()  # reads nothing meanwhile: the card sends no answer (seed 5.3.1)
"""

ROUND_TRIP_MS = 3000
"""The second host's time-outs: a round trip takes milliseconds; waiting for a board that
another host keeps takes all of it and ends in -4."""


@pytest.mark.parametrize(("first", "second"),
                         [("python", "python"), ("c", "c"), ("python", "c"), ("c", "python")])
def test_a_layer2_send_that_nobody_answers_keeps_no_other_host_waiting(
        built: None, card: Card, first: str, second: str) -> None:
    """A host sends COM_Tx_CAN_Layer2 with msg.e 0 (as the seed's table has it), which the
    card never answers (seed 5.3.1), and reads nothing. Another host's round trip goes
    through at once. Before, the first host's driver recorded the send in the ledger as a
    request awaited and kept the board's transaction lock for it until a DevGetMessage of
    that host timed out: the second host's DevPutMessage got -4 (DRV_CMD_ACTIVE) after its
    whole time-out, as long as the first host lived without reading."""
    host = subprocess.Popen([sys.executable, "-c", SILENT_HOST, str(card.directory), first],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert host.stdin is not None and host.stdout is not None
    try:
        assert host.stdout.readline() == f"{Drv.DRV_NO_ERROR}\n"
        driver: Any = d if second == "python" else CDriver()
        assert driver.DevOpenDriver(card.directory) == 0 and driver.DevInitBoard(0) == 0
        try:
            put = driver.DevPutMessage(0, tagged(5), ROUND_TRIP_MS)
            rc, got = driver.DevGetMessage(0, 288, ROUND_TRIP_MS)
        finally:
            while driver.DevCloseDriver() == 0:
                pass
    finally:
        host.stdin.close()  # the first host ends
        commands.wait(host, 30)
    assert put == Drv.DRV_NO_ERROR
    assert rc == Drv.DRV_NO_ERROR and tag_of(got) == 5
    assert host.returncode == 0


# --- forks ----------------------------------------------------------------------------------


@pytest.mark.parametrize("variant", ["plain", "sanitized"])
def test_a_c_host_forked_after_DevInitBoard_and_its_child_each_read_their_own_answers(
        built: None, card: Card, tmp_path: Path, variant: str) -> None:
    program = build(tmp_path, variant)
    assert run(program, card.directory, "fork", "200") == \
        "fork: parent and child each read their own 200 answers\n"


FORKED_PYTHON_HOST = """
import os, sys
from host_api import driver as d
from tests.test_libcif_hosts import python_pairs

d.native_transaction = sys.argv[2] == "native"
assert d.DevOpenDriver(sys.argv[1]) == 0 and d.DevInitBoard(0) == 0
child = os.fork()
wrong = []
python_pairs(range(1000, 1200) if child == 0 else range(0, 200), wrong)
d.DevCloseDriver()
if child == 0:
    print("\\n".join(wrong), file=sys.stderr)
    os._exit(1 if wrong else 0)
_, status = os.waitpid(child, 0)
print("\\n".join(wrong), file=sys.stderr)
sys.exit(1 if wrong or os.waitstatus_to_exitcode(status) else 0)
"""


@pytest.mark.parametrize("path", TRANSACTION_PATHS)
def test_a_python_host_forked_after_DevInitBoard_and_its_child_each_read_their_own_answers(
        card: Card, path: str) -> None:
    done = commands.run([sys.executable, "-c", FORKED_PYTHON_HOST, str(card.directory), path],
                        capture_output=True, text=True, timeout=120, cwd=ROOT, check=False)
    assert done.returncode == 0, done.stderr


# --- lock files that cannot be opened ---------------------------------------------------------


def test_a_lock_file_that_cannot_be_opened_fails_DevInitBoard_and_closes_nothing_else(
        built: None, card: Card, tmp_path: Path) -> None:
    """A directory in a lock file's place: -31 from both drivers; libcif keeps the
    program's descriptor 0, Python raises nothing."""
    (card.directory / "board0.io.lock").mkdir()
    program = build(tmp_path, "plain")
    stdin = tmp_path / "stdin"
    stdin.write_text("the program's own input\n")
    with stdin.open() as source:
        done = commands.run([str(program), "badlock"], stdin=source, capture_output=True,
                            text=True, timeout=30, check=False,
                            env={**os.environ, "CIF_DPM_DIR": str(card.directory)})
    assert done.returncode == 0, done.stderr
    assert d.DevOpenDriver(card.directory) == 0
    try:
        assert d.DevInitBoard(0) == Drv.DRV_USR_INIT_DRV_ERROR
        (card.directory / "board0.io.lock").rmdir()
        assert d.DevInitBoard(0) == Drv.DRV_NO_ERROR
    finally:
        d.DevCloseDriver()


def test_a_planted_link_in_a_lock_files_place_is_not_followed(
        built: None, card: Card, tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    victim.write_text("not the card's\n")
    (card.directory / "board0.transaction.lock").symlink_to(victim)
    for driver in (d, CDriver()):
        assert driver.DevOpenDriver(card.directory) == 0
        try:
            assert driver.DevInitBoard(0) == Drv.DRV_USR_INIT_DRV_ERROR
        finally:
            driver.DevCloseDriver()
    assert victim.read_text() == "not the card's\n"


# --- the ledger's rules, without a card -----------------------------------------------------


def ledger(path: Path) -> str:
    """The ledger's lines in the lock file ``path`` (up to its end, ``dpm.ledger.END``)."""
    return ledger_text(path.read_bytes()).decode("ascii")


def answer(request: Message, e: int = 0, f: int = 0) -> Message:
    return Message(rx=request.tx, tx=request.rx, b=0, data=b"", nr=request.nr, a=request.b,
                   f=f, e=e)


def test_another_owners_requests_are_stale_and_this_owners_given_up_ones_still_its_own(
        tmp_path: Path) -> None:
    path = tmp_path / "board0.transaction.lock"
    mine, other = Transaction(path), Transaction(path)
    try:
        assert mine.enter(0)
        mine.sent(tagged(1))
        mine.sent(tagged(2))
        mine.give_up()  # a get timed out: the lock goes with the last call
        mine.leave()
        assert mine.enter(0)  # this process again: its late answers are its own
        assert mine.answered(answer(tagged(1))) is Answer.OWN
        mine.leave()
        assert other.enter(0)  # another host: the rest is stale
        assert other.is_stale(answer(tagged(2)))
        assert other.answered(answer(tagged(2))) is Answer.STALE
        assert other.answered(answer(tagged(2))) is Answer.OTHER  # discarded once only
        other.leave()
        assert ledger(path) == ""
    finally:
        mine.close()
        other.close()


def test_a_long_uploads_parts_belong_to_it_until_the_last(tmp_path: Path) -> None:
    path = tmp_path / "board0.transaction.lock"
    host, nxt = Transaction(path), Transaction(path)
    try:
        upload = Message(rx=3, tx=16, b=66, nr=9, e=Ext.FIRST)
        assert host.enter(0)
        host.sent(upload)
        host.leave()
        assert host.answered(answer(upload, e=Ext.FIRST)) is Answer.OWN
        assert host.enter(0)
        host.give_up()
        host.leave()  # the host gives up; its remaining parts are stale for the next one
        assert nxt.enter(0)
        assert not nxt.is_stale(answer(upload, e=Ext.FIRST))  # a new upload's first part
        assert nxt.answered(answer(upload, e=Ext.CONT)) is Answer.STALE
        assert nxt.answered(answer(upload, e=Ext.LAST)) is Answer.STALE
        assert nxt.answered(answer(upload, e=Ext.LAST)) is Answer.OTHER
        nxt.leave()
    finally:
        host.close()
        nxt.close()


def test_a_load_function_sequence_is_no_long_upload(tmp_path: Path) -> None:
    """The load function's upload answers its first request with a piece marked FIRST and
    continues by the host's next request (e CONT): the first request awaits no more."""
    path = tmp_path / "board0.transaction.lock"
    host = Transaction(path)
    try:
        first = Message(rx=0, tx=16, b=6, nr=1, e=Ext.FIRST)
        assert host.enter(0)
        host.sent(first)
        assert host.answered(answer(first, e=Ext.FIRST)) is Answer.OWN
        host.sent(Message(rx=0, tx=16, b=6, nr=2, e=Ext.CONT))
        host.leave()
        assert ledger(path).count("\n") == 1  # the second request only
    finally:
        host.close()


def test_malformed_and_expired_ledger_lines_are_dropped(tmp_path: Path) -> None:
    path = tmp_path / "board0.transaction.lock"
    now = time.monotonic_ns() // 1_000_000
    path.write_text(f"1 2 3 17 2 16 0 {now}\n"  # kept
                    f"1 2 3 17 2 16 0 {now - 31_000}\n"  # older than 30 s
                    f"1 2 3 17 2 16 0 {now + 60_000}\n"  # another boot's clock
                    "1 2 300 17 2 16 0 5\nnonsense\n\n")
    host = Transaction(path)
    try:
        assert host.enter(0)
        assert ledger(path) == f"1 2 3 17 2 16 0 {now}\n"
        host.leave()
    finally:
        host.close()


@pytest.mark.parametrize("impl", ["python", "c"])
def test_lines_after_the_ledgers_end_are_no_requests(built: None, card: Card, impl: str) -> None:
    """[ours] A Python host empties the ledger by writing its END (a NUL) at the start, not
    by truncating the file: the lines after it are left from a longer ledger. A host that
    took them for a dead host's request would discard the answer to its own request with
    the same number and command."""
    request = tagged(7)
    now = time.monotonic_ns() // 1_000_000
    leftover = f"1 2 3 17 2 16 0 {now}\n1 2 {request.nr} 17 2 16 0 {now}\n"
    (card.directory / "board0.transaction.lock").write_bytes(b"\0" + leftover.encode())
    driver: Any = d if impl == "python" else CDriver()
    assert driver.DevOpenDriver(card.directory) == 0 and driver.DevInitBoard(0) == 0
    try:
        assert driver.DevPutMessage(0, request, 5000) == 0
        rc, got = driver.DevGetMessage(0, 288, 2000)
        assert rc == Drv.DRV_NO_ERROR and tag_of(got) == 7
    finally:
        while driver.DevCloseDriver() == 0:
            pass


@pytest.mark.parametrize("impl", ["python", "c"])
def test_python_and_c_hosts_end_the_ledger_alike_without_truncating_it(
        built: None, card: Card, impl: str) -> None:
    """[ours] A request goes into the ledger with its END (a NUL) in the same write, and the
    last answer empties it by an END at the start, through each host's map of the file
    (grown to the ledger's longest first), without a system call; the file never truncated
    (libcif truncated it after every write, two calls per change; issue 22). What follows
    the END is left from a longer ledger and no request."""
    path = card.directory / "board0.transaction.lock"
    leftover = b"\0" + b"9" * 200
    path.write_bytes(leftover)
    driver: Any = d if impl == "python" else CDriver()
    assert driver.DevOpenDriver(card.directory) == 0 and driver.DevInitBoard(0) == 0
    try:
        request = tagged(3)
        assert driver.DevPutMessage(0, request, 5000) == 0
        line = ledger(path)
        assert line.endswith(f" {request.nr} 17 2 16 0 {line.split()[-1]}\n")
        assert line.count("\n") == 1
        rc, got = driver.DevGetMessage(0, 288, 5000)
        assert rc == Drv.DRV_NO_ERROR and tag_of(got) == 3
        raw = path.read_bytes()
        assert ledger(path) == "" and len(raw) == LEDGER_BYTES, raw[:80]
        assert raw[len(line) + 1 : len(leftover)] == leftover[len(line) + 1 :]
    finally:
        while driver.DevCloseDriver() == 0:
            pass
