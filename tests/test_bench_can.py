"""``python -m bench.can --nodes N``: a smaller network than the full configuration, said so.

Where one CPU cannot boot 126 nodes in time (User-Mode Linux, ``make bench-vcan``) the
benchmark runs a smaller network; its JSON must say which one ran, and must not judge the
full configuration's targets by it.
"""

from __future__ import annotations

import json
import subprocess
import sys

from tests import commands
from tests.conftest import ROOT


def bench_can(*args: str, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    return commands.run([sys.executable, "-m", "bench.can", *args], cwd=ROOT,
                        capture_output=True, text=True, timeout=timeout)


def test_a_node_count_out_of_range_is_refused_in_plain_words() -> None:
    run = bench_can("--nodes", "128")
    assert run.returncode == 2
    assert "a node count from 1 to 127, not '128'" in run.stderr
    assert "Traceback" not in run.stderr


def test_a_channel_needs_the_socketcan_interface() -> None:
    run = bench_can("--channel", "vcan0")
    assert run.returncode == 2
    assert "--channel goes with --interface socketcan" in run.stderr


def test_a_capped_boot_phase_says_which_network_ran_and_judges_no_target() -> None:
    run = bench_can("--only", "boot", "--nodes", "4")
    assert run.returncode == 0, run.stderr[-2000:]
    document = json.loads(run.stdout)
    params = document["params"]
    assert (params["node_cap"], params["boot_nodes"], params["full_configuration"]) == (
        4, 4, False)
    assert params["node_cap_reason"] == "given by the caller (--nodes)"
    assert document["boot"]["cif"]["nodes"] == 4
    assert document["boot"]["baseline"]["nodes"] == 4
    assert len(document["boot"]["cif"]["runs"]) == 3
    assert document["meets_target"] == {"boot_127_nodes": None}
