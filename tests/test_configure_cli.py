"""`cifemu configure`, `cifemu firmware --configure`, interface errors and the demo's tidiness."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

from dpm.commands import COM_DOWNLOAD, COM_SHARED_MEMORY
from dpm.errors import CanF
from dpm.image import lock_path
from dpm.message import Message
from dpm.task2 import GlobalBits
from host_api.board import Board
from host_api.liveness import recorded_pid
from host_api.status import read_image, snapshot
from tests import commands
from tests.conftest import ROOT, start_card, wait_until

DEMO = ROOT / "cifemu" / "examples" / "demo.toml"


def cifemu(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "cifemu", *args], capture_output=True,
                        text=True, timeout=60, cwd=ROOT, env=env)


def nd_state(directory: Path, board: int = 0) -> list[int]:
    image = read_image(board, str(directory))
    return snapshot(image)["task2state"]["nd_state"] if image else []


def test_configure_brings_a_hand_started_card_to_data_exchange(tmp_path: Path) -> None:
    card = start_card(tmp_path, 0, "--simulate", str(DEMO))
    try:
        assert nd_state(tmp_path) == []
        out = cifemu("configure", str(DEMO), "--dpm-dir", str(tmp_path))
        assert out.returncode == 0, out.stderr
        assert "configuring: node 4" in out.stdout and "node 4 in data exchange" in out.stdout
        assert nd_state(tmp_path) == [1, 2, 3, 4]
        again = cifemu("configure", str(DEMO), "--dpm-dir", str(tmp_path), "--json")
        result = json.loads(again.stdout)
        assert again.returncode == 0 and result["ok"] is True and result["nd_state"] == [1, 2, 3, 4]
    finally:
        card.stop()


def test_configure_reports_nodes_that_never_come(tmp_path: Path) -> None:
    """The card is configured for node 5, which nobody simulates: Err_Event 34 at node 5."""
    network = tmp_path / "net.toml"
    network.write_text("[[node]]\nid = 1\n[[node]]\nid = 5\n")
    only_one = tmp_path / "sim.toml"
    only_one.write_text("[[node]]\nid = 1\n")
    card = start_card(tmp_path, 0, "--simulate", str(only_one))
    try:
        out = cifemu("configure", str(network), "--dpm-dir", str(tmp_path), "--json",
                     "--wait", "8")
        result = json.loads(out.stdout)
        assert out.returncode == 1
        assert result["missing"] == [5] and result["err_node_adr"] == 5
        assert result["err_event"] == 34 and "no response" in result["err_text"]
    finally:
        card.stop()


def test_configure_does_not_call_a_node_that_refuses_operational_configured(
        tmp_path: Path) -> None:
    """The card sets a node's Nd_state bit once it has started it; only the node's next
    heartbeat says whether it really runs. A node that stays out of OPERATIONAL (as a
    CANopenNode device does while its error register is set) is Err_Event 31 a moment
    later: configure must report that, not a network in data exchange. The consumer time is
    1 s (the node's heartbeat every 0.5 s), not shorter: this test is not about the period,
    and a 200 ms one was missed by a `cifemu sim` starved on a loaded machine (Err_Event 30
    before the 31 looked for, at three pytest-xdist workers)."""
    network = tmp_path / "net.toml"
    network.write_text("[[node]]\nid = 1\nheartbeat_ms = 1000\n"
                       "[node.sim]\nleave_operational_after_s = 0.0\n")
    card = start_card(tmp_path, 0, "--simulate", str(network))
    try:
        out = cifemu("configure", str(network), "--dpm-dir", str(tmp_path), "--json",
                     "--wait", "8")
        result = json.loads(out.stdout)
        assert out.returncode == 1, result
        assert result["ok"] is False
        assert (result["err_node_adr"], result["err_event"]) == (1, 31)
    finally:
        card.stop()


def test_configure_errors_are_one_line_or_one_json_object(tmp_path: Path) -> None:
    out = cifemu("configure", str(DEMO), "--dpm-dir", str(tmp_path))
    assert out.returncode == 1 and "Traceback" not in out.stderr
    assert out.stderr.count("\n") == 1 and "cifemu firmware --board 0" in out.stderr
    as_json = cifemu("configure", str(DEMO), "--dpm-dir", str(tmp_path), "--json")
    error = json.loads(as_json.stdout)["error"]
    assert as_json.returncode == 1 and error["driver_code"] == -34
    bad = tmp_path / "bad.toml"
    bad.write_text("[[node]]\nid = 300\n")
    out = cifemu("configure", str(bad), "--dpm-dir", str(tmp_path))
    assert out.returncode == 1 and "bad.toml" in out.stderr and "Traceback" not in out.stderr


def test_firmware_configure_gives_a_running_network_in_one_command(tmp_path: Path) -> None:
    card = start_card(tmp_path, 0, "--simulate", str(DEMO), "--configure")
    try:
        wait_until(lambda: nd_state(tmp_path) == [1, 2, 3, 4], 20, "four nodes in data exchange")
    finally:
        assert card.stop() == 0


def test_firmware_reports_an_interface_error_in_one_line_and_leaves_no_image(
        tmp_path: Path) -> None:
    for extra in (["--interface", "socketcan", "--channel", "nope", "--exit-on-bus-error"],
                  ["--interface", "socketcan", "--channel", "nope", "--simulate", str(DEMO)],
                  ["--interface", "no-such-interface", "--exit-on-bus-error"]):
        out = cifemu("firmware", "--dpm-dir", str(tmp_path), "--log-level", "WARNING", *extra)
        assert out.returncode == 1, extra
        assert out.stderr.startswith("cifemu firmware: cannot open CAN interface"), out.stderr
        assert out.stderr.count("\n") == 1 and "Traceback" not in out.stderr
        assert not (tmp_path / "board0.dpm").exists()


def test_a_card_whose_interface_cannot_open_stays_up_with_fat(tmp_path: Path) -> None:
    """Seed 4.3 FAT: "no further bus communication is possible" -- a faulty card, not a
    dead one. READY without RUN, FAT in the global bits (also after a warm start), every
    CAN-task command f 200, the RCS and PLC tasks still answer; one log line says why."""
    card = start_card(tmp_path, 0, "--interface", "no-such-interface", "--log-level", "ERROR")
    try:
        with Board(0, tmp_path) as board:
            for _ in range(2):
                diag = board.diagnostics()
                assert diag.bGlobalBits & GlobalBits.FAT and diag.can_state_name == "OFFLINE"
                answer = board.transact(Message(rx=3, tx=16, b=COM_DOWNLOAD,
                                                data=bytes([0, 127, 0, 0, 2]) + bytes(6)))
                assert answer.f == CanF.NOT_CONFIGURED
                shared = board.transact(Message(rx=2, tx=16, b=COM_SHARED_MEMORY,
                                                data=bytes([0, 1, 0, 0, 0, 4, 5, 1])))
                assert shared.f == 0
                board.reset()
    finally:
        assert card.stop() == 0
    log = card.log()
    assert "cannot open CAN interface 'no-such-interface'" in log and "FAT" in log


def test_demo_uses_the_default_directory_refuses_a_busy_board_and_cleans_up(
        tmp_path: Path) -> None:
    images = tmp_path / "cif"
    temp = tmp_path / "tmp"
    temp.mkdir()
    env = {**os.environ, "CIF_DPM_DIR": str(images), "TMPDIR": str(temp)}
    demo = subprocess.Popen([sys.executable, "-m", "cifemu", "demo"], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        wait_until(lambda: nd_state(images) == [1, 2, 3, 4], 30, "the demo's nodes")
        second = cifemu("demo", env=env)
        assert second.returncode == 1 and "already served by process" in second.stderr
        status = cifemu("status", "--json", env=env)  # found without --dpm-dir
        assert status.returncode == 0, status.stderr
    finally:
        demo.send_signal(signal.SIGINT)
        assert commands.wait(demo, 20) == 0
    assert not images.exists()
    assert list(temp.iterdir()) == []


def test_a_refusal_shows_the_msg_f_number_and_text(tmp_path: Path) -> None:
    """A database in the card's flash runs after the warm start that configure begins with,
    and the card refuses the on-line download (seed 5.2.2, msg.f 201 [ours])."""
    network = tmp_path / "net.toml"
    network.write_text("[[node]]\nid = 2\n")
    dbm = tmp_path / "plant.dbm"
    card = start_card(tmp_path)
    try:
        assert cifemu("dbm", "build", str(network), "-o", str(dbm)).returncode == 0
        stored = cifemu("dbm", "download", str(dbm), "--reset", "--dpm-dir", str(tmp_path))
        assert stored.returncode == 0, stored.stderr
        text = cifemu("configure", str(network), "--dpm-dir", str(tmp_path))
        as_json = cifemu("configure", str(network), "--dpm-dir", str(tmp_path), "--json")
    finally:
        card.stop()
    assert text.returncode == 1 and "Traceback" not in text.stderr
    assert "warm start first" in text.stdout
    assert ("msg.f = 201 (a database from flash runs: no on-line download); "
            in text.stderr)
    error = json.loads(as_json.stdout)["error"]
    assert as_json.returncode == 1 and error["msg_f"] == 201


def test_a_description_the_card_would_refuse_never_reaches_it(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[[node]]\nid = 1\n[[node.pdo]]\ndirection = "input"\ncob_id = 0x181\n'
                   'length = 8\ntransmission = 250\n')
    card = start_card(tmp_path)
    try:
        out = cifemu("configure", str(bad), "--dpm-dir", str(tmp_path))
        assert nd_state(tmp_path) == []
        status = json.loads(cifemu("status", "--json", "--dpm-dir", str(tmp_path)).stdout)
    finally:
        card.stop()
    assert out.returncode == 1 and "Traceback" not in out.stderr
    assert "63 (data check: unknown PDO" in out.stderr
    assert status["task2state"]["nd_cfg"] == []


def test_configure_waits_for_a_card_that_is_still_starting(tmp_path: Path) -> None:
    """configure waits for a firmware that holds its lock but is not READY yet (here 1.5 s
    of reset delay). The firmware creates its image before it takes the lock, so the wait
    is for the lock to name its pid: on the image alone, configure ran in between under
    load and rightly found no firmware (status 1, "is `cifemu firmware` running?").

    configure ends its wait at the first Err_Event: a node that answered the card's boot
    later than its 0.5 s SDO time-out, because the machine's load kept the firmware's
    threads (card and nodes in one process) from running, is Err_Event 34 and status 1 (CI
    at load 10; not reproduced in 24 runs at load 10-13, and no race with the reset delay
    in the boot's code). That is configure's answer to a late node, and the card (auto-clear
    off) boots the node again after 1 s: so 34 is taken here, as proof that configure
    reached the card and downloaded, and the four nodes must then reach data exchange."""
    card = subprocess.Popen([sys.executable, "-m", "cifemu", "firmware", "--dpm-dir", str(tmp_path),
                             "--simulate", str(DEMO), "--reset-delay", "1.5",
                             "--log-level", "WARNING"])
    try:
        wait_until(lambda: recorded_pid(lock_path(tmp_path, 0)) == card.pid, 20,
                   "the firmware's pid in its lock")
        out = cifemu("configure", str(DEMO), "--dpm-dir", str(tmp_path))
        if out.returncode != 0:
            assert out.returncode == 1 and "Err_Event 34 at node" in out.stdout, (
                out.stdout + out.stderr)
        wait_until(lambda: nd_state(tmp_path) == [1, 2, 3, 4], 10,
                   "the four nodes in data exchange (a node late under load booted again)")
    finally:
        card.terminate()
        commands.wait(card, 10)


def test_firmware_configure_that_fails_stops_the_card_with_status_1(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[[node]]\nid = 1\n[[node.pdo]]\ndirection = "input"\ncob_id = 0x181\n'
                   'length = 8\ntransmission = 250\n')
    out = commands.run([sys.executable, "-m", "cifemu", "firmware", "--dpm-dir", str(tmp_path),
                        "--simulate", str(DEMO), "--configure", str(bad), "--log-level",
                        "WARNING"], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 1
    assert "63 (data check: unknown PDO" in out.stderr and "the card stops" in out.stderr
    assert "Traceback" not in out.stderr
