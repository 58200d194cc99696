"""`cifemu monitor` against real firmware processes: the tap, shm, filters, log files."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import IO

from tests import commands
from tests.conftest import ROOT, ended, start_card, wait_until

DEMO = ROOT / "cifemu" / "examples" / "demo.toml"


def monitor(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "cifemu", "monitor", *args], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def pipes(proc: subprocess.Popen[str]) -> tuple[IO[str], IO[str]]:
    """A ``monitor``'s stdout and stderr (both pipes)."""
    assert proc.stdout is not None and proc.stderr is not None
    return proc.stdout, proc.stderr


def records(proc: subprocess.Popen[str]) -> list[dict[str, object]]:
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    return [json.loads(line) for line in out.splitlines()]


def test_the_tap_shows_a_configuration_decoded_on_the_virtual_bus(tmp_path: Path) -> None:
    """The monitor runs until the frames the test looks for came (then Ctrl-C), not for a
    fixed window: a loaded machine's configuration outlasted a 6 s one."""
    card = start_card(tmp_path, 0, "--simulate", str(DEMO))
    log = tmp_path / "trace.log"
    try:
        watching = monitor("--dpm-dir", str(tmp_path), "--network", str(DEMO), "--json",
                           "--duration", "120", "--log", str(log))
        out, err = pipes(watching)
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(iter(out.readline,
                                                                    "")), daemon=True)
        reader.start()
        wait_until(lambda: (tmp_path / "trace.log").exists(), 20, "the monitor's log file")
        configured = commands.run([sys.executable, "-m", "cifemu", "configure", str(DEMO),
                                   "--dpm-dir", str(tmp_path)], capture_output=True,
                                  timeout=60, cwd=ROOT)
        assert configured.returncode == 0
        wanted = ('"NMT start: node 4"', '"guarding request node 3"', '"SYNC"',
                  "SDO upload response node 3 1000h/00h")
        wait_until(lambda: all(any(w in line for line in list(lines)) for w in wanted), 30,
                   "the start, guarding and SYNC in the monitor's output")
        watching.send_signal(signal.SIGINT)
        commands.wait(watching, 30)
        assert ended(reader, 30), "the monitor's output was not read to its end"
        assert watching.returncode == 0, err.read()
        seen = [json.loads(line) for line in lines]
    finally:
        card.stop()
    texts = {str(r["text"]) for r in seen}
    assert "NMT reset node: node 1" in texts and "NMT start: node 4" in texts, sorted(texts)
    assert "boot-up node 2" in texts
    assert any(t.startswith("SDO upload request node 3 1000h/00h") for t in texts)
    assert any(t.startswith("SDO upload response node 3 1000h/00h") for t in texts)
    assert "guarding request node 3" in texts and "SYNC" in texts
    nmt = next(r for r in seen if r["kind"] == "nmt")
    boot = next(r for r in seen if r["text"] == "boot-up node 2")
    assert nmt["direction"] == "tx" and boot["direction"] == "rx"  # the card's side
    assert {r["channel"] for r in seen} == {"cifemu"}
    channels = {line.split()[1] for line in log.read_text().splitlines() if line.startswith("(")}
    assert channels == {"cifemu"}  # sent and received frames: one channel name


def test_filters_by_node_and_type_and_shows_the_emcy_meaning(tmp_path: Path) -> None:
    """Node 4 sends its EMCY burst once, 5 s after its start: the monitor listens before the
    network is configured (its first line, node 4's heartbeat, says so). Started after the
    card's own configuration, the monitor came up after the burst on a loaded machine (load
    24: no EMCY in its 20 s)."""
    card = start_card(tmp_path, 0, "--simulate", str(DEMO))
    try:
        watching = monitor("--dpm-dir", str(tmp_path), "--json", "--node", "4", "--type", "emcy",
                           "--type", "heartbeat", "--duration", "120")
        out, err = pipes(watching)
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(iter(out.readline,
                                                                   "")), daemon=True)
        reader.start()
        wait_until(lambda: lines, 30, "node 4's first heartbeat in the monitor")
        configured = commands.run([sys.executable, "-m", "cifemu", "configure", str(DEMO),
                                   "--dpm-dir", str(tmp_path)], capture_output=True,
                                  timeout=60, cwd=ROOT)
        assert configured.returncode == 0, configured.stderr
        wait_until(lambda: sum('"emcy"' in line for line in list(lines)) >= 2, 30,
                   "two of node 4's EMCYs in the monitor")
        watching.send_signal(signal.SIGINT)
        commands.wait(watching, 30)
        assert ended(reader, 30), "the monitor's output was not read to its end"
        assert watching.returncode == 0, err.read()
        guarding = records(monitor("--dpm-dir", str(tmp_path), "--json", "--node", "3",
                                   "--count", "4", "--duration", "10"))
    finally:
        card.stop()
    seen = [json.loads(line) for line in lines]
    assert {r["node"] for r in seen} == {4}
    assert {r["kind"] for r in seen} == {"heartbeat", "emcy"}
    emcys = [r for r in seen if r["kind"] == "emcy"]
    assert "4210h Temperature: device temperature" in str(emcys[0]["text"])
    assert {r["node"] for r in guarding} == {3}
    assert {r["kind"] for r in guarding} <= {"guarding", "heartbeat", "sdo", "pdo"}


def test_monitor_on_shm_sees_the_card_and_writes_asc(tmp_path: Path) -> None:
    channel = f"opmon{os.getpid()}"
    card = start_card(tmp_path, 0, "--interface", "shm", "--channel", channel, "--simulate",
                      str(DEMO), "--configure")
    asc = tmp_path / "bus.asc"
    try:
        seen = records(monitor("--interface", "shm", "--channel", channel, "--json",
                               "--type", "sync", "--count", "5", "--duration", "20",
                               "--log", str(asc)))
    finally:
        card.stop()
    assert [r["kind"] for r in seen] == ["sync"] * 5
    assert asc.read_text().count(" 80 ") >= 5


def test_monitor_errors_are_one_line(tmp_path: Path) -> None:
    for args in (["--dpm-dir", str(tmp_path)],
                 ["--interface", "socketcan", "--channel", "nope"],
                 ["--network", str(tmp_path / "missing.toml")]):
        done = commands.run([sys.executable, "-m", "cifemu", "monitor", *args],
                            capture_output=True, text=True, timeout=60, cwd=ROOT)
        assert done.returncode == 1, args
        assert done.stderr.startswith("cifemu monitor: ") and done.stderr.count("\n") == 1
    as_json = commands.run([sys.executable, "-m", "cifemu", "monitor", "--json", "--dpm-dir",
                            str(tmp_path)], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert as_json.returncode == 1 and "no firmware" in json.loads(as_json.stdout)["error"][
        "message"]


def test_the_cards_own_trace_labels_sent_and_received_frames_alike(tmp_path: Path) -> None:
    trace = tmp_path / "card.log"
    card = start_card(tmp_path, 0, "--simulate", str(DEMO), "--configure", "--trace", str(trace))
    try:
        wait_until(lambda: " 701#" in trace.read_text() if trace.exists() else False, 20,
                   "a received heartbeat in the trace")
    finally:
        card.stop()
    lines = [line.split() for line in trace.read_text().splitlines() if line.startswith("(")]
    sent = {fields[1] for fields in lines if fields[2].startswith("000#")}  # NMT: the card's
    received = {fields[1] for fields in lines if fields[2].startswith("701#")}
    assert sent == received == {"cifemu"}
