"""tools/vcan-vm's qemu backend, run for real: the fallback where User-Mode Linux cannot run.

These tests start their own virtual machine (qemu without KVM), so they run in the
host's ``make test``, not under ``make test-vcan`` (no ``vcan`` marker): the host needs
no SocketCAN. They skip only where qemu cannot be installed (not root, no apt-get, not
an x86-64 Linux). The first one builds the guest's kernel and initramfs into the cache,
which costs a download once.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from tests import commands
from tests.buses import socketcan_missing

# The first test's set-up may install qemu and download the kernel: more than the
# suite's usual two minutes on a fresh machine.
pytestmark = pytest.mark.timeout(420)

ROOT = Path(__file__).resolve().parents[1]
VCAN_VM = ROOT / "tools" / "vcan-vm"

ROUND_TRIP = """\
import os, subprocess, sys, time
import can
# A file still open in a process the command leaves running: only the guest's sync at the
# end brings it to the host (the guest caches what it writes to the host's files).
subprocess.Popen(["sh", "-c", "exec 3>kept_open.txt; echo written >&3; exec sleep 600"])
print("rmem", open("/proc/sys/net/core/rmem_default").read().strip(),
      "unbuffered", os.environ.get("PYTHONUNBUFFERED"), "mark", os.environ["VCAN_VM_MARK"])
print("operstate", open("/sys/class/net/vcan0/operstate").read().strip(),
      open("/sys/class/net/vcan1/operstate").read().strip())
with can.Bus(interface="socketcan", channel="vcan0") as a, \\
        can.Bus(interface="socketcan", channel="vcan0") as b:
    a.send(can.Message(arbitration_id=0x123, data=b"ping", is_extended_id=False))
    got = b.recv(5)
    b.send(can.Message(arbitration_id=0x124, data=got.data[::-1], is_extended_id=False))
    back = a.recv(5)
with open("answer.txt", "w") as out:
    out.write(" ".join(f"{m.arbitration_id:03X}#{m.data.hex()}" for m in (got, back)))
while open("kept_open.txt").read() != "written\\n":
    time.sleep(0.05)
print("on stderr", file=sys.stderr)
sys.exit(3)
"""
"""Two python-can buses on vcan0 inside the guest: a frame there and its answer back."""


def vcan_vm(*args: str, cwd: Path = ROOT, env: dict[str, str] | None = None,
            timeout: float = 240) -> subprocess.CompletedProcess[str]:
    return commands.run([str(VCAN_VM), *args], cwd=cwd, env=env, capture_output=True,
                        text=True, timeout=timeout)


@pytest.fixture(scope="module")
def qemu() -> None:
    """A first run (it installs qemu and builds the guest when they are missing); skips
    the tests where qemu cannot be installed, and only there."""
    if platform.system() != "Linux" or platform.machine() != "x86_64":
        pytest.skip("the qemu backend runs the host's programs: it needs an x86-64 Linux")
    first = vcan_vm("--backend", "qemu", "--", "true", timeout=360)
    if first.returncode == 125 and ("install" in first.stderr or "apt-get" in first.stderr):
        pytest.skip(f"qemu cannot be installed here: {first.stderr.strip()}")
    assert first.returncode == 0, first.stderr


def left_behind(mark: str) -> list[int]:
    """The processes that still carry ``mark`` in their environment (qemu inherits it)."""
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            environ = Path(f"/proc/{pid}/environ").read_bytes()
        except OSError:
            continue
        if f"VCAN_VM_MARK={mark}".encode() in environ.split(b"\0"):
            found.append(int(pid))
    return found


def test_qemu_runs_a_python_can_round_trip_on_vcan0_in_the_callers_directory(
        qemu: None, tmp_path: Path) -> None:
    mark = uuid.uuid4().hex
    script = tmp_path / "round_trip.py"
    script.write_text(ROUND_TRIP)
    result = vcan_vm("--backend", "qemu", "--vcan", "2", "--", sys.executable, script.name,
                     cwd=tmp_path, env={**os.environ, "VCAN_VM_MARK": mark})
    assert result.returncode == 3, result.stderr  # the command's own status
    lines = result.stdout.splitlines()
    assert f"rmem 4194304 unbuffered 1 mark {mark}" in lines, result.stdout
    assert "operstate unknown unknown" in lines, result.stdout  # vcan's "up" (no carrier)
    assert "on stderr" in result.stderr.splitlines()
    # Written inside, in the caller's directory, and on the host once the command ended.
    assert (tmp_path / "answer.txt").read_text() == "123#70696e67 124#676e6970"
    assert (tmp_path / "kept_open.txt").read_text() == "written\n"
    assert left_behind(mark) == []


def test_qemu_streams_output_and_kills_everything_at_the_time_out(qemu: None) -> None:
    mark = uuid.uuid4().hex
    limit = 30.0
    start = time.monotonic()
    proc = subprocess.Popen([str(VCAN_VM), "--backend", "qemu", "--timeout", str(limit), "--",
                             "sh", "-c", "echo started; sleep 600; echo never"], cwd=ROOT,
                            env={**os.environ, "VCAN_VM_MARK": mark}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stderr is not None
        assert proc.stdout.readline() == "started\n"  # while the command still runs
        streamed = time.monotonic() - start
        assert proc.poll() is None
        assert commands.wait(proc, limit + 30) == 124
    finally:
        proc.kill()
        proc.wait()
    elapsed = time.monotonic() - start
    assert streamed < limit and limit <= elapsed < limit + 20, (streamed, elapsed)
    assert proc.stdout.read() == ""
    assert "timed out after 30 s" in proc.stderr.read()
    assert left_behind(mark) == []


def test_auto_falls_back_to_qemu_when_user_mode_linux_cannot_start(
        qemu: None, tmp_path: Path) -> None:
    """A linux.uml that exits at once, first on PATH, stands for a host where User-Mode
    Linux cannot run (ptrace forbidden, say): the command runs under qemu all the same."""
    if socketcan_missing() is None:
        pytest.skip("this host has vcan0: --backend auto runs the command natively")
    fake = tmp_path / "bin" / "linux.uml"
    fake.parent.mkdir()
    fake.write_text("#!/bin/sh\necho 'fake linux.uml: cannot run here' >&2\nexit 1\n")
    fake.chmod(0o755)
    env = {**os.environ, "PATH": f"{fake.parent}{os.pathsep}{os.environ['PATH']}"}
    result = vcan_vm("--", "sh", "-c", "test -d /sys/class/net/vcan0 && exit 42", env=env)
    assert result.returncode == 42, result.stderr
    assert "falling back to qemu" in result.stderr


def test_help_names_every_backend_in_plain_text() -> None:
    result = commands.run([str(VCAN_VM), "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert "`" not in result.stdout, result.stdout  # read in a terminal: no markup
    for backend in ("native", "uml", "qemu"):
        assert f"\n  {backend} " in result.stdout, backend
