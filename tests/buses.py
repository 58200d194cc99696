"""Back-to-back CAN fixtures: one test body over every python-can transport.

As in python-can's ``test/back2back_test.py``, the transport is a fixture
parameter: ``virtual`` always runs, ``socketcan`` runs on ``vcan0`` and is
skipped, with the reason, where the machine has no SocketCAN or no vcan0.
A test gets a ``CanChannel`` and opens as many bus objects on it as it needs,
one per side (a python-can bus never receives its own frames, so a master and
its nodes each need their own). Every bus is shut down after the test.

Use it from a test module with ``pytest_plugins = ["tests.buses"]`` and a
``can_channel`` argument.
"""

from __future__ import annotations

import socket
import uuid
from collections.abc import Iterator

import can
import pytest

SOCKETCAN_CHANNEL = "vcan0"


HOW_TO_RUN = (f"run it with `make test-vcan` (a User-Mode Linux through tools/vcan-vm), or "
              f"on a Linux with vcan after `modprobe vcan; ip link add dev {SOCKETCAN_CHANNEL} "
              f"type vcan; ip link set up {SOCKETCAN_CHANNEL}`")
"""What a skipped SocketCAN test tells its user."""


def socketcan_missing() -> str | None:
    """Why SocketCAN tests cannot run on this machine, or None when they can."""
    if not hasattr(socket, "AF_CAN"):
        return f"this Python has no AF_CAN (SocketCAN is Linux only): {HOW_TO_RUN}"
    try:
        with socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW) as probe:
            probe.bind((SOCKETCAN_CHANNEL,))
    except OSError as exc:
        return (f"SocketCAN channel {SOCKETCAN_CHANNEL} is unavailable ({exc.strerror}): "
                f"{HOW_TO_RUN}")
    return None


class CanChannel:
    """One CAN channel of one interface; each ``open`` is another bus object on it."""

    def __init__(self, interface: str, channel: str) -> None:
        self.interface = interface
        self.channel = channel
        self._buses: list[can.BusABC] = []

    def open(self) -> can.BusABC:
        bus = can.Bus(interface=self.interface, channel=self.channel)
        self._buses.append(bus)
        return bus

    def close(self) -> None:
        for bus in self._buses:
            bus.shutdown()
        self._buses.clear()

    def __repr__(self) -> str:
        return f"{self.interface}:{self.channel}"


@pytest.fixture(params=["virtual", "socketcan"])
def can_channel(request: pytest.FixtureRequest) -> Iterator[CanChannel]:
    """A channel per test: a fresh virtual channel name, or the shared vcan0."""
    interface: str = request.param
    if interface == "socketcan":
        reason = socketcan_missing()
        if reason is not None:
            pytest.skip(reason)
        channel = CanChannel(interface, SOCKETCAN_CHANNEL)
    else:
        channel = CanChannel(interface, f"{request.node.nodeid}-{uuid.uuid4().hex}")
    yield channel
    channel.close()
