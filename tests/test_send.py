"""`cifemu send`: one frame or one NMT command through the card, seen on the bus."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from host_api.status import read_image, snapshot
from tests import commands
from tests.conftest import ROOT, start_card, wait_until

DEMO = ROOT / "cifemu" / "examples" / "demo.toml"


def cifemu(*args: str) -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "cifemu", *args], capture_output=True,
                        text=True, timeout=60, cwd=ROOT)


def nd_state(directory: Path) -> list[int]:
    image = read_image(0, str(directory))
    return snapshot(image)["task2state"]["nd_state"] if image else []


def test_a_frame_and_an_nmt_command_reach_the_bus(tmp_path: Path) -> None:
    card = start_card(tmp_path, 0, "--simulate", str(DEMO), "--configure")
    where = ("--dpm-dir", str(tmp_path))
    log = tmp_path / "trace.log"
    try:
        wait_until(lambda: nd_state(tmp_path) == [1, 2, 3, 4], 30, "the demo network running")
        watching = subprocess.Popen(
            [sys.executable, "-m", "cifemu", "monitor", *where, "--json", "--type", "other",
             "--type", "nmt", "--count", "3", "--duration", "30", "--log", str(log)],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        wait_until(log.exists, 20, "the monitor's log file")
        frame = cifemu("send", "123#DE.AD.BE.EF", *where)
        extended = cifemu("send", "1F334455#R2", *where)
        nmt = cifemu("send", "--nmt", "stop", "4", *where)
        out, err = watching.communicate(timeout=60)
    finally:
        card.stop()
    assert frame.returncode == 0, frame.stderr
    assert frame.stdout == "board 0: sent 123#DE.AD.BE.EF\n"
    assert extended.returncode == 0, extended.stderr
    assert nmt.returncode == 0 and nmt.stdout == "board 0: sent NMT stop to node 4\n"
    seen = [json.loads(line) for line in out.splitlines()]
    assert [(r["can_id"], r["extended"], r["remote"], r["dlc"], r["data"], r["direction"])
            for r in seen] == [(0x123, False, False, 4, "deadbeef", "tx"),
                               (0x1F334455, True, True, 2, "", "tx"),
                               (0x000, False, False, 2, "0204", "tx")], err


def test_a_malformed_frame_or_an_idle_card_says_what_to_do(tmp_path: Path) -> None:
    bad = cifemu("send", "1234#00", "--dpm-dir", str(tmp_path))
    assert bad.returncode == 2 and "3-digit (11-bit) or 8-digit (29-bit)" in bad.stderr
    card = start_card(tmp_path)
    try:
        idle = cifemu("send", "--nmt", "start", "0", "--dpm-dir", str(tmp_path))
    finally:
        card.stop()
    assert idle.returncode == 1 and "Traceback" not in idle.stderr
    assert "msg.f = 200 (DEVICE is not configured)" in idle.stderr
    assert f"`cifemu configure NETWORK.toml --dpm-dir {tmp_path}`" in idle.stderr


def test_help_of_send_reset_and_status_loads_neither_numpy_nor_the_driver() -> None:
    """Start-up: what parsing needs, no more (numpy alone costs 0.1 s of CPU)."""
    probe = ("import sys\nfrom cifemu.cli import main\n"
             "for command in ('send', 'reset', 'status'):\n"
             "    try:\n        main([command, '--help'])\n    except SystemExit:\n        pass\n"
             "heavy = {'numpy', 'host_api.driver', 'host_api.board', 'importlib.metadata', "
             "'rich'}\nprint(sorted(heavy & set(sys.modules)))\n")
    out = commands.run([sys.executable, "-c", probe], capture_output=True, text=True,
                       timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[-1] == "[]"
