"""The DBM builder: network description + EDS files -> the tables a card loads at reset."""

from __future__ import annotations

import datetime
from pathlib import Path

import pytest

from dbm_tools.builder import BuildError, build_dbm
from dbm_tools.container import read_dbm, write_dbm
from dbm_tools.eds import EdsError, read_eds
from dbm_tools.network import NetworkError, parse_network
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
    DescriptPdo,
    DescriptRecord,
    GlobalSet,
    NodesRecord,
    PlcParam,
    ProjektRecord,
    checksum_crc,
)
from dbm_tools.validate import check_dbm
from firmware.sim.network import object_dictionary

DATA = Path(__file__).resolve().parent / "data"
EDS = DATA / "io-module.eds"
DAY = datetime.date(2026, 11, 22)


def build(text: str, **options: object) -> dict[str, list[bytes]]:
    """Build from TOML text (EDS paths relative to tests/data); the tables by name."""
    dbm = build_dbm(parse_network(text, DATA), date=DAY, **options)  # type: ignore[arg-type]
    # no finding but the warning of a SYNC_Timer without a synchronous PDO (no SYNC is sent)
    assert [f for f in check_dbm(dbm) if (f.severity, f.field) != ("warning", "SYNC_Timer")] == []
    return {table.name: table.records for table in dbm.tables}


def nodes(tables: dict[str, list[bytes]]) -> dict[int, NodeParameterSet]:
    return {r.Node_Address: r.Node_Data_set for r in map(NodesRecord.decode, tables[NODES])}


# --- the EDS reader ---------------------------------------------------------------------------


def test_eds_gives_device_type_identity_and_enabled_pdos_with_nodeid_resolved() -> None:
    device = read_eds(EDS, 5)
    assert device.device_type == 0x00070191
    assert (device.vendor_name, device.vendor_number) == ("Acme Automation", 0xA5C3)
    assert (device.product_name, device.product_number) == ("IO-16/16/2 module", 0x1604)
    # TPDO1 2 bytes, TPDO2 4 bytes (two 16-bit inputs), RPDO1 2 bytes; TPDO3/RPDO2 disabled
    assert [(p.direction, p.number, p.cob_id, p.length, p.transmission, p.inhibit)
            for p in device.pdos] == [
        ("input", 1, 0x185, 2, 255, 0),
        ("input", 2, 0x285, 4, 254, 100),
        ("output", 1, 0x205, 2, 255, 0),
    ]
    assert [p.cob_id for p in read_eds(EDS, 17).pdos] == [0x191, 0x291, 0x211]


def test_eds_with_empty_device_info_numbers_reads_them_as_absent(tmp_path: Path) -> None:
    """CANopenEditor writes ``VendorNumber=`` and ``ProductNumber=`` for a project that
    leaves them blank (CANopenNode's own example DS301_profile.eds): the numbers come
    from 1018h instead, and the simulator and the network view load the file too."""
    blank = tmp_path / "blank.eds"
    blank.write_text(EDS.read_text().replace("VendorNumber=0x0000A5C3", "VendorNumber=")
                     .replace("ProductNumber=0x00001604", "ProductNumber=  "))
    device = read_eds(blank, 5)
    assert (device.vendor_name, device.product_name) == ("Acme Automation", "IO-16/16/2 module")
    assert (device.vendor_number, device.product_number) == (0xA5C3, 0x1604)  # from 1018h
    assert [p.cob_id for p in device.pdos] == [0x185, 0x285, 0x205]
    network = parse_network(f'[[node]]\nid = 5\neds = "{blank}"\n', tmp_path)
    od = object_dictionary(network.nodes[0], network.bus)
    assert od.device_information.vendor_name == "Acme Automation" and 0x1A00 in od


def test_eds_errors_name_the_file_and_the_pdo(tmp_path: Path) -> None:
    broken = tmp_path / "broken.eds"
    broken.write_text("[1000]\nParameterName=Device type\n")
    with pytest.raises(EdsError, match=r"broken\.eds"):
        read_eds(broken, 1)
    wide = tmp_path / "wide.eds"
    wide.write_text(EDS.read_text().replace("DefaultValue=0x60000208", "DefaultValue=0x60000240"))
    with pytest.raises(EdsError, match="TPDO1 maps 72 bits"):
        read_eds(wide, 1)
    extended = tmp_path / "extended.eds"
    extended.write_text(EDS.read_text().replace("$NODEID+0x180", "$NODEID+0x20000180"))
    with pytest.raises(EdsError, match="TPDO1 uses a 29-bit COB-ID"):
        read_eds(extended, 1)


# --- the tables ---------------------------------------------------------------------------------


NETWORK = """
[bus]
bitrate = 250000
sync_cob_id = 0x81
sync_period_ms = 10
auto_clear = true
byte_order = "motorola"
master_node_id = 100
heartbeat_ms = 300
global_start = true
wait_for_host = true
host_watchdog_ms = 750
handshake = "uncontrolled"

[[node]]
id = 5
eds = "io-module.eds"
name = "valve block"
heartbeat_ms = 400

[[node]]
id = 2
error_control = "guarding"
guard_time_ms = 200
life_time_factor = 4
boot = ["reset", "device", "guard", "start", "pdo"]
"""


def test_a_network_becomes_the_seven_tables_in_seed_order() -> None:
    dbm = build_dbm(parse_network(NETWORK, DATA), project="plant", date=DAY)
    assert [t.name for t in dbm.tables] == [
        GLOBAL, BUS_CAN, NODES, PLC_PARAM, PROJEKT, DESCRIPT, BUS_CAN_EXT
    ]
    assert dbm.table(NODES).key_length == 1  # type: ignore[union-attr]
    # its SYNC_Timer without a synchronous PDO: the one warning (the card sends no SYNC)
    assert [(f.severity, f.field) for f in check_dbm(dbm)] == [("warning", "SYNC_Timer")]
    assert read_dbm(write_dbm(dbm)) == dbm
    tables = {t.name: t.records for t in dbm.tables}
    glob = GlobalSet.decode(tables[GLOBAL][0])
    assert glob.szSegmentName == "CANopen "
    assert (glob.bSystemStart, glob.usHostWatchdogValue) == (1, 750)
    assert glob.usChecksumCRC == checksum_crc(dbm)
    assert BusParameterSet.decode(tables[BUS_CAN][0]) == BusParameterSet(3, 0x81, 10, 1, 1)
    assert ExtendedBusParameterSet.decode(tables[BUS_CAN_EXT][0]) == ExtendedBusParameterSet(
        bExtendedState=2, bNodeID=100, usProducerHeartbeatTime=300
    )
    assert PlcParam.decode(tables[PLC_PARAM][0]) == PlcParam(bMode=2, usWatchDogTime=750)
    assert ProjektRecord.decode(tables[PROJEKT][0]) == ProjektRecord("plant", "1.000",
                                                                     "22.11.2026")


def test_an_eds_node_takes_device_type_pdos_and_identity_from_its_data_sheet() -> None:
    tables = build(NETWORK)
    node = nodes(tables)[5]
    assert node.bNd_Flag == NdFlag.ACTIVE | NdFlag.HRTBT
    assert (node.usAddTypeInfo, node.usDevProfNum) == (0x0007, 401)  # object 1000h 0x00070191
    assert (node.usCobIDEmcy, node.usCobIDGuard) == (0x85, 0x705)
    assert (node.usGuardTime, node.bLifeTimeFactor) == (400, 0)  # heartbeat consumer time
    assert node.bitConfigNdState == 0
    # the node is told to produce its heartbeat at half the consumer time
    assert node.atSdoCfgData == [SdoCfgData(0x1017, 0, 2, (200).to_bytes(4, "little"))]
    assert node.atPdoCfgData == [
        PdoData(1, 2, 0x185, 255, 0), PdoData(1, 4, 0x285, 254, 100), PdoData(0, 2, 0x205, 255, 0)
    ]
    # inputs: node 2's generic TPDO takes 0..7 (address order), then node 5's
    assert (node.ausInputOffsets, node.ausOutputOffsets) == ([8, 10], [8])
    descript = {r[0]: DescriptRecord.decode(r) for r in tables[DESCRIPT]}
    assert descript[5] == DescriptRecord(
        bStationAddress=5, usIdentNumber=0x1604, usVendorNumber=0xA5C3,
        szVendorName="Acme Automation", szDeviceName="IO-16/16/2 module",
        szDescription="valve block", bMasterAddress=100,
        atPdos=[DescriptPdo(0x10, 2, 0, 8), DescriptPdo(0x10, 4, 0, 10),
                DescriptPdo(0x20, 2, 0, 8)],
    )


def test_a_node_without_eds_is_the_generic_module() -> None:
    tables = build("[[node]]\nid = 9\n")
    node = nodes(tables)[9]
    assert (node.usAddTypeInfo << 16) | node.usDevProfNum == 0x000F0191
    assert node.bNd_Flag == NdFlag.ACTIVE | NdFlag.HRTBT
    assert node.usGuardTime == 1000
    assert node.atPdoCfgData == [PdoData(0, 8, 0x209, 255), PdoData(1, 8, 0x189, 255)]
    assert (node.ausInputOffsets, node.ausOutputOffsets) == ([0], [0])
    descript = DescriptRecord.decode(tables[DESCRIPT][0])
    assert (descript.szDeviceName, descript.szDescription) == ("cifemu generic I/O", "node 9")


def test_guarding_none_and_inactive_nodes() -> None:
    tables = build(NETWORK + "\n[[node]]\nid = 3\nerror_control = \"none\"\nactive = false\n")
    guarded, quiet = nodes(tables)[2], nodes(tables)[3]
    assert guarded.bNd_Flag == NdFlag.ACTIVE
    assert (guarded.usGuardTime, guarded.bLifeTimeFactor) == (200, 4)
    assert guarded.bitConfigNdState == 0x08 | 0x10 | 0x20  # sync, emcy, sdo skipped
    assert guarded.atSdoCfgData == []
    assert quiet.bNd_Flag == 0
    assert (quiet.usGuardTime, quiet.bLifeTimeFactor, quiet.atSdoCfgData) == (0, 0, [])


def test_explicit_offsets_are_kept_and_automatic_ones_flow_around_them() -> None:
    tables = build("""
[[node]]
id = 1
[[node.pdo]]
direction = "input"
cob_id = 0x181
length = 4
offset = 6
[[node.pdo]]
direction = "input"
cob_id = 0x281
length = 4
[[node.pdo]]
direction = "input"
cob_id = 0x381
length = 3
word = true
[[node]]
id = 2
[[node.pdo]]
direction = "input"
cob_id = 0x182
length = 2
[[node.pdo]]
direction = "output"
cob_id = 0x202
length = 8
offset = 100
[[node]]
id = 3
[[node.sdo]]
index = 0x1017
subindex = 0
value = 50
size = 2
""")
    sets = nodes(tables)
    assert sets[1].ausInputOffsets == [6, 0, 10]  # 4 bytes fit before 6, 3 after 6..9
    assert sets[1].atPdoCfgData[2].bLength == 0x83  # MSK_WORD_PDO
    assert sets[2].ausInputOffsets == [13]
    assert sets[2].ausOutputOffsets == [100]
    assert sets[3].ausInputOffsets == [15] and sets[3].ausOutputOffsets == [0]
    # a description that writes 1017h itself keeps its value
    assert sets[3].atSdoCfgData == [SdoCfgData(0x1017, 0, 2, (50).to_bytes(4, "little"))]


@pytest.mark.parametrize(("text", "message"), [
    ("""[[node]]
id = 1
[[node.pdo]]
direction = "output"
cob_id = 0x201
offset = 10
[[node]]
id = 2
[[node.pdo]]
direction = "output"
cob_id = 0x202
length = 2
offset = 17
""", "output areas overlap: node 1 PDO 1 at 10..17 and node 2 PDO 1 at 17..18"),
    ("""[[node]]
id = 1
[[node.pdo]]
direction = "input"
cob_id = 0x181
offset = 3580
""", "runs past the 3584-byte area"),
    ("[[node]]\nid = 255\nlss = { vendor = 1, product = 2, revision = 3, serial = 4 }\n",
     "node 255"),
    ('[[node]]\nid = 4\neds = "missing.eds"\n', "not found"),
    ("[[node]]\nid = 4\n[[node.sdo]]\nindex = 0x1017\n",
     r"node 4\.sdo\[0\]: missing subindex, value"),
])
def test_descriptions_the_card_would_refuse_are_build_errors(text: str, message: str) -> None:
    with pytest.raises((BuildError, NetworkError), match=message):
        build_dbm(parse_network(text, DATA), date=DAY)


def test_the_process_image_fills_up() -> None:
    text = "".join(f"[[node]]\nid = {n}\n" for n in range(1, 127))
    assert len(build(text)[NODES]) == 126  # 126 * 8 bytes fit the 3584-byte areas
    pdos = "".join(
        f'[[node.pdo]]\ndirection = "input"\ncob_id = {0x180 + n}\nlength = 8\n'
        for n in range(1, 9)
    )
    crowded = "".join(f"[[node]]\nid = {n}\n{pdos}" for n in range(1, 58))
    with pytest.raises(BuildError, match="node 57 PDO 1: the input area of 3584 bytes is full"):
        build_dbm(parse_network(crowded, DATA), date=DAY)


def test_new_bus_options_are_checked() -> None:
    with pytest.raises(NetworkError, match=r"bus\.handshake"):
        parse_network('[bus]\nhandshake = "fast"\n')
    with pytest.raises(NetworkError, match=r"bus\.host_watchdog_ms"):
        parse_network("[bus]\nhost_watchdog_ms = 70000\n")
    with pytest.raises(NetworkError, match=r"bus\.master_node_id = 127"):
        parse_network("[bus]\nmaster_node_id = 127\n")
