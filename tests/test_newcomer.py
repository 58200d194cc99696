"""What a newcomer trips over first (issue 24): commands as the README prints them, run as a
person pastes them, and the one-line errors they get instead of tracebacks.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from dbm_tools.network import load_network
from dpm.layout import TASK2_STATE, TASK_STATE_SIZE
from dpm.task2 import ComDiagnostics
from host_api.network_view import remember_network
from tests import commands
from tests.conftest import ROOT, start_card, wait_until
from tests.readme_blocks import NETWORK as README_NETWORK
from tests.readme_blocks import readme_blocks
from tests.top_images import image as top_image
from tests.top_images import model as top_model

CC = shutil.which("cc") or shutil.which("gcc")


def cifemu(*args: str, cwd: Path | None = None,
           env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "cifemu", *args], cwd=cwd, env=env,
                        capture_output=True, text=True, timeout=180, check=False)


# --- cifemu legacy -- ./prog ----------------------------------------------------------------


@pytest.mark.skipif(CC is None, reason="no C compiler")
def test_cifemu_legacy_runs_a_program_of_this_directory_as_given(tmp_path: Path) -> None:
    """``cifemu legacy -- ./prog`` runs ./prog, as env, sudo and strace do; it was looked up
    on $PATH as ``prog`` and not found. A bare name is looked up on $PATH, and a missing
    program is one line."""
    assert CC is not None
    (tmp_path / "prog.c").write_text(
        '#include <stdio.h>\nint main(int argc, char **argv) '
        '{ printf("%s %d\\n", argv[0], argc); return 7; }\n')
    subprocess.run([CC, "prog.c", "-o", "prog"], cwd=tmp_path, check=True)
    done = cifemu("legacy", "--", "./prog", "one", "two", cwd=tmp_path)
    assert (done.returncode, done.stdout, done.stderr) == (7, "./prog 3\n", "")

    missing = cifemu("legacy", "--", "./absent", cwd=tmp_path)
    assert missing.returncode == 1
    assert missing.stderr == "cifemu legacy: ./absent: No such file or directory\n"
    bare = cifemu("legacy", "--", "prog", cwd=tmp_path)
    assert bare.returncode == 1 and bare.stderr.count("\n") == 1
    assert "prog: not found on $PATH" in bare.stderr and "./prog" in bare.stderr


# --- make: the i386 build's apt-get ---------------------------------------------------------


def fake_tools(tmp_path: Path) -> tuple[Path, Path]:
    """A bin directory with a cc that cannot build -m32 and an apt-get that only records its
    arguments: a machine without gcc-multilib, which this one (having it) cannot be made
    into otherwise, and an apt-get that installs nothing for real."""
    assert CC is not None
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    calls = tmp_path / "apt-calls"
    (bin_dir / "cc").write_text(
        f'#!/bin/sh\nfor a; do [ "$a" = -m32 ] && exit 1; done\nexec {CC} "$@"\n')
    (bin_dir / "apt-get").write_text(f'#!/bin/sh\necho "$@" >> {calls}\n')
    for tool in ("cc", "apt-get"):
        (bin_dir / tool).chmod(0o755)
    return bin_dir, calls


def make_build_legacy(tmp_path: Path, bin_dir: Path,
                      *extra: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    return commands.run(["make", "--no-print-directory", "-C", str(ROOT), "build-legacy",
                         f"CC={bin_dir / 'cc'}", f"BUILD={tmp_path / 'build'}", *extra],
                        env=env, capture_output=True, text=True, timeout=300, check=False)


@pytest.mark.skipif(CC is None or shutil.which("make") is None, reason="no C compiler or make")
def test_make_installs_nothing_with_cifemu_no_apt(tmp_path: Path) -> None:
    """``make test CIFEMU_NO_APT=1`` runs no apt-get (it installed gcc-multilib as root
    without asking); the i386 build is skipped with the reason its tests show."""
    bin_dir, calls = fake_tools(tmp_path)
    done = make_build_legacy(tmp_path, bin_dir, "CIFEMU_NO_APT=1")
    assert done.returncode == 0, done.stderr
    assert not calls.exists(), calls.read_text()
    assert (tmp_path / "build" / "libcifdev.so").exists()
    missing = (tmp_path / "build" / "i386" / "MISSING").read_text()
    assert "gcc-multilib" in missing and "skipped" in missing


@pytest.mark.skipif(CC is None or shutil.which("make") is None or os.geteuid() != 0,
                    reason="no C compiler or make, or not root (apt-get runs only as root)")
def test_make_says_what_it_installs_and_how_not_to(tmp_path: Path) -> None:
    bin_dir, calls = fake_tools(tmp_path)
    done = make_build_legacy(tmp_path, bin_dir)
    assert done.returncode == 0, done.stderr
    assert "install -y -qq gcc-multilib libc6-i386" in calls.read_text()
    assert "i386 build" in done.stdout and "CIFEMU_NO_APT=1" in done.stdout


# --- the demo's hints, pasted into a second terminal ----------------------------------------


def test_every_command_the_demo_prints_works_in_a_second_terminal(tmp_path: Path) -> None:
    """`make demo` runs .venv/bin/cifemu with cifemu not on $PATH; it told the user to run
    `cifemu status`: "command not found". Each command it prints now runs, pasted into a
    shell without cifemu on $PATH, without $CIF_DPM_DIR, in another directory."""
    images = tmp_path / "cif"
    plain_path = os.pathsep.join(d for d in os.environ["PATH"].split(os.pathsep)
                                 if not (Path(d) / "cifemu").exists())
    env = {k: v for k, v in os.environ.items() if k != "CIF_DPM_DIR"}
    env.update(PATH=plain_path, PYTHONUNBUFFERED="1")
    demo = subprocess.Popen([sys.executable, "-m", "cifemu", "demo", "--dpm-dir", str(images)],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert demo.stdout is not None
        lines: list[str] = []
        for line in demo.stdout:
            lines.append(line)
            if "Ctrl-C ends the demo" in line:
                break
        else:
            pytest.fail(f"the demo ended: {''.join(lines)}")
        assert "In another terminal:" in lines[-1], lines[-1]
        hints = [demo.stdout.readline().strip() for _ in range(3)]
        assert [h.split(" --")[0].rsplit(" ", 1)[1] for h in hints] == ["top", "status",
                                                                       "monitor"], hints
        second = tmp_path / "second"
        second.mkdir()
        # each stops by itself: top after one sample of the bus (0.5 s, not its 1.5)
        limits = {"top": " --once --sample 0.5", "status": "", "monitor": " --duration 0.5"}
        for hint in hints:
            sub = hint.split(" --")[0].rsplit(" ", 1)[1]
            pasted = commands.run(["bash", "-c", hint + limits[sub]], cwd=second, env=env,
                                  capture_output=True, text=True, timeout=120, check=False)
            assert pasted.returncode == 0, (hint, pasted.stderr)
            assert "command not found" not in pasted.stderr
    finally:
        demo.send_signal(signal.SIGINT)
        assert commands.wait(demo, 20) == 0


# --- Err_Event 30 in the words of the node's error control ----------------------------------

HEARTBEAT_FAILED = "heartbeat failed: no heartbeat within the consumer time"


def test_top_and_status_say_heartbeat_for_a_heartbeat_node(tmp_path: Path) -> None:
    """Err_Event 30 on a heartbeat node read "guarding failed" in top and status."""
    card = top_model(tmp_path)  # node 1: heartbeat (the default), node 2: guarding
    card.update_image(top_image(err=(1, 30)), 1.0)
    rows = {row.node: row for row in card.node_rows()}
    last_error = rows[1].last_error
    assert last_error is not None and last_error[1].startswith(HEARTBEAT_FAILED)
    assert f"Err_Event 30 at node 1: {HEARTBEAT_FAILED}" in card.new_events(0)[0]

    # status: the image of a card that reports it, and the network configure noted beside it
    (tmp_path / "board0.dpm").write_bytes(top_image(err=(1, 30)))
    remember_network(tmp_path, 0, tmp_path / "net.toml")
    done = cifemu("status", "--json", "--dpm-dir", str(tmp_path))
    assert done.stdout, done.stderr
    assert json.loads(done.stdout)["task2state"]["err_text"].startswith(HEARTBEAT_FAILED)
    # without the network the text names both protocols, never guarding alone
    (tmp_path / "board0.network").unlink()
    done = cifemu("status", "--json", "--dpm-dir", str(tmp_path))
    assert "heartbeat or guarding" in json.loads(done.stdout)["task2state"]["err_text"]


def test_the_firmware_log_gives_the_err_event_text(tmp_path: Path) -> None:
    """The log said `node 5: error 30` and no more."""
    network = tmp_path / "net.toml"
    network.write_text("[[node]]\nid = 5\nheartbeat_ms = 200\n"
                       "[node.sim]\nheartbeat_stop_after_s = 0.5\n")
    card = start_card(tmp_path, 0, "--simulate", str(network), "--configure",
                      "--log-level", "INFO")
    try:
        mm = card.map()
        try:
            wait_until(lambda: mm[TASK2_STATE + 3] == 30, 20, "Err_Event 30")
        finally:
            mm.close()
    finally:
        card.stop()
    log = card.log()
    assert f"node 5: Err_Event 30, {HEARTBEAT_FAILED}" in log, log


# --- cifemu 309: the hints the other commands give ------------------------------------------


def test_309_without_a_card_asks_whether_the_firmware_runs(tmp_path: Path) -> None:
    """`cifemu 309` gave a bare -34 where the other commands ask "is `cifemu firmware
    --board N` running?"."""
    env = dict(os.environ, CIF_DPM_DIR=str(tmp_path))
    done = cifemu("309", "exec", "--direct", "--board", "1", "1 read 0x1000 0 u32", env=env)
    assert done.returncode == 1
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert "(-34)" in done.stderr and "is `cifemu firmware --board 1` running?" in done.stderr


def test_309_serve_on_a_port_in_use_says_so_in_one_line(tmp_path: Path) -> None:
    """It printed Python's raw `[Errno 98] error while attempting to bind ...`."""
    card = start_card(tmp_path)
    try:
        with socket.socket() as taken:
            taken.bind(("127.0.0.1", 0))
            taken.listen()
            port = taken.getsockname()[1]
            done = cifemu("309", "serve", "--port", str(port), "--dpm-dir", str(tmp_path))
    finally:
        card.stop()
    assert done.returncode == 1
    assert done.stderr == (f"cifemu 309: port {port} on 127.0.0.1 is in use; choose another "
                           "with --port\n")


# --- silent no-ops --------------------------------------------------------------------------

NO_SYNC = """
[bus]
sync_period_ms = 10
[[node]]
id = 1
[[node.pdo]]
direction = "output"
cob_id = 0x201
transmission = 255
"""


def test_sync_period_without_a_synchronous_pdo_is_warned_of(tmp_path: Path) -> None:
    """The card sends no SYNC when no node has a synchronous PDO (seed 4.2); build, check and
    configure said nothing, and `monitor --type sync` then waited for ever."""
    network = tmp_path / "net.toml"
    network.write_text(NO_SYNC)
    built = cifemu("dbm", "build", str(network), "-o", str(tmp_path / "net.dbm"))
    assert built.returncode == 0, built.stderr
    assert "warning" in built.stdout and "the card sends no SYNC" in " ".join(built.stdout.split())
    checked = cifemu("dbm", "check", str(tmp_path / "net.dbm"), "--json")
    assert checked.returncode == 0
    assert any("the card sends no SYNC" in finding["detail"]
               for finding in json.loads(checked.stdout)), checked.stdout
    env = dict(os.environ, CIF_DPM_DIR=str(tmp_path / "no-card"))
    configured = cifemu("configure", str(network), env=env)  # no card: the warning comes first
    assert configured.stderr.startswith(
        "cifemu configure: warning: SYNC_Timer 10 ms, but no active node has a synchronous PDO")
    synchronous = tmp_path / "sync.toml"
    synchronous.write_text(NO_SYNC.replace("transmission = 255", "transmission = 1"))
    built = cifemu("dbm", "build", str(synchronous), "-o", str(tmp_path / "sync.dbm"))
    assert built.returncode == 0 and "warning" not in built.stdout


def test_sim_on_the_virtual_bus_says_nothing_outside_reaches_it(tmp_path: Path) -> None:
    network = tmp_path / "net.toml"
    network.write_text("[[node]]\nid = 1\n")
    sim = subprocess.Popen([sys.executable, "-m", "cifemu", "sim", str(network), "--interface",
                            "virtual", "--channel", "lonely", "--log-level", "WARNING"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert sim.stdout is not None and sim.stderr is not None
        assert sim.stdout.readline().startswith("simulating")
    finally:
        sim.terminate()
        _, err = commands.finish(sim, 20)
    assert "virtual bus lives in this process only" in err
    assert "--interface shm --channel lonely" in err


# --- the README's C example -----------------------------------------------------------------


@pytest.mark.skipif(CC is None, reason="no C compiler")
def test_the_readmes_card_line_and_app_c_exchange_process_data(tmp_path: Path) -> None:
    """The README started the C example's card without --configure: every DevExchangeIO of
    the program answered -21. Its card line, run as printed (in a directory of the test's),
    and its app.c, built and run as printed, exchange data."""
    blocks = readme_blocks()
    card_line = next(line for block in blocks if "./app" in block.code
                     and "cifemu firmware" in block.code
                     for line in block.code.splitlines() if line.startswith("cifemu firmware"))
    app = next(block for block in blocks if "cat > app.c" in block.code)
    images = tmp_path / "cif"
    (tmp_path / "net.toml").write_text(README_NETWORK)
    words = shlex.split(card_line.split("#")[0].replace("/dev/shm/cif", str(images)))
    assert words[-1] == "&", card_line
    card = subprocess.Popen([sys.executable, "-m", *words[:-1], "--log-level", "WARNING"],
                            cwd=tmp_path, stderr=subprocess.PIPE)
    try:
        nodes = sorted(node.id for node in load_network(tmp_path / "net.toml").nodes)

        def operating() -> bool:
            try:
                raw = (images / "board0.dpm").read_bytes()
            except OSError:
                return False
            state = ComDiagnostics.decode(raw[TASK2_STATE : TASK2_STATE + TASK_STATE_SIZE])
            return state.operating() == nodes

        wait_until(operating, 30, "the README card's nodes in data exchange")
        env = dict(os.environ, CIF_DPM_DIR=str(images),
                   PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
        done = commands.run(["bash", "-e", "-c", app.code], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=120, check=False)
    finally:
        card.terminate()
        commands.wait(card, 20)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.startswith("DevExchangeIO: 0,"), done.stdout


def test_monitor_says_it_waits_for_a_sync_that_does_not_come(tmp_path: Path) -> None:
    """`monitor --type sync --count 3` on a card that sends no SYNC waited for ever in
    silence; after two quiet seconds it says what it waits for, and why none may come.
    Once it has said so, Ctrl-C ends it: its own --duration would only add a wait."""
    network = tmp_path / "net.toml"
    network.write_text(NO_SYNC)
    card = start_card(tmp_path, 0, "--simulate", str(network), "--configure")
    try:
        monitor = subprocess.Popen([sys.executable, "-m", "cifemu", "monitor", "--dpm-dir",
                                    str(tmp_path), "--type", "sync", "--count", "3",
                                    "--duration", "60"], stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, text=True)
        try:
            assert monitor.stderr is not None
            first = monitor.stderr.readline() if commands.readable(monitor.stderr, 30) else ""
        finally:
            monitor.send_signal(signal.SIGINT)
            out, rest = commands.finish(monitor, 60)
    finally:
        card.stop()
    err = first + rest
    assert monitor.returncode == 0 and out == "", err
    assert err.startswith("cifemu monitor: no sync frame in 2 s, still waiting"), err
    assert "synchronous PDO" in err and err.count("\n") == 1
