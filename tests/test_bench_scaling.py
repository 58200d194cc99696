"""``python -m bench.scaling``: the scaling figures of issue 22 from a tiny run.

The full run takes minutes and its figures depend on the machine; what a test can hold
it to is that every section runs against real cards and nodes, loses nothing, and
reports each figure where the README's table takes it from, beside its baseline.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from typing import Any

from tests.conftest import ROOT

STOP_S = 10.0
"""Seconds the bench's processes have after SIGTERM before they are killed: a firmware on
``shm`` stops its SYNC timer process and unmaps its image, slower on a loaded machine."""


def bench_scaling(*args: str) -> subprocess.CompletedProcess[str]:
    """``python -m bench.scaling`` in a process group of its own, ended with everything it
    started on every path out: a failure, pytest-timeout's interruption, a Ctrl-C. The
    bench stops its firmwares and ``cifemu sim`` itself when it ends normally; killed, it
    left them running, orphaned."""
    command = [sys.executable, "-m", "bench.scaling", *args]
    bench = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, start_new_session=True)
    try:
        stdout, stderr = bench.communicate()
    finally:
        end_group(bench)
    return subprocess.CompletedProcess(command, bench.returncode, stdout, stderr)


def end_group(leader: subprocess.Popen[str]) -> None:
    """SIGTERM to every process of ``leader``'s group (the firmwares stop cleanly on it),
    SIGKILL to those left after ``STOP_S``; returns once the group is empty."""
    group = leader.pid
    deadline = time.monotonic() + STOP_S
    with contextlib.suppress(ProcessLookupError):
        os.killpg(group, signal.SIGTERM)
        while True:
            leader.poll()  # reaps the leader: a zombie still counts as the group's
            os.killpg(group, 0)  # ProcessLookupError: the group is empty
            if time.monotonic() > deadline:
                os.killpg(group, signal.SIGKILL)
            time.sleep(0.05)


def test_a_card_count_beyond_the_drivers_boards_is_refused_in_plain_words() -> None:
    run = bench_scaling("--cards", "5")
    assert run.returncode == 2
    assert "a card count from 1 to 4, not '5'" in run.stderr
    assert "Traceback" not in run.stderr


def test_a_tiny_run_gives_every_section_beside_its_baseline() -> None:
    run = bench_scaling("--quick", "--nodes", "2", "--cards", "2", "--cards-seconds",
                       "1")
    assert run.returncode == 0, run.stderr[-2000:]
    document: dict[str, Any] = json.loads(run.stdout)
    assert document["benchmark"] == "scaling"
    assert len(document["machine"]["loadavg"]) == 3
    assert len(document["loadavg_at_end"]) == 3

    (nodes,) = document["active_nodes"]
    assert nodes["nodes"] == 2
    for side in ("cif", "baseline"):
        assert nodes[side]["pdo_loop"]["failures"] == 0, side
        assert nodes[side]["pdo_loop"]["latency_us"]["p99"] > 0, side
        assert nodes[side]["sdo"]["failures"] == 0, side
        assert nodes[side]["sdo"]["expedited_uploads_per_s"] > 0, side
    assert nodes["ratio_to_baseline"]["pdo_loop_p50"] > 0

    assert document["cards"]["seconds"] == 1  # --cards-seconds: the hosts loop for 1 s
    (cards,) = document["cards"]["runs"]
    assert cards["cards"] == 2
    assert [card["board"] for card in cards["per_card"]] == [0, 1]
    for card in cards["per_card"]:
        assert "error" not in card, card
        assert card["failures"] == 0
        assert card["round_trips"] > 0
        assert card["firmware_pct"] > 0 and card["sim_pct"] > 0

    cost = document["frame_cost"]
    windows = cost["windows"]
    assert [w["period_ms"] for w in windows] == [None, 64.0, 16.0, 4.0]
    rates = [w["frames_per_s"] for w in windows]
    assert rates == sorted(rates), "more frames with every shorter period"
    assert rates[1] >= 250, "2 x 16 PDO frames every 64 ms: about 500/s"
    assert windows[-1]["firmware_pct"] > windows[0]["firmware_pct"]

    summary = document["summary"]
    assert [row["nodes"] for row in summary["active_nodes"]] == [2]
    assert [row["cards"] for row in summary["cards"]] == [2]
    assert summary["cpu_per_1000_frames_per_s"]["firmware_pct"] > 0
