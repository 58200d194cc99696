"""Record and data-set codecs, against the seed manual's examples and SyCon's real file."""

from __future__ import annotations

import pytest

from dbm_tools.container import DbmFile, DbmTable, read_dbm, write_dbm
from dbm_tools.errors import DbmError
from dbm_tools.parameters import (
    BUS_CAN_EXT_SIZE,
    BusParameterSet,
    ConfigNdState,
    ExtendedBusParameterSet,
    ExtendedState,
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
from tests.fixtures import real_dbm_bytes

# The seed's SDO example (5.2.5.1.1): object 0x6200 sub 5, 4 bytes 0x10010108.
SDO_EXAMPLE = SdoCfgData(0x6200, 0x05, 4, (0x10010108).to_bytes(4, "little"))
SDO_LIST_EXAMPLE = bytes.fromhex("0b00 0062 05 0400 08010110")

# A node 4 data set laid out as the seed's download message (5.2.5.1.2): one
# RXPDO and one TXPDO, so an ADD-tab of 1 input and 1 output offset, usAddTabLen 8.
NODE_4 = NodeParameterSet(
    bNd_Flag=NdFlag.ACTIVE,
    usAddTypeInfo=0x000F,
    usDevProfNum=401,
    usCobIDEmcy=0x84,
    usCobIDGuard=0x704,
    usGuardTime=500,
    bLifeTimeFactor=3,
    bitConfigNdState=0,
    atSdoCfgData=[SDO_EXAMPLE],
    atPdoCfgData=[PdoData(0, 2, 0x204, 255, 0), PdoData(1, 2, 0x184, 255, 0)],
    ausInputOffsets=[0x10],
    ausOutputOffsets=[0x20],
)
NODE_4_BYTES = bytes.fromhex(
    "3300"  # d[4]  usNodeParaLen 51
    "80"  # d[6]  bNd_Flag ACTIVE
    "0f00"  # d[7]  usAddTypeInfo
    "9101"  # d[9]  usDevProfNum 401
    "8400"  # d[11] usCobIDEmcy
    "0407"  # d[13] usCobIDGuard
    "f401"  # d[15] usGuardTime 500
    "03"  # d[17] bLifeTimeFactor
    "00"  # d[18] bitConfigNdState
    "00"  # d[19] abReserved
    + SDO_LIST_EXAMPLE.hex()  # d[20] usSdoCfgDataLen 11 + one entry
    + "1000 "  # usPdoCfgDataLen 2 + 2 * 7
    "00 02 0402 ff 0000 "  # RXPDO: 2 bytes on 0x204, type 255
    "01 02 8401 ff 0000 "  # TXPDO: 2 bytes on 0x184, type 255
    "0800 01 01 1000 2000"  # ADD-tab: usAddTabLen 8, 1 input, 1 output, offsets 0x10, 0x20
)


@pytest.fixture(scope="module")
def real() -> DbmFile:
    return read_dbm(real_dbm_bytes())


def only_record(dbm: DbmFile, name: str) -> bytes:
    table = dbm.table(name)
    assert table is not None
    (record,) = table.records
    return record


# --- GLOBAL --------------------------------------------------------------------------------


def test_real_global(real: DbmFile) -> None:
    record = only_record(real, GLOBAL)
    glob = GlobalSet.decode(record)
    assert glob.szSegmentName == "PB_COMBI"
    assert glob.usHostWatchdogValue == 1000
    assert (glob.bDbmVersion, glob.sVersion, glob.usChecksumCRC) == (1, 1, 0xE011)
    assert glob.abReservedA == bytes.fromhex("00ff0000000000000000")
    assert glob.bSystemStart == 0
    assert glob.encode() == record


def test_global_layout() -> None:
    raw = GlobalSet(
        bDbmVersion=2,
        sVersion=-2,
        usChecksumCRC=0x1234,
        bSystemStart=1,
        usHostWatchdogValue=500,
    ).encode()
    # seed 6.2.2: the CANopen segment name, then its NUL
    assert raw[:9] == bytes.fromhex("43414e6f70656e2000")
    assert len(raw) == 34
    assert raw[19] == 2
    assert raw[20:22] == b"\xfe\xff"
    assert raw[22:24] == b"\x34\x12"
    assert raw[28] == 1
    assert raw[32:34] == b"\xf4\x01"


def test_table_names_as_the_seed_spells_them() -> None:
    names = {
        GLOBAL: "474C4F42414C00",
        BUS_CAN: "4255535F43414E00",
        NODES: "4E4F44455300",
        PLC_PARAM: "504C435F504152414D00",
        PROJEKT: "50524F4A454B5400",
        DESCRIPT: "444553435249505400",
        BUS_CAN_EXT: "4255535F43414E5F45585400",
    }
    raw = write_dbm(DbmFile([DbmTable(name) for name in names]))
    for name, spelled in names.items():
        assert name.encode() + b"\0" == bytes.fromhex(spelled)
        assert bytes.fromhex(spelled) in raw


@pytest.mark.parametrize(
    "data",
    [
        bytes(33),
        bytes(35),
        b"CANopen !" + bytes(25),  # no NUL in szSegmentName[9]
        b"CAN\0open\0" + bytes(25),  # garbage after the NUL
    ],
)
def test_global_decode_refuses(data: bytes) -> None:
    with pytest.raises(DbmError):
        GlobalSet.decode(data)


@pytest.mark.parametrize(
    "glob",
    [
        GlobalSet(szSegmentName="CANopen 1"),
        GlobalSet(usHostWatchdogValue=65536),
        GlobalSet(sVersion=40000),
        GlobalSet(abReservedA=bytes(9)),
        GlobalSet(szSegmentName="CAN\u00f6\u20ac"),
    ],
)
def test_global_encode_refuses(glob: GlobalSet) -> None:
    with pytest.raises(DbmError):
        glob.encode()


# --- node parameter data set ---------------------------------------------------------------


def test_sdo_entry_example() -> None:
    assert SDO_EXAMPLE.encode() == SDO_LIST_EXAMPLE[2:]
    assert SdoCfgData.decode(SDO_LIST_EXAMPLE[2:]) == SDO_EXAMPLE
    only_sdo = NodeParameterSet(atSdoCfgData=[SDO_EXAMPLE]).encode()
    assert only_sdo[16:27] == SDO_LIST_EXAMPLE


def test_add_tab_example() -> None:
    raw = NODE_4.encode()
    assert raw[-8:] == bytes.fromhex("0800 01 01 1000 2000")


def test_empty_lists() -> None:
    raw = NodeParameterSet().encode()
    # usSdoCfgDataLen 2 for an empty SDO list (seed), likewise the PDO list; ADD-tab 4
    assert raw == bytes.fromhex("1800 80" + " 00" * 13 + " 0200 0200 0400 00 00")
    assert NodeParameterSet.decode(raw) == NodeParameterSet()


def test_node_set_matches_the_download_message() -> None:
    assert NODE_4.encode() == NODE_4_BYTES
    assert NodeParameterSet.decode(NODE_4_BYTES) == NODE_4
    assert len(NODE_4_BYTES) == int.from_bytes(NODE_4_BYTES[:2], "little")
    # msg.d[n] of the seed's message is data set byte n - 4
    assert NODE_4_BYTES[6 - 4] == 128
    assert NODE_4_BYTES[17 - 4] == 3
    assert NODE_4_BYTES[20 - 4 : 22 - 4] == b"\x0b\x00"


def test_node_set_keeps_reserved_and_flags() -> None:
    node = NodeParameterSet(
        bNd_Flag=NdFlag.ACTIVE | NdFlag.HRTBT,
        bitConfigNdState=ConfigNdState.RESET | ConfigNdState.TXRXPDO,
        abReserved=b"\x5a",
    )
    raw = node.encode()
    assert raw[2] == 0xC0
    assert raw[14:16] == b"\x81\x5a"
    assert NodeParameterSet.decode(raw) == node
    assert node.active
    assert not NodeParameterSet(bNd_Flag=NdFlag.HRTBT).active


def test_pdo_properties() -> None:
    word_pdo = PdoData(bTypeOfPdo=3, bLength=0x82, usPdoCOBId=0x181, bTransType=1)
    assert word_pdo.is_input
    assert word_pdo.data_length == 2
    assert word_pdo.word_oriented
    byte_pdo = PdoData(0, 8, 0x201, 254, 100)
    assert not byte_pdo.is_input
    assert not byte_pdo.word_oriented
    assert byte_pdo.encode() == bytes.fromhex("00 08 0102 fe 6400")


def test_node_set_structure_errors_carry_msg_f() -> None:
    with pytest.raises(DbmError) as caught:
        NodeParameterSet.decode(NODE_4_BYTES[:-1])
    assert caught.value.number == 59
    assert caught.value.field == "usNodeParaLen"


@pytest.mark.parametrize(
    "node",
    [
        NodeParameterSet(usCobIDEmcy=0x10000),
        NodeParameterSet(abReserved=b""),
        NodeParameterSet(atSdoCfgData=[SdoCfgData(0x1000, 0, 4, b"\x01")]),
        NodeParameterSet(atPdoCfgData=[PdoData(0, 256, 0x181, 1)]),
        NodeParameterSet(ausInputOffsets=[70000]),
        NodeParameterSet(ausInputOffsets=[0] * 256),
        NodeParameterSet(atSdoCfgData=[SDO_EXAMPLE] * 7282),
    ],
)
def test_node_set_encode_refuses(node: NodeParameterSet) -> None:
    with pytest.raises(DbmError):
        node.encode()


def test_nodes_record() -> None:
    record = NodesRecord(4, NODE_4)
    raw = record.encode()
    assert raw == b"\x04" + NODE_4_BYTES
    assert NodesRecord.decode(raw) == record
    with pytest.raises(DbmError):
        NodesRecord.decode(b"")
    with pytest.raises(DbmError):
        NodesRecord(128 * 2, NODE_4).encode()


# --- bus parameter data sets ---------------------------------------------------------------


def test_bus_parameters() -> None:
    bus = BusParameterSet(
        Baud_rate=2, COB_ID_SYNC=0x80, SYNC_Timer=100, Auto_Clear=1, Intel_Motorola=1
    )
    # msg.d[4] Baud_rate, d[5] COB-ID, d[7] SYNC timer, d[9] auto clear, d[10] format
    assert bus.encode() == bytes.fromhex("02 8000 6400 01 01")
    assert BusParameterSet.decode(bus.encode()) == bus
    with pytest.raises(DbmError) as caught:
        BusParameterSet.decode(bytes(8))
    assert caught.value.number == 59
    with pytest.raises(DbmError):
        BusParameterSet(COB_ID_SYNC=-1).encode()


def test_extended_bus_parameters() -> None:
    ext = ExtendedBusParameterSet(
        bExtendedState=ExtendedState.bi11Bit29BitSelector | ExtendedState.biNoGobalStartNode,
        ulAcceptCode=0x12345678,
        ulAcceptMask=0x1FFFFFFF,
        bNodeID=1,
        usProducerHeartbeatTime=1000,
    )
    raw = ext.encode()
    # msg.d[4] state, d[5-8] code, d[9-12] mask, d[13] node ID, d[14-15] heartbeat, rest 0
    assert raw == bytes.fromhex("03 78563412 ffffff1f 01 e803") + bytes(29)
    assert len(raw) == BUS_CAN_EXT_SIZE
    assert ExtendedBusParameterSet.decode(raw) == ext
    kept = ExtendedBusParameterSet(bReserved=7, ulReserved=(1, 2, 3, 4, 5, 6, 0xFFFFFFFF))
    assert ExtendedBusParameterSet.decode(kept.encode()) == kept
    with pytest.raises(DbmError) as caught:
        ExtendedBusParameterSet.decode(bytes(40))
    assert caught.value.number == 59
    with pytest.raises(DbmError):
        ExtendedBusParameterSet(ulReserved=(0,) * 8).encode()


# --- PLC_PARAM, PROJEKT, DESCRIPT ----------------------------------------------------------


def test_real_plc_param(real: DbmFile) -> None:
    record = only_record(real, PLC_PARAM)
    assert PlcParam.decode(record) == PlcParam(bMode=2, usWatchDogTime=1, bReserved=0)
    assert PlcParam(2, 1, 0).encode() == record
    with pytest.raises(DbmError):
        PlcParam.decode(bytes(5))


def test_real_projekt(real: DbmFile) -> None:
    record = only_record(real, PROJEKT)
    projekt = ProjektRecord.decode(record)
    assert projekt == ProjektRecord("PROFIBUS new network", "1.000", "27.03.2001")
    assert projekt.encode() == record
    raw = ProjektRecord("P", "V", "D").encode()
    assert (raw[0:1], raw[41:42], raw[130:131], len(raw)) == (b"P", b"V", b"D", 234)


@pytest.mark.parametrize(
    "projekt", [ProjektRecord("x" * 42), ProjektRecord(szDate="d" * 105), ProjektRecord("a\0b")]
)
def test_projekt_encode_refuses(projekt: ProjektRecord) -> None:
    with pytest.raises(DbmError):
        projekt.encode()


def test_projekt_decode_refuses() -> None:
    with pytest.raises(DbmError, match="NUL padded"):
        ProjektRecord.decode(b"name\0junk" + bytes(225))


def test_real_descript(real: DbmFile) -> None:
    record = only_record(real, DESCRIPT)
    descript = DescriptRecord.decode(record)
    assert descript.bStationAddress == 1
    assert descript.bRecordType == 2
    assert descript.usIdentNumber == 0x7508
    assert descript.szVendorName == "Hilscher GmbH"
    assert descript.szDeviceName == "CB_AB32-DPS"
    assert descript.szDescription == "Slave1"
    assert descript.abReserved == b"***reserved***"
    assert descript.atPdos == [DescriptPdo(0x25, 2, 0, 0), DescriptPdo(0x95, 2, 0, 0)]
    assert descript.encode() == record


def test_descript_layout() -> None:
    descript = DescriptRecord(
        5,
        usIdentNumber=0x1234,
        usVendorNumber=0xABCD,
        szVendorName="V",
        bMasterAddress=127,
        atPdos=[DescriptPdo(0x10, 8, 1, 0x0302)],
    )
    raw = descript.encode()
    assert raw[:6] == bytes.fromhex("05 02 1234 abcd")
    assert raw[6:8] == b"V\0"
    assert raw[102] == 127
    assert raw[118:] == bytes.fromhex("01 10 08 01 0203")
    assert DescriptRecord.decode(raw) == descript


@pytest.mark.parametrize("data", [bytes(118), bytes(120), bytes(118) + b"\x02" + bytes(5)])
def test_descript_decode_refuses(data: bytes) -> None:
    with pytest.raises(DbmError):
        DescriptRecord.decode(data)


# --- usChecksumCRC -------------------------------------------------------------------------


def test_checksum_crc_is_ccitt_false_over_records_in_table_order() -> None:
    dbm = DbmFile(
        [
            DbmTable(GLOBAL, [GlobalSet(usChecksumCRC=0x5555).encode()]),
            DbmTable("A", [b"1234", b"5"]),
            DbmTable("B", [b"6789"]),
        ]
    )
    # 0x29B1 is CRC-16/CCITT-FALSE's check value for "123456789"; GLOBAL is left out
    assert checksum_crc(dbm) == 0x29B1
    assert checksum_crc(DbmFile([])) == 0xFFFF
