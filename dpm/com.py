"""The data bytes of the CAN task's messages (msg.rx 3), as pure codecs.

Seed chapter 5.2 and 5.3 give every CAN-task message as a table of ``msg.d[]`` bytes;
``docs/card-commands.md`` adds our own 110-117. Each table is one class or one pair of
functions here, so the card's firmware, the host's on-line configuration and the CiA 309
gateway read and write the same bytes. Nothing here does I/O; ``dpm.message`` adds the
8-byte message header. A decoder raises ``MessageError`` for bytes that do not fit its
table; the task answers that with the msg.f its command documents.
"""

from __future__ import annotations

import struct
from collections import deque
from dataclasses import dataclass, field
from enum import IntFlag

from dpm.commands import NODE_DIAG_SIZE
from dpm.message import MessageError, Tdt, TelegramHeader, Tfc

_AREA_REQUEST = struct.Struct("<BBH")
"""Req_Adr, Area_Code, a word (Timeout or Add_Offset): COM_Start_Seq and COM_Download."""
_UPLOAD_REQUEST = struct.Struct("<BBHB")
_NODE_DIAG_HEAD = struct.Struct("<BHHBBB")
EMCY_ENTRIES = 5
"""COM_Node_Diag's Emcy_Data holds 40 bytes: five 8-byte EMCY messages."""
EMCY_ENTRY_SIZE = 8


def _need(data: bytes, size: int, what: str) -> None:
    if len(data) < size:
        raise MessageError(f"{what} needs {size} data bytes, got {len(data)}")


# --- COM_Start_Seq / COM_Download / COM_End_Seq / COM_Upload (seed 5.2.3 - 5.2.6) ---------


@dataclass(frozen=True, slots=True)
class StartSeqRequest:
    """COM_START_SEQ_REQUEST: a sequenced download of one node's data set."""

    area: int
    """Area_Code: the node address 1..126."""
    timeout_ms: int = 0
    """Timeout between the sequence's messages, in ms (0: none)."""
    req_adr: int = 0

    def encode(self) -> bytes:
        return _AREA_REQUEST.pack(self.req_adr, self.area, self.timeout_ms)

    @classmethod
    def decode(cls, data: bytes) -> StartSeqRequest:
        _need(data, _AREA_REQUEST.size, "COM_Start_Seq")
        req_adr, area, timeout = _AREA_REQUEST.unpack_from(data)
        return cls(area, timeout, req_adr)


def encode_start_seq_confirm(max_len_data_unit: int) -> bytes:
    """COM_START_SEQ_CONFIRM: Max_Len_Data_Unit, the data bytes per following COM_Download."""
    return bytes([max_len_data_unit])


def decode_start_seq_confirm(data: bytes) -> int:
    """Max_Len_Data_Unit of a COM_Start_Seq answer."""
    _need(data, 1, "COM_START_SEQ_CONFIRM")
    if data[0] == 0:
        raise MessageError("COM_START_SEQ_CONFIRM with Max_Len_Data_Unit 0")
    return data[0]


@dataclass(frozen=True, slots=True)
class DownloadRequest:
    """COM_DOWNLOAD_REQUEST: a node's data set (1..126), bus (127) or extended bus (128)."""

    area: int
    data: bytes = b""
    offset: int = 0
    """Add_Offset in the download area of a sequenced download."""
    req_adr: int = 0

    def encode(self) -> bytes:
        return _AREA_REQUEST.pack(self.req_adr, self.area, self.offset) + self.data

    @classmethod
    def decode(cls, data: bytes) -> DownloadRequest:
        _need(data, _AREA_REQUEST.size, "COM_Download")
        req_adr, area, offset = _AREA_REQUEST.unpack_from(data)
        return cls(area, bytes(data[_AREA_REQUEST.size :]), offset, req_adr)


END_SEQ_REQUEST = bytes([0])
"""COM_END_SEQ_REQUEST: Req_Adr, unused."""


@dataclass(frozen=True, slots=True)
class UploadRequest:
    """COM_UPLOAD_REQUEST: read back a stored data set; the answer is the bytes alone."""

    area: int
    length: int
    """Data_Len 1..240."""
    offset: int = 0
    req_adr: int = 0

    SIZE = _UPLOAD_REQUEST.size

    def encode(self) -> bytes:
        return _UPLOAD_REQUEST.pack(self.req_adr, self.area, self.offset, self.length)

    @classmethod
    def decode(cls, data: bytes) -> UploadRequest:
        if len(data) != _UPLOAD_REQUEST.size:
            raise MessageError(f"COM_Upload needs {_UPLOAD_REQUEST.size} data bytes")
        req_adr, area, offset, length = _UPLOAD_REQUEST.unpack(data)
        return cls(area, length, offset, req_adr)


# --- COM_Node_Diag (seed 5.2.7) ----------------------------------------------------------------


class NodeStatus(IntFlag):
    """Nodestatus_1, the first byte of a node's diagnosis."""

    NO_RESPONSE = 0x01
    EMCY_BUFFER_OVERFLOW = 0x02
    PRM_FAULT = 0x04
    """Master and node configuration differ."""
    GUARD_ACTIVE = 0x08
    DEACTIVATED = 0x80
    """The node is not handled by the master."""


def node_diag_request(node: int) -> bytes:
    """The telegram header of a COM_Node_Diag request."""
    return TelegramHeader(node, data_type=Tdt.UINT8, function=Tfc.READ).encode()


@dataclass(slots=True)
class NodeDiagnosis:
    """COM_ND_DIAGNOSTICS: the 48 bytes after the answer's telegram header.

    The card's node handlers keep one per node and update it in place (``emcy`` drops the
    oldest message when a sixth arrives; the handler sets ``EMCY_BUFFER_OVERFLOW``).
    """

    status: int = 0
    """Nodestatus_1 (``NodeStatus`` bits)."""
    add_info: int = 0
    profile: int = 0
    node_state: int = 0
    actual_error: int = 0
    """The node's current Err_Event."""
    emcy: deque[bytes] = field(default_factory=lambda: deque(maxlen=EMCY_ENTRIES))
    """The stored EMCY messages, 8 bytes each: the newest five, as the card keeps them."""

    def encode(self) -> bytes:
        kept = list(self.emcy)[-EMCY_ENTRIES:]
        entries = b"".join(e.ljust(EMCY_ENTRY_SIZE, b"\0")[:EMCY_ENTRY_SIZE] for e in kept)
        head = _NODE_DIAG_HEAD.pack(self.status, self.add_info, self.profile, self.node_state,
                                    self.actual_error, len(kept))
        return (head + entries).ljust(NODE_DIAG_SIZE, b"\0")

    @classmethod
    def decode(cls, data: bytes) -> NodeDiagnosis:
        _need(data, NODE_DIAG_SIZE, "COM_ND_DIAGNOSTICS")
        status, add_info, profile, state, error, count = _NODE_DIAG_HEAD.unpack_from(data)
        if count > EMCY_ENTRIES:
            raise MessageError(f"Emcy_Entries {count} exceeds {EMCY_ENTRIES}")
        at = _NODE_DIAG_HEAD.size
        emcy = [bytes(data[at + i * EMCY_ENTRY_SIZE : at + (i + 1) * EMCY_ENTRY_SIZE])
                for i in range(count)]
        return cls(status, add_info, profile, state, error, deque(emcy, maxlen=EMCY_ENTRIES))


def node_diag_answer(request: TelegramHeader, diagnosis: bytes) -> bytes:
    """The answer's data: the request's header with data_cnt 48, byte string, read; then the
    diagnosis. The unused header fields are echoed as the host sent them [ours]."""
    return TelegramHeader(request.device_adr, request.data_area, request.data_adr,
                          request.data_idx, len(diagnosis), Tdt.UINT8, Tfc.READ,
                          diagnosis).encode()


# --- COM_SDO_Up_Download (seed 5.2.8) --------------------------------------------------------


def sdo_request(node: int, index: int, subindex: int, data: bytes | None = None) -> bytes:
    """An upload (``data`` None, TASK_TFC_READ) or a download (TASK_TFC_WRITE) request."""
    if data is None:
        return TelegramHeader(node, 0, index, subindex, 0, 0, Tfc.READ).encode()
    return TelegramHeader(node, 0, index, subindex, len(data) & 0xFF, 0, Tfc.WRITE,
                          data).encode()


def sdo_abort_code(answer: bytes) -> int:
    """The Abort Reason Code after the telegram header of an answer with msg.f 3."""
    _need(answer, TelegramHeader.SIZE + 4, "an SDO abort answer")
    (code,) = struct.unpack_from("<I", answer, TelegramHeader.SIZE)
    return int(code)


def encode_sdo_abort(head: TelegramHeader, code: int) -> bytes:
    """The data of an answer with msg.f 3: the header and the node's abort code."""
    return head.encode() + struct.pack("<I", code)


# --- COM_NMT_Module_Protocol (seed 5.2.9) ----------------------------------------------------


@dataclass(frozen=True, slots=True)
class NmtRequest:
    """An NMT command specifier (``dpm.commands.Nmt``) for one node, or 0 for all."""

    command: int
    node: int = 0

    def encode(self) -> bytes:
        return bytes([self.command, self.node])

    @classmethod
    def decode(cls, data: bytes) -> NmtRequest:
        _need(data, 2, "COM_NMT_Module_Protocol")
        return cls(data[0], data[1])


# --- transparent CAN: COM_Send_CANMsg_Transparent / COM_Receive_CANMsg_Transparent ----------

TRANSPARENT_2A_SIZE = 10
"""msg.ln of a CAN 2.0A message (seed 5.2.10.1)."""
TRANSPARENT_2B_STANDARD_SIZE = 11
TRANSPARENT_2B_EXTENDED_SIZE = 13
_FRAME_FORMAT_EXTENDED = 0x80
_FRAME_INFO_RTR = 0x40
_ID2_RTR = 0x10
_DLC = 0x0F


@dataclass(frozen=True, slots=True)
class CanFrame:
    """One CAN frame as the host describes it: the DLC may say more than the data holds."""

    ident: int
    data: bytes = b""
    rtr: bool = False
    dlc: int | None = None
    """The Data Length Code sent; None: the data's length."""
    extended: bool = False

    @property
    def length_code(self) -> int:
        return len(self.data) if self.dlc is None else self.dlc

    @property
    def payload(self) -> bytes:
        """The data bytes on the bus: none for a remote frame, at most 8."""
        return b"" if self.rtr else self.data[: min(self.length_code, 8)]


def encode_transparent_2a(frame: CanFrame) -> bytes:
    """COM_Send_CANMsg_Transparent for 11-bit devices: ID.10..3, ID.2..0 RTR DLC, 8 data."""
    second = ((frame.ident & 0x7) << 5) | (_ID2_RTR if frame.rtr else 0) | frame.length_code & _DLC
    return bytes([(frame.ident >> 3) & 0xFF, second]) + frame.data.ljust(8, b"\0")[:8]


def encode_transparent_2b(frame: CanFrame) -> bytes:
    """The CAN 2.0B form: frame info, then 2 (11-bit) or 4 (29-bit) identifier bytes, 8 data.

    It is also COM_Receive_CANMsg_Transparent's indication of a 29-bit frame.
    """
    info = ((_FRAME_FORMAT_EXTENDED if frame.extended else 0)
            | (_FRAME_INFO_RTR if frame.rtr else 0) | frame.length_code & _DLC)
    if frame.extended:
        ident = ((frame.ident & 0x1FFFFFFF) << 3).to_bytes(4, "big")
    else:
        ident = ((frame.ident & 0x7FF) << 5).to_bytes(2, "big")
    return bytes([info]) + ident + frame.data.ljust(8, b"\0")[:8]


def decode_transparent(data: bytes) -> CanFrame:
    """A transparent message of any of the three forms, told apart by its length."""
    if len(data) == TRANSPARENT_2A_SIZE:
        return CanFrame((data[0] << 3) | (data[1] >> 5), bytes(data[2:]), bool(data[1] & _ID2_RTR),
                        data[1] & _DLC)
    if len(data) in (TRANSPARENT_2B_STANDARD_SIZE, TRANSPARENT_2B_EXTENDED_SIZE):
        info = data[0]
        extended = bool(info & _FRAME_FORMAT_EXTENDED)
        if extended != (len(data) == TRANSPARENT_2B_EXTENDED_SIZE):
            raise MessageError(f"frame format bit {int(extended)} with msg.ln {len(data)}")
        if extended:
            ident, payload = int.from_bytes(data[1:5], "big") >> 3, data[5:]
        else:
            ident, payload = (data[1] << 3) | (data[2] >> 5), data[3:]
        return CanFrame(ident, bytes(payload), bool(info & _FRAME_INFO_RTR), info & _DLC,
                        extended)
    raise MessageError(f"a transparent CAN message has 10, 11 or 13 data bytes, not {len(data)}")


# --- the 29-bit acceptance filter (seed 5.2.5.3, 5.2.11.1, revision 17) -----------------------

ACCEPT_RANGE_MAX = 0xF8FFFFFF
"""Seed 5.2.5.3.1 (revision 17): ulAcceptCode and ulAcceptMask are 0..0xF8FFFFFF."""
ACCEPT_ALL_MASK = ACCEPT_RANGE_MAX
"""The mask every bit of which is "don't care": every 29-bit frame passes."""
_ACCEPT_ID_SHIFT = 3
"""ID.4..0 sit in bits 7..3 of the fourth register byte (bit 2 RTR, bits 1..0 unused)."""
_EXTENDED_ID = 0x1FFFFFFF


def acceptance_identifier_bits(value: int) -> int:
    """The 29 identifier bits of a ulAcceptCode or ulAcceptMask long.

    The long holds the SJA1000's four acceptance registers in their order, ACR0..ACR3
    (AMR0..AMR3), read as an Intel long: byte 0 ID.28..21, byte 1 ID.20..13, byte 2
    ID.12..5, byte 3 ID.4..0 in its bits 7..3 - the layout of the Rx-Identifier bytes of
    COM_Receive_CANMsg_Transparent (5.2.11.1). Byte 3's low three bits (RTR and two unused
    ones) are no identifier bits; revision 17's range 0xF8FFFFFF keeps them 0.
    """
    registers = (value & 0xFFFFFFFF).to_bytes(4, "little")
    return int.from_bytes(registers, "big") >> _ACCEPT_ID_SHIFT


def acceptance_long(identifier_bits: int) -> int:
    """The ulAcceptCode / ulAcceptMask long for 29 identifier bits (the inverse)."""
    registers = ((identifier_bits & _EXTENDED_ID) << _ACCEPT_ID_SHIFT).to_bytes(4, "big")
    return int.from_bytes(registers, "little")


def accepts_extended(code: int, mask: int, ident: int) -> bool:
    """Whether the card passes a 29-bit frame to the host (seed 5.2.11.1).

    The SJA1000's single-filter rule for an extended frame: every identifier bit whose
    mask bit is 0 must equal the code's bit; a mask bit 1 is "don't care". ``code`` and
    ``mask`` are the data set's longs (``acceptance_identifier_bits``). [ours] The RTR bit
    is not compared: the range leaves it 0 in both, which on the chip would let no remote
    frame through, yet the indication carries an RTR bit; a remote frame passes as a data
    frame of its identifier does.
    """
    relevant = ~acceptance_identifier_bits(mask) & _EXTENDED_ID
    return (ident ^ acceptance_identifier_bits(code)) & relevant == 0


# --- layer 2 (seed 5.3): COM_Tx_CAN_Layer2, COM_CfgRx_Layer2, COM_Rx_CAN_Layer2 --------------

LAYER2_MAX_FRAMES = 127
"""Frames (or filters) in one layer-2 message."""


def encode_layer2_frame(frame: CanFrame) -> bytes:
    """One frame of COM_Tx_CAN_Layer2 / COM_Rx_CAN_Layer2: 2 identifier bytes, its data."""
    second = ((frame.ident & 0x7) << 5) | (_ID2_RTR if frame.rtr else 0) | frame.length_code & _DLC
    return bytes([(frame.ident >> 3) & 0xFF, second]) + frame.payload


def decode_layer2_frames(data: bytes) -> list[CanFrame]:
    """Every frame of a layer-2 message; a DLC above 8 or a cut frame is malformed."""
    frames: list[CanFrame] = []
    at = 0
    while at < len(data):
        if at + 2 > len(data):
            raise MessageError(f"a layer-2 frame header is cut at byte {at}")
        ident = (data[at] << 3) | (data[at + 1] >> 5)
        rtr, dlc = bool(data[at + 1] & _ID2_RTR), data[at + 1] & _DLC
        size = 0 if rtr else dlc
        if dlc > 8 or at + 2 + size > len(data):
            raise MessageError(f"layer-2 frame at byte {at}: DLC {dlc} with "
                               f"{len(data) - at - 2} bytes left")
        frames.append(CanFrame(ident, bytes(data[at + 2 : at + 2 + size]), rtr, dlc))
        at += 2 + size
    if not frames:
        raise MessageError("a layer-2 message holds at least one frame")
    return frames


def encode_rx_filters(idents: list[int]) -> bytes:
    """COM_CfgRx_Layer2: per filter ID.7..0, then ID.10..8."""
    return b"".join(bytes([i & 0xFF, (i >> 8) & 0x07]) for i in idents)


def decode_rx_filters(data: bytes) -> list[int]:
    if not data or len(data) % 2:
        raise MessageError(f"COM_CfgRx_Layer2 needs 2 bytes per filter, got {len(data)}")
    return [data[i] | ((data[i + 1] & 0x07) << 8) for i in range(0, len(data), 2)]


def encode_bootup_indication(node: int) -> bytes:
    """[ours] COM_Bootup_Indication: the node-ID whose boot-up message was seen."""
    return bytes([node])


# --- GET_CONFIGURATION ----------------------------------------------------------------------


def configuration_request(node: int) -> bytes:
    """GET_CONFIGURATION: the telegram header naming the node."""
    return TelegramHeader(node).encode()


def configuration_answer(head: TelegramHeader, record: bytes) -> bytes:
    """The node's DESCRIPT record without its first byte, after the request's header."""
    payload = record[1 : 1 + 255 - TelegramHeader.SIZE]
    return TelegramHeader(head.device_adr, head.data_area, head.data_adr, head.data_idx,
                          len(payload), head.data_type, head.function, payload).encode()


# --- our own commands 110-116 (docs/card-commands.md) [ours] ---------------------------------

_SDO_TIMEOUT = struct.Struct("<BH")
_NODE_SWITCH = struct.Struct("<BBH")
_GUARDING = struct.Struct("<BBHB")


@dataclass(frozen=True, slots=True)
class SdoTimeoutRequest:
    """COM_Set_SDO_Timeout: node 0..127 (0 every node and the default), time-out in ms."""

    node: int
    timeout_ms: int

    def encode(self) -> bytes:
        return _SDO_TIMEOUT.pack(self.node, self.timeout_ms)

    @classmethod
    def decode(cls, data: bytes) -> SdoTimeoutRequest:
        if len(data) != _SDO_TIMEOUT.size:
            raise MessageError(f"COM_Set_SDO_Timeout needs {_SDO_TIMEOUT.size} data bytes")
        return cls(*_SDO_TIMEOUT.unpack(data))


@dataclass(frozen=True, slots=True)
class NodeSwitch:
    """COM_Set_Guarding, COM_Set_Heartbeat_Consumer, COM_Set_Emcy_Consumer: node, on, u16.

    ``value`` is the guard time, the consumer time or the EMCY COB-ID; ``factor`` the life
    time factor, which only COM_Set_Guarding carries.
    """

    node: int
    on: bool
    value: int
    factor: int | None = None

    def encode(self) -> bytes:
        if self.factor is None:
            return _NODE_SWITCH.pack(self.node, int(self.on), self.value)
        return _GUARDING.pack(self.node, int(self.on), self.value, self.factor)

    @classmethod
    def decode(cls, data: bytes, guarding: bool = False) -> NodeSwitch:
        layout = _GUARDING if guarding else _NODE_SWITCH
        if len(data) != layout.size:
            raise MessageError(f"a node switch needs {layout.size} data bytes, got {len(data)}")
        if data[1] not in (0, 1):
            raise MessageError(f"on/off byte {data[1]}")
        fields = layout.unpack(data)
        return cls(fields[0], bool(fields[1]), fields[2], fields[3] if guarding else None)


def encode_word(value: int) -> bytes:
    """COM_Set_Heartbeat_Producer: the producer time in ms (0 off)."""
    return struct.pack("<H", value)


def decode_word(data: bytes) -> int:
    if len(data) != 2:
        raise MessageError(f"a word needs 2 data bytes, got {len(data)}")
    return int(struct.unpack("<H", data)[0])
