"""Flag bits of HostFlags (device writes) and DevFlags (host writes).

Each COM/ACK pair shares one bit position, so the state of a channel is
``HostFlags XOR DevFlags`` at that bit (docs/dpm.md section 2).
"""

from __future__ import annotations

from enum import IntFlag

# Plain ints for the hot paths: an IntFlag operand sends every ``&`` and
# ``^`` through the enum machinery, which costs microseconds per flag test.
# HostFlags, written by the device:
HOSTCOM = 0x01
DEVACK = 0x02
PDACK = 0x04
STATECOM = 0x08
SPCACK = 0x10
COM = 0x20
RUN = 0x40
READY = 0x80
# DevFlags, written by the host:
HOSTACK = 0x01
DEVCOM = 0x02
PDCOM = 0x04
STATEACK = 0x08
SPCCOM = 0x10
NOTREADY = 0x20
INIT = 0x40
RESET = 0x80


class HostFlag(IntFlag):
    """Bits of HostFlags at 0x1FFE, for display and decoding."""

    HOSTCOM = HOSTCOM
    DEVACK = DEVACK
    PDACK = PDACK
    STATECOM = STATECOM
    SPCACK = SPCACK
    COM = COM
    RUN = RUN
    READY = READY


class DevFlag(IntFlag):
    """Bits of DevFlags at 0x1FFF, for display and decoding."""

    HOSTACK = HOSTACK
    DEVCOM = DEVCOM
    PDCOM = PDCOM
    STATEACK = STATEACK
    SPCCOM = SPCCOM
    NOTREADY = NOTREADY
    INIT = INIT
    RESET = RESET


# The handshake channels: the bit position both sides toggle.
HOST_MBX = 0x01
"""Device -> host mailbox: a message waits while the bits differ."""
DEV_MBX = 0x02
"""Host -> device mailbox: free while the bits are equal."""
PD = 0x04
"""Process data handshake."""
STATE = 0x08
"""State field handshake (DevExchangeIOErr)."""
SPC = 0x10
"""Special control: a level the device mirrors."""

DEVICE_TOGGLE_BITS = HOST_MBX | DEV_MBX | PD | STATE | SPC
"""HostFlags bits that take part in a handshake (the rest are levels)."""


def pending(host_flags: int, dev_flags: int, channel: int) -> bool:
    """True when the two sides' bits of ``channel`` differ."""
    return bool((host_flags ^ dev_flags) & channel)
