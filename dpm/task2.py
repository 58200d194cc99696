"""Decoded views of the CANopen card's Task2Parameter and Task2State.

The raw bytes stay authoritative (the image, or a copy a host obtained from
DevGetTaskState); these classes only read them, so the status tool, tests and
the Board API share one decoding of the seed's COM_DIAGNOSTICS.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag

from dpm.errors import err_event_text

TASK_AREA_SIZE = 64


class GlobalBits(IntFlag):
    """global_bits of Task2State (seed manual 4.3)."""

    CTRL = 0x01
    ACLR = 0x02
    NEXC = 0x04
    FAT = 0x08
    EVE = 0x10
    NRDY = 0x20
    TOUT = 0x40


GLOBAL_BIT_TEXT: dict[GlobalBits, str] = {
    GlobalBits.CTRL: "CONTROL-ERROR: parameterization error",
    GlobalBits.ACLR: "AUTO-CLEAR-ERROR: communication to all nodes stopped",
    GlobalBits.NEXC: "NON-EXCHANGE-ERROR: at least one node not in data exchange",
    GlobalBits.FAT: "FATAL-ERROR: no further bus communication possible",
    GlobalBits.EVE: "EVENT-ERROR: transmission errors detected",
    GlobalBits.NRDY: "HOST-NOT-READY-NOTIFICATION",
    GlobalBits.TOUT: "TIMEOUT-ERROR: a CAN message could not be sent",
}


class CanState(IntEnum):
    """CAN_state: the main state of the master."""

    OFFLINE = 0x00
    STOP = 0x40
    CLEAR = 0x80
    OPERATE = 0xC0


class PlcMode(IntEnum):
    """bMode of COM_PLC_PARAMETER (seed manual 2.1)."""

    BUFFERED_DEVICE_CONTROLLED = 1
    UNCONTROLLED = 2
    BUFFERED_HOST_CONTROLLED = 3


BMODE_TO_EXCHANGE_MODE: dict[int, int] = {1: 2, 2: 3, 3: 4}
"""[ours] bMode -> process-data exchange mode (high nibble of bDriverType)."""

EXCHANGE_MODE_TEXT: dict[int, str] = {
    0: "none (unconfigured)",
    1: "1 bus-synchronous, device-controlled",
    2: "2 buffered, device-controlled",
    3: "3 uncontrolled",
    4: "4 buffered, host-controlled",
    5: "5 bus-synchronous, host-controlled",
}
"""The process-data exchange modes (high nibble of bDriverType), as a person reads them."""

PLC_PARAMETER = struct.Struct("<BH5s8s")


def node_bits(field16: bytes) -> list[int]:
    """Node addresses whose bit is set in a 16-byte node bit field (bit n = node n)."""
    return [n for n in range(128) if field16[n >> 3] & (1 << (n & 7))]


@dataclass(slots=True)
class ComPlcParameter:
    """COM_PLC_PARAMETER plus the connection-status bits (Task2Parameter)."""

    bMode: int = PlcMode.BUFFERED_HOST_CONTROLLED
    usWatchDogTime: int = 0
    abConnStatus: bytes = b"\xff" * 16

    def encode(self) -> bytes:
        head = PLC_PARAMETER.pack(self.bMode, self.usWatchDogTime, bytes(5), bytes(8))
        return head + bytes(32) + self.abConnStatus

    @classmethod
    def decode(cls, raw: bytes) -> ComPlcParameter:
        raw = bytes(raw).ljust(TASK_AREA_SIZE, b"\0")
        mode, watchdog, _, _ = PLC_PARAMETER.unpack_from(raw)
        return cls(bMode=mode, usWatchDogTime=watchdog, abConnStatus=raw[48:64])


COM_DIAGNOSTICS_HEAD = struct.Struct("<BBBBHHHH4s")


@dataclass(slots=True)
class ComDiagnostics:
    """COM_DIAGNOSTICS (Task2State), decoded."""

    bGlobalBits: int = 0
    bCAN_State: int = CanState.OFFLINE
    bErr_rem_adr: int = 0
    bErr_event: int = 0
    usBus_Error_Cnt: int = 0
    usBus_Off_Cnt: int = 0
    usMsg_Time_Out: int = 0
    usRx_Overflow: int = 0
    abNd_cfg: bytes = field(default=bytes(16))
    abNd_state: bytes = field(default=bytes(16))
    abNd_diag: bytes = field(default=bytes(16))

    @classmethod
    def decode(cls, raw: bytes) -> ComDiagnostics:
        raw = bytes(raw).ljust(TASK_AREA_SIZE, b"\0")
        bits, state, adr, event, bus_err, bus_off, timeouts, overflow, _ = (
            COM_DIAGNOSTICS_HEAD.unpack_from(raw)
        )
        return cls(bits, state, adr, event, bus_err, bus_off, timeouts, overflow,
                   raw[16:32], raw[32:48], raw[48:64])

    @property
    def global_bits(self) -> GlobalBits:
        return GlobalBits(self.bGlobalBits & 0x7F)

    @property
    def can_state_name(self) -> str:
        try:
            return CanState(self.bCAN_State).name
        except ValueError:
            return f"0x{self.bCAN_State:02X}"

    @property
    def err_text(self) -> str:
        return err_event_text(self.bErr_rem_adr, self.bErr_event)

    def configured(self) -> list[int]:
        return node_bits(self.abNd_cfg)

    def operating(self) -> list[int]:
        return node_bits(self.abNd_state)

    def diagnostic(self) -> list[int]:
        return node_bits(self.abNd_diag)
