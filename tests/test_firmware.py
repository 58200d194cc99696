"""The firmware process as a user meets it: its image, its life cycle, its messages."""

from __future__ import annotations

import json
import os
import signal
import stat
import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from dpm.message import Message
from dpm.task2 import ComPlcParameter
from host_api.board import Board, CifError
from tests import commands
from tests.conftest import HOST_FLAGS, READY, ROOT, Card, start_card, wait_until


@pytest.fixture(scope="module")
def untouched_card(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Card]:
    """A card just started, for the tests that only look at it (its file, its image, a
    second firmware's refusal, ``cifemu status``): one firmware start for them all."""
    running = start_card(tmp_path_factory.mktemp("untouched"))
    yield running
    running.stop()


def test_image_is_created_8k_with_mode_0660(untouched_card: Card) -> None:
    st = untouched_card.path.stat()
    assert st.st_size == 8192
    assert stat.S_IMODE(st.st_mode) == 0o660


def test_image_is_0660_whatever_the_umask(tmp_path: Path) -> None:
    old = os.umask(0o077)
    try:
        card = start_card(tmp_path)
    finally:
        os.umask(old)
    try:
        assert stat.S_IMODE(card.path.stat().st_mode) == 0o660
    finally:
        card.stop()


def test_identification_areas(untouched_card: Card) -> None:
    image = untouched_card.map()
    assert image[0x1E60:0x1E80] == b"CANopen Master  V1.070 cifemu   "
    assert image[0x1F90:0x1F98] == b"PLC     " and image[0x1FA0:0x1FA8] == b"CAN     "
    assert image[0x1FF8:0x1FFE] == bytes([8, 0x32, 5]) + b"CIF"
    assert struct.unpack_from("<I", image, 0x1D24)[0] == 1250100
    assert image[0x1FF7] == 0x44  # buffered host-controlled, event-driven state field
    assert image[0x1FFE] == 0x80  # READY; no configuration: no RUN, no COM


def test_a_second_firmware_for_the_same_board_refuses(untouched_card: Card) -> None:
    second = commands.run(
        [sys.executable, "-m", "cifemu", "firmware", "--board", "0", "--dpm-dir",
         str(untouched_card.directory)],
        capture_output=True, text=True, timeout=30,
    )
    assert second.returncode == 1
    assert "board 0 refused" in second.stderr and "already serves this board" in second.stderr
    assert untouched_card.proc.poll() is None and untouched_card.map()[0x1FFE] & 0x80


def test_another_board_in_the_same_directory_runs(card: Card) -> None:
    other = start_card(card.directory, 1)
    try:
        assert (card.directory / "board1.dpm").exists()
    finally:
        assert other.stop() == 0


def test_sigterm_shuts_down_with_ready_cleared(card: Card) -> None:
    image = card.map()
    card.proc.send_signal(signal.SIGTERM)
    assert commands.wait(card.proc, 10) == 0
    assert image[0x1FFE] & 0x80 == 0


def test_a_restarted_firmware_serves_the_same_image(tmp_path: Path) -> None:
    first = start_card(tmp_path)
    image = first.map()
    first.stop()
    second = start_card(tmp_path)
    try:
        assert image[0x1FFE] & 0x80
    finally:
        second.stop()


def test_board_raises_cif_errors_with_names(card: Card) -> None:
    with Board(0, card.directory) as b:
        answer = b.transact(Message(rx=2, tx=16, b=17, data=bytes([0, 1, 0, 0, 0, 2, 5, 1])))
        assert answer.f == 0 and answer.data[8:] == b"\0\0"
        b.warm_start(ComPlcParameter(bMode=2))
        assert b.protocol_parameters().bMode == 2
        with pytest.raises(CifError) as err:
            b.exchange_io(b"\x01", receive_size=1)
        assert err.value.code == -21 and err.value.name == "DRV_DEV_NO_COM_FLAG"
        assert "COM-flag not set" in str(err.value)
        assert b.diagnostics().can_state_name == "OFFLINE"
        assert b.trigger_watchdog() == 1
    with pytest.raises(CifError) as err:
        Board(3, card.directory).open()
    assert err.value.name == "DRV_USR_DEV_NUMBER_INVALID"


def test_bus_parameter_download_starts_the_network(card: Card) -> None:
    with Board(0, card.directory) as b:
        bad = bytes([0, 127, 0, 0, 9]) + struct.pack("<HH", 0x80, 0) + bytes([0, 0])
        assert b.transact(Message(rx=3, tx=16, b=68, data=bad)).f == 65
        assert b.diagnostics().can_state_name == "OFFLINE"
        good = bytes([0, 127, 0, 0, 2]) + struct.pack("<HH", 0x80, 0) + bytes([0, 0])
        assert b.transact(Message(rx=3, tx=16, b=68, data=good)).f == 0
        wait_until(lambda: b.diagnostics().can_state_name == "OPERATE", what="OPERATE")
        image = card.map()
        assert image[0x1FFE] & 0xE0 == 0xE0  # READY RUN COM
        b.set_host_ready(False, timeout=1000)
        assert b.diagnostics().can_state_name == "STOP"
        assert b.diagnostics().bGlobalBits & 0x20
        b.reset()  # an on-line configuration is not stored: lost at reset
        assert image[0x1FFE] & 0xE0 == 0x80


def test_status_command_shows_a_running_card(untouched_card: Card) -> None:
    out = commands.run(
        [sys.executable, "-m", "cifemu", "status", "--dpm-dir", str(untouched_card.directory)],
        capture_output=True, text=True, timeout=30, cwd=ROOT,
    )
    assert out.returncode == 0
    assert "READY" in out.stdout and "CANopen Master" in out.stdout
    assert "Task2State" in out.stdout and "OFFLINE" in out.stdout
    data = json.loads(commands.run(
        [sys.executable, "-m", "cifemu", "status", "--json", "--dpm-dir",
         str(untouched_card.directory)],
        capture_output=True, text=True, timeout=30, check=True,
    ).stdout)
    assert "READY" in data["host_flags"]
    assert data["rcs"]["exchange_mode"] == 4
    assert data["task2state"]["can_state"] == "OFFLINE"


def test_status_decodes_errors_with_the_seed_text(card: Card) -> None:
    with Board(0, card.directory) as b:
        b.warm_start(ComPlcParameter(bMode=9))
    data = json.loads(commands.run(
        [sys.executable, "-m", "cifemu", "status", "--json", "--dpm-dir", str(card.directory)],
        capture_output=True, text=True, timeout=30, check=True,
    ).stdout)
    assert data["task2state"]["err_event"] == 52
    assert data["task2state"]["err_text"] == "unknown handshake mode was configured"
    assert data["task2state"]["global_bits"] == ["CTRL"]


def test_status_without_a_card_says_what_to_do(tmp_path: Path) -> None:
    out = commands.run(
        [sys.executable, "-m", "cifemu", "status", "--dpm-dir", str(tmp_path)],
        capture_output=True, text=True, timeout=30,
    )
    assert out.returncode == 1 and "cifemu firmware" in out.stderr


def test_help_explains_the_commands() -> None:
    out = commands.run([sys.executable, "-m", "cifemu", "--help"], capture_output=True,
                       text=True, timeout=30, check=True).stdout
    for command in ("firmware", "status", "demo"):
        assert command in out
    fw = commands.run([sys.executable, "-m", "cifemu", "firmware", "--help"],
                      capture_output=True, text=True, timeout=30, check=True).stdout
    assert "--dpm-dir" in fw and "CIF_DPM_DIR" in fw


@pytest.mark.parametrize("extra", [[], ["--from-dbm"]])
def test_demo_runs_the_bundled_network_until_ctrl_c(tmp_path: Path, extra: list[str]) -> None:
    demo = subprocess.Popen(
        [sys.executable, "-m", "cifemu", "demo", "--dpm-dir", str(tmp_path), *extra],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=ROOT,
    )

    def operating() -> list[int]:
        out = commands.run([sys.executable, "-m", "cifemu", "status", "--json", "--dpm-dir",
                            str(tmp_path)], capture_output=True, text=True, timeout=30)
        return json.loads(out.stdout)["task2state"]["nd_state"] if out.returncode == 0 else []

    try:
        wait_until(lambda: operating() == [1, 2, 3, 4], 30, "the demo's four nodes")
    finally:
        demo.send_signal(signal.SIGINT)
        assert commands.wait(demo, 20) == 0, demo.stderr.read().decode() if demo.stderr else ""


# --- start-up: what a card that no option asked for does not load (docs/testing.md) ---------

COMPOSITION = ("cifemu.online_configure", "cifemu.commands.configure", "dbm_tools.builder",
               "host_api", "firmware.sim")
"""What only --configure (a host inside the card) and --simulate need."""


def test_firmware_command_loads_no_composition_until_an_option_asks() -> None:
    """The tests start some thousand firmwares: --configure's host (the DBM builder,
    host_api's Board) was a fifth of each start's CPU although few ask for it."""
    probe = ("import sys\nfrom cifemu.cli import main\n"
             "try:\n    main(['firmware', '--help'])\nexcept SystemExit:\n    pass\n"
             f"prefixes = {COMPOSITION!r}\n"
             "print(sorted(m for m in sys.modules if m.startswith(prefixes) or m == 'numpy'))\n")
    out = commands.run([sys.executable, "-c", probe], capture_output=True, text=True,
                       timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[-1] == "[]"


def test_a_card_without_configuration_maps_no_numpy(card: Card) -> None:
    """numpy costs a process 0.1 s of CPU to import; the card needs it only to compare
    outputs (``OutputWatch``), so a card that was never configured has not loaded it: its
    process maps none of numpy's libraries."""
    maps = Path(f"/proc/{card.proc.pid}/maps").read_text()
    assert "numpy" not in maps
    assert card.map()[HOST_FLAGS] & READY  # and it serves
