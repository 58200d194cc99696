"""cifemu record (issue 25 item 1): a recording attached to a card that runs already.

A real firmware, a real host process driving mailbox messages and process data through
host_api, and ``cifemu record`` attached meanwhile: the session holds what that host did
with its pid, and replays against a fresh card with no difference. Attaching twice, to no
card, or into a session that exists fails in one line and leaves nothing behind; a card
that stops ends the recording complete; a detached card runs no writer any more.
"""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
from pathlib import Path

import can

from dpm import flags as fl
from dpm import session as s
from dpm.commands import COM_SHARED_MEMORY
from dpm.message import Task
from dpm.tap import TapSubscriber, decode_frame
from dpm.transcript import transcript
from tests import commands
from tests.conftest import Card, LoadDeadline, start_card, wait_until

HOST = """
import sys
from host_api.board import Board, CifError
from dpm.commands import COM_SHARED_MEMORY
from dpm.message import Message, Task, Tdt, TelegramHeader, Tfc

READ = TelegramHeader(data_area=1, data_cnt=8, data_type=Tdt.UINT8, function=Tfc.READ).encode()
with Board(0, sys.argv[1]) as board:
    for nr in range(1, 4):
        answer = board.transact(Message(rx=Task.PLC, tx=Task.USER, b=COM_SHARED_MEMORY, nr=nr,
                                        data=READ))
        assert answer.f == 0 and answer.nr == nr, answer
    try:  # no network: the card exchanges, without COM
        board.exchange_io(b"\\x11\\x22\\x33", send_offset=4, receive_size=8)
    except CifError as exc:
        assert exc.name == "DRV_DEV_NO_COM_FLAG", exc
print("host done")
"""
"""Three COM_Shared_Memory reads of the receive area, then one exchange of 3 output bytes."""

WAIT_S = 60.0


def record(directory: Path, session: Path, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "cifemu", "record", "--dpm-dir",
                             str(directory), "-o", str(session), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def attached(recorder: subprocess.Popen[str]) -> None:
    """Return once ``cifemu record`` says it records (its first line)."""
    assert recorder.stdout is not None
    line = recorder.stdout.readline()
    assert line.startswith("recording board 0 into "), line + (
        recorder.stderr.read() if recorder.stderr else "")


def finish(recorder: subprocess.Popen[str]) -> tuple[int, str, str]:
    """SIGINT, as Ctrl-C; the exit status, the rest of stdout and stderr."""
    recorder.send_signal(signal.SIGINT)
    out, err = commands.finish(recorder, WAIT_S)
    return recorder.returncode, out, err


def run_host(card: Card) -> int:
    """The host program's pid, once it ran to its end."""
    host = subprocess.Popen([sys.executable, "-c", HOST, str(card.directory)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out, _ = commands.finish(host, WAIT_S)
    assert host.returncode == 0 and "host done" in out, out
    return host.pid


def writers_of(pid: int) -> list[int]:
    """The session writers the firmware ``pid`` runs (firmware.session_writer children)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            cmdline = (stat.parent / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid and b"firmware.session_writer" in cmdline:
            found.append(int(stat.parent.name))
    return found


def test_an_attached_recording_holds_the_hosts_session_and_replays(tmp_path: Path) -> None:
    card = start_card(tmp_path / "card")
    session = tmp_path / "session"
    try:
        recorder = record(card.directory, session)
        attached(recorder)
        wait_until(lambda: writers_of(card.proc.pid), WAIT_S, "a session writer after the attach")
        host_pid = run_host(card)
        code, out, err = finish(recorder)
        assert code == 0, err
        assert f"events and 0 frames recorded into {session}" in out
        # detached: the card runs no writer any more, its hooks are gone with it
        assert writers_of(card.proc.pid) == []
    finally:
        assert card.stop() == 0
    meta = s.decode_meta((session / s.META).read_text())
    assert meta["attached_by"] == recorder.pid and meta["firmware_pid"] == card.proc.pid
    events = s.decode_events((session / s.EVENTS).read_text())
    puts = [r for r in events if r.kind == s.PUT]
    answers = [r for r in events if r.kind == s.ANSWER]
    assert [(r.msg.rx, r.msg.b, r.msg.nr) for r in puts if r.msg] == [
        (Task.PLC, COM_SHARED_MEMORY, nr) for nr in (1, 2, 3)]
    assert [r.msg.a for r in answers if r.msg] == [COM_SHARED_MEMORY] * 3
    assert {r.pid for r in puts + answers} == {host_pid}
    assert [r.changes["SndPd"] for r in events if r.kind == s.EXCHANGE
            and "SndPd" in r.changes] == [[(4, b"\x11\x22\x33")]]
    # each HostFlags toggle in its place, though the card queues it with its message or
    # exchange: DEVACK before the put, HOSTCOM after the answer, PDACK before the exchange
    toggled = {r.before ^ r.after for r in events if r.kind == s.HOST_FLAGS}
    for number, event in enumerate(events):
        if event.kind in (s.PUT, s.EXCHANGE):
            flags = events[number - 1]
            assert number > 0 and flags.kind == s.HOST_FLAGS and flags.t == event.t
            assert flags.before ^ flags.after == (fl.DEVACK if event.kind == s.PUT
                                                  else fl.PDACK)
        if event.kind == s.ANSWER:
            flags = events[number + 1]
            assert flags.kind == s.HOST_FLAGS and flags.t == event.t
            assert flags.before ^ flags.after == fl.HOSTCOM
    assert {fl.DEVACK, fl.HOSTCOM, fl.PDACK} <= toggled
    assert all(a.t <= b.t for a, b in itertools.pairwise(events))  # as the card saw them
    assert list(can.LogReader(str(session / s.CAN_LOG))) == []  # no bus traffic: no frames
    fresh = start_card(tmp_path / "fresh")
    try:
        done = commands.run([sys.executable, "-m", "cifemu", "replay", str(session),
                             "--dpm-dir", str(fresh.directory)],
                            capture_output=True, text=True, timeout=WAIT_S, check=False)
    finally:
        fresh.stop()
    assert done.returncode == 0, done.stdout + done.stderr
    assert "no difference (9 steps)" in done.stdout


def test_a_second_recording_is_refused_and_the_first_goes_on(tmp_path: Path) -> None:
    card = start_card(tmp_path / "card")
    try:
        first = record(card.directory, tmp_path / "first")
        attached(first)
        second = record(card.directory, tmp_path / "second")
        out, err = commands.finish(second, WAIT_S)
        assert second.returncode == 1 and out == ""
        assert err == (f"cifemu record: board 0 refused the recording: it is being recorded "
                       f"already (attached by pid {first.pid}); end that recording first\n")
        assert not (tmp_path / "second").exists()  # a refusal leaves nothing behind
        run_host(card)
        code, out, err = finish(first)
        assert code == 0, err
        # the socket serves the next recording once the first has ended
        third = record(card.directory, tmp_path / "third", "--seconds", "0.5")
        out, err = commands.finish(third, WAIT_S)
        assert third.returncode == 0, err
    finally:
        assert card.stop() == 0
    assert len([r for r in s.decode_events((tmp_path / "first" / s.EVENTS).read_text())
                if r.kind == s.PUT]) == 3


def test_no_card_and_a_session_that_exists_are_one_line(tmp_path: Path) -> None:
    nobody = record(tmp_path / "images", tmp_path / "s")
    out, err = commands.finish(nobody, WAIT_S)
    assert nobody.returncode == 1
    assert err == (f"cifemu record: no card is running as board 0 in {tmp_path / 'images'} "
                   "(no record socket board0.record there)\n")
    assert not (tmp_path / "s").exists()
    card = start_card(tmp_path / "card")
    try:
        taken = tmp_path / "taken"
        taken.mkdir()
        (taken / s.EVENTS).write_text("mine\n")
        refused = record(card.directory, taken)
        out, err = commands.finish(refused, WAIT_S)
        assert refused.returncode == 1 and out == ""
        assert err == (f"cifemu record: {taken} already holds a session; a recording never "
                       "overwrites one\n")
        assert (taken / s.EVENTS).read_text() == "mine\n" and sorted(os.listdir(taken)) == [
            s.EVENTS]
        a_file = tmp_path / "a-file"
        a_file.write_text("")
        bad = record(card.directory, a_file)
        out, err = commands.finish(bad, WAIT_S)
        assert bad.returncode == 1 and out == ""
        assert err.startswith(f"cifemu record: cannot record into {a_file}: ")
        assert err.count("\n") == 1 and "Traceback" not in err
    finally:
        assert card.stop() == 0


def test_a_card_that_stops_ends_the_recording_complete(tmp_path: Path) -> None:
    card = start_card(tmp_path / "card")
    session = tmp_path / "session"
    try:
        recorder = record(card.directory, session)
        attached(recorder)
        run_host(card)
    finally:
        assert card.stop() == 0
    out, err = commands.finish(recorder, WAIT_S)
    assert recorder.returncode == 0, err
    assert "recorded into" in out and out.rstrip().endswith("; the card stopped")
    events = s.decode_events((session / s.EVENTS).read_text())
    assert len([r for r in events if r.kind == s.ANSWER]) == 3
    # the card's last word: READY dropped at its power-off
    assert events[-1].kind == s.HOST_FLAGS and events[-1].after == 0


def heard_heartbeat(card: Card) -> None:
    """Return once the card's frame tap (dpm.tap) showed a heartbeat of node 1."""
    tap = TapSubscriber(card.path)
    try:
        deadline = LoadDeadline(WAIT_S)
        while (left := deadline.left()) > 0:
            batch = tap.recv(timeout=min(left, 1.0))
            if batch is not None and any(decode_frame(frame)[0].arbitration_id == 0x701
                                         for frame in batch.frames):
                return
        raise AssertionError("no heartbeat of node 1 on the card's frame tap")
    finally:
        tap.close()


def test_frames_of_an_attached_recording_are_a_candump_log(tmp_path: Path) -> None:
    network = tmp_path / "net.toml"
    network.write_text('[[node]]\nid = 1\nname = "io"\n')
    card = start_card(tmp_path / "card", 0, "--simulate", str(network), "--configure")
    session = tmp_path / "session"
    try:
        recorder = record(card.directory, session)
        attached(recorder)
        sender = subprocess.Popen([sys.executable, "-m", "cifemu", "send", "--dpm-dir",
                                   str(card.directory), "123#DEADBEEF"],
                                  stderr=subprocess.PIPE, text=True)
        _, sent_err = commands.finish(sender, WAIT_S)
        assert sender.returncode == 0, sent_err
        heard_heartbeat(card)  # after the attach: one is in the recording
        code, out, err = finish(recorder)
        assert code == 0, err
    finally:
        card.stop()
    frames = list(can.LogReader(str(session / s.CAN_LOG)))
    assert [bytes(f.data) for f in frames if f.arbitration_id == 0x123 and not f.is_rx] == [
        bytes.fromhex("deadbeef")]  # sent by the card: T in candump's log
    assert any(f.arbitration_id == 0x701 and f.is_rx for f in frames)  # received: R
    assert f"and {len(frames)} frames recorded" in out
    puts = [r for r in s.decode_events((session / s.EVENTS).read_text()) if r.kind == s.PUT]
    assert [r.pid for r in puts] == [sender.pid]  # COM_Send_CANMsg_Transparent, its sender


USER_TESTS = '''
import pytest
from host_api.board import Board
from dpm.commands import COM_SHARED_MEMORY
from dpm.message import Message, Task, Tdt, TelegramHeader, Tfc

ONE_NODE = {"node": [{"id": 1}]}
READ = TelegramHeader(data_area=1, data_cnt=8, data_type=Tdt.UINT8, function=Tfc.READ).encode()


def talk(board_number):
    with Board(board_number) as board:
        board.transact(Message(rx=Task.PLC, tx=Task.USER, b=COM_SHARED_MEMORY, nr=7, data=READ))
        board.exchange_io(b"\\x5a" * 4, receive_size=4)


@pytest.mark.cif_network(ONE_NODE)
def test_the_users_mistake(cif_card):
    cif_card.wait_until_operating()
    talk(cif_card.board)
    assert False, "the user's mistake"


@pytest.mark.cif_network(ONE_NODE)
def test_passes_and_leaves_no_session(cif_card):
    cif_card.wait_until_operating()
    talk(cif_card.board)


@pytest.mark.cif_network(ONE_NODE)
@pytest.mark.cif_record("kept")
def test_passes_and_keeps_its_session(cif_card):
    cif_card.wait_until_operating()
    talk(cif_card.board)
    cif_card.restart()
    cif_card.wait_until_operating()
    assert [r.msg.nr for r in cif_card.records() if r.kind == "put"] == [7]
    # Its answer, not its exchange: a card in the uncontrolled handshake sees the outputs
    # at its next look, which the restart may come before.
    assert any(line.startswith("answer COM_Shared_Memory") for line in cif_card.transcript())
'''
"""A user's suite: a host talks to its card (one COM_Shared_Memory read, one exchange);
one test fails, one passes, one keeps its session across a restart of its card."""


def test_a_failing_tests_report_has_its_cards_transcript(tmp_path: Path) -> None:
    project = tmp_path / "project"
    project.mkdir()
    (project / "test_user.py").write_text(USER_TESTS)
    env = {**os.environ, "PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1"}  # -p cifemu loads it
    done = commands.run([sys.executable, "-m", "pytest", "-p", "cifemu", "-p",
                         "no:cacheprovider", "--basetemp", str(tmp_path / "base"),
                         "--strict-markers", "-q"], cwd=project, env=env,
                        capture_output=True, text=True, timeout=600, check=False)
    out = done.stdout
    assert done.returncode == 1, out + done.stderr
    assert "1 failed, 2 passed" in out, out[out.find("_ test_passes_and_keeps"):][:3000]
    report = out[out.index("_ test_the_users_mistake _"):out.index("short test summary info")]
    section = report[report.index("- cifemu board 0: transcript -"):]
    session = tmp_path / "base" / "test_the_users_mistake0" / "cifemu" / "session"
    assert f"steps recorded in {session} (cifemu replay SESSION" in section
    assert ("put COM_Shared_Memory node 0: f 0 e 0 area 1 adr 0x0 idx 0 cnt 8 type 5 "
            "function 1 d -") in section
    assert "answer COM_Shared_Memory node 0: f 0 e 0 area 1" in section
    assert "HostFlags: levels COM|RUN|READY" in section
    assert "exchange: SndPd[0] 5a5a5a5a" in section
    assert (session / s.EVENTS).exists()  # a failed test's session stays, to be replayed
    # a passed test's recording is gone; a marked one's stays where the marker says
    assert not (tmp_path / "base" / "test_passes_and_leaves_no_s0" / "cifemu" / "session"
                ).exists()
    kept = [s.decode_events((project / name / s.EVENTS).read_text())
            for name in ("kept", "kept-2")]
    assert [r.msg.nr for r in kept[0] if r.kind == s.PUT and r.msg] == [7]
    # the restarted card configured itself, which is no host's doing, before records() ended
    # the recording: nothing to show
    assert transcript(kept[1]) == []
