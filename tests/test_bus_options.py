"""``--bus-option`` and ``--bus-config``: any python-can interface, with its options.

What a user notices: the values arrive typed as python-can types its own
configuration files, a file's section fills in what the flags leave open, the
flags win, and a mistake is one line that names it (no traceback, exit 1). The
end-to-end test proves the options reach the card's CAN controller: the card dials
the socketcand host and port given as options (a real TCP listener of the test's).
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest

from dbm_tools.bus_options import BusOptionError, parse_option, select_bus
from dbm_tools.network import parse_network
from firmware.shm.station import channel_path
from tests import commands
from tests.conftest import TIME_SCALE


def test_values_are_typed_as_python_can_types_its_files() -> None:
    assert parse_option("port=29536") == ("port", 29536)
    assert parse_option("fd=true") == ("fd", True)
    assert parse_option("sleep_after_open=0.5") == ("sleep_after_open", 0.5)
    assert parse_option("host=10.0.0.2") == ("host", "10.0.0.2")
    assert parse_option("url=ws://h:1/a=b") == ("url", "ws://h:1/a=b")


@pytest.mark.parametrize(("text", "named"), [
    ("port", "'port'"), ("=1", "'=1'"), ("my-key=1", "'my-key=1'"),
    ("channel=can0", "--channel"), ("interface=x", "--interface"), ("bitrate=1", "--bitrate")])
def test_a_malformed_option_is_refused_by_name(text: str, named: str) -> None:
    with pytest.raises(BusOptionError, match=named):
        parse_option(text)


def test_a_file_section_fills_in_and_the_command_line_wins(tmp_path: Path) -> None:
    ini = tmp_path / "can.ini"
    ini.write_text("[default]\ninterface = virtual\n"
                   "[rack]\nbustype = socketcand\nchannel = can0\nbitrate = 250000\n"
                   "host = 10.0.0.2\nport = 29536\ntcp_tune = True\n")
    rack = select_bus(None, None, None, [], f"{ini}:rack")
    assert (rack.interface, rack.channel, rack.bitrate) == ("socketcand", "can0", 250000)
    assert rack.options == {"host": "10.0.0.2", "port": 29536, "tcp_tune": True}
    mine = select_bus("socketcand", "vcan0", 500000, ["port=1234"], f"{ini}:rack")
    assert (mine.channel, mine.bitrate, mine.options["port"]) == ("vcan0", 500000, 1234)
    assert select_bus(None, None, None, [], str(ini)).interface == "virtual"  # [default]


@pytest.mark.parametrize(("spec", "message"), [
    ("missing.ini", "no such file"), ("can.ini:nowhere", r"no section \[nowhere\]"),
    ("bad.ini", "--bus-config bad.ini")])
def test_a_config_file_that_cannot_be_used_is_named(tmp_path: Path, spec: str,
                                                    message: str,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "can.ini").write_text("[default]\ninterface = virtual\n")
    (tmp_path / "bad.ini").write_text("interface = no section header\n")
    with pytest.raises(BusOptionError, match=message):
        select_bus(None, None, None, [], spec)


def _cli(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "cifemu", *argv], capture_output=True,
                        text=True, timeout=60, cwd=cwd, check=False)


@pytest.mark.parametrize("command", [["firmware"], ["sim", "net.toml"], ["monitor"]])
@pytest.mark.parametrize(("flags", "named"), [
    (["--interface", "nosuchbus"], 'Unknown interface type "nosuchbus"'),
    (["--interface", "virtual", "--bus-option", "port"], "--bus-option 'port'"),
    (["--interface", "virtual", "--bus-config", "none.ini"], "--bus-config none.ini")])
def test_every_command_refuses_in_one_line(tmp_path: Path, command: list[str],
                                           flags: list[str], named: str) -> None:
    (tmp_path / "net.toml").write_text("[[node]]\nid = 1\n")
    card = ["--dpm-dir", str(tmp_path)] if command[0] != "sim" else ["--channel", "c"]
    if command[0] == "firmware":  # else a card whose interface cannot open stays up (FAT)
        card += ["--exit-on-bus-error", "--log-level", "WARNING"]
    done = _cli(*command, *flags, *card, cwd=tmp_path)
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and named in lines[0], done.stderr


def _dial_a_hang_up(
        start: Callable[[int], subprocess.Popen[str]]) -> tuple[subprocess.Popen[str], str, int]:
    """A listener on 127.0.0.1 that is no socketcand: ``start(port)`` starts the command that
    should dial it; the listener accepts that one connection and hangs up at once. The
    command once it ended, its standard error, and the port."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        listener.settimeout(30 * TIME_SCALE)
        port = listener.getsockname()[1]
        proc = start(port)
        try:
            connection, _ = listener.accept()
            connection.close()
            _, stderr = commands.finish(proc, 30)
        finally:
            if proc.poll() is None:
                proc.kill()
                commands.wait(proc, 10)
    return proc, stderr, port


def test_the_cards_controller_dials_the_host_and_port_given_as_options(tmp_path: Path) -> None:
    """socketcand's host and port exist only as options: the card's controller connects to
    the test's listener, which hangs up at once (it is no socketcand), and the card ends
    with one line naming the interface and its options (--exit-on-bus-error)."""
    card, stderr, port = _dial_a_hang_up(lambda port: subprocess.Popen(
        [sys.executable, "-m", "cifemu", "firmware", "--dpm-dir", str(tmp_path),
         "--interface", "socketcand", "--channel", "can0", "--bus-option",
         "host=127.0.0.1", "--bus-option", f"port={port}", "--exit-on-bus-error"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
    assert card.returncode == 1
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("cifemu firmware: cannot open CAN interface 'socketcand' channel "
                           f"'can0' with options host=127.0.0.1 port={port}: "), stderr
    assert "Traceback" not in stderr


# --- the network description's [bus]: interface, channel, options ----------------------------

RACK = ('[bus]\ninterface = "socketcand"\nchannel = "can0"\n'
        '[bus.options]\nhost = "127.0.0.1"\nport = {port}\ntcp_tune = true\n'
        '[[node]]\nid = 1\n')


def test_the_description_fills_in_what_the_command_line_leaves_open() -> None:
    rack = parse_network(RACK.format(port=29536)).bus
    assert rack.options == {"host": "127.0.0.1", "port": 29536, "tcp_tune": True}
    alone = select_bus(None, None, None, [], None, rack)
    assert (alone.interface, alone.channel, alone.options["port"]) == ("socketcand", "can0", 29536)
    mine = select_bus("socketcand", "vcan0", None, ["port=1"], None, rack)
    assert (mine.channel, mine.options) == ("vcan0", {"host": "127.0.0.1", "port": 1,
                                                      "tcp_tune": True})
    # Another interface on the command line: the file's channel and options are another bus's.
    other = select_bus("shm", None, None, [], None, rack)
    assert (other.interface, other.channel, other.options) == ("shm", None, {})


@pytest.mark.parametrize(("bus", "named"), [
    ('interface = "nosuchbus"', "bus.interface = 'nosuchbus' is not a python-can interface"),
    ('interface = 5', "bus.interface: expected str"),
    ('[bus.options]\nchannel = "can1"', "bus.options.channel: use bus.channel"),
    ('[bus.options]\nbustype = "pcan"', "bus.options.bustype: use bus.interface"),
    ('[bus.options]\n"my-key" = 1', "bus.options: key 'my-key' is not a python identifier"),
    ('[bus.options]\nwhen = 1979-05-27', "bus.options.when: a date is no python-can option"),
    ('options = "host=x"', "bus.options: expected dict")])
def test_a_description_bus_that_cannot_be_used_is_one_line(tmp_path: Path, bus: str,
                                                           named: str) -> None:
    (tmp_path / "net.toml").write_text(f"[bus]\n{bus}\n[[node]]\nid = 1\n")
    for command in (["sim", "net.toml", "--interface", "shm", "--channel", "c"],
                    ["firmware", "--simulate", "net.toml", "--dpm-dir", str(tmp_path)]):
        done = _cli(*command, cwd=tmp_path)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 1 and len(lines) == 1 and named in lines[0], done.stderr


def _sim_json(tmp_path: Path, *flags: str) -> dict[str, object]:
    """``cifemu sim net.toml --json``'s first line, then the simulation ends."""
    sim = subprocess.Popen([sys.executable, "-m", "cifemu", "sim", "net.toml", "--json",
                            "--log-level", "WARNING", *flags], cwd=tmp_path,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert sim.stdout is not None
        first = sim.stdout.readline()
    finally:
        sim.terminate()
        _, stderr = commands.finish(sim, 30)
    assert first, stderr
    return dict(json.loads(first))


def test_cifemu_sim_opens_the_bus_the_description_names(tmp_path: Path) -> None:
    channel = f"described-{uuid.uuid4().hex}"
    (tmp_path / "net.toml").write_text(f'[bus]\ninterface = "shm"\nchannel = "{channel}"\n'
                                       "[[node]]\nid = 1\n")
    try:
        shown = _sim_json(tmp_path)
        assert (shown["interface"], shown["channel"]) == ("shm", channel)
        mine = f"{channel}-flag"
        shown = _sim_json(tmp_path, "--channel", mine)  # the command line wins
        assert (shown["interface"], shown["channel"]) == ("shm", mine)
    finally:
        for name in (channel, f"{channel}-flag"):
            channel_path(name).unlink(missing_ok=True)


@pytest.mark.parametrize("command", [["sim", "net.toml", "--log-level", "WARNING"],
                                     ["firmware", "--simulate", "net.toml",
                                      "--exit-on-bus-error", "--log-level", "WARNING"]])
def test_the_descriptions_options_reach_python_can(tmp_path: Path, command: list[str]) -> None:
    """The host and port exist only in the file's [bus.options]: the bus dials the test's
    listener, which hangs up (it is no socketcand), and the command ends in one line naming
    the interface and the options it was opened with."""
    def start(port: int) -> subprocess.Popen[str]:
        (tmp_path / "net.toml").write_text(RACK.format(port=port))
        return subprocess.Popen([sys.executable, "-m", "cifemu", *command, *(
            ["--dpm-dir", str(tmp_path)] if command[0] == "firmware" else [])], cwd=tmp_path,
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    proc, stderr, port = _dial_a_hang_up(start)
    assert proc.returncode == 1
    last = stderr.strip().splitlines()[-1]
    assert "'socketcand' channel 'can0' with options host=127.0.0.1 " in last or (
        "socketcand channel can0 with options host=127.0.0.1 " in last), stderr
    assert f"port={port} tcp_tune=True: " in last, stderr
    assert "Traceback" not in stderr
