"""``python -m bench.scaling``: the scaling figures of issue 22 from a tiny run.

The full run takes minutes and its figures depend on the machine; what a test can hold
it to is that each section runs against real cards and nodes, loses nothing, and
reports each figure where the README's table takes it from, beside its baseline. The
frame cost section measures frame rates and CPU shares, which load moves: it is checked
alone on the machine (``test_bench_frame_cost.py``, marker ``serial``).
"""

from __future__ import annotations

import json
from typing import Any

from tests.scaling_bench import bench_scaling


def test_a_card_count_beyond_the_drivers_boards_is_refused_in_plain_words() -> None:
    run = bench_scaling("--cards", "5")
    assert run.returncode == 2
    assert "a card count from 1 to 4, not '5'" in run.stderr
    assert "Traceback" not in run.stderr


def test_a_tiny_run_gives_nodes_and_cards_beside_their_baselines() -> None:
    run = bench_scaling("--quick", "--only", "nodes", "cards", "--nodes", "2", "--cards", "2",
                        "--cards-seconds", "1")
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

    summary = document["summary"]
    assert [row["nodes"] for row in summary["active_nodes"]] == [2]
    assert [row["cards"] for row in summary["cards"]] == [2]
