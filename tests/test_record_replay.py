"""Record and replay (issue 25 items 1 and 2): a session recorded from the seed's 7.2
procedure (tests/c/operative.c, a real C program on libcif against a real firmware with
simulated nodes) replays against a fresh card with no difference; against a card whose
node 2 reports another device type, the diff names the message and the field.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import can
import pytest

from cifemu import libcif
from dbm_tools.builder import build_dbm
from dbm_tools.container import save_dbm
from dbm_tools.network import parse_network
from dpm import flags as fl
from dpm import session as s
from dpm.commands import Com
from dpm.message import Message
from tests.conftest import start_card
from tests.test_libcif_c import C_TESTS, NETWORK, compile_program

pytestmark = pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                                reason="no C compiler")

CHANGED_NODE_2 = NETWORK + "\n[node.sim]\ndevice_type = 0x000F0192\n"
"""Node 2 (the last [[node]]) reports profile 402 instead of the expected 401."""


@dataclass(frozen=True)
class Recording:
    session: Path
    program_pid: int


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Recording:
    """operative.c run once against a card started with --record."""
    libcif.build("all")
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
    return subprocess.run([sys.executable, "-m", "cifemu", "replay", *args],
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
    done = subprocess.run([sys.executable, "-m", "firmware", "--dpm-dir", str(tmp_path / "card"),
                           "--record", str(recorded.session)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 1
    assert "already holds a session" in done.stderr
    assert not (tmp_path / "card" / "board0.dpm").exists()


# --- the codec, without a card ------------------------------------------------------------

ROUND_TRIP = [
    s.Record(s.PUT, 1.5, 1e9, 4242, msg=Message(3, 16, 74, bytes(8), nr=7)),
    s.Record(s.ANSWER, 1.6, 1e9, None, msg=Message(16, 3, 0, b"\x01", nr=7, a=74, f=3),
             state=bytes(range(64))),
    s.Record(s.HOST_FLAGS, 1.7, 1e9, before=0x80, after=0x84),
    s.Record(s.DEV_FLAGS, 1.8, 1e9, before=0, after=fl.INIT, parameter=b"\x03" + bytes(47)),
    s.Record(s.EXCHANGE, 1.9, 1e9, changes={"SndPd": [(0, b"\xa0\xa1")], "RcvPd": [(3, b"\x01")]},
             state=bytes(64)),
]


@pytest.mark.parametrize("record", ROUND_TRIP, ids=[r.kind for r in ROUND_TRIP])
def test_every_kind_of_record_reads_back_as_written(record: s.Record) -> None:
    line = s.encode_record(record)
    assert json.loads(line)["kind"] == record.kind  # plain JSON, as docs/recording.md says
    assert s.decode_record(line) == record


@pytest.mark.parametrize(("line", "error"), [
    ('{"kind":"put","t":1,"wall":1,"pid":null,"msg":{"rx":3,"tx":16,"ln":2,"nr":0,"a":0,'
     '"f":0,"b":74,"e":0,"data":"00"}}', "msg.ln is not the length"),
    ('{"kind":"put","t":1,"wall":1,"pid":null,"msg":{"rx":300,"tx":16,"ln":0,"nr":0,"a":0,'
     '"f":0,"b":74,"e":0,"data":""}}', "'rx' is not an integer 0..255"),
    ('{"kind":"host_flags","t":1,"wall":1,"pid":true,"before":0,"after":1}', "not a process id"),
    ('{"kind":"host_flags","t":"x","wall":1,"pid":null,"before":0,"after":1}', "'t' is not"),
    ('{"kind":"exchange","t":1,"wall":1,"pid":null,"changes":{"PcMbx":[]}}', "the areas"),
    ('{"kind":"exchange","t":1,"wall":1,"pid":null,"changes":{"SndPd":[[0,"zz"]]}}',
     "not [offset, hex]"),
    ("[1, 2]", "not a JSON object"),
    ("{", "not JSON"),
])
def test_a_malformed_record_is_refused_with_the_reason(line: str, error: str) -> None:
    with pytest.raises(s.SessionError, match=re.escape(error)):
        s.decode_record(line)


def test_changed_runs_are_the_bytes_that_differ() -> None:
    old = bytes(200)
    new = bytearray(old)
    new[0:2] = b"\x01\x02"  # at the start
    new[63:66] = b"\x03\x04\x05"  # across a comparison chunk's edge
    new[199] = 6  # at the end
    assert s.changed_runs(old, bytes(new)) == [(0, b"\x01\x02"), (63, b"\x03\x04\x05"),
                                               (199, b"\x06")]
    assert s.changed_runs(old, old) == []
    image = bytearray(old)
    s.apply_runs(image, s.changed_runs(old, bytes(new)))
    assert image == new


def test_the_ledger_names_the_sender_of_a_message() -> None:
    ledger = b"111 9 6 74 3 16 0 5\n222 8 7 74 3 16 0 6\n"
    assert s.ledger_pid(ledger, Message(3, 16, 74, nr=7)) == 222
    assert s.ledger_pid(ledger, Message(3, 16, 74, nr=8)) is None
    assert s.ledger_pid(b"garbage\n", Message(3, 16, 74, nr=7)) is None
