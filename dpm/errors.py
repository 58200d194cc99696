"""Error numbers of the driver, the tasks' ``msg.f`` answers and ``Err_Event``.

The driver codes are those of the CIF device driver's CIFUSER.H; the ``msg.f``
and ``Err_Event`` texts are worded as in the seed manual so that a user can
look a number up in either place. Numbers marked [ours] are this project's.
"""

from __future__ import annotations

from enum import IntEnum


class Drv(IntEnum):
    """Driver return codes (CIFUSER.H)."""

    DRV_NO_ERROR = 0
    DRV_BOARD_NOT_INITIALIZED = -1
    DRV_INIT_STATE_ERROR = -2
    DRV_READ_STATE_ERROR = -3
    DRV_CMD_ACTIVE = -4
    DRV_PARAMETER_UNKNOWN = -5
    DRV_WRONG_DRIVER_VERSION = -6
    DRV_PCI_SET_CONFIG_MODE = -7
    DRV_PCI_READ_DPM_LENGTH = -8
    DRV_PCI_SET_RUN_MODE = -9
    DRV_DEV_DPM_ACCESS_ERROR = -10
    DRV_DEV_NOT_READY = -11
    DRV_DEV_NOT_RUNNING = -12
    DRV_DEV_WATCHDOG_FAILED = -13
    DRV_DEV_OS_VERSION_ERROR = -14
    DRV_DEV_SYSERR = -15
    DRV_DEV_MAILBOX_FULL = -16
    DRV_DEV_PUT_TIMEOUT = -17
    DRV_DEV_GET_TIMEOUT = -18
    DRV_DEV_GET_NO_MESSAGE = -19
    DRV_DEV_RESET_TIMEOUT = -20
    DRV_DEV_NO_COM_FLAG = -21
    DRV_DEV_EXCHANGE_FAILED = -22
    DRV_DEV_EXCHANGE_TIMEOUT = -23
    DRV_DEV_COM_MODE_UNKNOWN = -24
    DRV_DEV_FUNCTION_FAILED = -25
    DRV_DEV_DPMSIZE_MISMATCH = -26
    DRV_DEV_STATE_MODE_UNKNOWN = -27
    DRV_USR_OPEN_ERROR = -30
    DRV_USR_INIT_DRV_ERROR = -31
    DRV_USR_NOT_INITIALIZED = -32
    DRV_USR_COMM_ERR = -33
    DRV_USR_DEV_NUMBER_INVALID = -34
    DRV_USR_INFO_AREA_INVALID = -35
    DRV_USR_NUMBER_INVALID = -36
    DRV_USR_MODE_INVALID = -37
    DRV_USR_MSG_BUF_NULL_PTR = -38
    DRV_USR_MSG_BUF_TOO_SHORT = -39
    DRV_USR_SIZE_INVALID = -40
    DRV_USR_SIZE_ZERO = -42
    DRV_USR_SIZE_TOO_LONG = -43
    DRV_USR_DEV_PTR_NULL = -44
    DRV_USR_BUF_PTR_NULL = -45
    DRV_USR_SENDSIZE_TOO_LONG = -46
    DRV_USR_RECVSIZE_TOO_LONG = -47
    DRV_USR_SENDBUF_PTR_NULL = -48
    DRV_USR_RECVBUF_PTR_NULL = -49
    DRV_DEV_NO_VIRTUAL_MEM = -60
    DRV_DEV_UNMAP_VIRTUAL_MEM = -61
    DRV_DEV_REQUEST_IRQ_FAILED = -62
    DRV_USR_FILE_OPEN_FAILED = -100
    DRV_USR_FILE_SIZE_ZERO = -101
    DRV_USR_FILE_NO_MEMORY = -102
    DRV_USR_FILE_READ_FAILED = -103
    DRV_USR_INVALID_FILETYPE = -104
    DRV_USR_FILENAME_INVALID = -105
    DRV_RCS_ERROR_OFFSET = 1000


DRV_TEXT: dict[int, str] = {
    0: "no error",
    -1: "DRIVER board not initialized",
    -2: "DRIVER error in internal init state",
    -3: "DRIVER error in internal read state",
    -4: "DRIVER command on this channel is active",
    -5: "DRIVER unknown parameter in function occurred",
    -6: "DRIVER driver version is incompatible with DLL",
    -7: "DRIVER error while setting the PCI configuration mode",
    -8: "DRIVER could not read the PCI dual-port memory length",
    -9: "DRIVER error while setting the PCI run mode",
    -10: "DEVICE dual port ram not accessible",
    -11: "DEVICE not ready (ready flag failed)",
    -12: "DEVICE not running (running flag failed)",
    -13: "DEVICE watch dog test failed",
    -14: "DEVICE signals wrong OS version",
    -15: "DEVICE error in dual port flags",
    -16: "DEVICE send mailbox is full",
    -17: "DEVICE PutMessage timeout",
    -18: "DEVICE GetMessage timeout",
    -19: "DEVICE no message available",
    -20: "DEVICE RESET command timeout",
    -21: "DEVICE COM-flag not set",
    -22: "DEVICE IO data exchange failed",
    -23: "DEVICE IO data exchange timeout",
    -24: "DEVICE IO data mode unknown",
    -25: "DEVICE Function call failed",
    -26: "DEVICE DPM size differs from configuration",
    -27: "DEVICE State mode unknown",
    -30: "USER driver not opened",
    -31: "USER can't connect with DEV board",
    -32: "USER board not initialized",
    -33: "USER IOCTRL function failed",
    -34: "USER parameter for DEV number invalid",
    -35: "USER parameter InfoArea unknown",
    -36: "USER parameter Number invalid",
    -37: "USER parameter Mode invalid",
    -38: "USER NULL pointer assignment",
    -39: "USER Messagebuffer too short",
    -40: "USER size parameter invalid",
    -42: "USER size parameter with zero length",
    -43: "USER size parameter too long",
    -44: "USER device address null pointer",
    -45: "USER pointer to buffer is a null pointer",
    -46: "USER SendSize parameter too long",
    -47: "USER ReceiveSize parameter too long",
    -48: "USER pointer to send buffer is a null pointer",
    -49: "USER pointer to receive buffer is a null pointer",
    -60: "DEVICE virtual memory not available (Linux)",
    -61: "DEVICE unmapping virtual memory failed (Linux)",
    -62: "DEVICE interrupt request failed (Linux)",
    -100: "USER file not opened",
    -101: "USER file size zero",
    -102: "USER not enough memory to load file",
    -103: "USER file read failed",
    -104: "USER file type invalid",
    -105: "USER file name not valid",
}


def drv_name(code: int) -> str:
    """The CIFUSER.H name of a return code; RCS errors read DRV_RCS_ERROR_OFFSET+f."""
    if code >= Drv.DRV_RCS_ERROR_OFFSET:
        return f"DRV_RCS_ERROR_OFFSET+{code - Drv.DRV_RCS_ERROR_OFFSET}"
    try:
        return Drv(code).name
    except ValueError:
        return f"DRV_UNKNOWN_{code}"


def drv_text(code: int) -> str:
    """Human-readable meaning of a return code, with the task's msg.f text for 1000+f."""
    if code >= Drv.DRV_RCS_ERROR_OFFSET:
        f = code - Drv.DRV_RCS_ERROR_OFFSET
        return f"(RCS) error {f}: {MSG_F_TEXT.get(f, 'unknown error number')}"
    return DRV_TEXT.get(code, "unknown driver error")


# --- msg.f of the tasks' answers -------------------------------------------------

F_OK = 0
F_UNKNOWN_COMMAND = 152
"""COM_Upload's "unknown command, DEVICE needs newer firmware"; [ours] every task
answers an unknown msg.b with it."""
F_UNKNOWN_TASK = 153
"""[ours] the RCS answers a message whose msg.rx names no task with it."""

# PLC task, COM_Shared_Memory (seed 5.1.1)
F_ILLEGAL_AREA = 162
F_BUFFER_OVERFLOW = 163
F_ILLEGAL_COUNT = 165
F_UNKNOWN_DATA_TYPE = 166
F_UNKNOWN_FUNCTION = 167

# RCS task, load function (DBM.md section 3)
F_DB_NOT_VALID = 20
F_WRONG_MESSAGE_NUMBER = 22
F_WRONG_SIZE = 23
F_WRONG_SEQUENCE = 24
F_CHECKSUM = 25

MSG_F_TEXT: dict[int, str] = {
    0: "no error, command executed",
    3: "service was rejected by the node with Abort SDO service",
    17: "no response from the node, node is not present",
    19: "node is not in operational state, access denied",
    20: "database not valid for this device",
    21: "parameter fault in request",
    22: "wrong message number",
    23: "wrong size",
    24: "wrong sequence",
    25: "checksum error",
    48: "timeout",
    51: "maximum receive data buffer overstepped",
    52: "area_code unknown",
    53: "overstep of the buffer length",
    54: "unknown 'function' in HOST message or previous service still active",
    55: "faulty parameter detected",
    57: "sequence error",
    58: "no configuration record for this node",
    59: "data incomplete or faulty",
    60: "data check: double node address parameterized",
    61: "data check: Add-Tab size is too large",
    62: "data check: node parameter size is too large",
    63: "data check: unknown PDO transmission type",
    64: "data check: PDO data size is too large",
    65: "data check: unknown baud rate",
    66: "data check: COB-ID for SYNC messages out of range",
    67: "data check: SYNC message timer reload value out of range",
    68: "data check: input offset plus length too large",
    69: "data check: output offset plus length too large",
    70: "data check: PDO-cfg inconsistent to ADD-tab table",
    71: "data check: length of ADD-Tab inconsistent",
    72: "data check: length of whole data set inconsistent",
    73: "data check: COB-ID for EMCY message out of range",
    74: "data check: COB-ID for ND_GUARD message out of range",
    75: "data check: Length indicator of one PDO out of range",
    76: "data check: SDO data size is too large",
    152: "unknown command, DEVICE needs newer firmware",
    153: "unknown receiver task [ours]",
    161: "remote address out of range",
    162: "illegal address area",
    163: "data address together with the data count results an overflow in the buffer length",
    165: "illegal data count",
    166: "unknown data type",
    167: "unknown function",
    200: "DEVICE is not configured",
}


# --- Err_Event of Task2State (seed manual 4.3) ---------------------------------------

ERR_EVENT_DEVICE_TEXT: dict[int, str] = {
    0: "no error",
    52: "unknown handshake mode was configured",
    56: "baudrate out of range",
    60: "double node address was configured",
    210: "no database",
    212: "faulty reading of a data base",
    220: "HOST-watchdog error",
}
"""Err_Event numbers valid when Err_Node_adr is 255 (the device itself)."""

ERR_EVENT_NODE_TEXT: dict[int, str] = {
    0: "no error",
    30: "guarding failed",
    31: "node has change his state and is not longer operational",
    32: "sequence error in guarding protocol",
    33: "no response to a configured remote frame PDO",
    34: "no response of the node during its configuration",
    35: "the master configured node profile number is different from the node profile number",
    36: "the master configured node device type is different from the node device type",
    37: "unknown SDO response received",
    38: "length indicator of received SDO message unequal 8",
    39: "node not handled, node in stop",
}
"""Err_Event numbers valid when Err_Node_adr names a node."""

ERR_NODE_DEVICE = 255
ERR_EVENT_HANDSHAKE_MODE = 52
ERR_EVENT_NO_DATABASE = 210
ERR_EVENT_FAULTY_DATABASE = 212
ERR_EVENT_HOST_WATCHDOG = 220


def err_event_text(err_node_adr: int, err_event: int) -> str:
    """The seed's text for an Err_Event, looked up in the table its address selects."""
    table = ERR_EVENT_DEVICE_TEXT if err_node_adr == ERR_NODE_DEVICE else ERR_EVENT_NODE_TEXT
    return table.get(err_event, "unknown error event")
