"""``cifemu dbm`` as a user runs it: subprocesses, exit codes, what they print."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dbm_tools.builder import build_dbm
from dbm_tools.container import data_area, read_dbm, save_dbm
from dbm_tools.network import parse_network
from dbm_tools.parameters import BusParameterSet
from dbm_tools.tables import BUS_CAN, GLOBAL, GlobalSet
from tests import commands
from tests.conftest import ROOT, Card
from tests.fixtures import REAL_DBM as FIXTURE
from tests.fixtures import needs_real_dbm

NETWORK = """[bus]
bitrate = 250000
[[node]]
id = 3
boot = ["start", "pdo"]
[[node]]
id = 7
eds = "{eds}"
name = "valve block"
boot = ["start", "pdo"]
"""


def cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    """``python -m cifemu dbm ARGS``."""
    command = [sys.executable, "-m", "cifemu", "dbm", *map(str, args)]
    env = {**os.environ, "COLUMNS": "200"}  # rich wraps at 80 columns without a terminal
    return commands.run(command, cwd=ROOT, capture_output=True, text=True, timeout=60,
                        env=env)


def write_network(directory: Path) -> Path:
    path = directory / "plant.toml"
    path.write_text(NETWORK.format(eds=ROOT / "tests" / "data" / "io-module.eds"))
    return path


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One build for the module's tests, which only read it."""
    directory = tmp_path_factory.mktemp("built")
    out = directory / "plant.dbm"
    result = cli("build", write_network(directory), "-o", out, "--name", "Plant 1")
    assert result.returncode == 0, result.stderr
    assert "2 node(s), passes the card's checks" in result.stdout
    return out


def test_help_explains_every_command() -> None:
    result = cli("--help")
    assert result.returncode == 0
    for command in ("show", "check", "build", "diff", "download", "upload", "delete", "dir"):
        assert f"  {command}" in result.stdout
    result = cli("check", "--help")
    assert result.returncode == 0 and "212" in result.stdout and "Exit status 1" in result.stdout


def test_build_writes_a_database_the_card_accepts(built: Path) -> None:
    dbm = read_dbm(built.read_bytes())
    assert dbm.tables[0].name == GLOBAL
    assert "Plant 1" in built.read_bytes().decode("latin-1")


def test_build_reports_a_bad_description(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[[node]]\nid = 3\n[[node.pdo]]\ndirection = \"input\"\ncob_id = 0x183\n"
                   "offset = 3580\n")
    result = cli("build", bad, "-o", tmp_path / "bad.dbm")
    assert result.returncode == 1
    assert "node 3 PDO 1: input offset 3580 + 8 bytes runs past" in result.stderr
    assert not (tmp_path / "bad.dbm").exists()


@needs_real_dbm
def test_show_dumps_the_tables_it_does_not_know() -> None:
    result = cli("show", FIXTURE)
    assert result.returncode == 0, result.stderr
    assert "PB_COMBI" in result.stdout and "PROFIBUS new network" in result.stdout
    assert "BUS_DP record 1 (67 bytes)" in result.stdout
    assert "0000  43 00 00 06 2c 01 0b 00" in result.stdout


def test_show_decodes_canopen_tables(built: Path) -> None:
    result = cli("show", built)
    assert result.returncode == 0, result.stderr
    for text in ("NODES: node 7", "0x00070191: usDevProfNum 401", "HRTBT ACTIVE",
                 "node 7: SDO list", "1017h", "node 7: PDO list and ADD-tab", "0x287",
                 "250 kbit/s", "Acme Automation", "valve block", "matches the records"):
        assert text in result.stdout, text


def test_show_json_has_every_record(built: Path) -> None:
    result = cli("show", "--json", built)
    assert result.returncode == 0
    document = json.loads(result.stdout)
    tables = {t["name"]: t for t in document["tables"]}
    assert tables["GLOBAL"]["number"] == 8
    node = tables["NODES"]["records"][1]["decoded"]
    assert node["Node_Address"] == 7
    assert [p["usPdoCOBId"] for p in node["Node_Data_set"]["atPdoCfgData"]] == [
        0x187, 0x287, 0x207]


@needs_real_dbm
def test_show_json_gives_unknown_records_in_hex() -> None:
    fixture = {t["name"]: t for t in json.loads(cli("show", "--json", FIXTURE).stdout)["tables"]}
    assert "decoded" not in fixture["BUS_DP"]["records"][0]
    assert fixture["BUS_DP"]["records"][0]["hex"].startswith("43000006")


@needs_real_dbm
def test_check_of_a_foreign_database() -> None:
    result = cli("check", FIXTURE)
    assert result.returncode == 1
    assert ("error 20 (database not valid for this device) in table GLOBAL, record 1, field "
            "szSegmentName: segment name 'PB_COMBI'") in result.stdout
    assert "error 212 (faulty reading of a data base) in table BUS_CAN" in result.stdout
    assert "warning in table GLOBAL, record 1, field usChecksumCRC" in result.stdout
    assert "2 error(s), 1 warning(s)" in result.stdout


def test_check_exit_codes_and_findings(tmp_path: Path, built: Path) -> None:
    assert cli("check", built).returncode == 0
    dbm = read_dbm(built.read_bytes())
    dbm.tables[0].records[0] = GlobalSet(usChecksumCRC=0x1234).encode()
    save_dbm(tmp_path / "foreign-crc.dbm", dbm)
    result = cli("check", tmp_path / "foreign-crc.dbm")
    assert result.returncode == 0 and "warning in table GLOBAL" in result.stdout

    bus = dbm.table(BUS_CAN)
    assert bus is not None
    bus.records[0] = BusParameterSet(Baud_rate=9).encode()
    save_dbm(tmp_path / "baud.dbm", dbm)
    result = cli("check", "--json", tmp_path / "baud.dbm")
    assert result.returncode == 1
    findings = json.loads(result.stdout)
    assert [(f["number"], f["text"], f["table"], f["record"], f["field"]) for f in findings
            if f["severity"] == "error"] == [
        (65, "data check: unknown baud rate", "BUS_CAN", 1, "Baud_rate")]

    result = cli("check", tmp_path / "missing.dbm")
    assert result.returncode == 1 and "cannot read" in result.stderr
    (tmp_path / "junk.dbm").write_bytes(b"DBMFILE  \0junk")
    result = cli("check", tmp_path / "junk.dbm")
    assert result.returncode == 1 and "not a readable DBM" in result.stderr


def test_diff_names_table_record_and_field(tmp_path: Path, built: Path) -> None:
    same = cli("diff", built, built)
    assert (same.returncode, same.stdout.strip()) == (0, "no differences")
    network = write_network(tmp_path)
    network.write_text(network.read_text().replace("250000", "500000")
                       .replace('name = "valve block"', 'name = "pump"'))
    other = tmp_path / "other.dbm"
    assert cli("build", network, "-o", other, "--name", "Plant 1").returncode == 0
    result = cli("diff", built, other)
    assert result.returncode == 1
    assert "BUS_CAN record 1 Baud_rate: 3 -> 2" in result.stdout
    assert "DESCRIPT station 7 szDescription: valve block -> pump" in result.stdout
    found = json.loads(cli("diff", "--json", built, other).stdout)
    assert {"table": "DESCRIPT", "record": 7, "record_kind": "station",
            "field": "szDescription", "a": "valve block", "b": "pump"} in found


@needs_real_dbm
def test_diff_names_a_table_only_one_side_has(built: Path) -> None:
    result = cli("diff", "--json", built, FIXTURE)
    assert result.returncode == 1
    found = json.loads(result.stdout)
    assert {"table": "BUS_DP", "record": None, "record_kind": None, "field": None,
            "a": "absent", "b": "present"} in found
    assert any(d["table"] == "GLOBAL" and d["field"] == "szSegmentName" for d in found)


def test_json_errors_are_objects_and_a_closed_pipe_ends_quietly(tmp_path: Path,
                                                                built: Path) -> None:
    missing = tmp_path / "missing.dbm"
    result = cli("check", "--json", missing)
    assert (result.returncode, result.stderr) == (1, "")
    assert json.loads(result.stdout) == {"error": {
        "command": "dbm check", "message": f"cannot read {missing}: No such file or directory"}}
    result = cli("dir", "--json", "--dpm-dir", tmp_path, "--board", "1")
    error = json.loads(result.stdout)["error"]
    assert result.returncode == 1 and error["command"] == "dbm dir"
    assert "is `cifemu firmware --board 1` running?" in error["message"]
    # the reader is gone before the first line
    command = [sys.executable, "-m", "cifemu", "dbm", "show", "--json", str(built)]
    reader = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True)
    assert reader.stdout is not None and reader.stderr is not None
    reader.stdout.close()
    errors = reader.stderr.read()
    assert commands.wait(reader, 60) == 1
    assert errors == "", errors


def test_card_commands(card: Card, tmp_path: Path, built: Path) -> None:
    where = ("--dpm-dir", card.directory)
    result = cli("upload", "-o", tmp_path / "none.dbm", *where)
    assert result.returncode == 1 and "1200" in result.stderr
    result = cli("download", built, "--reset", *where)
    assert result.returncode == 0, result.stderr
    assert "stored in board 0's flash" in result.stdout
    assert "cold start done: READY RUN COM" in result.stdout
    result = cli("dir", *where)
    assert result.returncode == 0 and "segment 8 'CANopen '" in result.stdout
    result = cli("upload", "-o", tmp_path / "back.dbm", *where)
    assert result.returncode == 0, result.stderr
    assert data_area(read_dbm((tmp_path / "back.dbm").read_bytes())) == built.read_bytes()[44:]
    flash_file = card.directory / "flash" / "board0" / "database.bin"
    assert flash_file.read_bytes() == built.read_bytes()[44:]
    assert cli("show", flash_file).returncode == 0  # the flash holds a bare data area

    result = cli("delete", *where)
    assert result.returncode == 0 and "database deleted" in result.stdout
    result = cli("dir", "--json", *where)
    assert result.returncode == 0 and json.loads(result.stdout) == []


@needs_real_dbm
def test_card_refuses_a_foreign_database(card: Card) -> None:
    result = cli("download", FIXTURE, "--dpm-dir", card.directory)
    assert result.returncode == 1
    assert "warning" in result.stdout  # it fails the checks, and the card says so too:
    assert "DRV_RCS_ERROR_OFFSET+20 (1020)" in result.stderr
    assert "database not valid for this device" in result.stderr


def test_card_commands_without_a_card_say_what_to_do(tmp_path: Path) -> None:
    result = cli("delete", "--dpm-dir", tmp_path, "--board", "2")
    assert result.returncode == 1
    assert "is `cifemu firmware --board 2` running?" in result.stderr


def test_an_area_that_is_no_dbm_can_still_be_uploaded(card: Card, tmp_path: Path) -> None:
    """An upload returns what the flash holds, readable or not (written here by hand)."""
    area = data_area(build_dbm(parse_network("[[node]]\nid = 3\n")))
    broken = area[:-2] + b"\xff\xff"
    flash = card.directory / "flash" / "board0" / "database.bin"
    flash.write_bytes(broken)
    result = cli("upload", "-o", tmp_path / "out.dbm", "--dpm-dir", card.directory)
    assert result.returncode == 0
    assert "not readable" in result.stdout
    assert (tmp_path / "out.dbm").read_bytes() == broken
