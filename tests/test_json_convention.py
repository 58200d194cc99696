"""One JSON convention: snake_case keys, numbers as numbers, bytes as hex strings, errors as an
object on stdout with a non-zero exit, no traceback when the reader closes the pipe."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

from tests import commands
from tests.conftest import ROOT, start_card

DEMO = ROOT / "cifemu" / "examples" / "demo.toml"
SNAKE = re.compile(r"^[a-z][a-z0-9_]*$")
HEX = re.compile(r"^([0-9a-f]{2})*$")


def cifemu(*args: str) -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "cifemu", *args], capture_output=True,
                        text=True, timeout=60, cwd=ROOT)


def keys(value: Any, skip: frozenset[str] = frozenset()) -> set[str]:
    """Every key of a JSON document, except below keys in ``skip``."""
    if isinstance(value, dict):
        found = set(value)
        for key, item in value.items():
            if key not in skip:
                found |= keys(item, skip)
        return found
    if isinstance(value, list):
        return set().union(*(keys(item, skip) for item in value)) if value else set()
    return set()


def test_status_and_configure_follow_the_convention(tmp_path: Path) -> None:
    card = start_card(tmp_path, 0, "--simulate", str(DEMO))
    try:
        configured = cifemu("configure", str(DEMO), "--dpm-dir", str(tmp_path), "--json")
        status = cifemu("status", "--dpm-dir", str(tmp_path), "--json")
    finally:
        card.stop()
    for done in (configured, status):
        assert done.returncode == 0, done.stderr
        document = json.loads(done.stdout)
        assert all(SNAKE.match(key) for key in keys(document)), keys(document)
    snap = json.loads(status.stdout)
    assert isinstance(snap["device"]["serial_no"], int)
    assert isinstance(snap["rcs"]["rcs_version"], int)
    assert HEX.match(snap["process_data"]["inputs"]) and len(snap["process_data"]["inputs"]) == 64
    assert snap["task2state"]["nd_state"] == [1, 2, 3, 4]


def test_dbm_show_keys_are_snake_case_around_the_manuals_records(tmp_path: Path) -> None:
    dbm = tmp_path / "demo.dbm"
    assert cifemu("dbm", "build", str(DEMO), "-o", str(dbm)).returncode == 0
    shown = cifemu("dbm", "show", str(dbm), "--json")
    document = json.loads(shown.stdout)
    assert all(SNAKE.match(key) for key in keys(document, frozenset({"decoded"})))
    assert all(HEX.match(record["hex"]) for table in document["tables"]
               for record in table["records"])


def test_errors_with_json_are_an_object_on_stdout(tmp_path: Path) -> None:
    cases = [
        ("status", "--dpm-dir", str(tmp_path), "--json"),
        ("configure", str(DEMO), "--dpm-dir", str(tmp_path), "--json"),
        ("dbm", "show", str(tmp_path / "missing.dbm"), "--json"),
        ("dbm", "dir", "--dpm-dir", str(tmp_path), "--json"),
        ("monitor", "--dpm-dir", str(tmp_path), "--json"),
    ]
    for case in cases:
        done = cifemu(*case)
        assert done.returncode != 0, case
        error = json.loads(done.stdout)["error"]
        assert error["message"] and error["command"] in " ".join(case), case
        assert done.stderr == "", case


def test_a_closed_pipe_ends_quietly(tmp_path: Path) -> None:
    network = tmp_path / "big.toml"
    network.write_text("".join(f"[[node]]\nid = {n}\n" for n in range(1, 100)))
    dbm = tmp_path / "big.dbm"
    assert cifemu("dbm", "build", str(network), "-o", str(dbm)).returncode == 0
    proc = subprocess.Popen([sys.executable, "-m", "cifemu", "dbm", "show", str(dbm), "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    assert proc.stdout is not None and proc.stderr is not None
    assert proc.stdout.readline().strip() == b"{"
    proc.stdout.close()  # `| head -1`
    stderr = proc.stderr.read().decode()
    commands.wait(proc, 60)
    assert "Traceback" not in stderr and "BrokenPipeError" not in stderr, stderr
    assert proc.returncode == 1


def test_sim_announces_its_nodes_as_one_json_line(tmp_path: Path) -> None:
    sim = subprocess.Popen([sys.executable, "-m", "cifemu", "sim", str(DEMO), "--interface",
                            "virtual", "--channel", f"json{tmp_path.name}", "--json",
                            "--log-level", "WARNING"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert sim.stdout is not None
        first = json.loads(sim.stdout.readline())
    finally:
        sim.terminate()
        commands.wait(sim, 20)
    assert all(SNAKE.match(key) for key in keys(first))
    assert [node["id"] for node in first["nodes"]] == [1, 2, 3, 4]
    assert first["bitrate"] == 500000
    failed = cifemu("sim", str(tmp_path / "missing.toml"), "--interface", "virtual",
                    "--channel", "x", "--json")
    assert failed.returncode == 1 and json.loads(failed.stdout)["error"]["command"] == "sim"
