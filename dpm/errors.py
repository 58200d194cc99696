"""Error numbers of the driver, the tasks' ``msg.f`` answers and ``Err_Event``.

The driver codes are those of the CIF device driver's CIFUSER.H; the ``msg.f``
numbers come as one enum per task (names and texts together), the ``Err_Event``
numbers as one enum per kind of address. Texts are worded as in the seed manual
so that a user can look a number up in either place. Numbers marked [ours] are
this project's.
"""

from __future__ import annotations

from enum import IntEnum


class DpmError(Exception):
    """The root of what dpm raises: ``MessageError`` (bytes that are no message of the
    card's) and ``BoardBusyError`` (a board another firmware serves)."""


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
        return f"(RCS) error {f}: {msg_f_text(f)}"
    return DRV_TEXT.get(code, "unknown driver error")


# --- msg.f of the tasks' answers -------------------------------------------------


class MsgF(IntEnum):
    """A task's msg.f number and the seed's text for it; each task has its own table.

    The seed words a number per command, and a few numbers mean different things in
    different tasks (20 is the RCS's "database not valid" and the CAN task's "local
    resource"), so each task gets one enum, its members carrying ``text``.
    """

    text: str

    def __new__(cls, value: int, text: str) -> MsgF:
        member = int.__new__(cls, value)
        member._value_ = value
        member.text = text
        return member

    @classmethod
    def text_of(cls, number: int, default: str = "unknown error number") -> str:
        """The text of ``number`` in this table, or ``default`` for a number it lacks."""
        member = cls._value2member_map_.get(number)
        return member.text if isinstance(member, MsgF) else default


class RcsF(MsgF):
    """msg.f of the RCS task (msg.rx 0): the load function (seed 6.4, docs/dbm.md section 3)."""

    NO_ERROR = 0, "no error, command executed"
    DB_NOT_VALID = 20, "database not valid for this device"
    PARAMETER_FAULT = 21, "parameter fault in request"
    """[ours] an unknown load-function mode or a short message."""
    WRONG_MESSAGE_NUMBER = 22, "wrong message number"
    WRONG_SIZE = 23, "wrong size"
    WRONG_SEQUENCE = 24, "wrong sequence"
    CHECKSUM = 25, "checksum error"
    FLASH_FULL = 53, "overstep of the buffer length"
    """[ours] the flash could not take the database (its file system full or failing): the
    seed's "overstep of the buffer length"; the stored database stays as it was."""
    UNKNOWN_COMMAND = 152, "unknown command, DEVICE needs newer firmware"
    """COM_Upload's text; [ours] every task answers an unknown msg.b with it."""
    UNKNOWN_TASK = 153, "unknown receiver task [ours]"
    """[ours] the RCS answers a message whose msg.rx names no task with it."""
    NO_DATABASE = 200, "DEVICE is not configured"
    """[ours] an upload with nothing stored."""
    INTERNAL_ERROR = 254, "internal error of the firmware [ours]"
    """[ours] a handler failed unexpectedly; the firmware stays up and says so."""


class PlcF(MsgF):
    """msg.f of the PLC task (msg.rx 2): COM_Shared_Memory (seed 5.1.1)."""

    NO_ERROR = 0, "no error, command executed"
    UNKNOWN_COMMAND = 152, "unknown command, DEVICE needs newer firmware"
    REMOTE_ADDRESS = 161, "remote address out of range"
    ILLEGAL_AREA = 162, "illegal address area"
    BUFFER_OVERFLOW = (
        163, "data address together with the data count results an overflow in the buffer length"
    )
    ILLEGAL_COUNT = 165, "illegal data count"
    UNKNOWN_DATA_TYPE = 166, "unknown data type"
    UNKNOWN_FUNCTION = 167, "unknown function"
    INTERNAL_ERROR = 254, "internal error of the firmware [ours]"


class CanF(MsgF):
    """msg.f of the CAN task (msg.rx 3), seed 5.2.

    The data-check texts (48..76) are the COM_Download table of seed 5.2.5 letter for
    letter, typos included, so that a user finds them in the manual; where the seed words
    a number differently per command, the text is the most general one.
    """

    NO_ERROR = 0, "no error"
    SDO_ABORT = 3, "service was rejected by the node with Abort SDO service"
    NO_DESCRIPT_TABLE = 3, "service was rejected by the node with Abort SDO service"
    """[ours] GET_CONFIGURATION without a DESCRIPT table; the same number as SDO_ABORT (an
    enum alias), so it reads with SDO_ABORT's text."""
    NO_RESPONSE = 17, "no response from the node, node is not present"
    NODE_BUSY = 19, "node is not in operational state, access denied"
    LOCAL_RESOURCE = 20, "local resource not available"
    PARAMETER_FAULT = 21, "parameter fault in request"
    TIMEOUT = 48, "timeout"
    SDO_BUFFER = 51, "maximum receive data buffer overstepped"
    AREA_CODE = 52, "area_code unknown"
    BUFFER_LENGTH = 53, "overstep of the buffer length"
    SDO_FUNCTION = (
        54, "unknown 'function' in HOST message or previous service still active"
    )
    FAULTY_PARAMETER = 55, "faulty parameter detected"
    SEQUENCE = 57, "sequence error"
    NO_DESCRIPT_RECORD = 58, "no configuration record for this node"
    """[ours] GET_CONFIGURATION for a node the DESCRIPT table does not hold."""
    INCOMPLETE = 59, "data incomplete or faulty"
    DOUBLE_ADDRESS = 60, "data check: double node address parameterized"
    ADD_TAB_TOO_LARGE = 61, "data check: Add-Tab size is too large"
    NODE_PARAMETERS_TOO_LARGE = 62, "data check: node parameter size is too large"
    TRANSMISSION_TYPE = 63, "data check: unknown PDO transmsstion type"
    PDO_DATA_TOO_LARGE = 64, "data check: PDO data size is to olarge"
    BAUD_RATE = 65, "data check: unknown baud rate"
    SYNC_COB_ID = 66, "data check:COB-ID for SYNC messages out of range"
    SYNC_TIMER = 67, "data check:SYNC message timer reload value out of range"
    INPUT_OFFSET = 68, "data check: input offset plus length too large"
    OUTPUT_OFFSET = 69, "data check: output offset plus length too large"
    PDO_ADD_TAB = 70, "data check:PDO-cfg inconsistent to ADD-tab table"
    ADD_TAB_LENGTH = 71, "data check: length of ADD-Tab inconsistent"
    WHOLE_LENGTH = 72, "data check: length of whole data set inconsistent"
    EMCY_COB_ID = 73, "data check: COB-ID for EMCY message out of range"
    GUARD_COB_ID = 74, "data check: COB-ID for ND_GUARD message out of range"
    PDO_LENGTH = 75, "data check: Length indicator of one PDO out of range"
    SDO_DATA_TOO_LARGE = 76, "data check: SDO data size is too large"
    UNKNOWN_COMMAND = 152, "unknown command, DEVICE needs newer firmware"
    NODE_DIAG_ADDRESS = 161, "remote address out of range"
    NOT_CONFIGURED = 200, "DEVICE is not configured"
    FLASH_DATABASE_RUNS = 201, "a database from flash runs: no on-line download [ours]"
    """[ours] COM_Start_Seq, COM_Download, COM_End_Seq while a database from flash runs: the
    seed (5.2.2) says the on-line download cannot be used then, but gives no number."""
    INTERNAL_ERROR = 254, "internal error of the firmware [ours]"


def msg_f_text(f: int) -> str:
    """The text of an msg.f whose task is unknown (a driver code 1000 + f).

    The driver returns 1000 + f mostly for the RCS's load function (DevDownload), so the
    RCS's table is asked first, then the CAN task's and the PLC task's.
    """
    table = next((t for t in (RcsF, CanF, PlcF) if f in t._value2member_map_), RcsF)
    return table.text_of(f)


# The names the firmware's device loop and tasks share, as plain names.
F_UNKNOWN_COMMAND = RcsF.UNKNOWN_COMMAND
F_UNKNOWN_TASK = RcsF.UNKNOWN_TASK
F_INTERNAL_ERROR = RcsF.INTERNAL_ERROR


# --- Err_Event of Task2State (seed manual 4.3) ---------------------------------------

ERR_NODE_DEVICE = 255
"""Err_Node_adr of an event of the device itself."""


class DeviceEvent(MsgF):
    """Err_Event numbers valid when Err_Node_adr is 255 (the device itself)."""

    NO_ERROR = 0, "no error"
    HANDSHAKE_MODE = 52, "unknown handshake mode was configured"
    BAUD_RATE = 56, "baudrate out of range"
    DOUBLE_ADDRESS = 60, "double node address was configured"
    NO_DATABASE = 210, "no database"
    FAULTY_DATABASE = 212, "faulty reading of a data base"
    HOST_WATCHDOG = 220, "HOST-watchdog error"


class NodeEvent(MsgF):
    """Err_Event numbers valid when Err_Node_adr names a node."""

    NO_ERROR = 0, "no error"
    GUARDING_FAILED = 30, "guarding failed"
    LEFT_OPERATIONAL = 31, "node has change his state and is not longer operational"
    GUARD_SEQUENCE = 32, "sequence error in guarding protocol"
    NO_RTR_RESPONSE = 33, "no response to a configured remote frame PDO"
    NO_RESPONSE = 34, "no response of the node during its configuration"
    PROFILE_MISMATCH = (
        35,
        "the master configured node profile number is different from the node profile number",
    )
    DEVICE_TYPE_MISMATCH = (
        36, "the master configured node device type is different from the node device type"
    )
    UNKNOWN_SDO_RESPONSE = 37, "unknown SDO response received"
    SDO_LENGTH = 38, "length indicator of received SDO message unequal 8"
    NODE_STOPPED = 39, "node not handled, node in stop"


ERR_EVENT_HANDSHAKE_MODE = DeviceEvent.HANDSHAKE_MODE
ERR_EVENT_NO_DATABASE = DeviceEvent.NO_DATABASE
ERR_EVENT_FAULTY_DATABASE = DeviceEvent.FAULTY_DATABASE
ERR_EVENT_HOST_WATCHDOG = DeviceEvent.HOST_WATCHDOG
ERR_EVENT_OF_DATA_CHECK: dict[int, DeviceEvent] = {
    CanF.BAUD_RATE: DeviceEvent.BAUD_RATE, CanF.DOUBLE_ADDRESS: DeviceEvent.DOUBLE_ADDRESS}
"""A database in flash that fails these data checks (f 65 unknown baud rate, f 60 double
node address) shows the device's own Err_Event at address 255 (seed 4.3), not 212."""


ERROR_CONTROL_TEXT: dict[str | None, str] = {
    "heartbeat": "heartbeat failed: no heartbeat within the consumer time (the seed's "
                 "\"guarding failed\")",
    "guarding": "guarding failed: no answer to node guarding within the life time",
    None: "guarding failed: no heartbeat or guarding answer in time (the node's error control)",
}
"""Err_Event 30 by the node's error control [ours]. The seed has one text, "guarding
failed", for both protocols (the node's HRTBT bit, seed 5.2.5.3, chooses): on a heartbeat
node it sent its user looking for a guarding fault. Each text keeps the seed's words, so a
number looked up in either place reads the same; None: the node's kind is not known."""


def err_event_text(err_node_adr: int, err_event: int, error_control: str | None = None) -> str:
    """The seed's text for an Err_Event, looked up in the table its address selects.

    ``error_control`` is the node's supervision, "heartbeat" or "guarding" (its network
    description's error_control, or the card's HRTBT bit), where the caller knows it: the
    one set of texts the firmware's log, status, top and the gateway show."""
    if err_node_adr == ERR_NODE_DEVICE:
        return DeviceEvent.text_of(err_event, "unknown error event")
    if err_event == NodeEvent.GUARDING_FAILED:
        return ERROR_CONTROL_TEXT.get(error_control, ERROR_CONTROL_TEXT[None])
    return NodeEvent.text_of(err_event, "unknown error event")
