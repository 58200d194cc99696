"""`cifemu dbm export`: a DBM back to a network description that builds the same database."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from dbm_tools.builder import build_dbm
from dbm_tools.network import load_network
from tests import commands
from tests.conftest import ROOT

DEMO = ROOT / "cifemu" / "examples" / "demo.toml"
EDS = ROOT / "tests" / "data" / "io-module.eds"
VARIED = """[bus]
bitrate = 125000
sync_cob_id = 0x81
sync_period_ms = 20
auto_clear = true
byte_order = "motorola"
master_node_id = 99
heartbeat_ms = 250
global_start = true
accept_code = 0x1234567
accept_mask = 0x1FF00000
extended_ids = true
wait_for_host = true
host_watchdog_ms = 500
handshake = "uncontrolled"

[[node]]
id = 9
name = "drive \\"left\\""
error_control = "guarding"
guard_time_ms = 200
life_time_factor = 4
emcy_cob_id = 0x99
boot = ["reset", "device", "start", "pdo"]
device_type = 0x00020192
[[node.sdo]]
index = 0x6060
subindex = 0
value = 3
size = 1
[[node.pdo]]
direction = "output"
cob_id = 0x209
length = 6
transmission = 1
word = true
offset = 40
[[node.pdo]]
direction = "input"
cob_id = 0x189
length = 2
transmission = 254
inhibit = 100

[[node]]
id = 3
active = false
error_control = "none"

[[node]]
id = 7
eds = "{eds}"
heartbeat_ms = 300
"""


def cifemu(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "cifemu", "dbm", *map(str, args)],
                        capture_output=True, text=True, timeout=60, cwd=ROOT)


def round_trip(network: Path, tmp_path: Path) -> tuple[subprocess.CompletedProcess[str], Path]:
    first, again, exported = tmp_path / "first.dbm", tmp_path / "again.dbm", tmp_path / "x.toml"
    assert cifemu("build", network, "-o", first, "--name", "Plant").returncode == 0
    export = cifemu("export", first, "-o", exported)
    assert export.returncode == 0, export.stderr
    built = cifemu("build", exported, "-o", again, "--name", "Plant")
    assert built.returncode == 0, built.stderr
    return cifemu("diff", first, again), exported


def test_the_demo_network_builds_again_to_the_same_database(tmp_path: Path) -> None:
    diff, exported = round_trip(DEMO, tmp_path)
    assert diff.returncode == 0 and "no differences" in diff.stdout, diff.stdout
    network = load_network(exported)
    assert [node.name for node in network.nodes] == [
        node.name for node in load_network(DEMO).nodes]


def test_every_field_of_bus_and_nodes_survives_the_round_trip(tmp_path: Path) -> None:
    """Everything but DESCRIPT's identity of the EDS node (an EDS cannot be exported)."""
    network = tmp_path / "varied.toml"
    network.write_text(VARIED.format(eds=EDS))
    diff, exported = round_trip(network, tmp_path)
    changed = {line.split(":")[0] for line in diff.stdout.splitlines()[:-1]}
    descript = {f"DESCRIPT station 7 {field}" for field in (
        "szVendorName", "szDeviceName", "usIdentNumber", "usVendorNumber")}
    # GLOBAL's CRC covers DESCRIPT too
    assert changed == descript | {"GLOBAL record 1 usChecksumCRC"}, diff.stdout
    text = exported.read_text()
    assert "# node 7: " in text and "eds = ..." in text  # what the description cannot hold
    assert build_dbm(load_network(exported)).table("NODES") == build_dbm(
        load_network(network)).table("NODES")


def test_export_to_standard_output_and_a_file_that_is_no_dbm(tmp_path: Path) -> None:
    dbm = tmp_path / "demo.dbm"
    assert cifemu("build", DEMO, "-o", dbm).returncode == 0
    out = cifemu("export", dbm)
    assert out.returncode == 0 and "[bus]\nbitrate = 500000\n" in out.stdout
    assert "[[node]]\nid = 4\n" in out.stdout
    wrong = cifemu("export", DEMO)
    assert wrong.returncode == 1 and "Traceback" not in wrong.stderr
