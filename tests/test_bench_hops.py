"""``python -m bench hops``: the slowest round trips say which hop made them slow.

A hop's own p99 cannot say where the slowest round trips lost their time: they need not be
made of any one hop's slowest spans. The breakdown's ``tail`` looks at the round trips at or
above the end-to-end p99 only (issue 22: the PDO loop's p99).
"""

from __future__ import annotations

import os
import select

from bench.hops import breakdown, scheduling

HOPS = ["host -> card", "node", "card -> image"]


def test_the_tail_names_the_hop_of_the_slow_round_trips_not_the_fast_ones() -> None:
    fast = [[0, 10_000, 20_000, 30_000]] * 97
    # The fast round trips' longest hop is the node's; the slow ones wait for the card.
    slow = [[0, 4_000_000, 4_010_000, 4_020_000], [0, 9_000_000, 9_010_000, 9_020_000],
            [0, 10_000, 20_000, 3_000_000]]
    tail = breakdown(HOPS, fast + slow)["tail"]
    assert tail["round_trips"] == 1  # at or above the p99 of 100 round trips: the slowest
    assert [h["longest_in"] for h in tail["hops"]] == [1, 0, 0]
    assert tail["hops"][0]["mean_us"] == 9_000.0
    assert tail["from_us"] > 4_020.0


def test_the_mailbox_path_counts_each_round_trips_wake_ups_per_thread() -> None:
    """``plain_round_trip_scheduling`` (issue 22, the mailbox under load): what each round
    trip cost the host's thread and the card's, from /proc. Here the "card" is this process
    and each step sleeps once (a 0.5 ms select), so the host thread wakes once per step."""
    result = scheduling(lambda: select.select([], [], [], 0.0005), 20, os.getpid())
    assert result["round_trips"] == 20
    host = result["host_thread"]
    assert host["wakeups"] >= 1.0, host
    assert host["cpu_us"] > 0 and host["wait_us"] >= 0 and host["preemptions"] >= 0, host
    assert set(result["card_device_loop"]) == {"cpu_us", "wait_us", "wakeups", "preemptions"}
