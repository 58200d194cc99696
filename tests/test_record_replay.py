"""Record and replay (issue 25 items 1 and 2): a session recorded from the seed's 7.2
procedure (tests/c/operative.c, a real C program on libcif against a real firmware with
simulated nodes) replays against a fresh card with no difference; against a card whose
node 2 reports another device type, the diff names the message and the field.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import can
import pytest

from dbm_tools.builder import build_dbm
from dbm_tools.container import save_dbm
from dbm_tools.network import parse_network
from dpm import flags as fl
from dpm import session as s
from dpm.commands import Com
from tests import commands
from tests.conftest import start_card
from tests.libcif_host import C_NETWORK, C_TESTS, build_libcif, compile_program

NETWORK = C_NETWORK
"""operative.c's network: the seed's 7.2 procedure configures nodes 1 and 2."""

CHANGED_NODE_2 = NETWORK + "\n[node.sim]\ndevice_type = 0x000F0192\n"
"""Node 2 (the last [[node]]) reports profile 402 instead of the expected 401."""


@dataclass(frozen=True)
class Recording:
    session: Path
    program_pid: int


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Recording:
    """operative.c run once against a card started with --record."""
    build_libcif("all")
    root = tmp_path_factory.mktemp("recorded")
    network = root / "net.toml"
    network.write_text(NETWORK)
    dbm = root / "sycon.dbm"
    save_dbm(dbm, build_dbm(parse_network(NETWORK)))
    program = compile_program(C_TESTS / "operative.c", root / "operative", "plain")
    session = root / "session"
    card = start_card(root / "card", 0, "--simulate", str(network), "--flash",
                      str(root / "flash"), "--record", str(session))
    try:
        proc = subprocess.Popen([str(program), str(dbm)], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True,
                                env={**os.environ, "CIF_DPM_DIR": str(card.directory)})
        out, _ = proc.communicate(timeout=120)
        assert proc.returncode == 0, out
    finally:
        assert card.stop() == 0  # the recorder writes what it holds at power-off
    return Recording(session, proc.pid)


def replay(*args: str) -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "cifemu", "replay", *args],
                        capture_output=True, text=True, timeout=180, check=False)


def records(session: Path) -> list[s.Record]:
    return s.decode_events((session / s.EVENTS).read_text())


def test_the_session_holds_what_the_host_did_and_saw(recorded: Recording) -> None:
    meta = json.loads((recorded.session / s.META).read_text())
    assert meta["format"] == "cifemu-session" and meta["can_log"] == "can.log"
    events = records(recorded.session)
    sdo_puts = [r for r in events if r.kind == s.PUT and r.msg is not None
                and r.msg.b == Com.SDO_UP_DOWNLOAD]
    assert len(sdo_puts) == 4
    # the transaction ledger names the C program as the sender of each message
    assert {r.pid for r in sdo_puts} == {recorded.program_pid}
    answers = [r for r in events if r.kind == s.ANSWER and r.msg is not None
               and r.msg.a == Com.SDO_UP_DOWNLOAD]
    assert answers[0].msg is not None and answers[0].msg.data[8:] == bytes.fromhex("91010f00")
    assert answers[0].pid == recorded.program_pid and len(answers[0].state) == 64
    # step 2 and 3: Task2Parameter's bMode 3 as the warm start found it
    warm = [r for r in events if r.kind == s.DEV_FLAGS and r.after & ~r.before & fl.INIT]
    assert len(warm) == 1 and warm[0].parameter[0] == 3
    # the process data: outputs A0..A7 went out, node 1 echoed them
    outputs = [r.changes["SndPd"] for r in events if r.kind == s.EXCHANGE
               and "SndPd" in r.changes]
    inputs = [r.changes["RcvPd"] for r in events if r.kind == s.EXCHANGE
              and "RcvPd" in r.changes]
    assert outputs == [[(0, bytes(range(0xA0, 0xA8)))]]
    assert inputs[-1] == [(0, bytes(range(0xA0, 0xA8)))]
    assert any(r.kind == s.HOST_FLAGS and r.after & fl.COM for r in events)
    # the frames, as python-can reads a candump log: the SDO upload of 1000h and its answer
    frames = list(can.LogReader(str(recorded.session / s.CAN_LOG)))
    assert any(f.arbitration_id == 0x601 and bytes(f.data[:4]) == bytes.fromhex("40001000")
               for f in frames)
    assert any(f.arbitration_id == 0x581 and bytes(f.data[4:8]) == bytes.fromhex("91010f00")
               for f in frames)


def test_the_session_replays_against_a_fresh_card_with_no_difference(
        recorded: Recording, tmp_path: Path) -> None:
    network = tmp_path / "net.toml"
    network.write_text(NETWORK)
    card = start_card(tmp_path / "card", 0, "--simulate", str(network))
    try:
        done = replay(str(recorded.session), "--dpm-dir", str(card.directory))
    finally:
        card.stop()
    assert done.returncode == 0, done.stdout + done.stderr
    assert "no difference" in done.stdout


def test_another_device_type_shows_the_message_and_the_field(
        recorded: Recording, tmp_path: Path) -> None:
    network = tmp_path / "net.toml"
    network.write_text(CHANGED_NODE_2)
    card = start_card(tmp_path / "card", 0, "--simulate", str(network))
    try:
        done = replay(str(recorded.session), "--dpm-dir", str(card.directory),
                      "--step-timeout", "1")
    finally:
        card.stop()
    assert done.returncode == 1, done.stdout + done.stderr
    assert "answer COM_Node_Diag node 2: usProfileNumber 401 -> 402" in done.stdout
    assert "answer COM_Node_Diag node 2: Nodestatus_1 GUARD_ACTIVE -> PRM_FAULT" in done.stdout
    assert "\n-answer COM_Node_Diag node 2: " in done.stdout  # the diff -u lines


def test_two_recorded_sessions_compare_without_a_card(recorded: Recording,
                                                      tmp_path: Path) -> None:
    same = replay("--diff", str(recorded.session), str(recorded.session))
    assert same.returncode == 0 and "no difference" in same.stdout
    other = tmp_path / "other"
    shutil.copytree(recorded.session, other)
    lines = (other / s.EVENTS).read_text().splitlines()
    for i, line in enumerate(lines):  # the card now refuses the heartbeat time's write
        record = s.decode_record(line)
        if (record.kind == s.ANSWER and record.msg is not None
                and record.msg.a == Com.SDO_UP_DOWNLOAD and record.msg.data[2:4] == b"\x17\x10"
                and record.msg.data[7] == 2):
            record.msg.f = 17
            lines[i] = s.encode_record(record)
            break
    else:
        pytest.fail("no answer to the write of 1017h")
    (other / s.EVENTS).write_text("\n".join(lines) + "\n")
    done = replay("--diff", str(recorded.session), str(other))
    assert done.returncode == 1
    assert "answer COM_SDO_Up_Download node 1: f 0 -> 17" in done.stdout


def test_a_malformed_session_is_refused_with_its_line(recorded: Recording,
                                                      tmp_path: Path) -> None:
    bad = tmp_path / "bad"
    shutil.copytree(recorded.session, bad)
    lines = (bad / s.EVENTS).read_text().splitlines()
    lines[2] = lines[2].replace('"kind":"', '"kind":"x', 1)
    (bad / s.EVENTS).write_text("\n".join(lines) + "\n")
    done = replay("--diff", str(recorded.session), str(bad))
    assert done.returncode == 2
    assert "session.jsonl line 3: unknown kind" in done.stderr
    assert "Traceback" not in done.stderr


def test_a_recording_never_overwrites_a_session(recorded: Recording, tmp_path: Path) -> None:
    done = commands.run([sys.executable, "-m", "cifemu", "firmware", "--dpm-dir",
                         str(tmp_path / "card"), "--record", str(recorded.session)],
                        capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 1
    assert "already holds a session" in done.stderr
    assert not (tmp_path / "card" / "board0.dpm").exists()
