"""A C host program (echo.c) against the emulated card, built with libcif.

``cifemu libcif --cflags --libs`` gives the flags that compile a program written for the
real card's driver API against the emulated one. A legacy binary that exists only as a
binary runs the same way under ``cifemu legacy -- ./program`` (docs/legacy.md): the
fixture's ``$CIF_DPM_DIR`` reaches it too.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from cifemu.pytest_plugin import CifCard

HERE = Path(__file__).parent


@pytest.fixture(scope="module")
def echo(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """echo.c compiled once for the module's tests."""
    cc = shutil.which("cc")
    if cc is None:
        pytest.skip("no C compiler")
    flags = subprocess.run([sys.executable, "-m", "cifemu", "libcif", "--cflags", "--libs"],
                           capture_output=True, text=True, check=True).stdout.split()
    program = tmp_path_factory.mktemp("build") / "echo"
    subprocess.run([cc, "-Wall", "-Wextra", "-Werror", str(HERE / "echo.c"), *flags,
                    "-o", str(program)], check=True)
    return program


@pytest.mark.cif_network("network.toml")
def test_the_c_program_sees_its_outputs_echoed(cif_card: CifCard, echo: Path) -> None:
    cif_card.wait_until_operating()
    done = subprocess.run([str(echo), str(cif_card.board), "8"], capture_output=True,
                          text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout == "deadbeef01234567\n"
