"""``dpm._quicklock.Lock``: threading.Lock's semantics without a clock reading on a free
acquire (issue 22; the readings are counted in tests/test_cia309_server.py)."""

from __future__ import annotations

import threading
import time

import pytest

from dpm._quicklock import Lock
from tests.conftest import ended


def test_acquire_release_and_the_errors_of_threading_lock() -> None:
    lock = Lock()
    assert not lock.locked()
    assert lock.acquire()
    assert lock.locked()
    assert not lock.acquire(False)
    assert not lock.acquire(timeout=0)
    lock.release()
    with pytest.raises(RuntimeError):
        lock.release()
    with pytest.raises(ValueError):
        lock.acquire(False, 1.0)
    with pytest.raises(ValueError):
        lock.acquire(timeout=-2)
    with lock:
        assert lock.locked()
    assert not lock.locked()


def test_a_timed_acquire_waits_its_time_and_another_thread_may_release() -> None:
    lock = Lock()
    lock.acquire()
    began = time.monotonic()
    assert not lock.acquire(timeout=0.05)
    assert time.monotonic() - began >= 0.05
    releaser = threading.Timer(0.05, lock.release)
    releaser.start()
    assert lock.acquire(timeout=10)  # released by the timer's thread, as threading.Lock may be
    releaser.join()
    lock.release()


def test_threads_that_contend_never_hold_it_together() -> None:
    lock = Lock()
    inside = 0
    overlaps = 0

    def work() -> None:
        nonlocal inside, overlaps
        for _ in range(2_000):
            with lock:
                inside += 1
                if inside != 1:
                    overlaps += 1
                time.sleep(0)
                inside -= 1

    threads = [threading.Thread(target=work) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        assert ended(thread, 30), "a worker did not end"
    assert overlaps == 0 and inside == 0
