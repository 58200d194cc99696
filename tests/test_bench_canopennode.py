"""``make bench-vcan``'s race against CANopenNode's gateway, where CANopenNode is not built.

CANopenNode is never part of this repository: a machine without it still runs the rest of
``bench.vcan``, and the phase's JSON says what is missing and how to build it beside the
project. Where it is built, ``canopend`` in ``$CIFEMU_CANOPENNODE/bin`` wins over PATH. The
race itself needs vcan0 and runs in ``make bench-vcan``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bench import canopennode, vcan


@pytest.fixture
def nowhere(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """No canopend in the cache directory nor on PATH."""
    monkeypatch.setattr(canopennode, "CANOPENNODE_DIR", tmp_path / "canopennode")
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.setenv("PATH", str(empty))
    return tmp_path


def test_without_canopend_the_phase_says_so_and_how_to_build_it(nowhere: Path) -> None:
    document = vcan.run(only=("cia309_vs_canopennode",))
    phase = document["cia309_vs_canopennode"]
    assert set(phase) == {"skipped", "build"}
    assert phase["skipped"].startswith(f"canopend not found in {nowhere / 'canopennode' / 'bin'}")
    assert "docs/benchmarks.md" in phase["skipped"]
    steps = phase["build"]
    assert steps[0].startswith("git clone https://github.com/CANopenNode/CANopenLinux ")
    assert any(step.endswith("submodule update --init") for step in steps)
    assert any(step.startswith("make -C ") and step.endswith("/cocomm") for step in steps)
    assert steps[-1].endswith("~/.cache/cifemu/canopennode/bin/")
    assert "machine" in document  # the run goes on: the document is whole


def test_canopend_in_the_cache_directory_comes_before_path(nowhere: Path) -> None:
    built = nowhere / "canopennode" / "bin" / "canopend"
    built.parent.mkdir(parents=True)
    built.write_text("#!/bin/sh\n")
    built.chmod(0o755)
    assert canopennode.program("canopend") == str(built)
    assert canopennode.missing() is None
    assert canopennode.program("cocomm") is None
