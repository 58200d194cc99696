"""The COM_Download data checks: every msg.f number a data set can earn, provoked on purpose."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from dbm_tools.container import DbmFile, DbmTable, read_dbm, write_dbm
from dbm_tools.parameters import (
    BusParameterSet,
    ExtendedBusParameterSet,
    NdFlag,
    NodeParameterSet,
    PdoData,
    SdoCfgData,
)
from dbm_tools.tables import (
    BUS_CAN,
    BUS_CAN_EXT,
    DESCRIPT,
    GLOBAL,
    NODES,
    PLC_PARAM,
    PROJEKT,
    DescriptRecord,
    GlobalSet,
    NodesRecord,
    PlcParam,
    ProjektRecord,
    checksum_crc,
)
from dbm_tools.validate import (
    Finding,
    check_bus_parameters,
    check_dbm,
    check_extended_bus_parameters,
    check_node_addresses,
    check_node_parameters,
)
from dpm.errors import CanF, DeviceEvent
from tests.fixtures import real_dbm_bytes

DBM_DOC = Path(__file__).resolve().parents[1] / "docs" / "dbm.md"

DATA_SET_NUMBERS = {53, 55, 59, 60, 61, 62, 63, 64, 65, 66, 68, 69, 70, 71, 72, 73, 74, 75, 76}
"""Every data-check number the card answers with; 67 is not one: every SYNC_Timer is valid
(seed revision 16)."""


def valid_node(**changes: Any) -> NodeParameterSet:
    """A node set that passes every check; encoded it is 51 bytes:
    header 0..15, SDO list 16..26, PDO list 27..42, ADD-tab 43..50."""
    node = NodeParameterSet(
        bNd_Flag=NdFlag.ACTIVE,
        usDevProfNum=401,
        usCobIDEmcy=0x84,
        usCobIDGuard=0x704,
        usGuardTime=500,
        bLifeTimeFactor=3,
        atSdoCfgData=[SdoCfgData(0x6200, 5, 4, b"\x08\x01\x01\x10")],
        atPdoCfgData=[PdoData(0, 2, 0x204, 255), PdoData(1, 2, 0x184, 255)],
        ausInputOffsets=[0],
        ausOutputOffsets=[0],
    )
    return replace(node, **changes)


VALID = valid_node().encode()


def patched(offset: int, value: int, size: int = 2) -> bytes:
    return VALID[:offset] + value.to_bytes(size, "little") + VALID[offset + size :]


def numbers(findings: list[Finding]) -> set[int]:
    return {finding.number for finding in findings}


def nodes_check(node: NodeParameterSet | bytes, address: int = 4) -> list[Finding]:
    data = node if isinstance(node, bytes) else node.encode()
    return check_node_parameters(data, address)


def sync_node(active: bool = True, trans_type: int = 1) -> NodeParameterSet:
    return valid_node(
        bNd_Flag=NdFlag.ACTIVE if active else 0,
        atPdoCfgData=[PdoData(0, 2, 0x204, trans_type), PdoData(1, 2, 0x184, 255)],
    )


# number provoked -> the crafted check
CASES: list[tuple[int, str, Callable[[], list[Finding]]]] = [
    (
        53,
        "node set over 1000 bytes",
        lambda: nodes_check(valid_node(atSdoCfgData=[SdoCfgData(0x2000, 1, 4)] * 110)),
    ),
    (53, "bus set over 1000 bytes", lambda: check_bus_parameters(bytes(1001))),
    (53, "extended set over 1000 bytes", lambda: check_extended_bus_parameters(bytes(1001))),
    (55, "node address 0", lambda: nodes_check(VALID, 0)),
    (55, "node address 128", lambda: nodes_check(VALID, 128)),
    (
        55,
        "PDO COB-ID 0",
        lambda: nodes_check(
            valid_node(atPdoCfgData=[PdoData(0, 2, 0, 255), PdoData(1, 2, 0x184, 255)])
        ),
    ),
    (
        55,
        "PDO COB-ID 2048",
        lambda: nodes_check(
            valid_node(atPdoCfgData=[PdoData(0, 2, 0x204, 255), PdoData(1, 2, 2048, 255)])
        ),
    ),
    (55, "SDO bLength 0", lambda: nodes_check(valid_node(atSdoCfgData=[SdoCfgData(0x1017, 0, 0)]))),
    (55, "Auto_Clear 2", lambda: check_bus_parameters(BusParameterSet(Auto_Clear=2).encode())),
    (
        55,
        "Intel_Motorola 2",
        lambda: check_bus_parameters(BusParameterSet(Intel_Motorola=2).encode()),
    ),
    (
        55,
        "reserved bExtendedState bit",
        lambda: check_extended_bus_parameters(ExtendedBusParameterSet(bExtendedState=4).encode()),
    ),
    (
        55,
        "master bNodeID 127",
        lambda: check_extended_bus_parameters(ExtendedBusParameterSet(bNodeID=127).encode()),
    ),
    (59, "node set cut short", lambda: nodes_check(VALID[:-1])),
    (59, "node set of one byte", lambda: nodes_check(VALID[:1])),
    (59, "empty node set", lambda: nodes_check(b"")),
    (59, "SDO list not 2 + n * 9", lambda: nodes_check(patched(16, 10))),
    (59, "PDO list not 2 + n * 7", lambda: nodes_check(patched(27, 15))),
    (59, "bus set of 6 bytes", lambda: check_bus_parameters(BusParameterSet().encode()[:6])),
    (59, "bus set of 8 bytes", lambda: check_bus_parameters(BusParameterSet().encode() + b"\0")),
    (59, "extended set of 40 bytes", lambda: check_extended_bus_parameters(bytes(40))),
    (60, "node twice", lambda: check_node_addresses([4, 5, 4])),
    (60, "node on the master's ID", lambda: check_node_addresses([4, 5], master_node_id=5)),
    (61, "usAddTabLen past the end", lambda: nodes_check(patched(43, 10))),
    (62, "usNodeParaLen over 1000", lambda: nodes_check(patched(0, 1001))),
    (63, "transmission type 241", lambda: nodes_check(sync_node(trans_type=241))),
    (63, "transmission type 251", lambda: nodes_check(sync_node(trans_type=251))),
    (64, "usPdoCfgDataLen past the end", lambda: nodes_check(patched(27, 2 + 7 * 4))),
    (65, "Baud_rate 9", lambda: check_bus_parameters(BusParameterSet(Baud_rate=9).encode())),
    (66, "COB_ID_SYNC 0", lambda: check_bus_parameters(BusParameterSet(COB_ID_SYNC=0).encode())),
    (
        66,
        "COB_ID_SYNC 2048",
        lambda: check_bus_parameters(BusParameterSet(COB_ID_SYNC=2048).encode()),
    ),
    (68, "input offset + length > 3584", lambda: nodes_check(valid_node(ausInputOffsets=[3583]))),
    (69, "output offset + length > 3584", lambda: nodes_check(valid_node(ausOutputOffsets=[3583]))),
    (70, "an input offset too many", lambda: nodes_check(valid_node(ausInputOffsets=[0, 2]))),
    (70, "an output offset missing", lambda: nodes_check(valid_node(ausOutputOffsets=[]))),
    (71, "bInputCount disagrees with usAddTabLen", lambda: nodes_check(patched(45, 2, 1))),
    (72, "a byte after the set", lambda: nodes_check(VALID + b"\0")),
    (72, "usNodeParaLen beyond the ADD-tab", lambda: nodes_check(patched(0, 52) + b"\0")),
    (72, "usNodeParaLen shorter than the header", lambda: nodes_check(patched(0, 10)[:10])),
    (72, "no room for the ADD-tab", lambda: nodes_check(patched(0, 45)[:45])),
    (73, "EMCY COB-ID 0", lambda: nodes_check(valid_node(usCobIDEmcy=0))),
    (73, "EMCY COB-ID 2048", lambda: nodes_check(valid_node(usCobIDEmcy=2048))),
    (74, "guard COB-ID 0", lambda: nodes_check(valid_node(usCobIDGuard=0))),
    (74, "guard COB-ID 0xFFFF", lambda: nodes_check(valid_node(usCobIDGuard=0xFFFF))),
    (
        75,
        "PDO length 0",
        lambda: nodes_check(
            valid_node(atPdoCfgData=[PdoData(0, 0, 0x204, 255), PdoData(1, 2, 0x184, 255)])
        ),
    ),
    (
        75,
        "word PDO length 9",
        lambda: nodes_check(
            valid_node(atPdoCfgData=[PdoData(0, 0x89, 0x204, 255), PdoData(1, 2, 0x184, 255)])
        ),
    ),
    (76, "SDO bLength 5", lambda: nodes_check(valid_node(atSdoCfgData=[SdoCfgData(0x1017, 0, 5)]))),
    (76, "usSdoCfgDataLen past the end", lambda: nodes_check(patched(16, 2 + 9 * 4))),
]


@pytest.mark.parametrize(
    ("number", "check"), [(n, c) for n, _, c in CASES], ids=[f"{n}-{w}" for n, w, _ in CASES]
)
def test_provoked(number: int, check: Callable[[], list[Finding]]) -> None:
    findings = check()
    assert number in numbers(findings)
    for finding in findings:
        assert finding.text == CanF.text_of(finding.number)
        assert finding.severity == "error"
        assert finding.detail


def test_every_data_set_number_is_provoked() -> None:
    assert {number for number, _, _ in CASES} == DATA_SET_NUMBERS


def test_valid_sets_pass() -> None:
    assert nodes_check(VALID) == []
    assert nodes_check(VALID, 127) == []
    assert nodes_check(valid_node(ausInputOffsets=[3582], ausOutputOffsets=[3582])) == []
    assert check_bus_parameters(BusParameterSet().encode()) == []
    assert check_extended_bus_parameters(ExtendedBusParameterSet(bNodeID=126).encode()) == []
    assert check_node_addresses(list(range(1, 128))) == []


@pytest.mark.parametrize("trans_type", [0, 1, 240, 252, 253, 254, 255])
def test_valid_transmission_types(trans_type: int) -> None:
    assert nodes_check(sync_node(trans_type=trans_type)) == []


def test_structural_findings_name_the_field() -> None:
    (finding,) = nodes_check(patched(43, 10))
    assert finding.number == 61
    assert finding.field == "usAddTabLen"
    assert finding.text == "data check: Add-Tab size is too large"


def test_oversized_declared_length_reports_both() -> None:
    assert numbers(nodes_check(patched(0, 1001))) == {59, 62}


def test_every_sync_timer_is_valid() -> None:
    """Seed revision 16: SYNC_Timer 0 (no SYNC from the card) is valid, 67 never comes."""
    for timer in (0, 10, 0xFFFF):
        assert check_bus_parameters(BusParameterSet(SYNC_Timer=timer).encode()) == []


def test_double_address_findings_point_at_the_record() -> None:
    (finding,) = check_node_addresses([4, 5, 4])
    assert (finding.number, finding.record, finding.field) == (60, 3, "Node_Address")


def test_error_texts_are_the_documented_ones() -> None:
    """The COM_Download table of docs/dbm.md (the seed's 5.2.5, letter for letter)."""
    text = DBM_DOC.read_text(encoding="utf-8")
    section = text[text.index("### Data checks (the numbers of COM_Download)") :]
    table = section[: section.index("\n## ")]
    rows = dict(re.findall(r"^\| (\d+) \| (.+) \|$", table, flags=re.MULTILINE))
    assert len(rows) == 24
    for number, wording in rows.items():
        assert CanF.text_of(int(number)) == wording
    assert DeviceEvent.FAULTY_DATABASE.text == "faulty reading of a data base"


# --- whole databases -----------------------------------------------------------------------


def sealed(dbm: DbmFile) -> DbmFile:
    """Store our usChecksumCRC in GLOBAL, as our writers do."""
    glob = dbm.table(GLOBAL)
    assert glob is not None
    glob.records[0] = replace(
        GlobalSet.decode(glob.records[0]), usChecksumCRC=checksum_crc(dbm)
    ).encode()
    return dbm


def canopen_dbm(
    nodes: list[bytes] | None = None,
    bus: BusParameterSet | None = None,
    ext: ExtendedBusParameterSet | None = None,
) -> DbmFile:
    node_records = [NodesRecord(4, valid_node()).encode()] if nodes is None else nodes
    return sealed(
        DbmFile(
            [
                DbmTable(GLOBAL, [GlobalSet().encode()]),
                DbmTable(BUS_CAN_EXT, [(ext or ExtendedBusParameterSet(bNodeID=1)).encode()]),
                DbmTable(NODES, node_records, key_length=1),
                DbmTable(BUS_CAN, [(bus or BusParameterSet()).encode()]),
                DbmTable(PLC_PARAM, [PlcParam().encode()]),
                DbmTable(PROJEKT, [ProjektRecord("demo", "1.0", "22.11.2026").encode()]),
                DbmTable(DESCRIPT, [DescriptRecord(4, szDeviceName="I/O").encode()]),
            ]
        )
    )


def changed(dbm: DbmFile, name: str, records: list[bytes]) -> DbmFile:
    table = dbm.table(name)
    assert table is not None
    table.records = records
    return dbm


def test_good_database_passes() -> None:
    dbm = canopen_dbm()
    assert check_dbm(dbm) == []
    assert check_dbm(read_dbm(write_dbm(dbm))) == []


def test_minimal_database_passes() -> None:
    dbm = sealed(
        DbmFile(
            [
                DbmTable(GLOBAL, [GlobalSet().encode()]),
                DbmTable(BUS_CAN, [BusParameterSet().encode()]),
            ]
        )
    )
    assert check_dbm(dbm) == []


def test_foreign_crc_is_only_a_warning() -> None:
    dbm = changed(canopen_dbm(), GLOBAL, [GlobalSet(usChecksumCRC=1).encode()])
    (finding,) = check_dbm(dbm)
    assert (finding.number, finding.severity, finding.field) == (0, "warning", "usChecksumCRC")
    assert finding.text == "no error"


def test_real_profibus_file() -> None:
    findings = check_dbm(read_dbm(real_dbm_bytes()))
    errors = {(f.number, f.table) for f in findings if f.severity == "error"}
    assert errors == {(20, GLOBAL), (212, BUS_CAN)}
    assert [f.field for f in findings if f.severity == "warning"] == ["usChecksumCRC"]


@pytest.mark.parametrize(
    ("damage", "number", "table"),
    [
        (lambda d: d.tables.pop(0), 20, GLOBAL),
        (lambda d: d.tables.insert(0, d.tables.pop(1)), 20, GLOBAL),
        (lambda d: changed(d, GLOBAL, [GlobalSet().encode()] * 2), 20, GLOBAL),
        (lambda d: changed(d, GLOBAL, [GlobalSet().encode()[:33]]), 20, GLOBAL),
        (lambda d: changed(d, GLOBAL, [GlobalSet(szSegmentName="CANopen").encode()]), 20, GLOBAL),
        (lambda d: d.tables.pop(3), 212, BUS_CAN),
        (lambda d: changed(d, BUS_CAN, []), 212, BUS_CAN),
        (lambda d: changed(d, BUS_CAN_EXT, [bytes(41)] * 2), 212, BUS_CAN_EXT),
        (lambda d: changed(d, PLC_PARAM, [bytes(3)]), 212, PLC_PARAM),
        (lambda d: setattr(d.tables[2], "key_length", 0), 212, NODES),
        (lambda d: changed(d, NODES, [b""]), 212, NODES),
        (lambda d: changed(d, BUS_CAN, [BusParameterSet(Baud_rate=9).encode()]), 65, BUS_CAN),
        (lambda d: changed(d, BUS_CAN, [bytes(6)]), 59, BUS_CAN),
        (
            lambda d: changed(d, BUS_CAN_EXT, [ExtendedBusParameterSet(bNodeID=200).encode()]),
            55,
            BUS_CAN_EXT,
        ),
        (lambda d: changed(d, NODES, [b"\x04" + VALID[:-2]]), 59, NODES),
    ],
)
def test_damaged_database(damage: Callable[[DbmFile], object], number: int, table: str) -> None:
    dbm = canopen_dbm()
    damage(dbm)
    errors = [f for f in check_dbm(dbm) if f.severity == "error"]
    assert (number, table) in {(f.number, f.table) for f in errors}


def test_node_findings_carry_table_and_record() -> None:
    dbm = canopen_dbm(
        [
            NodesRecord(2, valid_node()).encode(),
            NodesRecord(3, valid_node(usCobIDEmcy=0)).encode(),
        ]
    )
    (finding,) = check_dbm(dbm)
    assert (finding.number, finding.table, finding.record) == (73, NODES, 2)


def test_double_node_address_in_nodes() -> None:
    record = NodesRecord(4, valid_node()).encode()
    (finding,) = check_dbm(canopen_dbm([record, NodesRecord(5, valid_node()).encode(), record]))
    assert (finding.number, finding.table, finding.record) == (60, NODES, 3)


def test_node_on_master_node_id() -> None:
    dbm = canopen_dbm(ext=ExtendedBusParameterSet(bNodeID=4))
    (finding,) = check_dbm(dbm)
    assert (finding.number, finding.table, finding.record) == (60, NODES, 1)


def test_sync_timer_0_with_a_synchronous_node() -> None:
    """Seed revision 16: a database whose SYNC comes from another station is valid."""
    nodes = [NodesRecord(4, sync_node()).encode()]
    assert check_dbm(canopen_dbm(nodes, bus=BusParameterSet(SYNC_Timer=0))) == []
    assert check_dbm(canopen_dbm(nodes, bus=BusParameterSet(SYNC_Timer=10))) == []


@pytest.mark.parametrize(("table", "record"), [(DESCRIPT, bytes(120)), (PROJEKT, bytes(233))])
def test_tables_the_card_never_reads_only_warn(table: str, record: bytes) -> None:
    dbm = sealed(changed(canopen_dbm(), table, [record]))
    (finding,) = check_dbm(dbm)
    assert (finding.number, finding.severity, finding.table, finding.record) == (
        0,
        "warning",
        table,
        1,
    )
