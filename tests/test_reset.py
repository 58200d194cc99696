"""`cifemu reset` (SyCon's "Reset device"), and refusals that say what to do next."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from cifemu.cli import COMMANDS, build_parser
from dpm import errors
from tests import commands
from tests.conftest import ROOT, start_card


def cifemu(*args: str) -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "cifemu", *args], capture_output=True,
                        text=True, timeout=60, cwd=ROOT)


def test_reset_starts_the_stored_database_and_configure_says_how_to_replace_it(
        tmp_path: Path) -> None:
    """A database stored without --reset runs after `cifemu reset`; configure then refuses
    (f 201) and names the way through, and that way works as printed."""
    network = tmp_path / "net.toml"
    network.write_text("[[node]]\nid = 2\n")
    dbm = tmp_path / "plant.dbm"
    where = ("--dpm-dir", str(tmp_path))
    card = start_card(tmp_path)
    try:
        assert cifemu("dbm", "build", str(network), "-o", str(dbm)).returncode == 0
        assert cifemu("dbm", "download", str(dbm), *where).returncode == 0
        reset = cifemu("reset", *where)
        refused = cifemu("configure", str(network), "--wait", "0", *where)
        deleted = cifemu("dbm", "delete", *where)
        configured = cifemu("configure", str(network), "--wait", "0", *where)
        warm = cifemu("reset", "--warm", "--json", *where)
    finally:
        card.stop()
    assert reset.returncode == 0, reset.stderr
    lines = reset.stdout.splitlines()
    assert lines[0] == "board 0: cold start (DevReset COLDSTART)"
    assert "board 0: READY" in lines
    assert lines[-1].startswith("board 0: cold start done, READY RUN")
    assert lines[-1].endswith("the database from the flash runs")
    assert refused.returncode == 1 and "msg.f = 201" in refused.stderr
    assert f"`cifemu dbm delete --dpm-dir {tmp_path}`" in refused.stderr
    assert "[ours]" not in refused.stderr
    assert deleted.returncode == 0, deleted.stderr
    assert configured.returncode == 0, configured.stderr
    outcome = json.loads(warm.stdout)
    assert outcome["start"] == "warm" and outcome["database_stored"] is False
    assert outcome["flags"][0] == "READY" and "RUN" not in outcome["flags"]


def test_reset_without_a_card_says_which_firmware_to_start(tmp_path: Path) -> None:
    out = cifemu("reset", "--board", "2", "--dpm-dir", str(tmp_path))
    assert out.returncode == 1 and "Traceback" not in out.stderr
    assert f"`cifemu firmware --board 2 --dpm-dir {tmp_path}` running?" in out.stderr


def test_no_help_text_carries_the_projects_marker() -> None:
    """[ours] marks the project's documents; a user's --help never shows it."""
    helps: dict[str, str] = {}

    def walk(parser: argparse.ArgumentParser, name: str) -> None:
        helps[name] = parser.format_help()
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for word, child in action.choices.items():
                    walk(child, f"{name} {word}".strip())

    walk(build_parser(), "")
    assert {c.name for c in COMMANDS} < set(helps) and "dbm download" in helps
    assert [name for name, text in helps.items() if "[ours]" in text] == []


def test_no_error_text_carries_the_projects_marker() -> None:
    tables = [errors.RcsF, errors.PlcF, errors.CanF, errors.DeviceEvent, errors.NodeEvent]
    texts = [member.text for table in tables for member in table]
    texts += list(errors.ERROR_CONTROL_TEXT.values())
    assert texts and not [text for text in texts if "[ours]" in text]


STOP_STORM = """
import signal, sys, time
from firmware.device import Device
device = Device(0, sys.argv[1], flash_dir=sys.argv[1] + "/flash")
signal.signal(signal.SIGALRM, lambda signum, frame: device.stop())
signal.setitimer(signal.ITIMER_REAL, 0.0005, 0.0005)
for _ in range(20000):
    assert device.sleep(0.5)  # told to stop: at once
signal.setitimer(signal.ITIMER_REAL, 0)
print("done")
"""


def test_a_stop_from_a_signal_handler_never_deadlocks_a_sleeping_card(tmp_path: Path) -> None:
    """``cifemu firmware`` stops the card from its SIGTERM handler, also while the card
    sleeps through an emulated slow reset (--reset-delay). A handler that interrupted that
    sleep inside a ``threading.Event``'s own wait, holding its lock, deadlocked the card: the
    firmware ignored SIGTERM for good (seen once under load). Here a timer signal stops the
    card 2,000 times a second while it sleeps, in a process of its own, as the firmware's."""
    out = commands.run([sys.executable, "-c", STOP_STORM, str(tmp_path)], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout == "done\n", out.stderr
