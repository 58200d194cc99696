"""CiA 305 layer setting services (LSS): the numbers the card's host side, the simulated
devices and the bus monitor share.

LSS is CiA's, not the card's, but three packages speak it: the CiA 309 gateway's LSS master
(``host_api.cia309.lss``, through the card's layer-2 access), the simulated slaves
(``firmware.sim.lss``) and the monitor's decoder. They sit in layers that never import each
other, so the numbers live here, beside the card's header, once.
"""

from __future__ import annotations

from typing import NamedTuple

LSS_REQUEST_COB_ID = 0x7E5
"""LSS master -> slaves."""
LSS_ANSWER_COB_ID = 0x7E4
"""LSS slaves -> master."""

# Command specifiers (the first data byte of every LSS frame)
SWITCH_STATE_GLOBAL = 0x04
CONFIGURE_NODE_ID = 0x11
CONFIGURE_BIT_TIMING = 0x13
ACTIVATE_BIT_TIMING = 0x15
STORE_CONFIGURATION = 0x17
SWITCH_SELECTIVE_VENDOR = 0x40
SWITCH_SELECTIVE_PRODUCT = 0x41
SWITCH_SELECTIVE_REVISION = 0x42
SWITCH_SELECTIVE_SERIAL = 0x43
SWITCH_SELECTIVE_ANSWER = 0x44
IDENTIFY_REMOTE_VENDOR = 0x46
IDENTIFY_REMOTE_PRODUCT = 0x47
IDENTIFY_REMOTE_REVISION_LOW = 0x48
IDENTIFY_REMOTE_REVISION_HIGH = 0x49
IDENTIFY_REMOTE_SERIAL_LOW = 0x4A
IDENTIFY_REMOTE_SERIAL_HIGH = 0x4B
IDENTIFY_NON_CONFIGURED_REMOTE = 0x4C
IDENTIFY_SLAVE = 0x4F
IDENTIFY_NON_CONFIGURED_SLAVE = 0x50
FASTSCAN = 0x51
INQUIRE_VENDOR = 0x5A
INQUIRE_PRODUCT = 0x5B
INQUIRE_REVISION = 0x5C
INQUIRE_SERIAL = 0x5D
INQUIRE_NODE_ID = 0x5E

# The modes of switch state global
WAITING = 0
"""Every slave to LSS waiting (an unconfigured one given a node-ID then starts up under it)."""
CONFIGURATION = 1
"""Every slave to LSS configuration."""

FASTSCAN_RESET = 0x80
"""Fastscan's BitChecked 80h: every unconfigured slave answers and restarts its scan at the
vendor-ID."""

UNCONFIGURED = 0xFF
"""The node-ID of a slave without one: inquire node-ID reports it, configure node-ID takes it
to make a slave unconfigured."""

# Error codes of the configure answers
ERROR_NONE = 0
ERROR_NODE_ID_RANGE = 1
"""Configure node-ID: the node-ID is out of range (valid: 1..127 and 255)."""
ERROR_BIT_TIMING_NOT_SUPPORTED = 1
"""Configure bit timing: the table selector or the index is not supported."""
ERROR_IMPLEMENTATION_SPECIFIC = 0xFF
"""The spec-error byte holds the device's own code."""

BIT_TIMING_TABLE: dict[int, int] = {
    0: 1_000_000, 1: 800_000, 2: 500_000, 3: 250_000, 4: 125_000,
    6: 50_000, 7: 20_000, 8: 10_000,
}
"""Table selector 0 (the CiA 301 bit timings), index -> bit/s; index 5 is reserved and 9 is
automatic bit rate detection."""


class LssAddress(NamedTuple):
    """The four LSS numbers: object 1018h sub 1..4 of a device, in that order (a tuple, so
    that ``switch_state_selective(*address)`` and 1018h's sub-indexes read alike)."""

    vendor: int
    product: int
    revision: int
    serial: int
