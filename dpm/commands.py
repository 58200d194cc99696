"""Command codes (msg.b / msg.a) of the card's three tasks, and the numbers their messages carry.

This module and its siblings in ``dpm`` are the card's header: every other package imports
the numbers from here and defines none of its own, so the firmware, the host side, the
benchmarks and libcif's C header (checked against this module by a test) cannot drift apart.
Names follow the seed manual (``COM_SDO_Up_Download`` is ``Com.SDO_UP_DOWNLOAD``);
``docs/card-commands.md`` describes every message.
"""

from __future__ import annotations

import struct
from enum import IntEnum

from dpm.errors import CanF, NodeEvent
from dpm.message import Task


class Rcs(IntEnum):
    """Commands of the RCS task (msg.rx 0)."""

    LOAD_FUNCTION = 6
    """Download, upload, delete and directory of the flash database (seed 6.4)."""


class LoadMode(IntEnum):
    """Mode byte (d[0]) of an RCS load-function message."""

    UPLOAD = 2
    DOWNLOAD = 3
    DELETE = 4
    DIRECTORY = 5


LOAD_SEGMENT = 8
"""Start segment of the CANopen database in a load-function message."""
LOAD_CHUNK = 240
"""Data bytes per load-function message after the first."""
LOAD_FIRST_LENGTH = 51
"""Length of the first download message: mode, segment, header and root bytes."""
LOAD_ROOT_BYTES = 16
"""The data area's root words w0..w7 in the first download message."""
DIRECTORY_ENTRY = struct.Struct("<B9sHHI")
"""[ours] one entry of the flash directory (mode 5): bSegment, szSegmentName[9], usLength,
usChecksum, ulStored (Unix time of the store)."""


class Plc(IntEnum):
    """Commands of the PLC task (msg.rx 2)."""

    COM_SHARED_MEMORY = 17


# data_area of a COM_Shared_Memory message (seed 5.1.1)
AREA_BY_FUNCTION = 0
"""The area follows the function: read the receive area, write the send area."""
AREA_RECEIVE = 1
AREA_SEND = 2


class Com(IntEnum):
    """Commands of the CAN task (msg.rx 3), seed chapter 5.2; 110-117 are ours [ours]."""

    GET_CONFIGURATION = 15
    SEND_CANMSG_TRANSPARENT = 65
    RECEIVE_TRANSPARENT = 65
    """An unsolicited indication to the host carries the same code as the send command."""
    NODE_DIAG = 66
    START_SEQ = 67
    DOWNLOAD = 68
    END_SEQ = 69
    SDO_UP_DOWNLOAD = 74
    UPLOAD = 80
    RESET_ERR_EVENT = 81
    CFGRX_LAYER2 = 82
    RX_CAN_LAYER2 = 83
    TX_CAN_LAYER2 = 84
    NMT_MODULE_PROTOCOL = 96
    SET_SDO_TIMEOUT = 110
    SET_GUARDING = 111
    SET_HEARTBEAT_CONSUMER = 112
    SET_EMCY_CONSUMER = 113
    SET_HEARTBEAT_PRODUCER = 114
    SET_NODE_ID = 115
    BOOTUP_FORWARDING = 116
    BOOTUP_INDICATION = 117


UNANSWERED = frozenset({(int(Task.CAN), int(Com.TX_CAN_LAYER2))})
"""(msg.rx, msg.b) of the requests the card does not answer, whatever msg.e:
COM_Tx_CAN_Layer2 (seed 5.3.1, "The message itself does not have any answer message";
its table gives msg.e 0, "extension, not used"). [ours] The emulated card answers one it
cannot execute (no well-formed frame) with its msg.f, as it answers every error, even to a
request sent with msg.e NAK (RCS_NAK_MSK: no answer when all goes well, seed 5.2.10). The
drivers' ledgers await no answer to a request of this set nor to one with the NAK bit
(``host_api.locks``; libcif/src/chanlock.c, with this set's one member as ``UNANSWERED_RX``
and ``UNANSWERED_B`` in libcif/src/dpm.h, checked by tests/test_libcif_headers.py)."""


class Nmt(IntEnum):
    """NMT command specifiers (CiA 301), as COM_NMT_Module_Protocol and the bus carry them."""

    START = 0x01
    STOP = 0x02
    PREOPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


NMT_COMMANDS = frozenset(Nmt)

# Areas and sizes of CAN-task messages (seed 5.2)
AREA_BUS = 127
"""COM_Download / COM_Upload area code of the bus parameters."""
AREA_EXTENDED = 128
"""... of the extended bus parameters."""
DOWNLOAD_AREA_SIZE = 1000
"""Bytes of the download area that one COM_Start_Seq sequence may fill."""
MAX_LEN_DATA_UNIT = 240
"""Bytes of a node data set per COM_Download (COM_Start_Seq's Max_Len_Data_Unit)."""
SDO_MAX_DATA = 247
"""Data bytes in one COM_SDO_Up_Download message: 255 minus the telegram header."""
LONG_SDO_LIMIT = 65536
"""[ours] bytes one long (concatenated) SDO transfer may carry (docs/card-commands.md)."""
NODE_DIAG_SIZE = 48
"""Bytes of a COM_Node_Diag answer."""

# The seed's spellings as plain names, so a module reads like the manual's tables:
# ``from dpm.commands import COM_NODE_DIAG``. Each is the enum member above, never a new number.
LOAD_FUNCTION = Rcs.LOAD_FUNCTION
MODE_UPLOAD = LoadMode.UPLOAD
MODE_DOWNLOAD = LoadMode.DOWNLOAD
MODE_DELETE = LoadMode.DELETE
MODE_DIRECTORY = LoadMode.DIRECTORY
COM_SHARED_MEMORY = Plc.COM_SHARED_MEMORY
GET_CONFIGURATION = Com.GET_CONFIGURATION
COM_SEND_CANMSG_TRANSPARENT = Com.SEND_CANMSG_TRANSPARENT
COM_RECEIVE_TRANSPARENT = Com.RECEIVE_TRANSPARENT
COM_NODE_DIAG = Com.NODE_DIAG
COM_START_SEQ = Com.START_SEQ
COM_DOWNLOAD = Com.DOWNLOAD
COM_END_SEQ = Com.END_SEQ
COM_SDO_UP_DOWNLOAD = Com.SDO_UP_DOWNLOAD
COM_UPLOAD = Com.UPLOAD
COM_RESET_ERR_EVENT = Com.RESET_ERR_EVENT
COM_CFGRX_LAYER2 = Com.CFGRX_LAYER2
COM_RX_CAN_LAYER2 = Com.RX_CAN_LAYER2
COM_TX_CAN_LAYER2 = Com.TX_CAN_LAYER2
COM_NMT_MODULE_PROTOCOL = Com.NMT_MODULE_PROTOCOL
COM_SET_SDO_TIMEOUT = Com.SET_SDO_TIMEOUT
COM_SET_GUARDING = Com.SET_GUARDING
COM_SET_HEARTBEAT_CONSUMER = Com.SET_HEARTBEAT_CONSUMER
COM_SET_EMCY_CONSUMER = Com.SET_EMCY_CONSUMER
COM_SET_HEARTBEAT_PRODUCER = Com.SET_HEARTBEAT_PRODUCER
COM_SET_NODE_ID = Com.SET_NODE_ID
COM_BOOTUP_FORWARDING = Com.BOOTUP_FORWARDING
COM_BOOTUP_INDICATION = Com.BOOTUP_INDICATION
NMT_START = Nmt.START
NMT_STOP = Nmt.STOP
NMT_PREOP = Nmt.PREOPERATIONAL
NMT_RESET_NODE = Nmt.RESET_NODE
NMT_RESET_COMM = Nmt.RESET_COMMUNICATION

# msg.f of CAN-task answers and the Err_Event numbers of a node that the CiA 309 gateway
# translates into 309-3 errors, under the names it uses: each is a member of dpm.errors'
# one table (CanF, NodeEvent), never a number of its own.
F_SDO_ABORT = CanF.SDO_ABORT
F_NO_RESPONSE = CanF.NO_RESPONSE
F_NOT_OPERATIONAL = CanF.NODE_BUSY
F_LOCAL_RESOURCE = CanF.LOCAL_RESOURCE
F_PARAMETER_FAULT = CanF.PARAMETER_FAULT
F_TIMEOUT = CanF.TIMEOUT
F_RECEIVE_BUFFER_OVERSTEPPED = CanF.SDO_BUFFER
F_BUFFER_LENGTH_OVERSTEPPED = CanF.BUFFER_LENGTH
F_SERVICE_ACTIVE = CanF.SDO_FUNCTION
F_FAULTY_PARAMETER = CanF.FAULTY_PARAMETER
F_SEQUENCE_ERROR = CanF.SEQUENCE
F_DOUBLE_NODE_ADDRESS = CanF.DOUBLE_ADDRESS
F_REMOTE_ADDRESS_RANGE = CanF.NODE_DIAG_ADDRESS
F_NOT_CONFIGURED = CanF.NOT_CONFIGURED
F_HANDLER_FAILED = CanF.INTERNAL_ERROR
ERR_EVENT_GUARDING_FAILED = NodeEvent.GUARDING_FAILED
ERR_EVENT_LEFT_OPERATIONAL = NodeEvent.LEFT_OPERATIONAL
ERR_EVENT_GUARD_SEQUENCE = NodeEvent.GUARD_SEQUENCE
ERR_EVENT_NODE_STOPPED = NodeEvent.NODE_STOPPED
NODE_DIAG_EMCY_ENTRY = 8
"""Bytes of one EMCY entry in a COM_Node_Diag answer."""

# For libcif's com_user.h and rcsdef.h (checked against them by tests/test_libcif_headers.py).
RCS_SYSTEM_FUNCTION = 1
"""RCS_B_SYSFKT (rcsdef.h): msg.b of the RCS task's system functions."""


class NodeState(IntEnum):
    """Node_state of a COM_Node_Diag answer: the node's guarding answer (seed 5.2.7)."""

    DISCONNECTED = 1
    CONNECTING = 2
    PREPARING = 3
    PREPARED = 4
    OPERATIONAL = 5
    PREOPERATIONAL = 127
