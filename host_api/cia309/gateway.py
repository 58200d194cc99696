"""The CiA 309-1 (v2.0.0) services over the emulated card: a class 3 gateway in Python.

``Gateway`` offers one method per service of 309-1 clauses 4.1 to 4.7 and the long SDO
transfers of clause 5, with the arguments the 309-1 tables name; a failure raises
:class:`Cia309Error` carrying the 309 reason (an SDO abort code or a 309-3 error number,
and the card's ``msg.f`` where the card said no). Networks 1..4 are boards 0..3
(docs/cia309.md). Events (RPDO received, error control, emergency, boot-up, progress of long
SDO transfers) reach subscribers::

    with Gateway(boards=[0], directory=tmp) as gateway:
        gateway.sdo_download(0x1017, 0, 500, node_id=4, data_type=DataType.UNSIGNED16)
        data = gateway.sdo_upload(0x1017, 0, node_id=4)
        with gateway.events() as stream:
            event = stream.wait_for(lambda e: isinstance(e, BootUpEvent), timeout=5)

How it sits on the card (docs/card-commands.md for the commands of our own):

* One ``_Link`` per board owns the host mailbox: a single reader thread takes every
  message with ``DevGetMessage`` and routes answers by (``msg.a``, ``msg.nr``) to the
  waiting call and indications (layer-2 frames, boot-up) to the gateway's own listeners.
  Two readers would steal each other's answers, so the link also holds the board's
  transaction lock for its lifetime: another host's ``Board.transact`` gets
  DRV_CMD_ACTIVE instead of silently losing its answer to us.
* A monitor thread per board polls Task2State every 10 ms: Nd_state and Nd_diag changes,
  CAN_state and the error counters become error control and emergency events
  (COM_Node_Diag is read when a node's Nd_diag bit sets).
* Subscribers are called from one dispatcher thread, never from the reader, so a callback
  may itself call gateway services.
* ``session()`` gives another face on the same links with its own defaults (network,
  node-ID, command time-out, command size): the 309-3 server gives one to each client.
"""

from __future__ import annotations

import itertools
import logging
import queue
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import TracebackType

from dbm_tools.container import DbmFile, DbmTable, read_data_area, write_dbm
from dbm_tools.errors import DbmError
from dbm_tools.parameters import (
    ASYNC_RTR,
    SYNC_RTR,
    ExtendedBusParameterSet,
    NdFlag,
    NodeParameterSet,
)
from dbm_tools.tables import (
    BUS_CAN,
    BUS_CAN_EXT,
    GLOBAL,
    NODES,
    NODES_KEY_LENGTH,
    PLC_PARAM,
    GlobalSet,
    PlcParam,
    checksum_crc,
)
from dbm_tools.validate import check_dbm
from dpm.errors import Drv, err_event_text
from dpm.message import Ext, Message, TelegramHeader, Tfc
from dpm.task2 import CanState, ComDiagnostics
from host_api import driver as d
from host_api.board import Board, CifError
from host_api.cia309.ascii import (
    MAX_NODE_ID,
    MAX_PDO_NUMBER,
    MAX_PDO_OBJECTS,
    TRANSMISSION_EVENT,
    BootUpEvent,
    EmergencyEvent,
    ErrorControlEvent,
    Event,
    GatewayError,
    NmtState,
    PdoMapping,
    RpdoEvent,
    SdoProgressEvent,
    VersionInfo,
)
from host_api.cia309.datatypes import DataType
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload, flash_directory, upload_database

log = logging.getLogger(__name__)

__all__ = [
    "ALL_NODES",
    "MAX_COMMAND_SIZE",
    "MAX_SDO_DATA",
    "CanFrame",
    "Cia309Error",
    "DeviceError",
    "EventStream",
    "FrameListener",
    "Gateway",
    "IndicationQueue",
    "Subscription",
    "decode_value",
    "encode_value",
]

ALL_NODES = 0
"""The node-ID that addresses every node in the NMT services (309-1 "All")."""
MAX_SDO_DATA = 65536
"""Bytes one SDO transfer may carry through the card (docs/card-commands.md)."""
MAX_COMMAND_SIZE = 131072
"""[ours] the largest command size ``set_command_size`` accepts: a 64 KiB DOMAIN in
base64 on one 309-3 line, with room for the rest of the request."""
VENDOR_ID = 0x00434946
"""[ours] vendor-ID reported by ``get_version``: "CIF" in ASCII, not a CiA-assigned number."""
GATEWAY_CLASS = 3
PROTOCOL_VERSION = (2, 0)

DEFAULT_ANSWER_TIMEOUT = 120.0
"""[ours] seconds a call waits for the card when no command time-out is set. The card
answers every request itself (its SDO time-out runs out first); this only bounds the wait
on a card that stopped."""
RTR_ANSWER_TIMEOUT = 1.0
"""[ours] seconds ``read_pdo_data`` waits for the answer to its remote frame."""
MONITOR_PERIOD = 0.01
READ_SLICE_MS = 20
"""How long one DevGetMessage of the reader waits; a pause request waits at most this."""
ABANDONED_NR_S = 60.0
"""A message number whose caller gave up stays reserved this long for its late answer."""
TRANSACTION_LOCK_WAIT_S = 5.0
RESET_TIMEOUT_MS = 10000

CAN_TASK, USER = 3, 16
SDO_PART = 247
"""Data bytes in one COM_SDO_Up_Download message: 255 minus the telegram header."""
DOWNLOAD_UNIT = 240
"""Bytes of a node data set per COM_Download (COM_Start_Seq's Max_Len_Data_Unit)."""
AREA_BUS = 127
NODE_DIAG_SIZE = 48
EMCY_ENTRY = 8
EMCY_HISTORY = 64
"""EMCYs the gateway keeps per node for ``read_device_error``."""

# CAN-task messages (seed 5.2 and docs/card-commands.md)
COM_NODE_DIAG = 66
COM_START_SEQ, COM_DOWNLOAD, COM_END_SEQ = 67, 68, 69
COM_SDO_UP_DOWNLOAD = 74
COM_UPLOAD = 80
COM_CFGRX_LAYER2 = 82
COM_RX_CAN_LAYER2 = 83
COM_TX_CAN_LAYER2 = 84
COM_NMT_MODULE_PROTOCOL = 96
COM_SET_SDO_TIMEOUT = 110
COM_SET_GUARDING = 111
COM_SET_HEARTBEAT_CONSUMER = 112
COM_SET_EMCY_CONSUMER = 113
COM_SET_HEARTBEAT_PRODUCER = 114
COM_SET_NODE_ID = 115
COM_BOOTUP_FORWARDING = 116
COM_BOOTUP_INDICATION = 117

NMT_START, NMT_STOP, NMT_PREOP, NMT_RESET_NODE, NMT_RESET_COMM = 0x01, 0x02, 0x80, 0x81, 0x82
PROGRAM_CONTROL = 0x1F51
"""CiA 302-3 program control of a remote controller: sub 1 takes these commands."""
PROGRAM_STOP, PROGRAM_START, PROGRAM_RESET = 0, 1, 2

# msg.f of the card (seed 5.2, docs/card-commands.md)
F_SDO_ABORT = 3
F_LOCAL_RESOURCE = 20
F_FAULTY_PARAMETER = 55

# Err_Event numbers of a node (seed 4.3) that error control events translate
GUARDING_FAILED, LEFT_OPERATIONAL, GUARD_SEQUENCE, NODE_STOPPED = 30, 31, 32, 39

COB_ID_INVALID = 1 << 31
COB_ID_29_BIT = 1 << 29
COB_ID_MASK = 0x7FF
PDO_BYTES = 8

CIA305_BIT_RATES = {0: 0, 1: 1, 2: 2, 3: 3, 4: 4, 6: 6, 7: 7, 8: 8}
"""CiA 305 bit-rate table index -> the card's Baud_rate code (seed 5.2.5.4.1). Index 5 is
reserved in CiA 305 and 9 (automatic detection) is beyond the card; both are refused with
503, as Lely's gateway refuses the rates its device lacks."""

_F_ERRORS: dict[int, GatewayError] = {
    17: GatewayError.TIME_OUT,  # no response from the node
    48: GatewayError.TIME_OUT,  # download sequence timed out
    19: GatewayError.INTERNAL_STATE,  # the node boots: its SDO channel is the card's
    54: GatewayError.INTERNAL_STATE,  # another transfer to the node still runs
    57: GatewayError.INTERNAL_STATE,  # sequence error of a split transfer
    60: GatewayError.INTERNAL_STATE,  # the node-ID is taken by a configured node
    200: GatewayError.INTERNAL_STATE,  # the network is not configured / not running
    254: GatewayError.INTERNAL_STATE,  # the card's handler failed
    F_LOCAL_RESOURCE: GatewayError.UNSUPPORTED_NODE,  # the node is not configured
    161: GatewayError.UNSUPPORTED_NODE,  # node address out of range
    51: GatewayError.OUT_OF_MEMORY,  # upload larger than the card's buffer
    53: GatewayError.OUT_OF_MEMORY,  # download larger than the card's buffer
    21: GatewayError.SYNTAX_ERROR,  # parameter fault
    F_FAULTY_PARAMETER: GatewayError.SYNTAX_ERROR,
    152: GatewayError.REQUEST_NOT_SUPPORTED,  # unknown command: firmware without it
    153: GatewayError.REQUEST_NOT_SUPPORTED,  # unknown task
}
"""[ours] the card's msg.f -> the 309-3 error number a client sees."""

_ABORT_ERRORS: dict[int, GatewayError] = {
    0x0504_0000: GatewayError.TIME_OUT,
    0x0504_0005: GatewayError.OUT_OF_MEMORY,
    0x0604_0042: GatewayError.PDO_LENGTH_EXCEEDED,
}
"""SDO abort codes that have a 309-3 error number of their own (as Lely's gateway maps them)."""

TYPE_LENGTH_MISMATCH = 0x0607_0010


# --------------------------------------------------------------------------- errors


class Cia309Error(Exception):
    """A 309-1 service failed; ``reason`` is what a 309-3 answer carries.

    Exactly one of ``error`` (a 309-3 error number) and ``abort_code`` (the node's SDO
    abort) is set; ``f`` is the card's msg.f when the card refused the request.
    """

    def __init__(
        self,
        error: GatewayError | None,
        message: str,
        *,
        abort_code: int | None = None,
        f: int | None = None,
    ) -> None:
        self.error = error
        self.abort_code = abort_code
        self.f = f
        super().__init__(message)

    @property
    def reason(self) -> int:
        """The abort code or the 309-3 error number."""
        if self.abort_code is not None:
            return self.abort_code
        assert self.error is not None
        return int(self.error)

    @classmethod
    def abort(cls, code: int, what: str) -> Cia309Error:
        """An SDO abort; the few codes 309-3 has numbers for become those numbers."""
        error = _ABORT_ERRORS.get(code)
        if error is not None:
            return cls(error, f"{what}: SDO abort 0x{code:08X}")
        return cls(None, f"{what}: SDO abort 0x{code:08X}", abort_code=code)

    @classmethod
    def card(cls, f: int, what: str) -> Cia309Error:
        """The card answered msg.f != 0."""
        error = _F_ERRORS.get(f, GatewayError.INTERNAL_STATE)
        return cls(error, f"{what}: the card answered msg.f = {f}", f=f)

    @classmethod
    def driver(cls, code: int, what: str) -> Cia309Error:
        """A driver call failed: its time-outs are 103, anything else 102."""
        timeouts = (Drv.DRV_DEV_PUT_TIMEOUT, Drv.DRV_DEV_GET_TIMEOUT, Drv.DRV_DEV_RESET_TIMEOUT)
        error = GatewayError.TIME_OUT if code in timeouts else GatewayError.INTERNAL_STATE
        return cls(error, f"{what}: {CifError(code)}")


def _syntax(message: str) -> Cia309Error:
    return Cia309Error(GatewayError.SYNTAX_ERROR, message)


# --------------------------------------------------------------------------- values


Value = bytes | bytearray | int | float | str | tuple[int, int]
"""What ``sdo_download`` accepts: CiA 301 bytes, or a Python value of the data type
(``(days, ms)`` for TIME_OF_DAY and TIME_DIFFERENCE)."""

_SIGNED = {
    DataType.INTEGER8, DataType.INTEGER16, DataType.INTEGER24, DataType.INTEGER32,
    DataType.INTEGER40, DataType.INTEGER48, DataType.INTEGER56, DataType.INTEGER64,
}
_TIMES = {DataType.TIME_OF_DAY, DataType.TIME_DIFFERENCE}
_TIME_MS_MASK = 0x0FFF_FFFF


def encode_value(data_type: DataType, value: Value) -> bytes:
    """The CiA 301 bytes of a Python value; bytes pass unchanged (their length is checked).

    Raises Cia309Error 101 for a value that is not of the type, as a 309-3 gateway
    answers a value it cannot parse.
    """
    size = data_type.size
    if isinstance(value, bytes | bytearray):
        if size is not None and len(value) != size:
            raise _syntax(f"{len(value)} bytes are no {data_type.value} value ({size} bytes)")
        return bytes(value)
    try:
        if data_type in _TIMES:
            assert isinstance(value, tuple)
            days, milliseconds = value
            return (milliseconds & _TIME_MS_MASK).to_bytes(4, "little") + days.to_bytes(
                2, "little"
            )
        if data_type is DataType.REAL32:
            assert isinstance(value, int | float)
            return struct.pack("<f", value)
        if data_type is DataType.REAL64:
            assert isinstance(value, int | float)
            return struct.pack("<d", value)
        if data_type is DataType.VISIBLE_STRING:
            assert isinstance(value, str)
            return value.encode("latin-1")
        if data_type is DataType.UNICODE_STRING:
            assert isinstance(value, str)
            return value.encode("utf-16-le")
        assert isinstance(value, int) and size is not None
        return value.to_bytes(size, "little", signed=data_type in _SIGNED)
    except (AssertionError, OverflowError, UnicodeEncodeError, struct.error, ValueError):
        raise _syntax(f"{value!r} is no {data_type.value} value") from None


def decode_value(data_type: DataType, data: bytes) -> int | float | str | bytes | tuple[int, int]:
    """The Python value of uploaded bytes; a length that does not fit the type raises the
    SDO abort 06070010h, as Lely's gateway answers it."""
    size = data_type.size
    if size is not None and len(data) != size:
        raise Cia309Error(None, f"{len(data)} bytes are no {data_type.value} value",
                          abort_code=TYPE_LENGTH_MISMATCH)
    if data_type in _TIMES:
        return int.from_bytes(data[4:], "little"), int.from_bytes(data[:4], "little") & (
            _TIME_MS_MASK
        )
    if data_type is DataType.REAL32:
        return float(struct.unpack("<f", data)[0])
    if data_type is DataType.REAL64:
        return float(struct.unpack("<d", data)[0])
    if data_type is DataType.VISIBLE_STRING:
        return data.decode("latin-1")
    if data_type is DataType.UNICODE_STRING:
        return data.decode("utf-16-le", errors="replace")
    if size is None:
        return bytes(data)
    return int.from_bytes(data, "little", signed=data_type in _SIGNED)


# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class DeviceError:
    """309-1 Table 20, the remote result of ``read_device_error``.

    ``error`` is the node's actual error as the card records it (its Err_Event number,
    0 for none) with the seed's text; ``emergencies`` are the EMCYs received since the
    previous ``read_device_error`` (the gateway keeps the last 64 per node).
    """

    network: int
    node_id: int
    error: int
    error_text: str
    emergencies: tuple[EmergencyEvent, ...]


@dataclass(frozen=True)
class CanFrame:
    """One 11-bit CAN frame, as layer-2 access sends and receives it."""

    cob_id: int
    data: bytes = b""
    remote: bool = False
    dlc: int | None = None
    """For a remote frame, the data length asked for; None: ``len(data)``."""

    def encode(self) -> bytes:
        """The seed's layer-2 form (5.3.1): ID.10..3, then ID.2..0 | RTR | DLC, then data."""
        dlc = len(self.data) if self.dlc is None else self.dlc
        second = ((self.cob_id & 0x7) << 5) | (0x10 if self.remote else 0) | (dlc & 0x0F)
        return bytes([self.cob_id >> 3, second]) + (b"" if self.remote else self.data)


def _layer2_frames(data: bytes) -> list[CanFrame]:
    """The frames of a COM_Rx_CAN_Layer2 indication (seed 5.3.2.2)."""
    frames = []
    at = 0
    while at + 2 <= len(data):
        cob_id = (data[at] << 3) | (data[at + 1] >> 5)
        remote = bool(data[at + 1] & 0x10)
        dlc = data[at + 1] & 0x0F
        size = 0 if remote else min(dlc, PDO_BYTES)
        frames.append(CanFrame(cob_id, bytes(data[at + 2 : at + 2 + size]), remote, dlc))
        at += 2 + size
    return frames


# --------------------------------------------------------------------------- events


class Subscription:
    """A callback registered with ``Gateway.subscribe``; ``cancel`` removes it."""

    def __init__(self, events: _Events, callback: Callable[[Event], None]) -> None:
        self._events = events
        self.callback = callback

    def cancel(self) -> None:
        self._events.remove(self)


class EventStream:
    """Events as a queue (``Gateway.events``): for code that waits for them in turn."""

    def __init__(self, gateway: Gateway) -> None:
        self._queue: queue.SimpleQueue[Event] = queue.SimpleQueue()
        self._subscription = gateway.subscribe(self._queue.put)

    def get(self, timeout: float | None = None) -> Event:
        """The next event; ``queue.Empty`` when none came within ``timeout`` seconds."""
        return self._queue.get(timeout=timeout)

    def wait_for(self, predicate: Callable[[Event], bool], timeout: float) -> Event:
        """The first event (from now on, in order) ``predicate`` accepts; TimeoutError
        when none does within ``timeout`` seconds. Events it skips are dropped."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"no matching event within {timeout} s")
            try:
                event = self._queue.get(timeout=remaining)
            except queue.Empty:
                continue
            if predicate(event):
                return event

    def __iter__(self) -> Iterator[Event]:
        while True:
            yield self._queue.get()

    def close(self) -> None:
        self._subscription.cancel()

    def __enter__(self) -> EventStream:
        return self

    def __exit__(
        self, t: type[BaseException] | None, v: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


_STOP = object()


class _Events:
    """One dispatcher thread calls the subscribers, so none runs on the mailbox reader."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[Event | object] = queue.SimpleQueue()
        self._subscriptions: list[Subscription] = []
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="cia309-events", daemon=True)
        self._thread.start()

    def emit(self, event: Event) -> None:
        self._queue.put(event)

    def add(self, callback: Callable[[Event], None]) -> Subscription:
        subscription = Subscription(self, callback)
        with self._lock:
            self._subscriptions.append(subscription)
        return subscription

    def remove(self, subscription: Subscription) -> None:
        with self._lock:
            if subscription in self._subscriptions:
                self._subscriptions.remove(subscription)

    def close(self) -> None:
        self._queue.put(_STOP)
        self._thread.join(timeout=2)

    def _run(self) -> None:
        while True:
            event = self._queue.get()
            if event is _STOP:
                return
            with self._lock:
                subscriptions = list(self._subscriptions)
            for subscription in subscriptions:
                try:
                    subscription.callback(event)  # type: ignore[arg-type]
                except Exception:
                    log.exception("an event subscriber failed on %r", event)


class FrameListener:
    """Frames of chosen identifiers received by layer-2 access (``Gateway.listen``)."""

    def __init__(self, link: _Link, cob_ids: frozenset[int]) -> None:
        self._link = link
        self.cob_ids = cob_ids
        self._queue: queue.SimpleQueue[CanFrame] = queue.SimpleQueue()

    def put(self, frame: CanFrame) -> None:
        self._queue.put(frame)

    def get(self, timeout: float | None = None) -> CanFrame:
        """The next frame; ``queue.Empty`` when none came within ``timeout`` seconds."""
        return self._queue.get(timeout=timeout)

    def close(self) -> None:
        self._link.remove_listener(self)

    def __enter__(self) -> FrameListener:
        return self

    def __exit__(
        self, t: type[BaseException] | None, v: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


class IndicationQueue:
    """Every COM_Rx_CAN_Layer2 indication (msg.b 83) as the card sent it, for code that
    reads the layer-2 messages itself (the LSS master): call it with a time-out."""

    def __init__(self, link: _Link) -> None:
        self._link = link
        self._queue: queue.SimpleQueue[Message] = queue.SimpleQueue()

    def put(self, msg: Message) -> None:
        self._queue.put(msg)

    def __call__(self, timeout: float) -> Message | None:
        """The next indication within ``timeout`` seconds (0: only one already here)."""
        try:
            if timeout <= 0:
                return self._queue.get_nowait()
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def close(self) -> None:
        self._link.remove_indication_queue(self)


# --------------------------------------------------------------------------- PDOs


@dataclass
class _Pdo:
    """A PDO the gateway created (309-1 4.2.2/4.2.3), served by layer-2 access."""

    number: int
    cob_id: int
    transmission_type: int
    sizes: tuple[int, ...]
    inhibit_s: float = 0.0
    last: bytes | None = None
    sent_at: float = 0.0

    @property
    def length(self) -> int:
        return sum(self.sizes)

    @property
    def rtr(self) -> bool:
        return self.transmission_type in (SYNC_RTR, ASYNC_RTR)

    def unpack(self, data: bytes) -> tuple[int, ...]:
        values = []
        at = 0
        for size in self.sizes:
            values.append(int.from_bytes(data[at : at + size], "little"))
            at += size
        return tuple(values)

    def pack(self, values: Sequence[int]) -> bytes:
        if len(values) != len(self.sizes):
            raise Cia309Error(GatewayError.PDO_LENGTH_EXCEEDED,
                              f"PDO {self.number} maps {len(self.sizes)} objects, "
                              f"not {len(values)}")
        data = b""
        for value, size in zip(values, self.sizes, strict=True):
            if not -(1 << (8 * size - 1)) <= value < (1 << (8 * size)):
                raise _syntax(f"{value} does not fit {size} bytes")
            data += (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")
        return data


def _pdo_sizes(mapped_objects: Sequence[PdoMapping]) -> tuple[int, ...]:
    if not 1 <= len(mapped_objects) <= MAX_PDO_OBJECTS:
        raise _syntax(f"a PDO maps 1..{MAX_PDO_OBJECTS} objects, not {len(mapped_objects)}")
    sizes = []
    for mapping in mapped_objects:
        dtype = mapping.dtype
        if dtype is None and mapping.index is not None:
            dtype = _DUMMY_TYPES.get(mapping.index)
        size = None if dtype is None else dtype.size
        if size is None:
            raise _syntax("a mapped object needs a data type of fixed size, or a dummy index "
                          "(0001h..001Bh): the gateway has no object dictionary to look "
                          "sizes up in")
        sizes.append(size)
    if sum(sizes) > PDO_BYTES:
        raise Cia309Error(GatewayError.PDO_LENGTH_EXCEEDED,
                          f"the mapped objects take {sum(sizes)} bytes, a PDO has 8")
    return tuple(sizes)


_DUMMY_TYPES = {dtype.cia301_index: dtype for dtype in reversed(DataType)
                if dtype.cia301_index is not None and dtype.size is not None}
"""CiA 301 data type index -> its type: Lely's ``set rpdo`` maps dummies by index alone."""


def _pdo_cob_id(cob_id: int) -> int | None:
    """The 11-bit identifier, or None when bit 31 marks the PDO invalid (CiA 301)."""
    if cob_id & COB_ID_INVALID:
        return None
    if cob_id & COB_ID_29_BIT or cob_id & ~(COB_ID_INVALID | 0x4000_0000 | COB_ID_MASK):
        raise Cia309Error(GatewayError.REQUEST_NOT_SUPPORTED,
                          f"COB-ID 0x{cob_id:X}: layer-2 access has 11-bit identifiers only")
    return cob_id & COB_ID_MASK


# --------------------------------------------------------------------------- the link


@dataclass
class _Pending:
    """A request waiting for its answer; a long upload collects several messages."""

    b: int
    multipart: bool
    on_part: Callable[[Message], None] | None
    messages: list[Message] = field(default_factory=list)
    done: threading.Event = field(default_factory=threading.Event)
    abandoned_at: float | None = None

    def deliver(self, msg: Message) -> None:
        self.messages.append(msg)
        sequence = msg.e & Ext.SEQ_MASK
        if self.multipart and not msg.f and sequence in (Ext.FIRST, Ext.CONT):
            if self.on_part is not None:
                self.on_part(msg)
            return
        if self.on_part is not None and self.multipart and sequence == Ext.LAST:
            self.on_part(msg)
        self.done.set()


class _Gate:
    """Requests share a link; a reset or a flash transfer takes it alone.

    The thread holding it alone may still send requests (re-configuring after a reset).
    """

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._active = 0
        self._owner: int | None = None

    @contextmanager
    def shared(self) -> Iterator[None]:
        me = threading.get_ident()
        with self._condition:
            if self._owner != me:
                while self._owner is not None:
                    self._condition.wait()
            self._active += 1
        try:
            yield
        finally:
            with self._condition:
                self._active -= 1
                self._condition.notify_all()

    @contextmanager
    def exclusive(self) -> Iterator[None]:
        me = threading.get_ident()
        with self._condition:
            while self._owner is not None:
                self._condition.wait()
            self._owner = me
            while self._active:
                self._condition.wait()
        try:
            yield
        finally:
            with self._condition:
                self._owner = None
                self._condition.notify_all()


PUT_RETRY_S = 0.0002


def _put(number: int, msg: Message, timeout: float) -> int:
    """DevPutMessage without waiting on the doorbell, retried until ``timeout`` seconds.

    [ours] The reader thread waits on the board's doorbell in DevGetMessage; a second
    thread waiting there too (DevPutMessage with a time-out, on a full mailbox) makes the
    driver's poll object fail ("concurrent poll() invocation"). A full mailbox empties
    within a device loop turn, so a short retry costs nothing.
    """
    deadline = time.monotonic() + timeout
    while True:
        code = d.DevPutMessage(number, msg, 0)
        if code not in (Drv.DRV_DEV_MAILBOX_FULL, Drv.DRV_CMD_ACTIVE):
            return int(code)
        if time.monotonic() > deadline:
            return Drv.DRV_DEV_PUT_TIMEOUT
        time.sleep(PUT_RETRY_S)


class _LinkBoard(Board):
    """The board as the gateway holds it: sending never waits on the doorbell (see
    ``_put``), and reading the mailbox is the reader thread's alone."""

    def put_message(self, msg: Message, timeout: int | None = None) -> None:
        code = _put(self.number, msg, self._timeout(timeout) / 1000.0)
        if code != Drv.DRV_NO_ERROR:
            raise CifError(code, "DevPutMessage")

    def get_message(self, timeout: int | None = None) -> Message:
        raise CifError(Drv.DRV_CMD_ACTIVE, "DevGetMessage: the 309 gateway reads this mailbox")


class _Link:
    """One board: its mailbox reader, its Task2State monitor, the gateway state kept for it."""

    def __init__(self, number: int, directory: str | Path | None, emit: Callable[[Event], None]):
        self.number = number
        self.network = number + 1
        self._emit = emit
        try:
            self.board = _LinkBoard(number, directory).open()
        except CifError as exc:
            raise Cia309Error.driver(exc.code, f"board {number}") from exc
        self._transaction = d._driver.boards[number].transaction_lock
        self._holding = self._transaction.acquire(TRANSACTION_LOCK_WAIT_S)
        if not self._holding:
            self.board.close()
            raise Cia309Error(GatewayError.INTERNAL_STATE,
                              f"board {number}: another host holds its mailbox")
        self._closing = threading.Event()
        self._pending: dict[int, _Pending] = {}
        self._pending_lock = threading.Lock()
        self._numbers = itertools.cycle(range(1, 256))
        self.gate = _Gate()
        self._reader_condition = threading.Condition()
        self._reader_paused = False
        self._reader_busy = False
        self._sdo_channels: dict[int, threading.Lock] = {}
        self._sdo_channels_lock = threading.Lock()
        self._listeners: list[FrameListener] = []
        self._indication_queues: list[IndicationQueue] = []
        self._filters: set[int] = set()
        self.rpdos: dict[int, _Pdo] = {}
        self.tpdos: dict[int, _Pdo] = {}
        self.pdo_lock = threading.Lock()
        self.rtr_waiters: dict[int, queue.SimpleQueue[bytes]] = {}
        self.settings: dict[tuple[int, int], bytes] = {}
        """Card settings the gateway made (COM_Set_*), by (msg.b, node): replayed after
        ``initialize_gateway`` re-configures the card."""
        self.bootup_forwarding = False
        self.supervision: dict[int, str | None] = {}
        """Error control the gateway switched at run time, by node: "heartbeat",
        "guarding" or None; other nodes supervise as their data set says."""
        self._node_sets: dict[int, NodeParameterSet | None] = {}
        self.emcy_history: dict[int, deque[EmergencyEvent]] = {}
        self.expected: dict[int, NmtState] = {}
        """The state the gateway's own NMT command put a node in, until it operates again."""
        self.rebooting: dict[int, float] = {}
        """Nodes the gateway reset, with the time the card took the command: a node the card
        boots again within one monitor turn never shows a gap in Nd_state."""
        self._reported: dict[int, int] = {}
        self._last_state: ComDiagnostics | None = None
        self._can_state: int | None = None
        self._state_lock = threading.Lock()
        self._reader = threading.Thread(target=self._read_loop, daemon=True,
                                        name=f"cia309-reader-{number}")
        self._monitor = threading.Thread(target=self._monitor_loop, daemon=True,
                                         name=f"cia309-monitor-{number}")
        self._reader.start()
        self._monitor.start()

    def close(self) -> None:
        self._closing.set()
        for thread in (self._reader, self._monitor):
            if thread is not threading.current_thread():
                thread.join(timeout=2)
        if self._holding:
            self._transaction.release()
        self.board.close()

    # --- the mailbox -------------------------------------------------------------------------

    def _read_loop(self) -> None:
        while not self._closing.is_set():
            with self._reader_condition:
                while self._reader_paused and not self._closing.is_set():
                    self._reader_condition.wait(0.1)
                self._reader_busy = True
            try:
                code, msg = d.DevGetMessage(self.number, d.MSG_BUFFER_SIZE, READ_SLICE_MS)
            finally:
                with self._reader_condition:
                    self._reader_busy = False
                    self._reader_condition.notify_all()
            if code == Drv.DRV_NO_ERROR and msg is not None:
                try:
                    self._route(msg)
                except Exception:
                    log.exception("board %d: routing %r failed", self.number, msg)
            elif code not in (Drv.DRV_DEV_GET_TIMEOUT, Drv.DRV_DEV_GET_NO_MESSAGE):
                self._closing.wait(0.01)  # the card restarts (-11) or is gone

    @contextmanager
    def reader_paused(self) -> Iterator[None]:
        """The reader stands still: a driver call that waits on the doorbell (DevReset)
        may, as only one thread of a process may wait there at a time."""
        with self._reader_condition:
            self._reader_paused = True
            while self._reader_busy:
                self._reader_condition.wait()
        try:
            yield
        finally:
            with self._reader_condition:
                self._reader_paused = False
                self._reader_condition.notify_all()

    @contextmanager
    def mailbox_released(self) -> Iterator[None]:
        """The reader stands still and the transaction lock is free, so a driver routine
        with its own request/answer loop (DevDownload, the flash directory) can run."""
        with self.reader_paused():
            self._transaction.release()
            self._holding = False
            try:
                yield
            finally:
                self._holding = self._transaction.acquire(TRANSACTION_LOCK_WAIT_S)
                if not self._holding:
                    log.warning("board %d: another host took the mailbox", self.number)

    def _route(self, msg: Message) -> None:
        if msg.a == 0:
            self._indication(msg)
            return
        with self._pending_lock:
            pending = self._pending.get(msg.nr)
            if pending is None or pending.b != msg.a:
                log.debug("board %d: no caller for %r", self.number, msg)
                return
            if pending.abandoned_at is not None:
                del self._pending[msg.nr]
                return
        pending.deliver(msg)

    def request(
        self,
        b: int,
        data: bytes,
        timeout: float,
        *,
        e: int = 0,
        multipart: bool = False,
        on_part: Callable[[Message], None] | None = None,
    ) -> list[Message]:
        """Send one CAN-task command and wait for its answer (several for a long upload)."""
        with self.gate.shared():
            nr, pending = self._register(b, multipart, on_part)
            try:
                msg = Message(rx=CAN_TASK, tx=USER, b=b, data=data, nr=nr, e=e)
                code = _put(self.number, msg, timeout)
                if code != Drv.DRV_NO_ERROR:
                    raise Cia309Error.driver(code, "DevPutMessage")
                if not pending.done.wait(timeout):
                    pending.abandoned_at = time.monotonic()
                    raise Cia309Error(GatewayError.TIME_OUT,
                                      f"board {self.number}: no answer to msg.b {b} "
                                      f"within {timeout:g} s")
            finally:
                if pending.abandoned_at is None:
                    with self._pending_lock:
                        self._pending.pop(nr, None)
            return pending.messages

    @contextmanager
    def sdo_channel(self, node: int, timeout: float) -> Iterator[None]:
        """The node's SDO channel for one transfer: the card runs one transfer per node
        and refuses a second (f 54), so the gateway's sessions take turns; 103 when the
        turn does not come within the time-out."""
        with self._sdo_channels_lock:
            channel = self._sdo_channels.setdefault(node, threading.Lock())
        if not channel.acquire(timeout=timeout):
            raise Cia309Error(GatewayError.TIME_OUT, f"node {node}: its SDO channel stays busy")
        try:
            yield
        finally:
            channel.release()

    def command(self, b: int, data: bytes, timeout: float, what: str) -> Message:
        """A request whose answer must say f 0; f 3 with four data bytes carries the SDO
        abort of a node the card wrote to (COM_Set_Guarding writes 100Ch/100Dh/1017h)."""
        answer = self.request(b, data, timeout)[-1]
        if answer.f == F_SDO_ABORT and len(answer.data) == 4:
            raise Cia309Error.abort(int.from_bytes(answer.data, "little"), what)
        if answer.f:
            raise Cia309Error.card(answer.f, what)
        return answer

    def send(self, b: int, data: bytes) -> None:
        """A command without an answer (COM_Tx_CAN_Layer2)."""
        with self.gate.shared():
            msg = Message(rx=CAN_TASK, tx=USER, b=b, data=data)
            code = _put(self.number, msg, 1.0)
            if code != Drv.DRV_NO_ERROR:
                raise Cia309Error.driver(code, "DevPutMessage")

    def _register(
        self, b: int, multipart: bool, on_part: Callable[[Message], None] | None
    ) -> tuple[int, _Pending]:
        now = time.monotonic()
        with self._pending_lock:
            for nr, old in list(self._pending.items()):
                if old.abandoned_at is not None and now - old.abandoned_at > ABANDONED_NR_S:
                    del self._pending[nr]
            for _ in range(255):
                nr = next(self._numbers)
                if nr not in self._pending:
                    pending = _Pending(b, multipart, on_part)
                    self._pending[nr] = pending
                    return nr, pending
        raise Cia309Error(GatewayError.OUT_OF_MEMORY,
                          f"board {self.number}: 255 requests wait for answers")

    # --- layer 2 -------------------------------------------------------------------------------

    def add_filters(self, cob_ids: Iterable[int], timeout: float) -> None:
        """COM_CfgRx_Layer2 for identifiers not filtered yet (a filter stays until a start)."""
        new = sorted(set(cob_ids) - self._filters)
        if not new:
            return
        data = b"".join(bytes([cob_id & 0xFF, cob_id >> 8]) for cob_id in new)
        answer = self.request(COM_CFGRX_LAYER2, data, timeout)[-1]
        if answer.f == F_FAULTY_PARAMETER:
            raise Cia309Error(GatewayError.PDO_ALREADY_USED,
                              f"identifier(s) {', '.join(f'0x{i:X}' for i in new)} in use by "
                              "the card's CANopen side", f=answer.f)
        if answer.f:
            raise Cia309Error.card(answer.f, "COM_CfgRx_Layer2")
        self._filters.update(new)

    def add_listener(self, listener: FrameListener, timeout: float) -> None:
        self.add_filters(listener.cob_ids, timeout)
        with self.pdo_lock:
            self._listeners.append(listener)

    def remove_listener(self, listener: FrameListener) -> None:
        with self.pdo_lock:
            if listener in self._listeners:
                self._listeners.remove(listener)

    def add_indication_queue(self, indications: IndicationQueue) -> None:
        with self.pdo_lock:
            self._indication_queues.append(indications)

    def remove_indication_queue(self, indications: IndicationQueue) -> None:
        with self.pdo_lock:
            if indications in self._indication_queues:
                self._indication_queues.remove(indications)

    def send_frames(self, frames: Sequence[CanFrame]) -> None:
        data = b"".join(frame.encode() for frame in frames)
        if not frames or len(data) > 255:
            raise _syntax(f"{len(frames)} frames do not fit one COM_Tx_CAN_Layer2")
        self.send(COM_TX_CAN_LAYER2, data)

    def starting(self) -> None:
        """The gateway starts the card: CAN init now, CAN active when the monitor sees the
        bus run again (a start with a stored database is quicker than a monitor turn)."""
        with self._state_lock:
            self._can_state = CanState.OFFLINE
            self._node_sets.clear()
        self._emit(ErrorControlEvent(self.network, self.own_node_id(),
                                     error=GatewayError.CAN_INIT))

    def restore_after_start(self, timeout: float) -> None:
        """A card start dropped the layer-2 filters and boot-up forwarding: set them again."""
        filters, self._filters = self._filters, set()
        self._node_sets.clear()
        self.add_filters(filters, timeout)
        if self.bootup_forwarding:
            self.command(COM_BOOTUP_FORWARDING, b"\x01", timeout, "COM_Bootup_Forwarding")

    def _indication(self, msg: Message) -> None:
        if msg.b == COM_BOOTUP_INDICATION and msg.data:
            if self.bootup_forwarding:
                self._emit(BootUpEvent(self.network, msg.data[0]))
            return
        if msg.b != COM_RX_CAN_LAYER2:
            return
        with self.pdo_lock:
            queues = list(self._indication_queues)
        for indications in queues:
            indications.put(msg)
        for frame in _layer2_frames(msg.data):
            self._frame(frame)

    def _frame(self, frame: CanFrame) -> None:
        with self.pdo_lock:
            listeners = [item for item in self._listeners if frame.cob_id in item.cob_ids]
            rpdos = [pdo for pdo in self.rpdos.values() if pdo.cob_id == frame.cob_id]
            for pdo in rpdos:
                if not frame.remote and len(frame.data) >= pdo.length:
                    pdo.last = frame.data[: pdo.length]
        for listener in listeners:
            listener.put(frame)
        for pdo in rpdos:
            if frame.remote or len(frame.data) < pdo.length:
                continue  # a PDO length error: nothing to unmap
            waiter = self.rtr_waiters.get(pdo.number)
            if waiter is not None:
                waiter.put(frame.data)
            self._emit(RpdoEvent(self.network, pdo.number, pdo.unpack(frame.data)))

    # --- card configuration read back ------------------------------------------------------

    def upload_area(self, area: int, timeout: float) -> bytes | None:
        """A data set as the card holds it (COM_Upload); None when it has none (f 20)."""
        def chunk(offset: int) -> bytes | None:
            request = bytes([0, area]) + struct.pack("<H", offset) + bytes([DOWNLOAD_UNIT])
            answer = self.request(COM_UPLOAD, request, timeout)[-1]
            if answer.f == F_LOCAL_RESOURCE:
                return None
            if answer.f:
                raise Cia309Error.card(answer.f, f"COM_Upload of area {area}")
            return answer.data

        first = chunk(0)
        if first is None or area == AREA_BUS:
            return first
        (total,) = struct.unpack_from("<H", first, 0)
        data = first
        while len(data) < total:
            more = chunk(len(data))
            if not more:
                break
            data += more
        return data[:total]

    def download_area(self, area: int, data: bytes, timeout: float) -> None:
        """COM_Download of a data set, split by COM_Start_Seq when it is long (seed 5.2.3)."""
        if len(data) <= DOWNLOAD_UNIT:
            self.command(COM_DOWNLOAD, bytes([0, area, 0, 0]) + data, timeout, "COM_Download")
            return
        self.command(COM_START_SEQ, bytes([0, area]) + struct.pack("<H", 1000), timeout,
                     "COM_Start_Seq")
        for offset in range(0, len(data), DOWNLOAD_UNIT):
            part = bytes([0, area]) + struct.pack("<H", offset) + data[offset : offset + 240]
            self.command(COM_DOWNLOAD, part, timeout, "COM_Download")
        self.command(COM_END_SEQ, b"\0", timeout, "COM_End_Seq")

    def node_set(self, node: int, timeout: float) -> NodeParameterSet | None:
        """The node's parameter data set in the card (cached until the next start)."""
        if node not in self._node_sets:
            raw = self.upload_area(node, timeout) if node < AREA_BUS else None
            try:
                self._node_sets[node] = NodeParameterSet.decode(raw) if raw else None
            except DbmError:
                self._node_sets[node] = None
        return self._node_sets[node]

    def supervised_by(self, node: int, timeout: float) -> str | None:
        """How the card supervises the node: "heartbeat", "guarding" or None."""
        if node in self.supervision:
            return self.supervision[node]
        params = self.node_set(node, timeout)
        if params is None or not params.usGuardTime:
            return None
        return "heartbeat" if params.bNd_Flag & NdFlag.HRTBT else "guarding"

    # --- Task2State --------------------------------------------------------------------------

    def _monitor_loop(self) -> None:
        while not self._closing.wait(MONITOR_PERIOD):
            try:
                self._monitor_once()
            except Cia309Error as exc:
                log.debug("board %d: monitor: %s", self.number, exc)
            except Exception:
                log.exception("board %d: monitor failed", self.number)

    def own_node_id(self) -> int:
        data = self.settings.get((COM_SET_NODE_ID, 0))
        return data[0] if data else 0

    def _monitor_once(self) -> None:
        read_at = time.monotonic()
        code, raw = d.DevGetTaskState(self.number, 2, 64)
        if code != Drv.DRV_NO_ERROR:
            return
        state = ComDiagnostics.decode(raw)
        # At the first look every pending diagnosis counts as new, so the EMCYs
        # collected before the gateway opened reach the history too.
        previous = self._last_state or replace(state, abNd_diag=bytes(16))
        self._last_state = state
        with self._state_lock:
            if self._can_state is None:
                self._can_state = state.bCAN_State
            elif state.bCAN_State != self._can_state:
                self._can_state = state.bCAN_State
                if state.bCAN_State == CanState.OPERATE:
                    self._emit(ErrorControlEvent(self.network, self.own_node_id(),
                                                 error=GatewayError.CAN_ACTIVE))
                elif state.bCAN_State == CanState.OFFLINE:
                    self._node_sets.clear()
                    self._emit(ErrorControlEvent(self.network, self.own_node_id(),
                                                 error=GatewayError.CAN_INIT))
        own = self.own_node_id()
        for counter, error in (
            ("usBus_Error_Cnt", GatewayError.ERROR_PASSIVE),
            ("usBus_Off_Cnt", GatewayError.BUS_OFF),
            ("usRx_Overflow", GatewayError.CAN_BUFFER_OVERFLOW),
        ):
            if getattr(state, counter) > getattr(previous, counter):
                self._emit(ErrorControlEvent(self.network, own, error=error))
        operating = set(state.operating())
        before = set(previous.operating())
        timeout = DEFAULT_ANSWER_TIMEOUT
        rebooted = {node for node in operating
                    if self.rebooting.get(node, read_at) < read_at}
        for node in sorted((operating - before) | rebooted):
            self.rebooting.pop(node, None)
            self.expected.pop(node, None)
            self._reported.pop(node, None)
            started = self.supervised_by(node, timeout) == "heartbeat"
            self._emit(ErrorControlEvent(self.network, node, NmtState.OPERATIONAL,
                                         GatewayError.HEARTBEAT_STARTED if started else None))
        for node in sorted(before - operating):
            if node in self.expected:
                self._emit(ErrorControlEvent(self.network, node, self.expected[node]))
        for node in state.diagnostic():
            self.read_diagnosis(node, timeout, operating=node in operating)

    def read_diagnosis(self, node: int, timeout: float, *, operating: bool) -> int:
        """COM_Node_Diag: EMCYs into the history and out as events, a failure out as an
        error control event; returns the node's Actual_Error."""
        head = TelegramHeader(node, 0, 0, 0, 0, 5, Tfc.READ).encode()
        answer = self.command(COM_NODE_DIAG, head, timeout, "COM_Node_Diag")
        raw = TelegramHeader.decode(answer.data).payload.ljust(NODE_DIAG_SIZE, b"\0")
        node_state, actual_error, entries = raw[5], raw[6], raw[7]
        history = self.emcy_history.setdefault(node, deque(maxlen=EMCY_HISTORY))
        for index in range(min(entries, (NODE_DIAG_SIZE - 8) // EMCY_ENTRY)):
            entry = raw[8 + EMCY_ENTRY * index : 8 + EMCY_ENTRY * (index + 1)]
            event = EmergencyEvent(self.network, node, int.from_bytes(entry[:2], "little"),
                                   entry[2], bytes(entry[3:8]))
            history.append(event)
            self._emit(event)
        if not operating and actual_error and self._reported.get(node) != actual_error:
            self._reported[node] = actual_error
            try:
                nmt_state: NmtState | None = NmtState(node_state)
            except ValueError:
                nmt_state = None
            error = _error_control(actual_error, self.supervised_by(node, timeout))
            self._emit(ErrorControlEvent(self.network, node, nmt_state, error))
        return actual_error


def _error_control(event: int, supervision: str | None) -> GatewayError:
    """The 309-3 error of a node's Err_Event [ours, after Lely's gateway]: guarding and
    heartbeat time-outs by the supervision in force, a state the node should not be in
    as 204, a node that cannot be reached (no answer, wrong device) as lost connection."""
    if event == GUARDING_FAILED:
        if supervision == "heartbeat":
            return GatewayError.HEARTBEAT_LOST
        return GatewayError.LOST_GUARDING_MESSAGE
    if event == GUARD_SEQUENCE:
        return GatewayError.LOST_GUARDING_MESSAGE
    if event in (LEFT_OPERATIONAL, NODE_STOPPED):
        return GatewayError.WRONG_NMT_STATE
    return GatewayError.LOST_CONNECTION


# --------------------------------------------------------------------------- the gateway


class _Core:
    """What every session of one gateway shares: the links and the event dispatcher."""

    def __init__(self, boards: Sequence[int], directory: str | Path | None) -> None:
        self.directory = directory
        self.events = _Events()
        self.links: dict[int, _Link] = {}
        try:
            for number in boards:
                link = _Link(number, directory, self.events.emit)
                self.links[link.network] = link
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        for link in self.links.values():
            link.close()
        self.links.clear()
        self.events.close()


class Gateway:
    """The 309-1 services on the card's networks (network N = board N - 1).

    ``network`` and ``node_id`` arguments left None take the session's defaults; a node-ID
    given becomes the default for the following requests (309-1 3.2.1.23). With a single
    network, it is the default network from the start (3.2.1.21: "the unique network").
    """

    def __init__(
        self,
        boards: Sequence[int] = (0,),
        directory: str | Path | None = None,
    ) -> None:
        self._core = _Core(boards, directory)
        self._owner = True
        networks = sorted(self._core.links)
        self.default_network: int | None = networks[0] if len(networks) == 1 else None
        self.default_node_id: int | None = None
        self.command_timeout: float | None = None
        """Seconds (``set_command_timeout``); None: wait for the card."""
        self.command_size: int | None = None

    def session(self) -> Gateway:
        """Another session on the same card(s): shared links and events, own defaults."""
        other = object.__new__(Gateway)
        other._core = self._core
        other._owner = False
        other.default_network = self.default_network
        other.default_node_id = None
        other.command_timeout = None
        other.command_size = None
        return other

    def close(self) -> None:
        """End the gateway (its owner only; sessions have nothing of their own to close)."""
        if self._owner:
            self._core.close()

    def __enter__(self) -> Gateway:
        return self

    def __exit__(
        self, t: type[BaseException] | None, v: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    @property
    def networks(self) -> list[int]:
        return sorted(self._core.links)

    # --- addressing (309-1 3.2.1) --------------------------------------------------------

    def resolve_network(self, network: int | None) -> int:
        """The network a request means: ``network``, else the default (104 without one);
        106 for a network the gateway does not serve."""
        return self._link(network).network

    def _link(self, network: int | None) -> _Link:
        if network is None:
            if self.default_network is None:
                raise Cia309Error(GatewayError.NO_DEFAULT_NET, "no default network set")
            network = self.default_network
        link = self._core.links.get(network)
        if link is None:
            raise Cia309Error(GatewayError.UNSUPPORTED_NET,
                              f"network {network} is not served (networks {self.networks})")
        return link

    def _node(self, node_id: int | None, *, all_nodes: bool = False) -> int:
        if node_id is None:
            if self.default_node_id is None:
                raise Cia309Error(GatewayError.NO_DEFAULT_NODE, "no default node-ID set")
            return self.default_node_id
        if node_id == ALL_NODES and all_nodes:
            return ALL_NODES
        if not 1 <= node_id <= MAX_NODE_ID:
            raise Cia309Error(GatewayError.UNSUPPORTED_NODE, f"node-ID {node_id}")
        self.default_node_id = node_id
        return node_id

    def _timeout(self) -> float:
        return DEFAULT_ANSWER_TIMEOUT if self.command_timeout is None else self.command_timeout

    # --- events ------------------------------------------------------------------------------

    def subscribe(self, callback: Callable[[Event], None]) -> Subscription:
        """Call ``callback`` with every event of every network, on the dispatcher thread."""
        return self._core.events.add(callback)

    def events(self) -> EventStream:
        """Events from now on, as a queue; close it (or use ``with``) when done."""
        return EventStream(self)

    # --- layer 2 (also for the LSS services) ----------------------------------------------

    def send_frames(self, frames: Sequence[CanFrame], *, network: int | None = None) -> None:
        """Send 11-bit frames as they are (COM_Tx_CAN_Layer2, seed 5.3.1)."""
        self._link(network).send_frames(frames)

    def listen(self, cob_ids: Iterable[int], *, network: int | None = None) -> FrameListener:
        """Receive the frames of ``cob_ids`` (COM_CfgRx_Layer2); 400 when the card's
        CANopen side uses one of them. Close the listener when done."""
        link = self._link(network)
        listener = FrameListener(link, frozenset(cob_ids))
        link.add_listener(listener, self._timeout())
        return listener

    def layer2_indications(self, *, network: int | None = None) -> IndicationQueue:
        """The raw layer-2 indications from now on (the frames ``listen`` filters for
        arrive in them too); close the queue when done."""
        link = self._link(network)
        indications = IndicationQueue(link)
        link.add_indication_queue(indications)
        return indications

    def transact(self, message: Message, *, network: int | None = None) -> Message:
        """A CAN-task command of the caller's making and its answer, through the gateway's
        mailbox reader (a second reader would steal answers); ``msg.nr`` is assigned."""
        return self._link(network).request(message.b, message.data, self._timeout(),
                                           e=message.e)[-1]

    def board(self, *, network: int | None = None) -> Board:
        """The network's board, for sending (``put_message``); reading its mailbox is the
        gateway's alone."""
        return self._link(network).board

    # --- 4.1 SDO access -------------------------------------------------------------------

    def sdo_upload(
        self,
        index: int,
        subindex: int,
        *,
        network: int | None = None,
        node_id: int | None = None,
        data_type: DataType | None = None,
        offset: int = 0,
        length: int | None = None,
    ) -> bytes:
        """309-1 4.1.2: the object's data (``offset``/``length`` select part of a string
        or domain; the whole object is read, as CiA 301 has no partial access).

        The data type only limits offset and length; ``decode_value`` reads the bytes.
        """
        link = self._link(network)
        node = self._node(node_id)
        _check_partial(data_type, offset, length)
        data = self._upload(link, node, index, subindex)
        if offset or length is not None:
            end = None if length is None else offset + length
            return data[offset:end]
        return data

    def extended_sdo_upload(
        self, index: int, *, network: int | None = None, node_id: int | None = None
    ) -> dict[int, bytes]:
        """309-1 4.1.3: every sub-index of an object; sub-indices the node does not have
        (abort 06090011h) are left out."""
        link = self._link(network)
        node = self._node(node_id)
        count = self._upload(link, node, index, 0)
        result = {0: count}
        for subindex in range(1, (count[0] if count else 0) + 1):
            try:
                result[subindex] = self._upload(link, node, index, subindex)
            except Cia309Error as exc:
                if exc.abort_code != 0x0609_0011:
                    raise
        return result

    def sdo_download(
        self,
        index: int,
        subindex: int,
        data: Value,
        *,
        network: int | None = None,
        node_id: int | None = None,
        data_type: DataType | None = None,
        offset: int = 0,
        length: int | None = None,
    ) -> None:
        """309-1 4.1.4: write ``data`` (bytes, or a value of ``data_type``).

        With ``offset`` the object is read first and the data written into it there.
        """
        link = self._link(network)
        node = self._node(node_id)
        _check_partial(data_type, offset, length)
        if data_type is None:
            if not isinstance(data, bytes | bytearray):
                raise _syntax("a value other than bytes needs its data type")
            raw = bytes(data)
        else:
            raw = encode_value(data_type, data)
        if length is not None and len(raw) != length:
            raise _syntax(f"{len(raw)} bytes of data, length {length}")
        if offset:
            current = self._upload(link, node, index, subindex)
            raw = current[:offset].ljust(offset, b"\0") + raw + current[offset + len(raw) :]
        self._download(link, node, index, subindex, raw)

    def configure_sdo_timeout(self, sdo_timeout: int, *, network: int | None = None) -> None:
        """309-1 4.1.5: the time-out, in ms, of every client SDO of the card."""
        link = self._link(network)
        if not 1 <= sdo_timeout <= 0xFFFF:
            raise _syntax(f"SDO time-out {sdo_timeout} ms is not 1..65535")
        self._setting(link, COM_SET_SDO_TIMEOUT, 0, bytes([0]) + struct.pack("<H", sdo_timeout),
                      "COM_Set_SDO_Timeout")

    def _sdo_header(self, node: int, index: int, subindex: int, count: int, function: int
                    ) -> bytes:
        if not 0 <= index <= 0xFFFF or not 0 <= subindex <= 0xFF:
            raise _syntax(f"multiplexer {index:#x}:{subindex}")
        return TelegramHeader(node, 0, index, subindex, count, 0, function).encode()

    def _upload(self, link: _Link, node: int, index: int, subindex: int) -> bytes:
        head = self._sdo_header(node, index, subindex, 0, Tfc.READ)
        transferred = 0

        def progress(msg: Message) -> None:
            nonlocal transferred
            transferred += max(0, len(msg.data) - TelegramHeader.SIZE)
            self._core.events.emit(SdoProgressEvent(link.network, node, True, transferred))

        with link.sdo_channel(node, self._timeout()):
            answers = link.request(COM_SDO_UP_DOWNLOAD, head, self._timeout(), multipart=True,
                                   e=Ext.FIRST, on_part=progress)  # e 4: the long form
        _check_sdo(answers[-1], f"SDO upload {index:04X}:{subindex} from node {node}")
        return b"".join(answer.data[TelegramHeader.SIZE :] for answer in answers)

    def _download(self, link: _Link, node: int, index: int, subindex: int, data: bytes) -> None:
        what = f"SDO download {index:04X}:{subindex} to node {node}"
        if len(data) > MAX_SDO_DATA:
            raise Cia309Error(GatewayError.OUT_OF_MEMORY,
                              f"{what}: {len(data)} bytes, at most {MAX_SDO_DATA}")
        if len(data) <= SDO_PART:
            head = self._sdo_header(node, index, subindex, len(data), Tfc.WRITE)
            with link.sdo_channel(node, self._timeout()):
                answer = link.request(COM_SDO_UP_DOWNLOAD, head + data, self._timeout())[-1]
            _check_sdo(answer, what)
            return
        parts = [data[at : at + SDO_PART] for at in range(0, len(data), SDO_PART)]
        with link.sdo_channel(node, self._timeout()):
            for number, part in enumerate(parts):
                last = number == len(parts) - 1
                e = Ext.FIRST if number == 0 else Ext.LAST if last else Ext.CONT
                head = self._sdo_header(node, index, subindex, len(part), Tfc.WRITE)
                answer = link.request(COM_SDO_UP_DOWNLOAD, head + part, self._timeout(), e=e)[-1]
                _check_sdo(answer, what)
                transferred = min(len(data), (number + 1) * SDO_PART)
                self._core.events.emit(SdoProgressEvent(link.network, node, False, transferred))

    # --- 4.2 PDO access ---------------------------------------------------------------------

    def configure_rpdo(
        self,
        pdo_number: int,
        cob_id: int,
        tx_type: int,
        mapped_objects: Sequence[PdoMapping],
        *,
        network: int | None = None,
    ) -> None:
        """309-1 4.2.2: a PDO the gateway receives, by layer-2 access to ``cob_id``.

        Bit 31 of the COB-ID deletes the PDO. 400 when the card's CANopen side or another
        gateway PDO uses the identifier, 401 when the objects exceed 8 bytes.
        """
        link = self._link(network)
        _check_pdo_number(pdo_number)
        _check_tx_type(tx_type)
        identifier = _pdo_cob_id(cob_id)
        if identifier is None:
            with link.pdo_lock:
                link.rpdos.pop(pdo_number, None)
            return
        sizes = _pdo_sizes(mapped_objects)
        self._check_unused(link, identifier, link.rpdos, pdo_number)
        link.add_filters([identifier], self._timeout())
        with link.pdo_lock:
            link.rpdos[pdo_number] = _Pdo(pdo_number, identifier, tx_type, sizes)

    def configure_tpdo(
        self,
        pdo_number: int,
        cob_id: int,
        tx_type: int,
        mapped_objects: Sequence[PdoMapping],
        *,
        inhibit_time: int | None = None,
        event_timer: int | None = None,
        sync_start_value: int | None = None,
        network: int | None = None,
    ) -> None:
        """309-1 4.2.3: a PDO the gateway sends on ``write_pdo_data``.

        [ours] Every transmission type sends at the write: the host sees no SYNC, and the
        card keeps remote frames of identifiers it does not filter. The inhibit time (ms,
        as Lely's ``set tpdox`` gives it) spaces writes; the event timer and the SYNC start
        value are checked and have no effect.
        """
        link = self._link(network)
        _check_pdo_number(pdo_number)
        _check_tx_type(tx_type)
        identifier = _pdo_cob_id(cob_id)
        if identifier is None:
            with link.pdo_lock:
                link.tpdos.pop(pdo_number, None)
            return
        sizes = _pdo_sizes(mapped_objects)
        for name, value, high in (("inhibit time", inhibit_time, 0xFFFF),
                                  ("event timer", event_timer, 0xFFFF),
                                  ("SYNC start value", sync_start_value, 240)):
            if value is not None and not 0 <= value <= high:
                raise _syntax(f"{name} {value} is not 0..{high}")
        self._check_unused(link, identifier, link.tpdos, pdo_number)
        pdo = _Pdo(pdo_number, identifier, tx_type, sizes, (inhibit_time or 0) / 1000.0)
        with link.pdo_lock:
            link.tpdos[pdo_number] = pdo

    @staticmethod
    def _check_unused(link: _Link, cob_id: int, same_kind: dict[int, _Pdo], number: int) -> None:
        with link.pdo_lock:
            for pdo in [*link.rpdos.values(), *link.tpdos.values()]:
                if pdo.cob_id == cob_id and same_kind.get(number) is not pdo:
                    raise Cia309Error(GatewayError.PDO_ALREADY_USED,
                                      f"COB-ID 0x{cob_id:X} is PDO {pdo.number}'s")

    def read_pdo_data(self, pdo_number: int, *, network: int | None = None) -> tuple[int, ...]:
        """309-1 4.2.4: the values of an RPDO's mapped objects (raw, one per object): the
        last received (zeros before the first), or for types 252/253 the answer to a
        remote frame sent now (103 when none comes within a second)."""
        link = self._link(network)
        with link.pdo_lock:
            pdo = link.rpdos.get(pdo_number)
        if pdo is None:
            raise Cia309Error(GatewayError.INTERNAL_STATE, f"no RPDO {pdo_number} configured")
        if not pdo.rtr:
            return pdo.unpack(pdo.last or bytes(pdo.length))
        waiter: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        link.rtr_waiters[pdo_number] = waiter
        try:
            link.send_frames([CanFrame(pdo.cob_id, remote=True, dlc=pdo.length)])
            wait = min(RTR_ANSWER_TIMEOUT, self._timeout())
            try:
                return pdo.unpack(waiter.get(timeout=wait))
            except queue.Empty:
                raise Cia309Error(GatewayError.TIME_OUT,
                                  f"no answer to the remote frame of RPDO {pdo_number}") from None
        finally:
            link.rtr_waiters.pop(pdo_number, None)

    def write_pdo_data(
        self, pdo_number: int, values: Sequence[int], *, network: int | None = None
    ) -> None:
        """309-1 4.2.5: send a TPDO with one raw value per mapped object."""
        link = self._link(network)
        with link.pdo_lock:
            pdo = link.tpdos.get(pdo_number)
        if pdo is None:
            raise Cia309Error(GatewayError.INTERNAL_STATE, f"no TPDO {pdo_number} configured")
        data = pdo.pack(values)
        wait = pdo.sent_at + pdo.inhibit_s - time.monotonic()
        if wait > 0:
            time.sleep(wait)  # the inhibit time spaces the frames (CiA 301)
        with link.pdo_lock:
            pdo.last = data
        link.send_frames([CanFrame(pdo.cob_id, data)])
        pdo.sent_at = time.monotonic()

    # --- 4.3 NMT ------------------------------------------------------------------------------

    def _nmt(self, command: int, expected: NmtState | None, node_id: int | None,
             network: int | None) -> None:
        link = self._link(network)
        node = self._node(node_id, all_nodes=True)
        targets = range(1, MAX_NODE_ID + 1) if node == ALL_NODES else [node]
        # The card clears Nd_state before it answers: the state to report must be known
        # before the monitor can see the bit go.
        for target in targets:
            if expected is None:
                link.expected.pop(target, None)
            else:
                link.expected[target] = expected
        link.command(COM_NMT_MODULE_PROTOCOL, bytes([command, node]), self._timeout(),
                     "COM_NMT_Module_Protocol")
        if command in (NMT_RESET_NODE, NMT_RESET_COMM):
            now = time.monotonic()  # later looks at a running node see it booted again
            for target in targets:
                link.rebooting[target] = now

    def start_node(self, node_id: int | None = None, *, network: int | None = None) -> None:
        """309-1 4.3.2: NMT start remote node (``ALL_NODES``: every node)."""
        self._nmt(NMT_START, None, node_id, network)

    def stop_node(self, node_id: int | None = None, *, network: int | None = None) -> None:
        """309-1 4.3.3: NMT stop remote node."""
        self._nmt(NMT_STOP, NmtState.STOPPED, node_id, network)

    def set_node_to_preoperational(
        self, node_id: int | None = None, *, network: int | None = None
    ) -> None:
        """309-1 4.3.4: NMT enter pre-operational."""
        self._nmt(NMT_PREOP, NmtState.PRE_OPERATIONAL, node_id, network)

    def reset_node(self, node_id: int | None = None, *, network: int | None = None) -> None:
        """309-1 4.3.5: NMT reset node; the card boots the node again."""
        self._nmt(NMT_RESET_NODE, None, node_id, network)

    def reset_communication(
        self, node_id: int | None = None, *, network: int | None = None
    ) -> None:
        """309-1 4.3.6: NMT reset communication."""
        self._nmt(NMT_RESET_COMM, None, node_id, network)

    def enable_node_guarding(
        self,
        guard_time: int,
        lifetime_factor: int,
        *,
        network: int | None = None,
        node_id: int | None = None,
    ) -> None:
        """309-1 4.3.7: guard the node (guard time in ms); the card writes 1017h = 0,
        100Ch and 100Dh to it. A guard time or life time factor of 0 disables guarding
        (as Lely's ``enable guarding``). Refused (102) while the card consumes the node's
        heartbeat, as 309-1 demands; 107 for a node the card does not manage."""
        link = self._link(network)
        node = self._node(node_id)
        if not 0 <= guard_time <= 0xFFFF or not 0 <= lifetime_factor <= 0xFF:
            raise _syntax(f"guard time {guard_time} / life time factor {lifetime_factor}")
        if not guard_time or not lifetime_factor:
            self.disable_node_guarding(network=link.network, node_id=node)
            return
        if link.supervised_by(node, self._timeout()) == "heartbeat":
            raise Cia309Error(GatewayError.INTERNAL_STATE,
                              f"node {node}: its heartbeat is consumed; disable it first")
        data = bytes([node, 1]) + struct.pack("<H", guard_time) + bytes([lifetime_factor])
        self._setting(link, COM_SET_GUARDING, node, data, "COM_Set_Guarding")
        link.supervision[node] = "guarding"

    def disable_node_guarding(
        self, *, network: int | None = None, node_id: int | None = None
    ) -> None:
        """309-1 4.3.8: stop guarding the node; nothing to do for a node supervised by
        its heartbeat (the card's command would end that supervision too)."""
        link = self._link(network)
        node = self._node(node_id)
        if link.supervised_by(node, self._timeout()) == "heartbeat":
            return
        self._setting(link, COM_SET_GUARDING, node, bytes([node, 0, 0, 0, 0]),
                      "COM_Set_Guarding")
        link.supervision[node] = None

    def start_heartbeat_consumer(
        self, heartbeat_consumer_time: int, *, network: int | None = None,
        node_id: int | None = None,
    ) -> None:
        """309-1 4.3.9: consume the node's heartbeat with this time (ms; 0 disables it)."""
        link = self._link(network)
        node = self._node(node_id)
        if not 0 <= heartbeat_consumer_time <= 0xFFFF:
            raise _syntax(f"heartbeat consumer time {heartbeat_consumer_time}")
        if not heartbeat_consumer_time:
            self.disable_heartbeat_consumer(network=link.network, node_id=node)
            return
        data = bytes([node, 1]) + struct.pack("<H", heartbeat_consumer_time)
        self._setting(link, COM_SET_HEARTBEAT_CONSUMER, node, data,
                      "COM_Set_Heartbeat_Consumer")
        link.supervision[node] = "heartbeat"

    def disable_heartbeat_consumer(
        self, *, network: int | None = None, node_id: int | None = None
    ) -> None:
        """309-1 4.3.10: stop consuming the node's heartbeat; nothing to do for a guarded
        node."""
        link = self._link(network)
        node = self._node(node_id)
        if link.supervised_by(node, self._timeout()) == "guarding":
            return
        self._setting(link, COM_SET_HEARTBEAT_CONSUMER, node, bytes([node, 0, 0, 0]),
                      "COM_Set_Heartbeat_Consumer")
        link.supervision[node] = None

    def _setting(self, link: _Link, b: int, key: int, data: bytes, what: str) -> None:
        link.command(b, data, self._timeout(), what)
        link.settings.pop((b, key), None)  # the latest setting is replayed last
        link.settings[(b, key)] = data

    # --- 4.4 device failure management -------------------------------------------------

    def read_device_error(
        self, *, network: int | None = None, node_id: int | None = None
    ) -> DeviceError:
        """309-1 4.4.2: the node's actual error and the EMCYs received since the last call."""
        link = self._link(network)
        node = self._node(node_id)
        operating = link._last_state is not None and node in link._last_state.operating()
        error = link.read_diagnosis(node, self._timeout(), operating=operating)
        history = link.emcy_history.pop(node, deque())
        text = err_event_text(node, error) if error else "no error"
        return DeviceError(link.network, node, error, text, tuple(history))

    # --- 4.5 interface configuration -----------------------------------------------------

    def initialize_gateway(
        self, bit_rate_index: int | None = None, *, network: int | None = None
    ) -> None:
        """309-1 4.5.2: a power-on equivalent reset of the CAN interface, with a new bit
        rate (CiA 305 table index; 503 for one the card lacks).

        The card forgets an on-line configuration at a start, so the gateway reads it back
        (every node data set and the bus parameters), warm-starts the card, downloads it
        again with the new Baud_rate and repeats its own settings (SDO time-out, error
        control, EMCY consumers, node-ID, heartbeat producer, layer-2 filters). Extended
        bus parameters come back from flash only.
        """
        link = self._link(network)
        if bit_rate_index is not None and bit_rate_index not in CIA305_BIT_RATES:
            raise Cia309Error(GatewayError.LSS_BIT_RATE_NOT_SUPPORTED,
                              f"bit rate index {bit_rate_index}")
        timeout = self._timeout()
        with link.gate.exclusive():
            bus = link.upload_area(AREA_BUS, timeout)
            if bus is None and bit_rate_index is not None:
                raise Cia309Error(GatewayError.INTERNAL_STATE,
                                  "the network has no bus parameters to set a bit rate in")
            nodes = _node_areas(link, timeout)
            self._start_card(link, timeout)
            for node, data in nodes.items():
                link.download_area(node, data, timeout)
            if bus is not None:
                if bit_rate_index is not None:
                    bus = bytes([CIA305_BIT_RATES[bit_rate_index]]) + bus[1:]
                link.download_area(AREA_BUS, bus, timeout)
            for (b, _), data in list(link.settings.items()):
                link.command(b, data, timeout, f"repeating msg.b {b}")

    def _start_card(self, link: _Link, timeout: float) -> None:
        """A warm start (the host's protocol parameters stay), then the gateway's layer-2
        state again. Call with the link held alone."""
        link.starting()
        try:
            with link.reader_paused():
                link.board.reset(d.WARMSTART, RESET_TIMEOUT_MS)
        except CifError as exc:
            raise Cia309Error.driver(exc.code, "DevReset") from exc
        link.restore_after_start(timeout)

    def store_configuration(
        self, storage_specifier: int | None = None, *, network: int | None = None
    ) -> None:
        """309-1 4.5.3: the live configuration into the card's flash, as a DBM.

        Node data sets and bus parameters are read back (COM_Upload); GLOBAL keeps the
        stored database's start-up flag, the watchdog time and handshake mode are the
        card's current ones; extended bus parameters come from the stored database with
        the node-ID and heartbeat producer the gateway set. 102 when the network has no
        configuration.
        """
        link = self._link(network)
        _check_specifier(storage_specifier)
        timeout = self._timeout()
        with link.gate.exclusive():
            bus = link.upload_area(AREA_BUS, timeout)
            if bus is None:
                raise Cia309Error(GatewayError.INTERNAL_STATE, "the network is not configured")
            nodes = _node_areas(link, timeout)
            with link.mailbox_released():
                code, stored_area = upload_database(link.number)
                stored = _read_area(stored_area) if code == Drv.DRV_NO_ERROR else None
                dbm = self._dbm(link, bus, nodes, stored)
                code = DevDownload(link.number, CONFIGURATION_DOWNLOAD, write_dbm(dbm))
            if code != Drv.DRV_NO_ERROR:
                raise Cia309Error.driver(code, "DevDownload")

    def _dbm(self, link: _Link, bus: bytes, nodes: dict[int, bytes],
             stored: DbmFile | None) -> DbmFile:
        parameters = link.board.protocol_parameters()
        global_set = GlobalSet(usHostWatchdogValue=parameters.usWatchDogTime)
        extended = ExtendedBusParameterSet()
        if stored is not None:
            table = stored.table(GLOBAL)
            if table and table.records:
                global_set.bSystemStart = GlobalSet.decode(table.records[0]).bSystemStart
            table = stored.table(BUS_CAN_EXT)
            if table and table.records:
                extended = ExtendedBusParameterSet.decode(table.records[0])
        node_id = link.settings.get((COM_SET_NODE_ID, 0))
        if node_id:
            extended.bNodeID = node_id[0]
        producer = link.settings.get((COM_SET_HEARTBEAT_PRODUCER, 0))
        if producer:
            (extended.usProducerHeartbeatTime,) = struct.unpack("<H", producer)
        tables = [
            DbmTable(GLOBAL, [global_set.encode()]),
            DbmTable(BUS_CAN, [bus]),
            DbmTable(NODES, [bytes([node]) + data for node, data in sorted(nodes.items())],
                     key_length=NODES_KEY_LENGTH),
            DbmTable(PLC_PARAM, [PlcParam(parameters.bMode, parameters.usWatchDogTime).encode()]),
            DbmTable(BUS_CAN_EXT, [extended.encode()]),
        ]
        dbm = DbmFile(tables)
        global_set.usChecksumCRC = checksum_crc(dbm)
        tables[0].records[0] = global_set.encode()
        errors = [finding for finding in check_dbm(dbm) if finding.severity == "error"]
        if errors:
            raise Cia309Error(GatewayError.INTERNAL_STATE,
                              f"the live configuration makes no valid database: {errors[0]}")
        return dbm

    def restore_configuration(
        self, storage_specifier: int | None = None, *, network: int | None = None
    ) -> None:
        """309-1 4.5.4: the stored configuration back: a warm start loads it from flash.
        102 when the flash holds none."""
        link = self._link(network)
        _check_specifier(storage_specifier)
        timeout = self._timeout()
        with link.gate.exclusive():
            with link.mailbox_released():
                code, entries = flash_directory(link.number)
            if code != Drv.DRV_NO_ERROR:
                raise Cia309Error.driver(code, "flash directory")
            if not entries:
                raise Cia309Error(GatewayError.INTERNAL_STATE, "no configuration is stored")
            link.settings.clear()
            link.supervision.clear()
            self._start_card(link, timeout)

    def set_heartbeat_producer(
        self, heartbeat_producer_time: int, *, network: int | None = None
    ) -> None:
        """309-1 4.5.5: the card's own heartbeat (ms, 0 = off), sent as 0x700 + its node-ID."""
        link = self._link(network)
        if not 0 <= heartbeat_producer_time <= 0xFFFF:
            raise _syntax(f"heartbeat producer time {heartbeat_producer_time}")
        self._setting(link, COM_SET_HEARTBEAT_PRODUCER, 0,
                      struct.pack("<H", heartbeat_producer_time), "COM_Set_Heartbeat_Producer")

    def set_node_id(self, node_id: int, *, network: int | None = None) -> None:
        """309-1 4.5.6: the card's own node-ID; 102 when a configured node has it."""
        link = self._link(network)
        if not 1 <= node_id <= MAX_NODE_ID:
            raise Cia309Error(GatewayError.UNSUPPORTED_NODE, f"node-ID {node_id}")
        self._setting(link, COM_SET_NODE_ID, 0, bytes([node_id]), "COM_Set_Node_ID")

    def start_emergency_consumer(
        self, cob_id: int, *, network: int | None = None, node_id: int | None = None
    ) -> None:
        """309-1 4.5.7: collect the node's EMCYs from ``cob_id`` (0: 0x80 + node-ID)."""
        self._emergency_consumer(True, cob_id, network, node_id)

    def stop_emergency_consumer(
        self, cob_id: int = 0, *, network: int | None = None, node_id: int | None = None
    ) -> None:
        """309-1 4.5.8: ignore the node's EMCYs."""
        self._emergency_consumer(False, cob_id, network, node_id)

    def _emergency_consumer(self, on: bool, cob_id: int, network: int | None,
                            node_id: int | None) -> None:
        link = self._link(network)
        node = self._node(node_id)
        if not 0 <= cob_id <= COB_ID_MASK:
            raise _syntax(f"EMCY COB-ID 0x{cob_id:X} is not an 11-bit identifier")
        data = bytes([node, int(on)]) + struct.pack("<H", cob_id)
        self._setting(link, COM_SET_EMCY_CONSUMER, node, data, "COM_Set_Emcy_Consumer")

    def set_command_timeout(self, time_out: int) -> None:
        """309-1 4.5.9: this session's calls give up after ``time_out`` ms (103); 0: wait
        for the card. The card's work is not undone: a late answer is dropped."""
        if time_out < 0:
            raise _syntax(f"command time-out {time_out}")
        self.command_timeout = time_out / 1000.0 if time_out else None

    def set_bootup_forwarding(self, command: bool, *, network: int | None = None) -> None:
        """309-1 4.5.10: boot-up messages as ``BootUpEvent``s (COM_Bootup_Forwarding)."""
        link = self._link(network)
        link.command(COM_BOOTUP_FORWARDING, bytes([int(command)]), self._timeout(),
                     "COM_Bootup_Forwarding")
        link.bootup_forwarding = command

    # --- 4.6 gateway management ------------------------------------------------------------

    def set_default_network(self, default_network: int) -> None:
        """309-1 4.6.2; 106 for a network the gateway does not serve."""
        self._link(default_network)
        self.default_network = default_network

    def set_default_node_id(self, default_node_id: int, *, network: int | None = None) -> None:
        """309-1 4.6.3; ``network`` is only checked (one default node-ID per session)."""
        if network is not None:
            self._link(network)
        self._node(default_node_id)

    def get_version(self, *, network: int | None = None) -> VersionInfo:
        """309-1 4.6.4 from the card's VERSIONINFO and FIRMWAREINFO: product code =
        ulDeviceNo, revision = firmware version major.minor, serial = ulSerialNo."""
        link = self._link(network)
        try:
            version = link.board.info(d.GET_VERSION_INFO, 32)
            firmware = link.board.info(d.GET_FIRMWARE_INFO, 32)
        except CifError as exc:
            raise Cia309Error.driver(exc.code, "DevGetInfo") from exc
        _, device_number, serial_bcd = struct.unpack_from("<III", version)
        return VersionInfo(VENDOR_ID, device_number, _revision(firmware[16:32]),
                           _from_bcd(serial_bcd), GATEWAY_CLASS, PROTOCOL_VERSION)

    def set_command_size(self, size: int) -> None:
        """309-1 4.6.5: promise to accept commands up to ``size`` bytes; 600 above
        ``MAX_COMMAND_SIZE``."""
        if not 1 <= size <= MAX_COMMAND_SIZE:
            raise Cia309Error(GatewayError.OUT_OF_MEMORY,
                              f"command size {size}: at most {MAX_COMMAND_SIZE}")
        self.command_size = size

    # --- 4.7 controller management ---------------------------------------------------------

    def reset_controller(self, *, network: int | None = None, node_id: int | None = None
                         ) -> None:
        """309-1 4.7.2: without a node-ID the card itself (a warm start: an on-line
        configuration is gone, a stored one comes back); with one the node's program
        (CiA 302-3: 1F51h sub 1 = 2)."""
        link = self._link(network)
        if node_id is not None:
            self._program_control(link, node_id, PROGRAM_RESET)
            return
        with link.gate.exclusive():
            self._start_card(link, self._timeout())

    def start_controller(self, *, network: int | None = None, node_id: int | None = None
                         ) -> None:
        """309-1 4.7.3: the card: HOST_READY (the bus runs); a node: 1F51h sub 1 = 1."""
        self._controller(True, network, node_id)

    def stop_controller(self, *, network: int | None = None, node_id: int | None = None
                        ) -> None:
        """309-1 4.7.4: the card: HOST_NOT_READY (outputs to zero, PDOs stop); a node:
        1F51h sub 1 = 0."""
        self._controller(False, network, node_id)

    def _controller(self, run: bool, network: int | None, node_id: int | None) -> None:
        link = self._link(network)
        if node_id is not None:
            self._program_control(link, node_id, PROGRAM_START if run else PROGRAM_STOP)
            return
        try:
            link.board.set_host_ready(run, 0)  # the bus follows when it is configured
        except CifError as exc:
            raise Cia309Error.driver(exc.code, "DevSetHostState") from exc

    def _program_control(self, link: _Link, node_id: int, command: int) -> None:
        node = self._node(node_id)
        self._download(link, node, PROGRAM_CONTROL, 1, bytes([command]))


# --------------------------------------------------------------------------- helpers


_PARTIAL_TYPES = {DataType.OCTET_STRING, DataType.VISIBLE_STRING, DataType.UNICODE_STRING,
                  DataType.DOMAIN, DataType.HEX}


def _check_partial(data_type: DataType | None, offset: int, length: int | None) -> None:
    """309-1 3.2.1.24: offset (and length) only for strings and domains."""
    if not offset and length is None:
        return
    if data_type is not None and data_type not in _PARTIAL_TYPES:
        raise _syntax(f"offset and length apply to strings and domains, not {data_type.value}")
    if offset < 0 or (length is not None and length < 0) or offset > MAX_SDO_DATA:
        raise _syntax(f"offset {offset} / length {length}")


def _check_sdo(answer: Message, what: str) -> None:
    if answer.f == F_SDO_ABORT and len(answer.data) >= TelegramHeader.SIZE + 4:
        (code,) = struct.unpack_from("<I", answer.data, TelegramHeader.SIZE)
        raise Cia309Error.abort(code, what)
    if answer.f:
        raise Cia309Error.card(answer.f, what)


def _check_pdo_number(number: int) -> None:
    if not 1 <= number <= MAX_PDO_NUMBER:
        raise _syntax(f"PDO number {number} is not 1..{MAX_PDO_NUMBER}")


def _check_tx_type(tx_type: int) -> None:
    if not (0 <= tx_type <= 240 or tx_type in (252, 253, 254, TRANSMISSION_EVENT)):
        raise _syntax(f"transmission type {tx_type}")


def _check_specifier(specifier: int | None) -> None:
    if specifier not in (None, 0):
        raise Cia309Error(GatewayError.REQUEST_NOT_SUPPORTED,
                          f"storage specifier {specifier}: the card has one store")


def _node_areas(link: _Link, timeout: float) -> dict[int, bytes]:
    """Every node data set the card holds (areas 1..126; 127 is the bus parameters')."""
    nodes = {}
    for node in range(1, AREA_BUS):
        data = link.upload_area(node, timeout)
        if data is not None:
            nodes[node] = data
    return nodes


def _read_area(area: bytes) -> DbmFile | None:
    try:
        return read_data_area(area)
    except DbmError:
        return None


def _revision(version: bytes) -> int:
    """"V1.070 cifemu" -> 1.70 as the 309-3 ``<major>.<minor>`` of a revision number."""
    text = version.split(b"\0", 1)[0].decode("latin-1").strip().lstrip("Vv").split()
    major, _, minor = (text[0] if text else "0").partition(".")
    try:
        return (int(major) << 16) | int(minor or "0")
    except ValueError:
        return 0


def _from_bcd(value: int) -> int:
    result = 0
    for shift in range(28, -4, -4):
        result = result * 10 + ((value >> shift) & 0xF)
    return result
