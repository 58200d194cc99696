"""``python -m bench.scaling --only cost``: the card's CPU as its bus traffic grows.

A throughput check: the frames a second of each window and the firmware's share of a core
are what load takes from, so this module is ``serial`` (tests/selection.py): ``make
test`` runs it alone on the machine, after the parallel pass. Beside busy workers its
checks lost their margin and failed the parallel pass (docs/testing.md).
"""

from __future__ import annotations

import json
from typing import Any

from tests.scaling_bench import bench_scaling


def test_frame_rates_and_the_firmwares_cpu_grow_with_shorter_periods() -> None:
    run = bench_scaling("--quick", "--only", "cost")
    assert run.returncode == 0, run.stderr[-2000:]
    document: dict[str, Any] = json.loads(run.stdout)
    cost = document["frame_cost"]
    windows = cost["windows"]
    assert [w["period_ms"] for w in windows] == [None, 64.0, 16.0, 4.0]
    rates = [w["frames_per_s"] for w in windows]
    assert rates == sorted(rates), "more frames with every shorter period"
    assert rates[1] >= 250, "2 x 16 PDO frames every 64 ms: about 500/s"
    assert windows[-1]["firmware_pct"] > windows[0]["firmware_pct"]
    assert document["summary"]["cpu_per_1000_frames_per_s"]["firmware_pct"] > 0
