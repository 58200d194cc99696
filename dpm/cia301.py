"""CiA 301 numbers that the card, the simulated nodes and the host tools share.

They are CANopen's, not the card's, but the firmware's master, the simulated devices, the
CiA 309 gateway and the bus monitor all speak them, from layers that never import each
other; so they live here, beside the card's header, once. The card's own NMT command
specifiers (COM_NMT_Module_Protocol carries them) are ``dpm.commands.Nmt``.
"""

from __future__ import annotations

# Predefined connection set: identifiers and bases (the node-ID is added to a base)
COB_ID_NMT = 0x000
COB_ID_SYNC = 0x080
"""The default SYNC identifier; a network may choose another (1005h, the card's COB_ID_SYNC)."""
COB_ID_TIME = 0x100
EMCY_BASE = 0x080
TPDO_BASES = (0x180, 0x280, 0x380, 0x480)
"""TPDO1..4 of a node: what the node sends, the card's inputs."""
RPDO_BASES = (0x200, 0x300, 0x400, 0x500)
"""RPDO1..4 of a node: what the node receives, the card's outputs."""
SDO_RESPONSE_BASE = 0x580
SDO_REQUEST_BASE = 0x600
ERROR_CONTROL_BASE = 0x700
"""Heartbeat, node guarding and boot-up messages."""

# NMT states, as a node reports them: the low 7 bits of its heartbeat or guarding answer
# (CiA 301 7.2.8.3.2). Here once for the card's node handlers, the simulated nodes and the
# bus monitor.
INITIALISING = 0
BOOT_UP = INITIALISING
"""The one byte of a boot-up message: the node leaves INITIALISING (CiA 301 7.2.8.3.3)."""
STOPPED = 4
OPERATIONAL = 5
PRE_OPERATIONAL = 127

# PDO transmission types (1400h/1800h sub 2)
SYNC_ACYCLIC = 0
"""Synchronous, sent at a SYNC only when the data changed (TPDO)."""
SYNC_TYPES_MAX = 240
"""The highest synchronous type: 1..240 send at every n-th SYNC."""
SYNC_RTR = 252
"""Sampled at SYNC, sent on a remote request."""
ASYNC_RTR = 253
"""Sent on a remote request only."""
EVENT_MANUFACTURER = 254
EVENT_PROFILE = 255
EVENT_TYPES = (EVENT_MANUFACTURER, EVENT_PROFILE)
"""Event-driven: manufacturer-specific (254) and device-profile (255)."""
