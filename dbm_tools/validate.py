"""The CAN task's data checks, answering with the seed's msg.f numbers (seed 5.2.5).

The firmware runs these on every COM_Download data set and on every record of
a stored database at reset, and host tools run `check_dbm` before a download,
so both see the same verdicts. The seed lists the numbers but not the limits
behind them; those chosen here:

- download area 1000 bytes (seed 5.2.5): a longer data set is 53, an
  usNodeParaLen above it 62;
- node addresses 1..127 (seed 6.3.2), the master's own bNodeID 0..126
  (seed 5.2.5.3.1, 0 = none); otherwise 55;
- COB-IDs 1..2047 everywhere [ours]: the values both of the seed's statements
  allow. Its message tables say "1-2048" (EMCY, ND_GUARD, SYNC), its prose "0
  to 2047" (usCobIDEmcy, usCobIDGuard) and "1 to 2048" (SYNC); 0 is NMT, which
  no node may send on, and 2048 does not fit 11 bits. EMCY 73, ND_GUARD 74,
  SYNC 66, a PDO 55 (no number of its own);
- PDO length (bLength & 0x7F) 1..8: 75; transmission types of CiA 301,
  0..240 and 252..255: 63;
- SDO bLength 1..4 (the 4-byte value field): above is 76, 0 is 55;
- process image 3584 bytes each way: input offset + length above is 68,
  output 69;
- SYNC_Timer is any u16, so 67 never comes: 0 is valid with synchronous PDOs
  too. Revision 16 of the seed ("SYNC timer can be configured to value 0
  also") and 5.2.5.4.1 ("A value of 0 disables the timer"): the SYNC then
  comes from another station;
- 60: two NODES records for one address, or a node on the master's bNodeID;
- Auto_Clear and Intel_Motorola 0/1, bExtendedState bits 0..1 only: 55.

Structural defects of a node set (59, 61, 64, 71, 72, 76) come from the
decoder in dbm_tools.parameters, so the firmware and this module agree.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

from dbm_tools.container import FIRST_TABLE, DbmFile, DbmTable
from dbm_tools.errors import DbmError
from dbm_tools.parameters import (
    ACLR_ACTIVE,
    ACLR_INACTIVE,
    BAUD_RATES_KBIT,
    INTEL,
    MOTOROLA,
    BusParameterSet,
    ExtendedBusParameterSet,
    ExtendedState,
    NodeParameterSet,
)
from dbm_tools.tables import (
    BUS_CAN,
    BUS_CAN_EXT,
    DESCRIPT,
    GLOBAL,
    NODES,
    NODES_KEY_LENGTH,
    PLC_PARAM,
    PROJEKT,
    SEGMENT_NAME_CANOPEN,
    DescriptRecord,
    GlobalSet,
    PlcParam,
    ProjektRecord,
    checksum_crc,
)
from dpm.cia301 import SYNC_TYPES_MAX
from dpm.commands import DOWNLOAD_AREA_SIZE
from dpm.errors import CanF, DeviceEvent, RcsF
from dpm.layout import IO_AREA_SIZE

PROCESS_IMAGE_SIZE = IO_AREA_SIZE
"""Bytes of the process image each way (the card's send and receive areas)."""
NODE_ADDRESSES = range(1, 128)
MASTER_NODE_IDS = range(127)
COB_IDS = range(1, 2048)
PDO_LENGTHS = range(1, 9)
SDO_LENGTH_MAX = 4
TRANSMISSION_TYPES = frozenset(range(241)) | frozenset(range(252, 256))


@dataclass(frozen=True)
class Finding:
    """One violated check: the number the card answers with, and where.

    `text` is the seed's wording of `number`; `detail` says what exactly was
    wrong. Warnings (number 0: the card would still answer "no error") flag
    things a card ignores but a user may want to know, like a foreign CRC.
    """

    number: int
    detail: str
    table: str | None = None
    record: int | None = None
    field: str | None = None
    severity: Literal["error", "warning"] = "error"

    @property
    def text(self) -> str:
        if self.number == DeviceEvent.FAULTY_DATABASE:
            return DeviceEvent.FAULTY_DATABASE.text  # a stored database, seen at start-up
        if self.number == RcsF.DB_NOT_VALID:
            return RcsF.DB_NOT_VALID.text  # the load function's verdict on a whole DBM
        return CanF.text_of(self.number)


def _warning(detail: str, table: str, record: int, field: str | None = None) -> Finding:
    return Finding(CanF.NO_ERROR, detail, table, record, field, severity="warning")


def _from_error(error: DbmError, default: int) -> Finding:
    return Finding(error.number or default, error.reason, field=error.field)


def _size_findings(data: bytes) -> list[Finding]:
    if len(data) > DOWNLOAD_AREA_SIZE:
        return [
            Finding(CanF.BUFFER_LENGTH,
                    f"{len(data)} bytes exceed the {DOWNLOAD_AREA_SIZE}-byte area")
        ]
    return []


def _check_pdo_areas(node_set: NodeParameterSet) -> list[Finding]:
    inputs = [pdo for pdo in node_set.atPdoCfgData if pdo.is_input]
    outputs = [pdo for pdo in node_set.atPdoCfgData if not pdo.is_input]
    findings = []
    if len(inputs) != len(node_set.ausInputOffsets) or len(outputs) != len(
        node_set.ausOutputOffsets
    ):
        findings.append(
            Finding(
                CanF.PDO_ADD_TAB,
                f"{len(inputs)} input and {len(outputs)} output PDOs, ADD-tab has "
                f"{len(node_set.ausInputOffsets)} and {len(node_set.ausOutputOffsets)} offsets",
                field="bInputCount",
            )
        )
    for number, pdos, offsets, what in (
        (CanF.INPUT_OFFSET, inputs, node_set.ausInputOffsets, "input"),
        (CanF.OUTPUT_OFFSET, outputs, node_set.ausOutputOffsets, "output"),
    ):
        for pdo, offset in zip(pdos, offsets, strict=False):
            if offset + pdo.data_length > PROCESS_IMAGE_SIZE:
                findings.append(
                    Finding(
                        number,
                        f"{what} offset {offset} + {pdo.data_length} bytes exceeds"
                        f" {PROCESS_IMAGE_SIZE}",
                        field="ausIOOffsets",
                    )
                )
    return findings


def _check_node_values(node_set: NodeParameterSet) -> list[Finding]:
    findings = []
    for number, value, what in (
        (CanF.EMCY_COB_ID, node_set.usCobIDEmcy, "usCobIDEmcy"),
        (CanF.GUARD_COB_ID, node_set.usCobIDGuard, "usCobIDGuard"),
    ):
        if value not in COB_IDS:
            findings.append(Finding(number, f"{what} {value} not in 1..2047", field=what))
    for index, sdo in enumerate(node_set.atSdoCfgData, start=1):
        if sdo.bLength > SDO_LENGTH_MAX:
            findings.append(
                Finding(CanF.SDO_DATA_TOO_LARGE, f"SDO {index}: bLength {sdo.bLength}",
                        field="bLength")
            )
        elif sdo.bLength == 0:
            findings.append(Finding(CanF.FAULTY_PARAMETER, f"SDO {index}: bLength 0",
                                    field="bLength"))
    for index, pdo in enumerate(node_set.atPdoCfgData, start=1):
        if pdo.data_length not in PDO_LENGTHS:
            findings.append(
                Finding(CanF.PDO_LENGTH, f"PDO {index}: length {pdo.data_length}", field="bLength")
            )
        if pdo.bTransType not in TRANSMISSION_TYPES:
            findings.append(
                Finding(
                    CanF.TRANSMISSION_TYPE,
                    f"PDO {index}: bTransType {pdo.bTransType}",
                    field="bTransType",
                )
            )
        if pdo.usPdoCOBId not in COB_IDS:
            findings.append(
                Finding(
                    CanF.FAULTY_PARAMETER,
                    f"PDO {index}: usPdoCOBId {pdo.usPdoCOBId} not in 1..2047",
                    field="usPdoCOBId",
                )
            )
    return findings + _check_pdo_areas(node_set)


def check_node_parameters(data: bytes, node: int) -> list[Finding]:
    """Check a node parameter data set downloaded for (or stored with) node address `node`."""
    findings = _size_findings(data)
    if node not in NODE_ADDRESSES:
        findings.append(
            Finding(CanF.FAULTY_PARAMETER, f"node address {node} not in 1..127",
                    field="Node_Address")
        )
    declared = int.from_bytes(data[:2], "little")
    if declared > DOWNLOAD_AREA_SIZE:
        findings.append(
            Finding(
                CanF.NODE_PARAMETERS_TOO_LARGE,
                f"usNodeParaLen {declared} exceeds {DOWNLOAD_AREA_SIZE}",
                field="usNodeParaLen",
            )
        )
    try:
        node_set = NodeParameterSet.decode(data)
    except DbmError as error:
        return [*findings, _from_error(error, CanF.INCOMPLETE)]
    return findings + _check_node_values(node_set)


def check_bus_parameters(data: bytes) -> list[Finding]:
    """Check a bus parameter data set (it stands alone: no check looks at the nodes)."""
    findings = _size_findings(data)
    try:
        bus = BusParameterSet.decode(data)
    except DbmError as error:
        return [*findings, _from_error(error, CanF.INCOMPLETE)]
    if bus.Baud_rate not in BAUD_RATES_KBIT:
        findings.append(Finding(CanF.BAUD_RATE, f"Baud_rate {bus.Baud_rate}", field="Baud_rate"))
    if bus.COB_ID_SYNC not in COB_IDS:
        findings.append(
            Finding(
                CanF.SYNC_COB_ID, f"COB_ID_SYNC {bus.COB_ID_SYNC} not in 1..2047",
                field="COB_ID_SYNC"
            )
        )
    for value, allowed, what in (
        (bus.Auto_Clear, (ACLR_INACTIVE, ACLR_ACTIVE), "Auto_Clear"),
        (bus.Intel_Motorola, (INTEL, MOTOROLA), "Intel_Motorola"),
    ):
        if value not in allowed:
            findings.append(Finding(CanF.FAULTY_PARAMETER, f"{what} {value} not 0 or 1",
                                    field=what))
    return findings


def check_extended_bus_parameters(data: bytes) -> list[Finding]:
    """Check an extended bus parameter data set.

    ulAcceptCode/ulAcceptMask are not checked [ours]: revision 17's range 0-0xF8FFFFFF
    is the SJA1000 register layout (``dpm.com.acceptance_identifier_bits``), whose three
    bits outside it (RTR, unused) the filter ignores, so a value there harms nothing.
    """
    findings = _size_findings(data)
    try:
        ext = ExtendedBusParameterSet.decode(data)
    except DbmError as error:
        return [*findings, _from_error(error, CanF.INCOMPLETE)]
    known = int(ExtendedState.bi11Bit29BitSelector | ExtendedState.biNoGobalStartNode)
    if ext.bExtendedState & ~known:
        findings.append(
            Finding(
                CanF.FAULTY_PARAMETER,
                f"bExtendedState {ext.bExtendedState:#04x} sets reserved bits",
                field="bExtendedState",
            )
        )
    if ext.bNodeID not in MASTER_NODE_IDS:
        findings.append(
            Finding(CanF.FAULTY_PARAMETER, f"bNodeID {ext.bNodeID} not in 0..126", field="bNodeID")
        )
    return findings


def check_node_addresses(addresses: Sequence[int], master_node_id: int = 0) -> list[Finding]:
    """Error 60 for each address already used by an earlier node or by the master itself.

    Findings carry the 1-based position in `addresses` (the NODES record).
    """
    findings = []
    seen: set[int] = set()
    for record, address in enumerate(addresses, start=1):
        if address in seen:
            findings.append(
                Finding(
                    CanF.DOUBLE_ADDRESS,
                    f"node {address} configured twice",
                    record=record,
                    field="Node_Address",
                )
            )
        elif master_node_id and address == master_node_id:
            findings.append(
                Finding(
                    CanF.DOUBLE_ADDRESS,
                    f"node {address} is the master's bNodeID",
                    record=record,
                    field="Node_Address",
                )
            )
        seen.add(address)
    return findings


def _in_table(findings: list[Finding], table: str, record: int | None = None) -> list[Finding]:
    return [
        replace(f, table=table, record=f.record if record is None else record) for f in findings
    ]


def _single_record(dbm: DbmFile, name: str, required: bool) -> tuple[bytes | None, list[Finding]]:
    """The one record of a one-record table, or the 212 findings why there is none."""
    table = dbm.table(name)
    if table is None:
        missing = Finding(DeviceEvent.FAULTY_DATABASE, f"no {name} table", table=name)
        return None, [missing] if required else []
    if len(table.records) != 1:
        return None, [
            Finding(DeviceEvent.FAULTY_DATABASE, f"{len(table.records)} records, expected 1",
                    table=name)
        ]
    return table.records[0], []


def _check_global(dbm: DbmFile) -> list[Finding]:
    record, findings = _single_record(dbm, GLOBAL, required=True)
    if record is None:
        return [replace(f, number=RcsF.DB_NOT_VALID) for f in findings]
    if dbm.table_number(GLOBAL) != FIRST_TABLE:
        findings.append(
            Finding(RcsF.DB_NOT_VALID, f"GLOBAL is not table {FIRST_TABLE}", table=GLOBAL)
        )
    try:
        global_set = GlobalSet.decode(record)
    except DbmError as error:
        return [*findings, Finding(RcsF.DB_NOT_VALID, error.reason, GLOBAL, 1, error.field)]
    if global_set.szSegmentName != SEGMENT_NAME_CANOPEN:
        findings.append(
            Finding(
                RcsF.DB_NOT_VALID,
                f"segment name {global_set.szSegmentName!r}, expected {SEGMENT_NAME_CANOPEN!r}",
                GLOBAL,
                1,
                "szSegmentName",
            )
        )
    crc = checksum_crc(dbm)
    if global_set.usChecksumCRC != crc:
        findings.append(
            _warning(
                f"usChecksumCRC {global_set.usChecksumCRC:#06x}, records give {crc:#06x}"
                " (files written by SyCon never match)",
                GLOBAL,
                1,
                "usChecksumCRC",
            )
        )
    return findings


def _check_nodes(table: DbmTable | None, master_node_id: int) -> list[Finding]:
    if table is None:
        return []
    if table.key_length != NODES_KEY_LENGTH or not all(table.records):
        return [
            Finding(DeviceEvent.FAULTY_DATABASE, "NODES must be keyed on its 1-byte address",
                    table=NODES)
        ]
    findings = []
    for record, data in enumerate(table.records, start=1):
        findings += _in_table(check_node_parameters(data[1:], data[0]), NODES, record)
    addresses = [data[0] for data in table.records]
    findings += _in_table(check_node_addresses(addresses, master_node_id), NODES)
    return findings


def _sync_without_synchronous_pdo(bus_data: bytes, nodes: DbmTable | None) -> list[Finding]:
    """[ours] a warning: SYNC_Timer set while no active node has a synchronous PDO. The card
    accepts it and then sends no SYNC at all (seed 4.2: "activated only if at least one node
    uses SYNC controlled transmission types"); a tool user expecting SYNC frames hears why."""
    try:
        bus = BusParameterSet.decode(bus_data)
        node_sets = [NodeParameterSet.decode(data[1:]) for data in (nodes.records if nodes else [])]
    except DbmError:
        return []  # the data checks report it
    synchronous = any(pdo.bTransType <= SYNC_TYPES_MAX for node_set in node_sets
                      if node_set.active for pdo in node_set.atPdoCfgData)
    if bus.SYNC_Timer == 0 or synchronous or not node_sets:
        return []
    return [Finding(CanF.NO_ERROR, f"SYNC_Timer {bus.SYNC_Timer} ms, but no active node has a "
                    "synchronous PDO (transmission type 0..240): the card sends no SYNC",
                    field="SYNC_Timer", severity="warning")]


def check_dbm(dbm: DbmFile, warnings: bool = True) -> list[Finding]:
    """All checks a card applies to a stored CANopen database, plus warnings for host tools.

    GLOBAL problems are 20 (the card refuses the download); a missing or
    malformed BUS_CAN, PLC_PARAM or multi-record single tables are 212 (the
    card reads the database at reset and fails); BUS_CAN, BUS_CAN_EXT and
    NODES records get the COM_Download data checks. PROJEKT and DESCRIPT are
    never read by the card, so their defects are warnings.

    ``warnings`` False leaves out the checks that can only warn (SYNC without a
    synchronous PDO, PROJEKT, DESCRIPT): the card, which acts on errors only, skips
    decoding every node set and DESCRIPT record once more at each start (127 node sets:
    1.6 ms of CPU).
    """
    findings = _check_global(dbm)
    master_node_id = 0
    ext, found = _single_record(dbm, BUS_CAN_EXT, required=False)
    findings += found
    if ext is not None:
        ext_findings = check_extended_bus_parameters(ext)
        findings += _in_table(ext_findings, BUS_CAN_EXT, 1)
        if not ext_findings:
            master_node_id = ExtendedBusParameterSet.decode(ext).bNodeID
    findings += _check_nodes(dbm.table(NODES), master_node_id)
    bus, found = _single_record(dbm, BUS_CAN, required=True)
    findings += found
    if bus is not None:
        findings += _in_table(check_bus_parameters(bus), BUS_CAN, 1)
        if warnings:
            findings += _in_table(_sync_without_synchronous_pdo(bus, dbm.table(NODES)),
                                  BUS_CAN, 1)
    plc, found = _single_record(dbm, PLC_PARAM, required=False)
    findings += found
    if plc is not None:
        try:
            PlcParam.decode(plc)
        except DbmError as error:
            findings.append(Finding(DeviceEvent.FAULTY_DATABASE, error.reason, PLC_PARAM, 1,
                                    error.field))
    if warnings:
        findings += _check_unread_tables(dbm)
    return findings


def _check_unread_tables(dbm: DbmFile) -> list[Finding]:
    findings = []
    for name, decode in ((PROJEKT, ProjektRecord.decode), (DESCRIPT, DescriptRecord.decode)):
        table = dbm.table(name)
        for record, data in enumerate(table.records if table else [], start=1):
            try:
                decode(data)
            except DbmError as error:
                findings.append(_warning(error.reason, name, record))
    return findings
