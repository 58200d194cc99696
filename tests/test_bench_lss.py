"""``python -m bench.lss`` on a machine too slow for its scans: a message, not a traceback."""

from __future__ import annotations

import pytest

from bench import lss


def test_a_fast_scan_that_finds_no_slave_is_a_message_not_a_traceback(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """canopen's fast_scan reads a step unanswered within RESPONSE_TIMEOUT as a 1-bit, and a
    loaded machine answers late: it then finds fewer than 8 slaves, or none. 9aa3708 went on
    to the card's scans and ended in a traceback: the median of no slave (StatisticsError),
    or, at load 20, the card's own fastscan giving up (LssError 103). A step time-out of 0
    stands in for the slow machine here (none can be ordered up): the run stops at the
    baseline's scan with one line and status 1, before any card starts."""
    monkeypatch.setattr(lss, "DEFAULT_SCAN_TIMEOUT_S", 0.0)
    monkeypatch.setattr(lss, "simulated_card", _no_card)
    assert lss.main([]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "python -m bench.lss: canopen's fast_scan found 0 of 8 slaves" in err
    assert "load average" in err and "quieter" in err


def _no_card(description: str) -> None:
    raise AssertionError("the card's scan ran after the baseline had failed")
