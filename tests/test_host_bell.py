"""The host's doorbell calls in C (``host_api._devflags.change_ring`` and ``wait_ring``).

A Python host changes DevFlags and rings the device in one call, and waits for the card's
rings with one ``poll`` and one ``recvmmsg`` (issue 22). Real sockets: a file system socket
stands in for the device's ``board<N>.bell``, a host's autobound one for the host's; what a
user of the driver would notice is the flag byte, the ring the device receives (its byte
and whom it came from), and whether a wait ends, how soon and with which ring.
"""

from __future__ import annotations

import mmap
import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from dpm.doorbell import RING, WANT_ACK, HostBell
from dpm.layout import DEV_FLAGS, DPM_SIZE
from host_api._devflags import change_ring, wait_ring


@pytest.fixture
def device(tmp_path: Path) -> Iterator[socket.socket]:
    """A datagram socket at a file system path, as the firmware's bell."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(os.fspath(tmp_path / "board0.bell"))
    sock.settimeout(5.0)
    try:
        yield sock
    finally:
        sock.close()


@pytest.fixture
def host() -> Iterator[socket.socket]:
    """A host's socket: Linux autobind, an abstract name of its own, not blocking."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"")
    sock.setblocking(False)
    try:
        yield sock
    finally:
        sock.close()


def test_change_ring_toggles_the_byte_then_rings_the_device_from_the_host(
        device: socket.socket, host: socket.socket) -> None:
    image = mmap.mmap(-1, DPM_SIZE)
    image[DEV_FLAGS] = 0x81
    address = os.fsencode(device.getsockname())
    assert change_ring(image, DEV_FLAGS, 0x04, 0x80, 0x02, host.fileno(), address,
                       RING[0]) == 0x07
    assert image[DEV_FLAGS] == 0x07
    payload, sender = device.recvfrom(16)
    assert payload == RING
    assert sender == host.getsockname()  # the device learns whom to ring back


def test_change_ring_changes_the_flags_when_nobody_listens(tmp_path: Path,
                                                          host: socket.socket) -> None:
    """A ring is a hint: a device not started yet polls when it comes (dpm.doorbell)."""
    image = mmap.mmap(-1, DPM_SIZE)
    gone = os.fsencode(tmp_path / "board0.bell")
    assert change_ring(image, DEV_FLAGS, 0, 0, 0x02, host.fileno(), gone, RING[0]) == 0x02
    assert image[DEV_FLAGS] == 0x02


def test_change_ring_rejects_what_is_no_flag_byte_or_no_socket_path(
        device: socket.socket, host: socket.socket) -> None:
    image = mmap.mmap(-1, DPM_SIZE)
    address = os.fsencode(device.getsockname())
    with pytest.raises(IndexError):
        change_ring(image, DPM_SIZE, 0, 0, 1, host.fileno(), address, 1)
    with pytest.raises(ValueError):
        change_ring(image, DEV_FLAGS, 0, 0, 1, host.fileno(), b"x" * 200, 1)
    with pytest.raises(ValueError):
        change_ring(image, DEV_FLAGS, 0, 0, 1, host.fileno(), b"", 1)
    assert image[DEV_FLAGS] == 0  # nothing changed when the call was refused


def test_wait_ring_takes_every_queued_ring_and_returns_the_last(
        device: socket.socket, host: socket.socket) -> None:
    to = host.getsockname()
    for payload in (RING, bytes([WANT_ACK]), RING, bytes([WANT_ACK])):
        device.sendto(payload, to)
    assert wait_ring(host.fileno(), 1.0) == WANT_ACK
    assert wait_ring(host.fileno(), 0) == -1, "a ring was left in the queue"


def test_wait_ring_waits_its_time_without_a_ring(host: socket.socket) -> None:
    began = time.monotonic()
    assert wait_ring(host.fileno(), 0.05) == -1
    assert time.monotonic() - began >= 0.05


def test_wait_ring_wakes_at_the_ring_and_lets_other_threads_run(
        device: socket.socket, host: socket.socket) -> None:
    """The interpreter lock is released while it waits: the ring comes from a thread."""
    ringer = threading.Timer(0.05, device.sendto, (RING, host.getsockname()))
    began = time.monotonic()
    ringer.start()
    try:
        assert wait_ring(host.fileno(), 10.0) == RING[0]
    finally:
        ringer.join()
    assert time.monotonic() - began < 5.0


def test_a_host_bell_rings_and_hears_the_device_through_the_c_calls(
        tmp_path: Path, device: socket.socket) -> None:
    """HostBell's address for the C ring is the device's socket beside the image."""
    bell = HostBell(tmp_path / "board0.dpm")
    try:
        image = mmap.mmap(-1, DPM_SIZE)
        change_ring(image, DEV_FLAGS, 0, 0, 0x02, bell.sock.fileno(), bell.device_path,
                    RING[0])
        payload, sender = device.recvfrom(16)
        assert (payload, sender) == (RING, bell.sock.getsockname())
        device.sendto(bytes([WANT_ACK]), sender)
        assert wait_ring(bell.sock.fileno(), 5.0) == WANT_ACK
    finally:
        bell.close()



@pytest.fixture
def wake() -> Iterator[tuple[int, int]]:
    """A thread's wake-up pipe, both ends not blocking (the CiA 309 reader's)."""
    r, w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        yield r, w
    finally:
        os.close(r)
        os.close(w)


def test_wait_ring_ends_on_the_wake_up_pipe_and_empties_it(
        host: socket.socket, wake: tuple[int, int]) -> None:
    """-2: woken, not rung; every byte written so far is read, so the next wait waits."""
    r, w = wake
    os.write(w, b"w" * 100)  # more than one read of 64 takes
    assert wait_ring(host.fileno(), 5.0, r) == -2
    with pytest.raises(BlockingIOError):
        os.read(r, 1)
    began = time.monotonic()
    assert wait_ring(host.fileno(), 0.05, r) == -1
    assert time.monotonic() - began >= 0.05


def test_wait_ring_woken_and_rung_at_once_reports_the_ring(
        device: socket.socket, host: socket.socket, wake: tuple[int, int]) -> None:
    r, w = wake
    os.write(w, b"w")
    device.sendto(bytes([WANT_ACK]), host.getsockname())
    assert wait_ring(host.fileno(), 5.0, r) == WANT_ACK
    with pytest.raises(BlockingIOError):
        os.read(r, 1)
    assert wait_ring(host.fileno(), 0) == -1, "the ring was left in the queue"


def test_wait_ring_on_the_wake_up_pipe_wakes_from_another_thread(
        host: socket.socket, wake: tuple[int, int]) -> None:
    r, w = wake
    waker = threading.Timer(0.05, os.write, (w, b"w"))
    began = time.monotonic()
    waker.start()
    try:
        assert wait_ring(host.fileno(), 10.0, r) == -2
    finally:
        waker.join()
    assert time.monotonic() - began < 5.0


def test_wait_ring_without_time_takes_what_is_queued_without_waiting(
        device: socket.socket, host: socket.socket) -> None:
    """Time-out 0 (an event loop's selector said readable): no ppoll first; -1 when none."""
    assert wait_ring(host.fileno(), 0) == -1
    for payload in (bytes([WANT_ACK]), RING):
        device.sendto(payload, host.getsockname())
    assert wait_ring(host.fileno(), 0) == RING[0]
    assert wait_ring(host.fileno(), 0) == -1
