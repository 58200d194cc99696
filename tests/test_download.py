"""A DBM into the card's flash and out again: DevDownload, the RCS load function, start-up.

Every test talks to a real firmware process; its flash is the test's own
directory (conftest's ``private_flash``).
"""

from __future__ import annotations

import signal
import struct
import subprocess
import sys
import threading
from pathlib import Path

import pytest

import host_api as d
from dbm_tools.builder import build_dbm
from dbm_tools.container import data_area, read_data_area, save_dbm, write_dbm
from dbm_tools.network import parse_network
from dbm_tools.parameters import BusParameterSet, NodeParameterSet
from dbm_tools.tables import BUS_CAN, DESCRIPT, NODES, NodesRecord
from dbm_tools.validate import check_dbm
from dpm.errors import Drv
from dpm.message import Message
from dpm.task2 import CanState, ComDiagnostics, ComPlcParameter, GlobalBits
from firmware.device import Device
from firmware.flash import DATABASE_FILE
from host_api.download import (
    CONFIGURATION_DOWNLOAD,
    FIRMWARE_DOWNLOAD,
    delete_database,
    flash_directory,
    upload_database,
)
from host_api.registry import registry
from tests import commands
from tests.conftest import ROOT, Card, start_card, wait_until
from tests.fixtures import REAL_DBM as FIXTURE
from tests.fixtures import needs_real_dbm

QUICK = 'boot = ["start", "pdo"]\n'
"""Boot steps that wait for no answer: no node answers on the test bus, and the CAN task's
boot timeouts would only make every card's shutdown seconds slower."""
TWO_NODES = (f"[bus]\nbitrate = 125000\n[[node]]\nid = 3\n{QUICK}"
             f"[[node]]\nid = 4\nname = \"pump\"\n{QUICK}")
READY, RUN, COM = 0x80, 0x40, 0x20
NOTREADY = 0x20


def make_dbm(directory: Path, text: str = TWO_NODES, name: str = "net.dbm") -> Path:
    dbm = build_dbm(parse_network(text))
    assert check_dbm(dbm) == []
    path = directory / name
    save_dbm(path, dbm)
    return path


def host_flags(board: int) -> int:
    return registry.boards[board].host()


def diagnostics(board: int) -> ComDiagnostics:
    rc, raw = d.DevGetTaskState(board, 2, 64)
    assert rc == 0
    return ComDiagnostics.decode(raw)


def cold_start(board: int) -> None:
    assert d.DevReset(board, d.COLDSTART, 5000) == 0


def load(board: int, data: bytes, e: int, nr: int) -> Message:
    """One raw load-function message (msg.b 6 to the RCS) and its answer."""
    assert d.DevPutMessage(board, Message(rx=0, tx=16, b=6, data=data, nr=nr, e=e), 1000) == 0
    rc, answer = d.DevGetMessage(board, d.MSG_BUFFER_SIZE, 2000)
    assert rc == 0 and answer is not None
    assert (answer.rx, answer.tx, answer.a, answer.b, answer.nr) == (16, 0, 6, 0, nr)
    return answer


def first_message(area: bytes) -> bytes:
    """d[0] = 3, root words w0..w7, the GLOBAL record (table 8's first record)."""
    global_record = read_data_area(area).tables[0].records[0]
    return bytes([3]) + area[:16] + global_record


# --- the whole way: build, check, download, start ------------------------------------------


def test_build_check_download_start_reaches_operate(board: int, tmp_path: Path) -> None:
    path = make_dbm(tmp_path)
    area = path.read_bytes()[44:]
    seen: list[tuple[int, int]] = []
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, path, lambda *p: seen.append(p)) == 0
    assert seen[-1] == (len(area), len(area)) and len(seen) == -(-len(area) // 240)
    assert host_flags(board) & (RUN | COM) == 0  # the database waits for the next start
    assert upload_database(board) == (0, area)
    rc, entries = flash_directory(board)
    assert rc == 0 and [(e.segment, e.name, e.length) for e in entries] == [
        (8, "CANopen ", len(area))
    ]
    assert entries[0].checksum == struct.unpack_from("<H", area)[0]

    cold_start(board)
    wait_until(lambda: host_flags(board) & (READY | RUN | COM) == READY | RUN | COM,
               what="READY RUN COM from the stored database")
    diag = diagnostics(board)
    assert diag.bCAN_State == CanState.OPERATE
    assert diag.configured() == [3, 4]
    assert diag.bErr_event != 212
    # PLC_PARAM and GLOBAL set the protocol parameters of a cold start
    rc, raw = d.DevGetTaskParameter(board, 2, 64)
    parameter = ComPlcParameter.decode(raw)
    assert (parameter.bMode, parameter.usWatchDogTime) == (3, 1000)


def test_the_stored_descript_answers_get_configuration(board: int, tmp_path: Path) -> None:
    path = make_dbm(tmp_path)
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, path) == 0
    cold_start(board)
    descript = read_data_area(path.read_bytes()[44:]).table(DESCRIPT)
    assert descript is not None
    record = {r[0]: r for r in descript.records}[4]
    header = bytes([4, 0, 0, 0, 0, 0, 0, 1])
    assert d.DevPutMessage(board, Message(rx=3, tx=16, b=15, nr=9, data=header), 1000) == 0
    rc, answer = d.DevGetMessage(board, d.MSG_BUFFER_SIZE, 2000)
    assert rc == 0 and answer is not None and answer.f == 0
    assert answer.data[8:] == record[1:]
    assert b"pump" in answer.data


def test_a_database_needing_the_host_waits_for_host_ready(board: int, tmp_path: Path) -> None:
    path = make_dbm(tmp_path, "[bus]\nwait_for_host = true\nhandshake = \"uncontrolled\"\n"
                              "host_watchdog_ms = 300\n[[node]]\nid = 3\n" + QUICK)
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, path) == 0
    cold_start(board)
    wait_until(lambda: host_flags(board) & RUN, what="RUN: the card is configured")
    assert host_flags(board) & COM == 0
    assert registry.boards[board].dev() & NOTREADY
    diag = diagnostics(board)
    assert diag.bCAN_State == CanState.STOP and GlobalBits.NRDY in diag.global_bits
    # bMode 2 (uncontrolled: exchange mode 3) and GLOBAL's supervision time
    rc, raw = d.DevGetTaskParameter(board, 2, 64)
    parameter = ComPlcParameter.decode(raw)
    assert rc == 0 and (parameter.bMode, parameter.usWatchDogTime) == (2, 300)
    assert d.DevGetInfo(board, d.GET_IO_INFO, 6)[1][1] == 3
    assert d.DevSetHostState(board, d.HOST_READY, 2000) == 0  # waits for COM
    assert diagnostics(board).bCAN_State == CanState.OPERATE
    # a warm start takes the host's parameters: they rank above the flash (seed 2)
    assert d.DevPutTaskParameter(board, 2, struct.pack("<BH", 3, 0)) == 0
    assert d.DevReset(board, d.WARMSTART, 5000) == 0
    assert d.DevGetInfo(board, d.GET_IO_INFO, 6)[1][1] == 4


# --- every refusal of the card ---------------------------------------------------------------


@needs_real_dbm
def test_the_real_profibus_file_is_not_a_canopen_database(board: int) -> None:
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, FIXTURE) == 1020
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, FIXTURE.read_bytes()) == 1020
    assert upload_database(board) == (1200, b"")  # nothing stored


def test_card_refusals_carry_the_load_function_numbers(board: int, tmp_path: Path) -> None:
    area = make_dbm(tmp_path).read_bytes()[44:]
    first = first_message(area)
    # 20: segment name
    assert load(board, first[:17] + b"PB_COMBI\0" + first[26:], 4, 1).f == 20
    # 23: sizes (first message length; w5 != w6; a data area beyond 65534 bytes)
    assert load(board, first[:-1], 4, 1).f == 23
    words = bytearray(first)
    words[13:15] = struct.pack("<H", 300)  # w6
    assert load(board, bytes(words), 4, 1).f == 23
    words[11:15] = struct.pack("<HH", 0x8000, 0x8000)
    assert load(board, bytes(words), 4, 1).f == 23
    # 24: a continuation without a download, a download command without e = 4
    assert load(board, area[:240], 8, 2).f == 24
    assert load(board, area[:240], 0x0C, 2).f == 24
    assert load(board, first, 0, 1).f == 24
    # 22: message numbers must count up
    assert load(board, first, 4, 1).f == 0
    assert load(board, area[:240], 8, 3).f == 22
    assert load(board, area[:240], 8, 3).f == 24  # the error ended the download
    # 23: a piece of the wrong size, a last piece that does not complete the area
    assert load(board, first, 4, 1).f == 0
    assert load(board, area[:200], 8, 2).f == 23
    assert load(board, first, 4, 1).f == 0
    assert load(board, area[:240], 0x0C, 2).f == 23
    # 21 [ours]: unknown mode, empty message, delete of another segment
    assert load(board, bytes([9]), 0, 1).f == 21
    assert load(board, b"", 0, 1).f == 21
    assert load(board, bytes([4, 7]), 0, 1).f == 21
    # 25: the checksum w0, sent through DevDownload from a file with a broken w0
    broken = bytearray(write_dbm(read_data_area(area)))
    broken[44] ^= 0xFF
    (tmp_path / "broken.dbm").write_bytes(broken)
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, tmp_path / "broken.dbm") == 1025
    # nothing of all this reached the flash
    assert flash_directory(board) == (0, [])


def test_a_download_may_start_over_and_message_numbers_wrap(board: int, tmp_path: Path) -> None:
    area = make_dbm(tmp_path).read_bytes()[44:]
    first = first_message(area)
    assert load(board, first, 4, 1).f == 0
    assert load(board, first, 4, 255).f == 0  # a new first message starts over
    pieces = [area[at : at + 240] for at in range(0, len(area), 240)]
    for index, piece in enumerate(pieces):
        e = 0x0C if index == len(pieces) - 1 else 8
        assert load(board, piece, e, index & 0xFF).f == 0  # 255 -> 0 -> 1 ...
    assert upload_database(board) == (0, area)


def test_upload_protocol_marks_first_continue_last(board: int, tmp_path: Path) -> None:
    area = make_dbm(tmp_path).read_bytes()[44:]
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, area) == 0  # a bare data area
    first = load(board, bytes([2]), 4, 7)
    assert (first.e, first.data) == (4, area[:240])
    second = load(board, bytes([2]), 8, 8)
    assert (second.e, second.data) == (8, area[240:480])
    assert load(board, bytes([2]), 8, 10).f == 22
    assert load(board, bytes([2]), 8, 11).f == 24  # the upload was abandoned


def test_driver_file_errors(board: int, tmp_path: Path) -> None:
    path = make_dbm(tmp_path)
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, "") == Drv.DRV_USR_FILENAME_INVALID
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, tmp_path / "none.dbm") == (
        Drv.DRV_USR_FILE_OPEN_FAILED)
    (tmp_path / "empty.dbm").write_bytes(b"")
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, tmp_path / "empty.dbm") == (
        Drv.DRV_USR_FILE_SIZE_ZERO)
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, b"") == Drv.DRV_USR_FILE_SIZE_ZERO
    # /proc/self/mem opens but reading its first page fails with EIO: a real read error
    (tmp_path / "unreadable.dbm").symlink_to("/proc/self/mem")
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, tmp_path / "unreadable.dbm") == (
        Drv.DRV_USR_FILE_READ_FAILED)
    text = tmp_path / "net.txt"
    text.write_bytes(path.read_bytes())
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, text) == Drv.DRV_USR_INVALID_FILETYPE
    (tmp_path / "notes.dbm").write_text("not a database")
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, tmp_path / "notes.dbm") == (
        Drv.DRV_USR_INVALID_FILETYPE)
    (tmp_path / "short.dbm").write_bytes(path.read_bytes()[:-2])
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, tmp_path / "short.dbm") == (
        Drv.DRV_USR_INVALID_FILETYPE)
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, bytes(500)) == (
        Drv.DRV_USR_INVALID_FILETYPE)  # no GLOBAL behind root slot 8
    assert d.DevDownload(board, FIRMWARE_DOWNLOAD, path) == Drv.DRV_DEV_FUNCTION_FAILED
    assert d.DevDownload(board, 7, path) == Drv.DRV_USR_MODE_INVALID
    assert d.DevDownload(3, CONFIGURATION_DOWNLOAD, path) == Drv.DRV_USR_NOT_INITIALIZED


# --- delete, kill, faulty flash --------------------------------------------------------------


def test_delete_leaves_the_card_ready_without_run(board: int, tmp_path: Path) -> None:
    """[ours] RUN drops with the delete's answer (seed 7.2 step 1 reads bHostFlags again and
    waits for RDY alone); the network runs on from RAM until the next start."""
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, make_dbm(tmp_path)) == 0
    cold_start(board)
    wait_until(lambda: host_flags(board) & RUN, what="RUN")
    assert delete_database(board) == 0
    assert flash_directory(board) == (0, [])
    assert host_flags(board) & (READY | RUN) == READY  # already as the answer arrives
    cold_start(board)
    assert host_flags(board) & (READY | RUN | COM) == READY
    assert (diagnostics(board).bErr_rem_adr, diagnostics(board).bErr_event) == (0, 0)
    assert delete_database(board) == 0  # nothing to delete is no error


def test_sigkill_in_the_middle_of_a_download_keeps_the_previous_database(tmp_path: Path) -> None:
    flash = tmp_path / "my-flash"
    card = start_card(tmp_path, 0, "--flash", str(flash))
    try:
        assert d.DevOpenDriver(tmp_path) == 0 and d.DevInitBoard(0) == 0
        old = make_dbm(tmp_path, name="old.dbm").read_bytes()[44:]
        new = make_dbm(tmp_path, "[[node]]\nid = 9\n" + QUICK, "new.dbm").read_bytes()[44:]
        assert d.DevDownload(0, CONFIGURATION_DOWNLOAD, old) == 0
        assert load(0, first_message(new), 4, 1).f == 0
        assert load(0, new[:240], 8, 2).f == 0
        card.proc.send_signal(signal.SIGKILL)
        commands.wait(card.proc, 10)
        d.DevCloseDriver()
        assert (flash / DATABASE_FILE).read_bytes() == old
        card = start_card(tmp_path, 0, "--flash", str(flash))
        assert d.DevOpenDriver(tmp_path) == 0 and d.DevInitBoard(0) == 0
        wait_until(lambda: host_flags(0) & RUN, what="RUN from the old database")
        assert diagnostics(0).configured() == [3, 4]
        assert upload_database(0) == (0, old)
        assert sorted(p.name for p in flash.iterdir()) == [DATABASE_FILE]
    finally:
        while d.DevCloseDriver() == 0:
            pass
        card.stop()


def faulty_bus(area: bytes) -> bytes:
    """The same database with an unknown baud rate (65) in BUS_CAN."""
    dbm = read_data_area(area)
    table = dbm.table(BUS_CAN)
    assert table is not None
    table.records[0] = BusParameterSet(Baud_rate=9).encode()
    return data_area(dbm)


def faulty_node(area: bytes, address: int) -> bytes:
    """The same database with node ``address``'s EMCY COB-ID 0 (73)."""
    dbm = read_data_area(area)
    table = dbm.table(NODES)
    assert table is not None
    for index, raw in enumerate(table.records):
        record = NodesRecord.decode(raw)
        if record.Node_Address == address:
            record.Node_Data_set.usCobIDEmcy = 0
            table.records[index] = record.encode()
    return data_area(dbm)


def double_node(area: bytes) -> bytes:
    """The same database with its first NODES record twice (60)."""
    dbm = read_data_area(area)
    table = dbm.table(NODES)
    assert table is not None
    table.records.append(table.records[0])
    return data_area(dbm)


@pytest.mark.parametrize(("damage", "where", "event", "text"), [
    (faulty_bus, 255, 56, "baudrate out of range"),
    (double_node, 255, 60, "double node address was configured"),
    (lambda area: faulty_node(area, 4), 4, 212, None),
    (lambda area: area[:300], 255, 212, "faulty reading of a data base"),
    (lambda area: b"\x01\x02", 255, 212, "faulty reading of a data base"),
], ids=["bus", "double", "node", "truncated", "garbage"])
def test_a_faulty_database_in_flash_gives_the_seeds_err_event(
    tmp_path: Path, private_flash: Path, damage: object, where: int, event: int,
    text: str | None
) -> None:
    """Seed 4.3: a bad baud rate is 56 and a double node address 60, both at address 255;
    any other fault is 212, at the node whose record failed or at 255."""
    area = make_dbm(tmp_path).read_bytes()[44:]
    flash = private_flash / "board0"
    flash.mkdir(parents=True)
    (flash / DATABASE_FILE).write_bytes(damage(area))  # type: ignore[operator]
    card = start_card(tmp_path)
    try:
        assert d.DevOpenDriver(tmp_path) == 0 and d.DevInitBoard(0) == 0
        assert host_flags(0) & (READY | RUN) == READY
        diag = diagnostics(0)
        assert (diag.bErr_rem_adr, diag.bErr_event) == (where, event)
        assert GlobalBits.CTRL in diag.global_bits
        assert text is None or diag.err_text == text
        assert diag.configured() == []
    finally:
        while d.DevCloseDriver() == 0:
            pass
        card.stop()


def test_a_data_set_the_can_task_refuses_gives_212_at_its_node(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """check_dbm checks the node sets the CAN task takes (``take_node``), so no real
    database reaches this path; the refusal is forced (the only stand-in in these tests)
    to show where it lands."""
    device = Device(0, tmp_path, flash_dir=tmp_path / "flash")
    device.flash.store(make_dbm(tmp_path).read_bytes()[44:])
    refused: list[int] = []

    def refuse(address: int, data: bytes, params: NodeParameterSet) -> int:
        refused.append(address)
        return 62

    monkeypatch.setattr(device.can, "take_node", refuse)
    loop = threading.Thread(target=device.run)
    loop.start()
    try:
        wait_until(lambda: device.mm[0x1FFE] & READY, what="READY")
        assert refused == [3]  # the first node's refusal ends the start-up
        diag = ComDiagnostics.decode(bytes(device.mm[0x1F40:0x1F80]))
        assert (diag.bErr_rem_adr, diag.bErr_event) == (3, 212)
        assert not device.mm[0x1FFE] & RUN
    finally:
        device.stop()
        loop.join(10)


def test_two_hosts_never_interleave_their_downloads(card: Card, tmp_path: Path) -> None:
    paths = [make_dbm(tmp_path, f"[[node]]\nid = {n}\n{QUICK}", f"net{n}.dbm") for n in (5, 6)]
    command = [sys.executable, "-m", "cifemu", "dbm", "download", "--dpm-dir",
               str(card.directory)]
    hosts = [subprocess.Popen([*command, str(p)], cwd=ROOT, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for p in paths * 2]
    for host in hosts:
        _, err = commands.finish(host, 60)
        assert host.returncode == 0, err
    stored = (card.directory / "flash" / "board0" / DATABASE_FILE).read_bytes()
    assert stored in [p.read_bytes()[44:] for p in paths]


def test_the_flash_file_is_the_data_area_as_sent(board: int, tmp_path: Path) -> None:
    path = make_dbm(tmp_path)
    assert d.DevDownload(board, CONFIGURATION_DOWNLOAD, path) == 0
    stored = tmp_path / "flash" / "board0" / DATABASE_FILE
    assert stored.read_bytes() == path.read_bytes()[44:]
    assert stored.stat().st_mode & 0o777 == 0o640
