"""The root exception of dbm_tools and the error texts of the CAN task's data checks.

Everything that reads or writes a DBM file or a data set ends in `DbmError`, so
a caller (the firmware loading its flash, a host tool reading a user's file)
needs a single ``except`` and never sees a bare IndexError or struct.error
from a truncated or hostile file. The package's other exceptions derive from it:
``NetworkError`` (a network description), ``EdsError`` (an EDS/DCF file),
``BuildError`` (a description that gives no usable database) and the file
commands' ``UsageError``.
"""

from __future__ import annotations

ERROR_TEXTS: dict[int, str] = {
    0: "no error",
    20: "database not valid for this device",
    48: "timeout",
    52: "area_code unknown",
    53: "overstep of the buffer length",
    55: "faulty parameter detected",
    57: "sequence error",
    59: "data incomplete or faulty",
    60: "data check: double node address parameterized",
    61: "data check: Add-Tab size is too large",
    62: "data check: node parameter size is too large",
    63: "data check: unknown PDO transmsstion type",
    64: "data check: PDO data size is to olarge",
    65: "data check: unknown baud rate",
    66: "data check:COB-ID for SYNC messages out of range",
    67: "data check:SYNC message timer reload value out of range",
    68: "data check: input offset plus length too large",
    69: "data check: output offset plus length too large",
    70: "data check:PDO-cfg inconsistent to ADD-tab table",
    71: "data check: length of ADD-Tab inconsistent",
    72: "data check: length of whole data set inconsistent",
    73: "data check: COB-ID for EMCY message out of range",
    74: "data check: COB-ID for ND_GUARD message out of range",
    75: "data check: Length indicator of one PDO out of range",
    76: "data check: SDO data size is too large",
    212: "faulty reading of a data base",
}
"""msg.f / Err_Event numbers with the seed manual's wording, typos included.

48..76 are the COM_Download table of seed 5.2.5 verbatim, so that a user can
find the text in the manual; 212 is the seed's Err_Event text; 20 is worded
as in docs/dbm.md section 3, because the seed uses 20 only for COM_Upload
(CON_LR), where it means something else.
"""


# The numbers dbm_tools reports, named for the code that raises or checks them.
NO_ERROR = 0
DATABASE_NOT_VALID = 20
BUFFER_OVERSTEP = 53
FAULTY_PARAMETER = 55
DATA_INCOMPLETE = 59
DOUBLE_NODE_ADDRESS = 60
ADD_TAB_TOO_LARGE = 61
NODE_PARAMETERS_TOO_LARGE = 62
TRANSMISSION_TYPE = 63
PDO_DATA_TOO_LARGE = 64
BAUD_RATE = 65
SYNC_COB_ID = 66
SYNC_TIMER = 67
INPUT_OFFSET = 68
OUTPUT_OFFSET = 69
PDO_ADD_TAB = 70
ADD_TAB_LENGTH = 71
WHOLE_LENGTH = 72
EMCY_COB_ID = 73
GUARD_COB_ID = 74
PDO_LENGTH = 75
SDO_DATA_TOO_LARGE = 76
FAULTY_DATABASE = 212


class DbmError(Exception):
    """A DBM file, table record or data set that cannot be read or written; the root of
    every exception dbm_tools raises.

    `number` is set when the defect is one the CAN task reports with a seed
    msg.f number (a data set's length fields), so the firmware can answer a
    COM_Download with it without re-deriving the cause. `record` counts from
    1, like the seed's dbm_fast_read set numbers and the directory slots.
    """

    def __init__(
        self,
        reason: str,
        *,
        table: str | None = None,
        record: int | None = None,
        field: str | None = None,
        number: int | None = None,
    ) -> None:
        self.reason = reason
        self.table = table
        self.record = record
        self.field = field
        self.number = number
        super().__init__(self._describe())

    def _describe(self) -> str:
        where = [
            f"{label} {value}"
            for label, value in (
                ("table", self.table),
                ("record", self.record),
                ("field", self.field),
            )
            if value is not None
        ]
        return f"{self.reason} ({', '.join(where)})" if where else self.reason
