"""The CAN task's data sets: node parameters, bus parameters, extended bus parameters.

These are the byte layouts of seed manual 5.2.5 exactly as a host sends them
with COM_Download (and as SyCon stores them in the NODES, BUS_CAN and
BUS_CAN_EXT tables), with no knowledge of the DBM container, so the firmware
decodes downloaded data with this same code.

Decoding is strict about structure and lenient about values: a set whose
length fields do not add up raises DbmError carrying the msg.f number the
CAN task answers with; out-of-range values decode fine and are judged by
dbm_tools.validate, so a tool can still show a faulty set to its user.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntFlag

from dbm_tools._binary import fixed, pack, unpack
from dbm_tools.errors import DbmError
from dpm import cia301
from dpm.cia301 import SYNC_RTR, SYNC_TYPES_MAX
from dpm.errors import CanF


class NdFlag(IntFlag):
    """bNd_Flag bits; the other bits are reserved."""

    HRTBT = 0x40
    """Supervise the node by heartbeat instead of node guarding."""
    ACTIVE = 0x80
    """The master boots and exchanges data with the node; inactive nodes keep their I/O areas."""


class ConfigNdState(IntFlag):
    """bitConfigNdState bits: a set bit SKIPS that step of the node's boot-up."""

    RESET = 0x01
    DEVICE = 0x02
    GUARD = 0x04
    SYNC = 0x08
    EMCY = 0x10
    SDO = 0x20
    START = 0x40
    TXRXPDO = 0x80


class ExtendedState(IntFlag):
    """bExtendedState bits (C bit fields, least significant first)."""

    bi11Bit29BitSelector = 0x01
    biNoGobalStartNode = 0x02


MSK_LENGTH = 0x7F
MSK_WORD_PDO = 0x80

BAUD_RATES_KBIT = {0: 1000, 1: 800, 2: 500, 3: 250, 4: 125, 5: 100, 6: 50, 7: 20, 8: 10}
"""Baud_rate codes (COM_BAUD_1000 = 0 ... COM_BAUD_10 = 8) and their bit rates."""

ACLR_INACTIVE = 0
ACLR_ACTIVE = 1
INTEL = 0
MOTOROLA = 1

ND_PRM_HEADER_SIZE = 16
SDO_CFG_DATA_SIZE = 9
PDO_DATA_SIZE = 7
LIST_LENGTH_SIZE = 2
ADD_TAB_HEADER_SIZE = 4
BUS_CAN_SIZE = 7
BUS_CAN_EXT_SIZE = 41

_HEADER_FORMAT = "HBHHHHHBB"
_SDO_FORMAT = "HBH"
_PDO_FORMAT = "BBHBH"
_BUS_CAN_FORMAT = "BHHBB"
_BUS_CAN_EXT_FORMAT = "BIIBHB7I"


@dataclass
class SdoCfgData:
    """One COM_SDO_CFG_DATA entry: an object value written to the node at boot-up.

    bLength is a word although its prefix says byte: only then is the seed's
    example list (one entry, usSdoCfgDataLen 11) consistent. abSdoValue is
    always the 4-byte field; bLength says how many of its bytes are sent.
    """

    usIndex: int
    bSubindex: int
    bLength: int
    abSdoValue: bytes = bytes(4)

    @classmethod
    def decode(cls, data: bytes) -> SdoCfgData:
        data = fixed(data, SDO_CFG_DATA_SIZE, "COM_SDO_CFG_DATA")
        index, subindex, length = unpack(_SDO_FORMAT, data, 0, "COM_SDO_CFG_DATA")
        return cls(index, subindex, length, data[5:])

    def encode(self) -> bytes:
        return pack(
            _SDO_FORMAT, self.usIndex, self.bSubindex, self.bLength, what="COM_SDO_CFG_DATA"
        ) + fixed(self.abSdoValue, 4, "abSdoValue")


@dataclass
class PdoData:
    """One COM_PDO_DATA entry; inputs and outputs are seen from the master."""

    bTypeOfPdo: int
    bLength: int
    usPdoCOBId: int
    bTransType: int
    usInhibitCycle: int = 0

    @property
    def is_input(self) -> bool:
        """A TXPDO of the node (bTypeOfPdo != 0) fills the master's input area."""
        return self.bTypeOfPdo != 0

    @property
    def sync_controlled(self) -> bool:
        """Transmission types 0-240 and 252 follow the SYNC; only these make the card send it."""
        return self.bTransType <= SYNC_TYPES_MAX or self.bTransType == SYNC_RTR

    @property
    def data_length(self) -> int:
        """Process data bytes: bLength without the word-orientation bit."""
        return self.bLength & MSK_LENGTH

    @property
    def word_oriented(self) -> bool:
        """Word PDOs are byte-swapped when the bus parameters select MOTOROLA."""
        return bool(self.bLength & MSK_WORD_PDO)

    @classmethod
    def decode(cls, data: bytes) -> PdoData:
        data = fixed(data, PDO_DATA_SIZE, "COM_PDO_DATA")
        return cls(*unpack(_PDO_FORMAT, data, 0, "COM_PDO_DATA"))

    def encode(self) -> bytes:
        return pack(
            _PDO_FORMAT,
            self.bTypeOfPdo,
            self.bLength,
            self.usPdoCOBId,
            self.bTransType,
            self.usInhibitCycle,
            what="COM_PDO_DATA",
        )


def _list_length(data: bytes, at: int, end: int, entry: int, faulty_size: int, what: str) -> int:
    """Read a list's length word; it counts itself and must hold whole entries up to `end`."""
    if at + LIST_LENGTH_SIZE > end:
        raise DbmError(f"no room for {what}", field=what, number=CanF.WHOLE_LENGTH)
    (length,) = unpack("H", data, at, what)
    if length < LIST_LENGTH_SIZE or (length - LIST_LENGTH_SIZE) % entry:
        raise DbmError(
            f"{what} {length} is not 2 + n * {entry}", field=what, number=CanF.INCOMPLETE
        )
    if at + length > end:
        raise DbmError(f"{what} {length} runs past usNodeParaLen", field=what, number=faulty_size)
    return length


@dataclass
class NodeParameterSet:
    """A node parameter data set: COM_ND_PRM_HEADER, SDO list, PDO list, ADD-tab.

    The ADD-tab's ausIOOffsets (all input offsets, then all output offsets)
    is kept as two lists, so that bInputCount and bOutputCount are their
    lengths and cannot disagree with them. All lengths (usNodeParaLen,
    usSdoCfgDataLen, usPdoCfgDataLen, usAddTabLen) are derived on encode.
    """

    bNd_Flag: int = int(NdFlag.ACTIVE)
    usAddTypeInfo: int = 0
    usDevProfNum: int = 0
    usCobIDEmcy: int = 0
    usCobIDGuard: int = 0
    usGuardTime: int = 0
    bLifeTimeFactor: int = 0
    bitConfigNdState: int = 0
    abReserved: bytes = b"\0"
    atSdoCfgData: list[SdoCfgData] = field(default_factory=list)
    atPdoCfgData: list[PdoData] = field(default_factory=list)
    ausInputOffsets: list[int] = field(default_factory=list)
    ausOutputOffsets: list[int] = field(default_factory=list)

    @property
    def active(self) -> bool:
        return bool(self.bNd_Flag & NdFlag.ACTIVE)

    @classmethod
    def decode(cls, data: bytes) -> NodeParameterSet:
        """Decode a whole set; `data` must be exactly usNodeParaLen bytes."""
        data = bytes(data)
        if len(data) < LIST_LENGTH_SIZE:
            raise DbmError("no usNodeParaLen", field="usNodeParaLen", number=CanF.INCOMPLETE)
        (total,) = unpack("H", data, 0, "usNodeParaLen")
        if total > len(data):
            raise DbmError(
                f"usNodeParaLen {total} but only {len(data)} bytes",
                field="usNodeParaLen",
                number=CanF.INCOMPLETE,
            )
        if total < len(data) or total < ND_PRM_HEADER_SIZE:
            raise DbmError(
                f"usNodeParaLen {total} but {len(data)} bytes",
                field="usNodeParaLen",
                number=CanF.WHOLE_LENGTH,
            )
        _, flag, add_type, profile, emcy, guard, guard_time, life, config = unpack(
            _HEADER_FORMAT, data, 0, "COM_ND_PRM_HEADER"
        )
        at = ND_PRM_HEADER_SIZE
        sdo_length = _list_length(
            data, at, total, SDO_CFG_DATA_SIZE, CanF.SDO_DATA_TOO_LARGE, "usSdoCfgDataLen"
        )
        sdos = [
            SdoCfgData.decode(data[i : i + SDO_CFG_DATA_SIZE])
            for i in range(at + LIST_LENGTH_SIZE, at + sdo_length, SDO_CFG_DATA_SIZE)
        ]
        at += sdo_length
        pdo_length = _list_length(
            data, at, total, PDO_DATA_SIZE, CanF.PDO_DATA_TOO_LARGE, "usPdoCfgDataLen"
        )
        pdos = [
            PdoData.decode(data[i : i + PDO_DATA_SIZE])
            for i in range(at + LIST_LENGTH_SIZE, at + pdo_length, PDO_DATA_SIZE)
        ]
        at += pdo_length
        if at + ADD_TAB_HEADER_SIZE > total:
            raise DbmError("no room for the ADD-tab", field="usAddTabLen", number=CanF.WHOLE_LENGTH)
        add_length, inputs, outputs = unpack("HBB", data, at, "COM_ND_PRM_ADD_TAB")
        if at + add_length > total:
            raise DbmError(
                f"usAddTabLen {add_length} runs past usNodeParaLen",
                field="usAddTabLen",
                number=CanF.ADD_TAB_TOO_LARGE,
            )
        if add_length != ADD_TAB_HEADER_SIZE + 2 * (inputs + outputs):
            raise DbmError(
                f"usAddTabLen {add_length} for {inputs} inputs and {outputs} outputs",
                field="usAddTabLen",
                number=CanF.ADD_TAB_LENGTH,
            )
        offsets = list(
            unpack(f"{inputs + outputs}H", data, at + ADD_TAB_HEADER_SIZE, "ausIOOffsets")
        )
        at += add_length
        if at != total:
            raise DbmError(
                f"data set ends at {at}, usNodeParaLen is {total}",
                field="usNodeParaLen",
                number=CanF.WHOLE_LENGTH,
            )
        return cls(
            flag,
            add_type,
            profile,
            emcy,
            guard,
            guard_time,
            life,
            config,
            data[ND_PRM_HEADER_SIZE - 1 : ND_PRM_HEADER_SIZE],
            sdos,
            pdos,
            offsets[:inputs],
            offsets[inputs:],
        )

    def encode(self) -> bytes:
        sdo_list = b"".join(sdo.encode() for sdo in self.atSdoCfgData)
        pdo_list = b"".join(pdo.encode() for pdo in self.atPdoCfgData)
        offsets = self.ausInputOffsets + self.ausOutputOffsets
        add_tab = pack(
            f"HBB{len(offsets)}H",
            ADD_TAB_HEADER_SIZE + 2 * len(offsets),
            len(self.ausInputOffsets),
            len(self.ausOutputOffsets),
            *offsets,
            what="COM_ND_PRM_ADD_TAB",
        )
        body = (
            pack(
                _HEADER_FORMAT[1:],
                self.bNd_Flag,
                self.usAddTypeInfo,
                self.usDevProfNum,
                self.usCobIDEmcy,
                self.usCobIDGuard,
                self.usGuardTime,
                self.bLifeTimeFactor,
                self.bitConfigNdState,
                what="COM_ND_PRM_HEADER",
            )
            + fixed(self.abReserved, 1, "abReserved")
            + pack("H", LIST_LENGTH_SIZE + len(sdo_list), what="usSdoCfgDataLen")
            + sdo_list
            + pack("H", LIST_LENGTH_SIZE + len(pdo_list), what="usPdoCfgDataLen")
            + pdo_list
            + add_tab
        )
        return pack("H", LIST_LENGTH_SIZE + len(body), what="usNodeParaLen") + body


@dataclass
class BusParameterSet:
    """The bus parameter data set (BUS_CAN); its download starts the network."""

    Baud_rate: int = 4
    COB_ID_SYNC: int = cia301.COB_ID_SYNC
    SYNC_Timer: int = 0
    Auto_Clear: int = ACLR_INACTIVE
    Intel_Motorola: int = INTEL

    @classmethod
    def decode(cls, data: bytes) -> BusParameterSet:
        if len(data) != BUS_CAN_SIZE:
            raise DbmError(
                f"bus parameter data set must be {BUS_CAN_SIZE} bytes, got {len(data)}",
                field="BUS_CAN",
                number=CanF.INCOMPLETE,
            )
        return cls(*unpack(_BUS_CAN_FORMAT, data, 0, "BUS_CAN"))

    def encode(self) -> bytes:
        return pack(
            _BUS_CAN_FORMAT,
            self.Baud_rate,
            self.COB_ID_SYNC,
            self.SYNC_Timer,
            self.Auto_Clear,
            self.Intel_Motorola,
            what="BUS_CAN",
        )


@dataclass
class ExtendedBusParameterSet:
    """The extended bus parameter data set (BUS_CAN_EXT), seed 5.2.5.3's layout.

    Seed 6.3.3 shows an older layout (ulReserved[8] right after the masks);
    both are 41 bytes, and the newer one names what the firmware uses.
    """

    bExtendedState: int = 0
    ulAcceptCode: int = 0
    ulAcceptMask: int = 0
    bNodeID: int = 0
    usProducerHeartbeatTime: int = 0
    bReserved: int = 0
    ulReserved: tuple[int, ...] = (0,) * 7

    @classmethod
    def decode(cls, data: bytes) -> ExtendedBusParameterSet:
        if len(data) != BUS_CAN_EXT_SIZE:
            raise DbmError(
                f"extended bus parameter data set must be {BUS_CAN_EXT_SIZE} bytes,"
                f" got {len(data)}",
                field="BUS_CAN_EXT",
                number=CanF.INCOMPLETE,
            )
        state, code, mask, node_id, heartbeat, reserved, *longs = unpack(
            _BUS_CAN_EXT_FORMAT, data, 0, "BUS_CAN_EXT"
        )
        return cls(state, code, mask, node_id, heartbeat, reserved, tuple(longs))

    def encode(self) -> bytes:
        if len(self.ulReserved) != 7:
            raise DbmError("ulReserved must hold 7 longs", field="ulReserved")
        return pack(
            _BUS_CAN_EXT_FORMAT,
            self.bExtendedState,
            self.ulAcceptCode,
            self.ulAcceptMask,
            self.bNodeID,
            self.usProducerHeartbeatTime,
            self.bReserved,
            *self.ulReserved,
            what="BUS_CAN_EXT",
        )
