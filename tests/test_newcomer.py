"""What a newcomer trips over first (issue 24): commands as the README prints them, run as a
person pastes them, and the one-line errors they get instead of tracebacks.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

CC = shutil.which("cc") or shutil.which("gcc")


def cifemu(*args: str, cwd: Path | None = None,
           env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "cifemu", *args], cwd=cwd, env=env,
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
