"""The master's worker threads at power-off (``firmware.can.workers``): a job under way ends
before the controller leaves the bus, and one that fails is logged, not kept in its future
where nobody looks (a COM_Set_Guarding cut short at power-off showed nothing)."""

from __future__ import annotations

import logging
import threading

import pytest

import firmware.can.workers
from firmware.can.workers import Workers
from tests.conftest import ended, wait_until, within


def test_a_power_off_waits_for_a_job_under_way(monkeypatch: pytest.MonkeyPatch) -> None:
    """The bound is raised so that a loaded machine cannot end the wait inside the window."""
    monkeypatch.setattr(firmware.can.workers, "WORKERS_JOIN_S", 60.0)
    workers = Workers()
    entered, release = threading.Event(), threading.Event()
    done: list[bool] = []

    def job() -> None:
        entered.set()
        assert within(release.wait, 5), "the test never let the job go"
        done.append(True)

    workers.submit(job)
    assert within(entered.wait, 5), "the job did not start"
    power_off = threading.Thread(target=workers.shutdown, daemon=True)
    try:
        power_off.start()
        assert not ended(power_off, 0.5), "the power-off did not wait for the job"
        release.set()
        assert ended(power_off, 5), "the power-off did not end after the job"
        assert done == [True]
    finally:
        release.set()


def test_a_power_off_waits_no_longer_than_its_bound(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(firmware.can.workers, "WORKERS_JOIN_S", 0.1)
    workers = Workers()
    release = threading.Event()
    workers.submit(release.wait, 60)
    power_off = threading.Thread(target=workers.shutdown, daemon=True)
    try:
        power_off.start()
        assert ended(power_off, 5), "a job blocked for good held the power-off"
    finally:
        release.set()


def test_a_failed_job_is_logged(caplog: pytest.LogCaptureFixture) -> None:
    workers = Workers()

    def job() -> None:
        raise ValueError("mmap closed")

    def failed() -> list[logging.LogRecord]:
        return [record for record in caplog.records if record.message == "worker job failed"]

    with caplog.at_level(logging.ERROR, logger="firmware.can.workers"):
        workers.submit(job)
        workers.shutdown()
        # the future's callbacks run after its waiters are woken: logged a moment later
        wait_until(lambda: bool(failed()), 5, "the failed job logged")
    [record] = failed()
    assert record.exc_info is not None and isinstance(record.exc_info[1], ValueError)
