"""The root exception of dbm_tools.

Everything that reads or writes a DBM file or a data set ends in `DbmError`, so
a caller (the firmware loading its flash, a host tool reading a user's file)
needs a single ``except`` and never sees a bare IndexError or struct.error
from a truncated or hostile file. The package's other exceptions derive from it:
``NetworkError`` (a network description), ``EdsError`` (an EDS/DCF file),
``BuildError`` (a description that gives no usable database) and the file
commands' ``UsageError``.
"""

from __future__ import annotations


class DbmError(Exception):
    """A DBM file, table record or data set that cannot be read or written; the root of
    every exception dbm_tools raises.

    `number` is set when the defect is one the CAN task reports with a seed
    msg.f number (``dpm.errors.CanF``) (a data set's length fields), so the firmware can answer a
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
