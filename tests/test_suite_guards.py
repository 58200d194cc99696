"""The suite's guards, run for real: ``make test-fast`` cannot start a firmware, and a libcif
that does not compile fails the tests that need it instead of skipping them.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

from cifemu import libcif
from tests import commands
from tests.conftest import ROOT
from tests.libcif_host import build_libcif, toolchain_missing
from tests.selection import marks_of_module

START_A_CARD_UNDER_THE_GUARD = """
import sys
from pathlib import Path
from tests.selection import forbid_processes
forbid_processes()
from tests.conftest import start_card
start_card(Path(sys.argv[1]))
print("a firmware started")
"""


def test_a_fast_test_that_starts_a_firmware_fails_and_says_what_to_do(tmp_path: Path) -> None:
    """In its own process: the guard's audit hook, once added, stays for the process."""
    done = commands.run([sys.executable, "-c", START_A_CARD_UNDER_THE_GUARD, str(tmp_path)],
                        capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert done.returncode != 0 and "a firmware started" not in done.stdout
    assert "subprocess.Popen here, so add this module to PROCESS_MODULES" in done.stderr
    assert not (tmp_path / "board0.dpm").exists()


def test_fast_is_a_mark_of_the_codec_modules_only() -> None:
    names = {name: {mark.name for mark in marks_of_module(name)}
             for name in ("test_com_codecs", "test_firmware", "test_vcan_vm", "test_soak")}
    assert names == {"test_com_codecs": {"fast"}, "test_firmware": set(),
                     "test_vcan_vm": {"vcan_vm"}, "test_soak": {"serial"}}


@pytest.fixture
def broken_libcif(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A copy of libcif/ whose sources do not compile, in place of this clone's."""
    copy = tmp_path / "libcif"
    shutil.copytree(libcif.SOURCE, copy, ignore=shutil.ignore_patterns("build"))
    source = copy / "src" / "bell.c"
    source.write_text(source.read_text() + "\nint broken_on_purpose(void) { return }\n")
    monkeypatch.setattr(libcif, "SOURCE", copy)
    monkeypatch.setattr(libcif, "BUILD", copy / "build")
    monkeypatch.setattr(libcif, "SHARED", copy / "build" / "libcif.so")
    return copy


def test_a_libcif_compile_error_fails_the_test(broken_libcif: Path) -> None:
    if toolchain_missing():
        pytest.skip(str(toolchain_missing()))
    with pytest.raises(pytest.fail.Exception, match="building libcif failed") as failed:
        build_libcif("all")
    assert "bell.c" in str(failed.value)
    assert not (broken_libcif / "build" / "libcif.so").exists()


def test_a_machine_without_a_compiler_skips_with_what_to_install(
        broken_libcif: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))  # no cc, gcc or make on it
    with pytest.raises(pytest.skip.Exception, match="no C compiler"):
        build_libcif("all")
