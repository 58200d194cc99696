"""Output off a terminal, and stale state marked stale (issue 24 item 9)."""

from __future__ import annotations

import datetime
import os
import re
import subprocess
import sys
from pathlib import Path

from dbm_tools.container import TOOL_DATE
from host_api.status import read_image, snapshot
from tests import commands
from tests.conftest import ROOT, start_card, wait_until

DEMO = ROOT / "cifemu" / "examples" / "demo.toml"


def cifemu(*args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}  # as a plain pipe has it
    return commands.run([sys.executable, "-m", "cifemu", *args], capture_output=True,
                        text=True, timeout=90, cwd=ROOT, env=env)


def nd_state(directory: Path) -> list[int]:
    image = read_image(0, str(directory))
    return snapshot(image)["task2state"]["nd_state"] if image else []


def test_top_once_in_a_pipe_cuts_nothing_and_a_stopped_card_is_stale(tmp_path: Path) -> None:
    card = start_card(tmp_path, 0, "--simulate", str(DEMO), "--configure")
    where = ("--dpm-dir", str(tmp_path), "--network", str(DEMO))
    try:
        wait_until(lambda: nd_state(tmp_path) == [1, 2, 3, 4], 30, "the demo network running")
        live = cifemu("top", "--once", "--sample", "1.5", *where)
        trace = cifemu("monitor", "--dpm-dir", str(tmp_path), "-t", "z", "--count", "3")
    finally:
        card.stop()
    stopped = cifemu("top", "--once", "--sample", "0.1", *where)
    assert live.returncode == 0, live.stderr
    assert "…" not in live.stdout and "OPERATIONAL" in live.stdout
    assert "stale" not in live.stdout
    assert stopped.returncode == 3
    assert "firmware not running (it stopped cleanly)" in stopped.stdout
    assert "None" not in stopped.stdout
    assert "stale: no firmware serves this image" in stopped.stdout
    assert re.search(r"CAN_state \w+ \(stale\)", stopped.stdout), stopped.stdout
    stamps = [line.split()[0] for line in trace.stdout.splitlines()]
    assert trace.returncode == 0 and len(stamps) == 3, trace.stderr
    assert stamps[0] == "(000.000000)"
    assert all(re.fullmatch(r"\(\d{3}\.\d{6}\)", s) for s in stamps) and stamps == sorted(stamps)


def test_candump_time_stamp_forms() -> None:
    from host_api.monitor.timestamps import Stamps  # here: the other tests run without it

    when = 1345212884.318850
    absolute, delta, zero, dated = (Stamps(form) for form in "adzA")
    assert absolute.stamp(when) == "(1345212884.318850)"
    assert [delta.stamp(t) for t in (when, when + 0.5, when + 0.75)] == [
        "(000.000000)", "(000.500000)", "(000.250000)"]
    assert [zero.stamp(t) for t in (when, when + 0.5, when + 12.75)] == [
        "(000.000000)", "(000.500000)", "(012.750000)"]
    local = datetime.datetime.fromtimestamp(when).strftime("%Y-%m-%d %H:%M:%S")
    assert dated.stamp(when) == f"({local}.318850)"


def test_dbm_show_heads_a_file_with_its_own_date(tmp_path: Path) -> None:
    dbm = tmp_path / "plant.dbm"
    assert cifemu("dbm", "build", str(DEMO), "-o", str(dbm), "--name", "Plant").returncode == 0
    out = cifemu("dbm", "show", str(dbm))
    text = " ".join(out.stdout.split())  # the title may wrap
    today = datetime.date.today().strftime("%d.%m.%Y")
    assert f"project 'Plant' of {today}, data area" in text, out.stdout
    assert TOOL_DATE not in text
