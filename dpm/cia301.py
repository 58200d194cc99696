"""CiA 301 numbers that the card, the simulated nodes and the host tools share.

They are CANopen's, not the card's, but the firmware's master, the simulated devices, the
CiA 309 gateway and the bus monitor all speak them, from layers that never import each
other; so they live here, beside the card's header, once. The card's own NMT command
specifiers (COM_NMT_Module_Protocol carries them) are ``dpm.commands.Nmt``.
"""

from __future__ import annotations

import struct

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
SDO_INITIATE = struct.Struct("<BHB")
"""An SDO initiate request's or response's command byte, index and subindex; four bytes of
data (an expedited value, a size) follow. The master's client and the simulated nodes'
server both make them."""
ERROR_CONTROL_BASE = 0x700
"""Heartbeat, node guarding and boot-up messages."""

NODE_ID_MAX = 127
"""The highest node-ID (CiA 301: 1..127; 0 is NMT's "all nodes" where a command allows it)."""
FUNCTION_CODE_MASK = 0x780
"""The function code of a predefined connection set identifier; the rest is the node-ID."""
NODE_ID_MASK = 0x7F
"""The node-ID's bits of such an identifier."""

# NMT states, as a node reports them: the low 7 bits of its heartbeat or guarding answer
# (CiA 301 7.2.8.3.2). Here once for the card's node handlers, the simulated nodes and the
# bus monitor.
INITIALISING = 0
BOOT_UP = INITIALISING
"""The one byte of a boot-up message: the node leaves INITIALISING (CiA 301 7.2.8.3.3)."""
STOPPED = 4
OPERATIONAL = 5
PRE_OPERATIONAL = 127
STATE_MASK = 0x7F
"""The state's bits in a heartbeat or guarding answer's one byte."""
TOGGLE_BIT = 0x80
"""Node guarding's toggle bit, beside the state in the answer's byte (always 0 in a heartbeat)."""

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

# SDO abort codes (CiA 301 7.2.4.3.17, table 22). The master's SDO client, the simulated
# nodes' servers and the CiA 309 gateway all send or read them; the texts a 309-3 answer
# carries are the gateway's (host_api.cia309.formatters).
ABORT_TOGGLE = 0x0503_0000
"""Toggle bit not alternated."""
ABORT_TIMEOUT = 0x0504_0000
"""SDO protocol timed out."""
ABORT_UNKNOWN_COMMAND = 0x0504_0001
"""Client/server command specifier not valid or unknown."""
ABORT_BLOCK_SIZE = 0x0504_0002
ABORT_SEQUENCE_NUMBER = 0x0504_0003
ABORT_CRC = 0x0504_0004
ABORT_OUT_OF_MEMORY = 0x0504_0005
ABORT_UNSUPPORTED_ACCESS = 0x0601_0000
ABORT_WRITE_ONLY = 0x0601_0001
"""Attempt to read a write-only object."""
ABORT_READ_ONLY = 0x0601_0002
"""Attempt to write a read-only object."""
ABORT_NO_OBJECT = 0x0602_0000
ABORT_NOT_MAPPABLE = 0x0604_0041
ABORT_PDO_LENGTH = 0x0604_0042
"""The objects to be mapped would exceed the PDO's length."""
ABORT_PARAMETER_INCOMPATIBLE = 0x0604_0043
ABORT_INTERNAL_INCOMPATIBLE = 0x0604_0047
ABORT_HARDWARE = 0x0606_0000
ABORT_TYPE_LENGTH_MISMATCH = 0x0607_0010
"""Data type does not match, length of service parameter does not match."""
ABORT_TYPE_LENGTH_HIGH = 0x0607_0012
ABORT_TYPE_LENGTH_LOW = 0x0607_0013
ABORT_NO_SUBINDEX = 0x0609_0011
ABORT_VALUE_RANGE = 0x0609_0030
"""Invalid value for parameter (download only)."""
ABORT_VALUE_HIGH = 0x0609_0031
ABORT_VALUE_LOW = 0x0609_0032
ABORT_MAX_BELOW_MIN = 0x0609_0036
ABORT_NO_SDO_CONNECTION = 0x060A_0023
"""Resource not available: SDO connection."""
ABORT_GENERAL = 0x0800_0000
ABORT_CANNOT_STORE = 0x0800_0020
"""Data cannot be transferred or stored to the application."""
ABORT_LOCAL_CONTROL = 0x0800_0021
"""... because of local control."""
ABORT_DEVICE_STATE = 0x0800_0022
"""... because of the present device state."""
ABORT_NO_DICTIONARY = 0x0800_0023
"""Object dictionary dynamic generation fails or no object dictionary is present."""
ABORT_NO_DATA = 0x0800_0024
