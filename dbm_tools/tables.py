"""Record codecs of the CANopen master's DBM tables (seed chapter 6, docs/dbm.md section 2).

BUS_CAN and BUS_CAN_EXT records are the download data sets themselves (use
dbm_tools.parameters); NODES records prefix a node parameter data set with
the node address. The other tables are DBM-only and live here.

Every ``decode`` raises DbmError for bytes its record cannot be, every ``encode`` for
values that do not fit the record's fields.
"""

from __future__ import annotations

import binascii
from dataclasses import dataclass, field

from dbm_tools._binary import decode_text, encode_text, fixed, pack, unpack
from dbm_tools.container import DbmFile
from dbm_tools.errors import DbmError
from dbm_tools.parameters import NodeParameterSet

GLOBAL = "GLOBAL"
BUS_CAN = "BUS_CAN"
BUS_CAN_EXT = "BUS_CAN_EXT"
NODES = "NODES"
PLC_PARAM = "PLC_PARAM"
PROJEKT = "PROJEKT"
DESCRIPT = "DESCRIPT"

NODES_KEY_LENGTH = 1
"""NODES is keyed on its leading node address byte (descriptor f0 0x11)."""

SEGMENT_NAME_CANOPEN = "CANopen "
"""szSegmentName of a CANopen master database (seed 6.2.2), trailing blank included."""

DBM_SET_GLOBAL_SIZE = 34
PLC_PARAM_SIZE = 4
PROJEKT_SIZE = 234
DESCRIPT_FIXED_SIZE = 119
DESCRIPT_PDO_SIZE = 5

_PROJEKT_FIELDS = (("szProjectName", 0, 41), ("szVersion", 41, 89), ("szDate", 130, 104))
"""Offsets of the strings in SyCon's sample record; the zero gaps are kept in the field sizes."""
_NAME_SIZE = 32


@dataclass
class GlobalSet:
    """DBM_SET_GLOBAL, the one record of GLOBAL: it tells a card whose database this is.

    The seed's struct names two fields abReservedB; the second is abReservedC
    here, as in docs/dbm.md. Defaults mirror SyCon's sample except the segment name.
    """

    szSegmentName: str = SEGMENT_NAME_CANOPEN
    abReservedA: bytes = bytes(10)
    bDbmVersion: int = 1
    sVersion: int = 1
    usChecksumCRC: int = 0
    abReservedB: bytes = bytes(4)
    bSystemStart: int = 0
    abReservedC: bytes = bytes(3)
    usHostWatchdogValue: int = 1000

    @classmethod
    def decode(cls, data: bytes) -> GlobalSet:
        data = fixed(data, DBM_SET_GLOBAL_SIZE, "DBM_SET_GLOBAL")
        if b"\0" not in data[:9]:
            raise DbmError("szSegmentName not NUL terminated", field="szSegmentName")
        dbm_version, version, crc = unpack("BhH", data, 19, "DBM_SET_GLOBAL")
        (system_start,) = unpack("B", data, 28, "bSystemStart")
        (watchdog,) = unpack("H", data, 32, "usHostWatchdogValue")
        return cls(
            decode_text(data[:9], "szSegmentName"),
            data[9:19],
            dbm_version,
            version,
            crc,
            data[24:28],
            system_start,
            data[29:32],
            watchdog,
        )

    def encode(self) -> bytes:
        return (
            encode_text(self.szSegmentName, 8, "szSegmentName")
            + b"\0"
            + fixed(self.abReservedA, 10, "abReservedA")
            + pack("BhH", self.bDbmVersion, self.sVersion, self.usChecksumCRC, what="GLOBAL")
            + fixed(self.abReservedB, 4, "abReservedB")
            + pack("B", self.bSystemStart, what="bSystemStart")
            + fixed(self.abReservedC, 3, "abReservedC")
            + pack("H", self.usHostWatchdogValue, what="usHostWatchdogValue")
        )


def checksum_crc(dbm: DbmFile) -> int:
    """The usChecksumCRC our writers store [ours]: CRC-16/CCITT-FALSE of all record
    payloads of all tables except GLOBAL, in table order.

    SyCon's own value is not reproducible, so a mismatch is only ever a warning.
    binascii's CRC-CCITT (poly 0x1021, unreflected, our initial value 0xFFFF, no final
    XOR) is that CRC, in C: every start checks the stored database with it.
    """
    crc = 0xFFFF
    for table in dbm.tables:
        if table.name == GLOBAL:
            continue
        for record in table.records:
            crc = binascii.crc_hqx(record, crc)
    return crc


@dataclass
class NodesRecord:
    """A NODES record: Node_Address, then the node parameter data set as downloaded."""

    Node_Address: int
    Node_Data_set: NodeParameterSet = field(default_factory=NodeParameterSet)

    @classmethod
    def decode(cls, data: bytes) -> NodesRecord:
        if not data:
            raise DbmError("empty NODES record", field="Node_Address")
        return cls(data[0], NodeParameterSet.decode(data[1:]))

    def encode(self) -> bytes:
        return pack("B", self.Node_Address, what="Node_Address") + self.Node_Data_set.encode()


@dataclass
class PlcParam:
    """The PLC_PARAM record [ours]: 4 bytes like SyCon's sample (02 01 00 00)."""

    bMode: int = 0
    usWatchDogTime: int = 0
    bReserved: int = 0

    @classmethod
    def decode(cls, data: bytes) -> PlcParam:
        return cls(*unpack("BHB", fixed(data, PLC_PARAM_SIZE, "PLC_PARAM"), 0, "PLC_PARAM"))

    def encode(self) -> bytes:
        return pack("BHB", self.bMode, self.usWatchDogTime, self.bReserved, what="PLC_PARAM")


@dataclass
class ProjektRecord:
    """The PROJEKT record: project name, version and date, at SyCon's offsets."""

    szProjectName: str = ""
    szVersion: str = ""
    szDate: str = ""

    @classmethod
    def decode(cls, data: bytes) -> ProjektRecord:
        data = fixed(data, PROJEKT_SIZE, "PROJEKT")
        name, version, date = (
            decode_text(data[at : at + size], what) for what, at, size in _PROJEKT_FIELDS
        )
        return cls(name, version, date)

    def encode(self) -> bytes:
        values = (self.szProjectName, self.szVersion, self.szDate)
        return b"".join(
            encode_text(value, size, what)
            for value, (what, _, size) in zip(values, _PROJEKT_FIELDS, strict=True)
        )


@dataclass
class DescriptPdo:
    """One PDO line of a DESCRIPT record (bFlags & 0x30: 0x10 input, 0x20 output)."""

    bFlags: int
    bSize: int
    bDataPosition: int
    usAddress: int

    def encode(self) -> bytes:
        return pack(
            "BBBH", self.bFlags, self.bSize, self.bDataPosition, self.usAddress, what="DESCRIPT PDO"
        )


@dataclass
class DescriptRecord:
    """A DESCRIPT record: what a legacy host reads back with GET_CONFIGURATION.

    Ident and vendor numbers are stored big-endian, unlike everything else.
    """

    bStationAddress: int
    bRecordType: int = 2
    usIdentNumber: int = 0
    usVendorNumber: int = 0
    szVendorName: str = ""
    szDeviceName: str = ""
    szDescription: str = ""
    bMasterAddress: int = 0
    bSettings: int = 0
    abReserved: bytes = bytes(14)
    atPdos: list[DescriptPdo] = field(default_factory=list)

    @classmethod
    def decode(cls, data: bytes) -> DescriptRecord:
        data = bytes(data)
        if len(data) < DESCRIPT_FIXED_SIZE:
            raise DbmError(f"DESCRIPT record of {len(data)} bytes", field="DESCRIPT")
        count = data[DESCRIPT_FIXED_SIZE - 1]
        if len(data) != DESCRIPT_FIXED_SIZE + DESCRIPT_PDO_SIZE * count:
            raise DbmError(
                f"DESCRIPT record of {len(data)} bytes for {count} PDOs", field="bPdoCount"
            )
        pdos = [
            DescriptPdo(*unpack("BBBH", data, at, "DESCRIPT PDO"))
            for at in range(DESCRIPT_FIXED_SIZE, len(data), DESCRIPT_PDO_SIZE)
        ]
        return cls(
            data[0],
            data[1],
            int.from_bytes(data[2:4], "big"),
            int.from_bytes(data[4:6], "big"),
            decode_text(data[6:38], "szVendorName"),
            decode_text(data[38:70], "szDeviceName"),
            decode_text(data[70:102], "szDescription"),
            data[102],
            data[103],
            data[104:118],
            pdos,
        )

    def encode(self) -> bytes:
        return (
            pack("BB", self.bStationAddress, self.bRecordType, what="DESCRIPT")
            # big-endian words: the little-endian packing, byte-swapped
            + pack("H", self.usIdentNumber, what="usIdentNumber")[::-1]
            + pack("H", self.usVendorNumber, what="usVendorNumber")[::-1]
            + encode_text(self.szVendorName, _NAME_SIZE, "szVendorName")
            + encode_text(self.szDeviceName, _NAME_SIZE, "szDeviceName")
            + encode_text(self.szDescription, _NAME_SIZE, "szDescription")
            + pack("BB", self.bMasterAddress, self.bSettings, what="DESCRIPT")
            + fixed(self.abReserved, 14, "abReserved")
            + pack("B", len(self.atPdos), what="bPdoCount")
            + b"".join(pdo.encode() for pdo in self.atPdos)
        )
