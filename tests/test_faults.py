"""Card-side faults on demand (issue 25, item 3; docs/faults.md): for each kind a host sees
the fault through the image and the driver, and sees the card recover, by the fault's time
or by `cifemu fault clear`. Real firmware processes, asked through the command, the Python
API (``host_api.faults``) and the pytest plugin's handle (``CifCard.fault``)."""

from __future__ import annotations

import os
import pwd
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from cifemu.pytest_plugin import CifCard
from dbm_tools.builder import build_dbm
from dbm_tools.container import write_dbm
from dbm_tools.network import load_network
from dpm import flags as fl
from dpm.commands import COM_RESET_ERR_EVENT
from dpm.errors import Drv
from dpm.faults import (
    DIE_EXIT_STATUS,
    FaultRequest,
    FaultRequestError,
    decode_reply,
    decode_request,
    encode_reply,
)
from dpm.layout import HOST_FLAGS, RCS_ERROR
from dpm.message import Message, Task
from dpm.task2 import GlobalBits
from host_api import driver as d
from host_api import faults
from host_api.board import Board, CifError
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload
from host_api.faults import FaultError
from host_api.liveness import firmware_liveness
from tests import commands
from tests.conftest import ROOT, Card, LoadDeadline, start_card, wait_until

QUIET_S = 0.3
"""How long a test watches for something that must not happen while a fault is in force:
the fault lasts longer than that, and the card would do it within milliseconds."""

ONE_NODE = {"node": [{"id": 1, "heartbeat_ms": 5000}]}
"""A generic I/O module (its inputs echo its outputs) supervised with a heartbeat slow enough
that a bus-off of two seconds costs the node nothing."""


def cifemu(*args: str) -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "cifemu", *args], capture_output=True,
                        text=True, timeout=60, cwd=ROOT)


def request() -> Message:
    """A command the CAN task answers at once, whatever its state (seed 5.2.12)."""
    return Message(rx=Task.CAN, tx=Task.USER, b=COM_RESET_ERR_EVENT)


def rcs_info(board: Board) -> bytes:
    return board.info(d.GET_RCS_INFO, 8)


@pytest.fixture
def opened(card: Card) -> Iterator[Board]:
    with Board(0, card.directory, timeout=2000) as board:
        yield board


# --- the request codec -----------------------------------------------------------------------


def test_requests_round_trip_and_malformed_ones_are_refused_with_the_field() -> None:
    flip = FaultRequest("flip", offset=3584 - 1, bit=7, for_ms=10)
    assert decode_request(flip.encode()) == flip
    assert decode_request(b'{"kind": "die", "hang": true}') == FaultRequest("die", hang=True)
    refusals = {
        b"\xff": "no JSON text",
        b"[1]": "no JSON object",
        b'{"for_ms": 5}': "without a kind",
        b'{"kind": "melt"}': "unknown fault kind 'melt'",
        b'{"kind": "stall"}': "stall needs its length",
        b'{"kind": "stall", "for_ms": 0}': "for_ms must be an integer 1..",
        b'{"kind": "stall", "for_ms": true}': "for_ms must be an integer",
        b'{"kind": "rcs-error", "code": 256}': "code must be an integer 1..255",
        b'{"kind": "flip", "offset": 3584, "bit": 0}': "offset must be an integer 0..3583",
        b'{"kind": "flip", "offset": 0, "bit": 8}': "bit must be an integer 0..7",
        b'{"kind": "watchdog", "code": 5}': "watchdog takes no code",
        b'{"kind": "die", "for_ms": 5}': "die takes for_ms only with hang",
        b'{"kind": "slow", "delay_ms": 5, "colour": 1}': "unknown field(s) ['colour']",
        b'{"kind": "die", "hang": "yes"}': "hang must be true or false",
        b"x" * 5000: "longer than 4096",
    }
    for data, reason in refusals.items():
        with pytest.raises(FaultRequestError, match=None) as refused:
            decode_request(data)
        assert reason in str(refused.value), (data, str(refused.value))
    with pytest.raises(FaultRequestError, match="no fault socket"):
        decode_reply(encode_reply(error="no fault socket"))


def test_the_command_says_in_one_line_what_is_wrong(tmp_path: Path) -> None:
    """No card, an unknown kind, a bad number: one line each, no traceback."""
    no_card = cifemu("fault", "--board", "2", "--dpm-dir", str(tmp_path), "stall", "500")
    unknown = cifemu("fault", "--dpm-dir", str(tmp_path), "melt")
    bad_number = cifemu("fault", "--dpm-dir", str(tmp_path), "flip", "4000", "1")
    not_a_number = cifemu("fault", "--dpm-dir", str(tmp_path), "slow", "soon")
    assert no_card.returncode == 1
    assert no_card.stderr == (
        f"cifemu fault: stall: no card serves board 2 in {tmp_path} (no fault socket "
        f"{tmp_path}/board2.fault); is `cifemu firmware --board 2 --dpm-dir {tmp_path}` "
        "running?\n")
    assert unknown.returncode == 2 and "invalid choice: 'melt'" in unknown.stderr
    assert bad_number.returncode == 1 and bad_number.stderr == (
        "cifemu fault: flip: offset must be an integer 0..3583, not 4000\n")
    assert not_a_number.returncode == 2 and "invalid int value: 'soon'" in not_a_number.stderr
    for out in (no_card, unknown, bad_number, not_a_number):
        assert "Traceback" not in out.stderr
    helped = cifemu("fault", "--help").stdout
    for kind in ("watchdog", "rcs-error", "stall", "slow", "flip", "bus-off", "die", "clear"):
        assert f"\n  {kind:10} " in helped, kind


# --- each kind, as a host sees it ------------------------------------------------------------


def test_the_device_watchdog_stops_until_cleared(card: Card, opened: Board) -> None:
    """While stopped the card answers no trigger: bHostWatchDog stays what the host copied.
    `cifemu fault clear` resumes it, and the waiting trigger is answered."""
    where = ("--dpm-dir", str(card.directory))
    first = opened.trigger_watchdog()
    wait_until(lambda: rcs_info(opened)[3] == first % 255 + 1, 5, "the trigger answered")
    stopped = cifemu("fault", *where, "watchdog")
    assert stopped.returncode == 0, stopped.stderr
    assert stopped.stdout == "board 0: in force: watchdog until cleared\n"
    trigger = opened.trigger_watchdog()
    assert trigger == first % 255 + 1
    window = LoadDeadline(QUIET_S)  # on the load clock: a starved card had no time to answer
    while window.left() > 0:
        assert rcs_info(opened)[3] == trigger, "a stopped watchdog answered"
        time.sleep(0.01)
    cleared = cifemu("fault", *where, "clear")
    assert cleared.returncode == 0 and cleared.stdout == "board 0: no fault in force\n"
    wait_until(lambda: rcs_info(opened)[3] == trigger % 255 + 1, 5, "the trigger answered")


def test_an_rcs_error_shows_in_rcsinfo_until_its_time_is_up(card: Card, opened: Board) -> None:
    """bRcsError through DevGetInfo(RCSINFO), also after a warm start; the card serves on;
    the error goes by itself after for_ms."""
    assert rcs_info(opened)[2] == 0
    before = time.monotonic()
    active = faults.inject("rcs-error", 0, card.directory, code=42, for_ms=4000)
    assert [(a.request.kind, a.request.code) for a in active] == [("rcs-error", 42)]
    assert rcs_info(opened)[2] == 42
    opened.reset(d.WARMSTART)
    assert rcs_info(opened)[2] == 42, "a start hid the RCS error"
    assert opened.transact(request()).f == 0, "the card stopped serving"
    wait_until(lambda: rcs_info(opened)[2] == 0, 10 + 4, "the RCS error gone")
    assert time.monotonic() - before >= 4.0
    assert faults.active(0, card.directory) == []


def test_a_stalled_mailbox_takes_no_message_until_its_time_is_up(card: Card,
                                                                  opened: Board) -> None:
    """DevPutMessage finds room once, then the mailbox stays full (-16), no answer comes
    (-18); after the stall the card takes the waiting message and answers new ones."""
    before = time.monotonic()
    faults.inject("stall", 0, card.directory, for_ms=2000)
    assert d.DevPutMessage(0, request(), 1000) == Drv.DRV_NO_ERROR
    assert d.DevGetMBXState(0) == (Drv.DRV_NO_ERROR, d.DEVICE_MBX_FULL, d.HOST_MBX_EMPTY)
    assert d.DevGetMessage(0, d.MSG_BUFFER_SIZE, 200) == (Drv.DRV_DEV_GET_TIMEOUT, None)
    assert d.DevPutMessage(0, request(), 0) == Drv.DRV_DEV_MAILBOX_FULL
    wait_until(lambda: d.DevGetMBXState(0)[1] == d.DEVICE_MBX_EMPTY, 10 + 2,
               "the card to take the waiting message")
    assert time.monotonic() - before >= 2.0
    assert opened.transact(request()).f == 0


def test_a_slow_card_answers_late_until_cleared(card: Card, opened: Board) -> None:
    delay = 1.0
    assert faults.inject("slow", 0, card.directory, delay_ms=1000)[0].request.delay_ms == 1000
    started = time.monotonic()
    assert opened.transact(request(), timeout=5000).f == 0
    assert time.monotonic() - started >= delay
    assert faults.clear(0, card.directory) == []
    started = time.monotonic()
    assert opened.transact(request(), timeout=5000).f == 0
    assert time.monotonic() - started < delay


@pytest.mark.cif_network(ONE_NODE)
def test_an_input_bit_flips_once_or_for_a_while(cif_card: CifCard) -> None:
    """Through the plugin's handle: bit 3 of input byte 0 inverted at one exchange, then at
    every exchange for for_ms, then never again."""
    cif_card.wait_until_operating()
    outputs = b"\x01\x02\x04\x08\x10\x20\x40\x80"
    with Board(cif_card.board, timeout=2000) as board:
        def inputs() -> bytes:
            return board.exchange_io(outputs, receive_size=8)

        wait_until(lambda: inputs() == outputs, 10, "the node to echo the outputs")
        cif_card.fault("flip", offset=0, bit=3)
        # DevExchangeIO reads the inputs of the cycle its previous call asked for: the flip
        # shows at the first or the second call, and at one call only
        seen = [inputs() for _ in range(6)]
        assert sorted(seen) == [outputs] * 5 + [b"\x09" + outputs[1:]], seen
        assert seen.index(b"\x09" + outputs[1:]) < 2
        before = time.monotonic()
        active = cif_card.fault("flip", offset=7, bit=7, for_ms=2500)
        assert active[0].describe().startswith("flip bit=7 offset=7 for 2500 ms")
        flipped = outputs[:7] + b"\x00"
        assert flipped in (inputs(), inputs())
        for _ in range(5):
            assert inputs() == flipped
        wait_until(lambda: inputs() == outputs, 10 + 2.5, "the flip to end")
        assert time.monotonic() - before >= 2.5
    assert cif_card.clear_faults() == []


@pytest.mark.cif_network(ONE_NODE)
def test_bus_off_counts_stops_the_bus_and_recovers(cif_card: CifCard) -> None:
    """Bus_Off_Cnt and EVE at once; outputs the host writes meanwhile reach no node; after
    the bus-off they do, and the node stayed in data exchange."""
    cif_card.wait_until_operating()
    with Board(cif_card.board, timeout=2000) as board:
        wait_until(lambda: board.exchange_io(b"\x11" * 8, receive_size=8) == b"\x11" * 8,
                   10, "the node to echo the outputs")
        before_diag = board.diagnostics()
        assert before_diag.usBus_Off_Cnt == 0 and not before_diag.bGlobalBits & GlobalBits.EVE
        before = time.monotonic()
        cif_card.fault("bus-off", for_ms=2000)
        diag = board.diagnostics()
        assert diag.usBus_Off_Cnt == 1 and diag.bGlobalBits & GlobalBits.EVE
        deadline = min(time.monotonic() + QUIET_S, before + 2.0)
        while time.monotonic() < deadline:
            assert board.exchange_io(b"\x22" * 8, receive_size=8) == b"\x11" * 8
        wait_until(lambda: board.exchange_io(b"\x22" * 8, receive_size=8) == b"\x22" * 8,
                   10 + 2, "the outputs to come back after the bus-off")
        assert time.monotonic() - before >= 2.0
        after = board.diagnostics()
    assert after.usBus_Off_Cnt == 1 and after.operating() == [1]


def test_the_firmware_dies_as_a_card_whose_watchdog_fires(tmp_path: Path) -> None:
    """READY drops, the process exits with status 70, a host's calls get -11 and a new host's
    DevInitBoard too; the database in flash is untouched: the next firmware runs it."""
    network = tmp_path / "net.toml"
    network.write_text("[[node]]\nid = 1\n")
    dbm = write_dbm(build_dbm(load_network(network)))
    card = start_card(tmp_path, 0, "--simulate", str(network))
    try:
        with Board(0, tmp_path, timeout=5000) as board:
            assert DevDownload(0, CONFIGURATION_DOWNLOAD, dbm) == Drv.DRV_NO_ERROR
            board.reset(d.COLDSTART)
            wait_until(lambda: board.diagnostics().operating() == [1], 20, "node 1 running")
            flash = {p: p.read_bytes() for p in (tmp_path / "flash").rglob("*") if p.is_file()}
            assert flash
            faults.inject("die", 0, tmp_path)
            assert commands.wait(card.proc, 30) == DIE_EXIT_STATUS
            with pytest.raises(CifError) as refused:
                board.transact(request(), timeout=500)
            assert refused.value.code == Drv.DRV_DEV_NOT_READY
        mm = card.map()
        assert not mm[HOST_FLAGS] & fl.READY
        mm.close()
        assert not firmware_liveness(tmp_path, 0).alive
        with pytest.raises(CifError) as refused:
            Board(0, tmp_path).open()
        assert refused.value.code == Drv.DRV_DEV_NOT_READY
        assert "fault die: the card's watchdog fired" in card.log()
        assert {p: p.read_bytes() for p in flash} == flash
        with pytest.raises(FaultError, match="no card serves board 0"):
            faults.active(0, tmp_path)
    finally:
        card.stop()
    card = start_card(tmp_path, 0, "--simulate", str(network))
    try:
        with Board(0, tmp_path, timeout=5000) as board:
            wait_until(lambda: board.diagnostics().operating() == [1], 20,
                       "node 1 running from the database in flash")
    finally:
        card.stop()


def test_the_firmware_stops_when_its_fault_socket_file_is_gone(card: Card) -> None:
    """A demo removes its directory as it ends, the fault socket's file with it: SIGTERM then
    still ends the firmware. The fault thread used to be woken by a datagram to that file,
    so power-off waited for it for good and the process stayed."""
    (card.directory / f"board{card.board}.fault").unlink()
    card.proc.terminate()
    assert commands.wait(card.proc, 20) == 0


def test_a_hanging_card_comes_back_by_a_cold_start(card: Card, opened: Board) -> None:
    """`die --hang`: READY drops and the process stays; with an RCS error in force a new
    host's DevInitBoard gets 1000 + bRcsError; a second `die --hang` moves the hang's end,
    and after for_ms the card starts cold (the host's protocol parameters, a warm start's,
    are gone) and serves again."""
    parameters = opened.protocol_parameters()
    parameters.usWatchDogTime = 1234
    assert d.DevPutTaskParameter(0, 2, parameters.encode()[:16]) == Drv.DRV_NO_ERROR
    mm = card.map()
    try:
        faults.inject("rcs-error", 0, card.directory, code=42)
        active = faults.inject("die", 0, card.directory, hang=True)
        assert {a.request.kind for a in active} == {"rcs-error", "die"}
        assert not mm[HOST_FLAGS] & fl.READY and mm[RCS_ERROR] == 42
        with pytest.raises(CifError) as refused:
            opened.transact(request(), timeout=200)
        assert refused.value.code == Drv.DRV_DEV_NOT_READY
        assert card.proc.poll() is None and firmware_liveness(card.directory, 0).alive
        new_host = commands.run(
            [sys.executable, "-c", "from host_api import driver as d; "
             f"d.DevOpenDriver({str(card.directory)!r}); print(d.DevInitBoard(0))"],
            cwd=ROOT, timeout=60, check=True, capture_output=True, text=True)
        assert new_host.stdout == "1042\n"
        before = time.monotonic()
        faults.inject("die", 0, card.directory, hang=True, for_ms=1000)  # the end moves
        assert not mm[HOST_FLAGS] & fl.READY
        wait_until(lambda: mm[HOST_FLAGS] & fl.READY, 10 + 1, "READY after the hang")
        assert time.monotonic() - before >= 1.0
        assert opened.transact(request()).f == 0
        assert opened.protocol_parameters().usWatchDogTime != 1234, "not a cold start"
        assert mm[RCS_ERROR] == 42
        assert faults.clear(0, card.directory) == []
        assert mm[RCS_ERROR] == 0
    finally:
        mm.close()


@pytest.mark.skipif(os.geteuid() != 0, reason="becoming another user needs root")
def test_a_user_outside_the_image_directory_cannot_inject_a_fault(tmp_path: Path) -> None:
    """docs/security.md: the fault socket is a file in the image directory (mode 2770), so
    the kernel keeps another user from it, as from the image and the doorbell."""
    place = Path(tempfile.mkdtemp(dir="/dev/shm", prefix="cifemu-test-"))
    os.chmod(place, 0o1777)  # every user may enter the parent, as /dev/shm
    cards = place / "cif"
    card = start_card(cards, 0, "--flash", str(tmp_path / "flash"))
    try:
        nobody = pwd.getpwnam("nobody")
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the child reports through its exit status
            code = 2
            try:
                os.setgroups([])
                os.setgid(nobody.pw_gid)
                os.setuid(nobody.pw_uid)
                faults.inject("die", 0, cards)
                code = 1
            except FaultError as exc:
                code = 0 if "no permission to reach the card's fault socket" in str(exc) else 3
            finally:
                os._exit(code)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
        assert card.proc.poll() is None and faults.active(0, cards) == []
    finally:
        card.stop()
        shutil.rmtree(place, ignore_errors=True)
