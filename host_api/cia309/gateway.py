"""The CiA 309-1 (v2.0.0) services over the emulated card: a class 3 gateway in Python.

``Gateway`` offers one method per service of 309-1 clauses 4.1 to 4.7 and the long SDO
transfers of clause 5, with the arguments the 309-1 tables name; a failure raises
:class:`~host_api.cia309.model.Cia309Error` carrying the 309 reason (an SDO abort code or
a 309-3 error number, and the card's ``msg.f`` where the card said no). Networks 1..4 are
boards 0..3. Events (RPDO received, error control, emergency, boot-up,
progress of long SDO transfers) reach subscribers::

    with Gateway(boards=[0], directory=tmp) as gateway:
        gateway.sdo_download(0x1017, 0, 500, node_id=4, data_type=DataType.UNSIGNED16)
        data = gateway.sdo_upload(0x1017, 0, node_id=4)
        with gateway.events() as stream:
            event = stream.wait_for(lambda e: isinstance(e, BootUpEvent), timeout=5)

This is the typed layer of Lely's split: it speaks the types of ``model`` and never
imports the 309-3 text layer. How it sits on the card: ``link`` (one mailbox reader per
board, the card's answers as 309 reasons), ``events`` (the dispatcher thread and the
Task2State monitor), ``pdo`` (the gateway's own PDOs); docs/card-commands.md for the
commands of our own. ``session()`` gives another face on the same links with its own
defaults (network, node-ID, command time-out, command size): the 309-3 server gives one to
each client.
"""

from __future__ import annotations

import asyncio
import functools
import queue
import struct
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from types import TracebackType

from dbm_tools.container import DbmFile, DbmTable, read_data_area, write_dbm
from dbm_tools.errors import DbmError
from dbm_tools.parameters import ExtendedBusParameterSet
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
from dpm.cia301 import ABORT_NO_SUBINDEX
from dpm.com import CanFrame, NodeSwitch, SdoTimeoutRequest
from dpm.commands import (
    AREA_BUS,
    AREA_EXTENDED,
    COM_BOOTUP_FORWARDING,
    COM_NMT_MODULE_PROTOCOL,
    COM_SDO_UP_DOWNLOAD,
    COM_SET_EMCY_CONSUMER,
    COM_SET_GUARDING,
    COM_SET_HEARTBEAT_CONSUMER,
    COM_SET_HEARTBEAT_PRODUCER,
    COM_SET_NODE_ID,
    COM_SET_SDO_TIMEOUT,
    F_SDO_ABORT,
    LONG_SDO_LIMIT,
    NMT_PREOP,
    NMT_RESET_COMM,
    NMT_RESET_NODE,
    NMT_START,
    NMT_STOP,
    SDO_MAX_DATA,
)
from dpm.errors import Drv, RcsF, err_event_text
from dpm.message import TELEGRAM_HEADER, Ext, Message, TelegramHeader, Tfc
from host_api import driver as d
from host_api.board import Board, CifError
from host_api.cia309.events import EventDispatcher, EventStream, Monitor, Subscription
from host_api.cia309.link import (
    DEFAULT_ANSWER_TIMEOUT,
    RESET_TIMEOUT_MS,
    FrameListener,
    IndicationQueue,
    InFlight,
    Link,
    card_error,
    driver_error,
)
from host_api.cia309.model import (
    ALL_NODES,
    MAX_COMMAND_SIZE,
    MAX_NODE_ID,
    Cia309Error,
    DataType,
    DeviceError,
    ErrorCode,
    Event,
    NmtState,
    PdoMapping,
    SdoProgressEvent,
    Value,
    VersionInfo,
    encode_value,
    syntax_error,
)
from host_api.cia309.pdo import (
    COB_ID_MASK,
    Pdo,
    check_pdo_number,
    check_tx_type,
    pdo_cob_id,
    pdo_sizes,
)
from host_api.download import (
    CONFIGURATION_DOWNLOAD,
    DevDownload,
    delete_database,
    flash_directory,
    upload_database,
)

__all__ = ["Gateway"]

VENDOR_ID = 0x00434946
"""[ours] vendor-ID reported by ``get_version``: "CIF" in ASCII, not a CiA-assigned number."""
GATEWAY_CLASS = 3
PROTOCOL_VERSION = (2, 0)

RTR_ANSWER_TIMEOUT = 1.0
"""[ours] seconds ``read_pdo_data`` waits for the answer to its remote frame."""

PROGRAM_CONTROL = 0x1F51
"""CiA 302-3 program control of a remote controller: sub 1 takes these commands."""
PROGRAM_STOP, PROGRAM_START, PROGRAM_RESET = 0, 1, 2

CIA305_BIT_RATES = {0: 0, 1: 1, 2: 2, 3: 3, 4: 4, 6: 6, 7: 7, 8: 8}
"""CiA 305 bit-rate table index -> the card's Baud_rate code (seed 5.2.5.4.1). Index 5 is
reserved in CiA 305 and 9 (automatic detection) is beyond the card; both are refused with
503, as Lely's gateway refuses the rates its device lacks."""


class _Core:
    """What every session of one gateway shares: the links, their monitors and the event
    dispatcher."""

    def __init__(self, boards: Sequence[int], directory: str | Path | None) -> None:
        self.directory = directory
        self.events = EventDispatcher()
        self.links: dict[int, Link] = {}
        self.monitors: dict[int, Monitor] = {}
        try:
            for number in boards:
                link = Link(number, directory, self.events.emit)
                self.links[link.network] = link
                self.monitors[link.network] = Monitor(link, self.events.emit)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        for monitor in self.monitors.values():
            monitor.close()
        self.monitors.clear()
        for link in self.links.values():
            link.close()
        self.links.clear()
        self.events.close()


class Gateway:
    """The 309-1 services on the card's networks (network N = board N - 1).

    ``network`` and ``node_id`` arguments left None take the session's defaults; a node-ID
    given becomes the default for the following requests (309-1 3.2.1.23). With a single
    network, it is the default network from the start (3.2.1.21: "the unique network").

    Raises: every service and the constructor raise only
    :class:`~host_api.cia309.model.Cia309Error` for a failure, with the 309-3 error number
    (``error``: 101 for an argument out of range, 103 for a time-out, 104/105 without a
    default, 106/107 for a network or node not served, 102 for what the card's state
    refuses) or the node's SDO abort (``abort_code``), and the card's ``f`` when it said no.
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

    def read_on(self, loop: asyncio.AbstractEventLoop) -> Callable[[], None]:
        """Read the networks' mailboxes on ``loop`` (call from its thread) instead of their
        reader threads (``Link.read_on``: one thread wake-up less per answer for a caller on
        that loop); returns what gives them back to their threads, to be called from the
        loop's thread before it ends. A network another loop reads already stays with it."""
        links = [link for link in self._core.links.values() if link.read_on(loop)]

        def back() -> None:
            for link in links:
                link.read_on_thread()

        return back

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

    def _link(self, network: int | None) -> Link:
        if network is None:
            if self.default_network is None:
                raise Cia309Error(ErrorCode.NO_DEFAULT_NET, "no default network set")
            network = self.default_network
        link = self._core.links.get(network)
        if link is None:
            raise Cia309Error(ErrorCode.UNSUPPORTED_NET,
                              f"network {network} is not served (networks {self.networks})")
        return link

    def _node(self, node_id: int | None, *, all_nodes: bool = False) -> int:
        if node_id is None:
            if self.default_node_id is None:
                raise Cia309Error(ErrorCode.NO_DEFAULT_NODE, "no default node-ID set")
            return self.default_node_id
        if node_id == ALL_NODES and all_nodes:
            return ALL_NODES
        if not 1 <= node_id <= MAX_NODE_ID:
            raise Cia309Error(ErrorCode.UNSUPPORTED_NODE, f"node-ID {node_id}")
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
        return EventStream(self._core.events)

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
                if exc.abort_code != ABORT_NO_SUBINDEX:
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
                raise syntax_error("a value other than bytes needs its data type")
            raw = bytes(data)
        else:
            raw = encode_value(data_type, data)
        if length is not None and len(raw) != length:
            raise syntax_error(f"{len(raw)} bytes of data, length {length}")
        if offset:
            current = self._upload(link, node, index, subindex)
            raw = current[:offset].ljust(offset, b"\0") + raw + current[offset + len(raw) :]
        self._download(link, node, index, subindex, raw)

    def configure_sdo_timeout(self, sdo_timeout: int, *, network: int | None = None) -> None:
        """309-1 4.1.5: the time-out, in ms, of every client SDO of the card."""
        link = self._link(network)
        if not 1 <= sdo_timeout <= 0xFFFF:
            raise syntax_error(f"SDO time-out {sdo_timeout} ms is not 1..65535")
        self._setting(link, COM_SET_SDO_TIMEOUT, 0, SdoTimeoutRequest(0, sdo_timeout).encode(),
                      "COM_Set_SDO_Timeout")

    def _sdo_header(self, node: int, index: int, subindex: int, count: int, function: int
                    ) -> bytes:
        if not 0 <= index <= 0xFFFF or not 0 <= subindex <= 0xFF:
            raise syntax_error(f"multiplexer {index:#x}:{subindex}")
        # TelegramHeader(...).encode() without the object: on every 309-3 read
        return TELEGRAM_HEADER.pack(node, 0, index, subindex, count, 0, function)

    def try_sdo_upload(self, index: int, subindex: int, on_done: Callable[[], None], *,
                       network: int | None = None, node_id: int | None = None
                       ) -> SdoUploadInFlight | None:
        """``sdo_upload`` of a whole object for a caller that cannot block (the 309-3
        server's event loop): sent now, ``on_done`` called from the mailbox reader's thread
        once the answer is there, then ``SdoUploadInFlight.result``. None, with nothing
        sent, when the request would have to wait (``Link.try_request``)."""
        link = self._link(network)
        node = self._node(node_id)
        head = self._sdo_header(node, index, subindex, 0, Tfc.READ)
        progress = functools.partial(self._upload_progress, link, node, [0])
        flight = link.try_request(COM_SDO_UP_DOWNLOAD, head, self._timeout(), on_done,
                                  multipart=True, e=Ext.FIRST, on_part=progress, sdo_node=node)
        return None if flight is None else SdoUploadInFlight(flight, node, index, subindex)

    def try_sdo_download(self, index: int, subindex: int, data: bytes,
                         on_done: Callable[[], None], *, network: int | None = None,
                         node_id: int | None = None) -> SdoDownloadInFlight | None:
        """``sdo_download`` of ``data`` that fits one message (an expedited download: the
        request ``_download`` sends for it) for a caller that cannot block, as
        ``try_sdo_upload``: sent now, ``on_done`` called once the card answered, then
        ``SdoDownloadInFlight.result``. None, with nothing sent, when it would have to wait
        or when ``data`` is longer than one message (a segmented download, several
        requests, is the blocking call's)."""
        if len(data) > SDO_MAX_DATA:
            return None
        link = self._link(network)
        node = self._node(node_id)
        head = self._sdo_header(node, index, subindex, len(data), Tfc.WRITE)
        flight = link.try_request(COM_SDO_UP_DOWNLOAD, head + data, self._timeout(), on_done,
                                  sdo_node=node)
        return None if flight is None else SdoDownloadInFlight(flight, node, index, subindex)

    def _upload_progress(self, link: Link, node: int, transferred: list[int], msg: Message
                         ) -> None:
        """The SdoProgressEvent of a long upload's part ``msg``; ``transferred``: one item,
        the bytes of the upload's parts so far. Bound per upload by ``functools.partial``,
        not a closure: made on every 309-3 read, the closure cost one Python call more per
        read (issue 22)."""
        transferred[0] += max(0, len(msg.data) - TelegramHeader.SIZE)
        self._core.events.emit(SdoProgressEvent(link.network, node, True, transferred[0]))

    def _upload(self, link: Link, node: int, index: int, subindex: int) -> bytes:
        """The object's data, asked for in the long form (msg.e 4: one answer when one
        message holds it, else several), whatever its type: the card's device loop serves
        it in its turn in C, a value that fits one message at the cost of the seed's form
        (msg.e 0; docs/dpm.md section 3)."""
        head = self._sdo_header(node, index, subindex, 0, Tfc.READ)
        progress = functools.partial(self._upload_progress, link, node, [0])
        with link.sdo_channel(node, self._timeout()):
            answers = link.request(COM_SDO_UP_DOWNLOAD, head, self._timeout(), multipart=True,
                                   e=Ext.FIRST, on_part=progress)
        return _upload_data(answers, _upload_what(node, index, subindex))

    def _download(self, link: Link, node: int, index: int, subindex: int, data: bytes) -> None:
        what = _download_what(node, index, subindex)
        if len(data) > LONG_SDO_LIMIT:
            raise Cia309Error(ErrorCode.OUT_OF_MEMORY,
                              f"{what}: {len(data)} bytes, at most {LONG_SDO_LIMIT}")
        if len(data) <= SDO_MAX_DATA:
            head = self._sdo_header(node, index, subindex, len(data), Tfc.WRITE)
            with link.sdo_channel(node, self._timeout()):
                answer = link.request(COM_SDO_UP_DOWNLOAD, head + data, self._timeout())[-1]
            _check_sdo(answer, what)
            return
        parts = [data[at : at + SDO_MAX_DATA] for at in range(0, len(data), SDO_MAX_DATA)]
        with link.sdo_channel(node, self._timeout()):
            for number, part in enumerate(parts):
                last = number == len(parts) - 1
                e = Ext.FIRST if number == 0 else Ext.LAST if last else Ext.CONT
                head = self._sdo_header(node, index, subindex, len(part), Tfc.WRITE)
                answer = link.request(COM_SDO_UP_DOWNLOAD, head + part, self._timeout(), e=e)[-1]
                _check_sdo(answer, what)
                transferred = min(len(data), (number + 1) * SDO_MAX_DATA)
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
        check_pdo_number(pdo_number)
        check_tx_type(tx_type)
        identifier = pdo_cob_id(cob_id)
        if identifier is None:
            with link.pdo_lock:
                link.rpdos.pop(pdo_number, None)
            return
        sizes = pdo_sizes(mapped_objects)
        self._check_unused(link, identifier, link.rpdos, pdo_number)
        link.add_filters([identifier], self._timeout())
        with link.pdo_lock:
            link.rpdos[pdo_number] = Pdo(pdo_number, identifier, tx_type, sizes)

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
        check_pdo_number(pdo_number)
        check_tx_type(tx_type)
        identifier = pdo_cob_id(cob_id)
        if identifier is None:
            with link.pdo_lock:
                link.tpdos.pop(pdo_number, None)
            return
        sizes = pdo_sizes(mapped_objects)
        for name, value, high in (("inhibit time", inhibit_time, 0xFFFF),
                                  ("event timer", event_timer, 0xFFFF),
                                  ("SYNC start value", sync_start_value, 240)):
            if value is not None and not 0 <= value <= high:
                raise syntax_error(f"{name} {value} is not 0..{high}")
        self._check_unused(link, identifier, link.tpdos, pdo_number)
        pdo = Pdo(pdo_number, identifier, tx_type, sizes, (inhibit_time or 0) / 1000.0)
        with link.pdo_lock:
            link.tpdos[pdo_number] = pdo

    @staticmethod
    def _check_unused(link: Link, cob_id: int, same_kind: dict[int, Pdo], number: int) -> None:
        with link.pdo_lock:
            for pdo in [*link.rpdos.values(), *link.tpdos.values()]:
                if pdo.cob_id == cob_id and same_kind.get(number) is not pdo:
                    raise Cia309Error(ErrorCode.PDO_ALREADY_USED,
                                      f"COB-ID 0x{cob_id:X} is PDO {pdo.number}'s")

    def read_pdo_data(self, pdo_number: int, *, network: int | None = None) -> tuple[int, ...]:
        """309-1 4.2.4: the values of an RPDO's mapped objects (raw, one per object): the
        last received (zeros before the first), or for types 252/253 the answer to a
        remote frame sent now (103 when none comes within a second)."""
        link = self._link(network)
        with link.pdo_lock:
            pdo = link.rpdos.get(pdo_number)
        if pdo is None:
            raise Cia309Error(ErrorCode.INTERNAL_STATE, f"no RPDO {pdo_number} configured")
        if not pdo.rtr:
            return pdo.unpack(pdo.last or bytes(pdo.length))
        waiter: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        link.rtr_waiters[pdo_number] = waiter
        try:
            link.send_frames([CanFrame(pdo.cob_id, rtr=True, dlc=pdo.length)])
            wait = min(RTR_ANSWER_TIMEOUT, self._timeout())
            try:
                return pdo.unpack(waiter.get(timeout=wait))
            except queue.Empty:
                raise Cia309Error(ErrorCode.TIME_OUT,
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
            raise Cia309Error(ErrorCode.INTERNAL_STATE, f"no TPDO {pdo_number} configured")
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
        monitor = self._core.monitors[link.network]
        node = self._node(node_id, all_nodes=True)
        targets = range(1, MAX_NODE_ID + 1) if node == ALL_NODES else [node]
        # The card clears Nd_state before it answers: the state to report must be known
        # before the monitor can see the bit go.
        for target in targets:
            if expected is None:
                monitor.expected.pop(target, None)
            else:
                monitor.expected[target] = expected
        link.command(COM_NMT_MODULE_PROTOCOL, bytes([command, node]), self._timeout(),
                     "COM_NMT_Module_Protocol")
        if command in (NMT_RESET_NODE, NMT_RESET_COMM):
            now = time.monotonic()  # later looks at a running node see it booted again
            for target in targets:
                monitor.rebooting[target] = now

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
            raise syntax_error(f"guard time {guard_time} / life time factor {lifetime_factor}")
        if not guard_time or not lifetime_factor:
            self.disable_node_guarding(network=link.network, node_id=node)
            return
        if link.supervised_by(node, self._timeout()) == "heartbeat":
            raise Cia309Error(ErrorCode.INTERNAL_STATE,
                              f"node {node}: its heartbeat is consumed; disable it first")
        data = NodeSwitch(node, True, guard_time, lifetime_factor).encode()
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
        self._setting(link, COM_SET_GUARDING, node, NodeSwitch(node, False, 0, 0).encode(),
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
            raise syntax_error(f"heartbeat consumer time {heartbeat_consumer_time}")
        if not heartbeat_consumer_time:
            self.disable_heartbeat_consumer(network=link.network, node_id=node)
            return
        data = NodeSwitch(node, True, heartbeat_consumer_time).encode()
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
        self._setting(link, COM_SET_HEARTBEAT_CONSUMER, node, NodeSwitch(node, False, 0).encode(),
                      "COM_Set_Heartbeat_Consumer")
        link.supervision[node] = None

    def _setting(self, link: Link, b: int, key: int, data: bytes, what: str) -> None:
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
        monitor = self._core.monitors[link.network]
        error = monitor.read_diagnosis(node, self._timeout(), operating=monitor.operating(node))
        history = monitor.emcy_history.pop(node, deque())
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
        control, EMCY consumers, node-ID, heartbeat producer, layer-2 filters).

        A database stored in flash would run after the start and refuse the on-line download
        (seed 5.2.2, f 201), so [ours] the gateway takes it out of the flash for the start,
        downloads its extended bus parameters on line with the rest, and puts it back
        afterwards, whatever happens: it takes effect again at the card's next start.
        """
        link = self._link(network)
        if bit_rate_index is not None and bit_rate_index not in CIA305_BIT_RATES:
            raise Cia309Error(ErrorCode.LSS_BIT_RATE_NOT_SUPPORTED,
                              f"bit rate index {bit_rate_index}")
        timeout = self._timeout()
        with link.gate.exclusive():
            bus = link.upload_area(AREA_BUS, timeout)
            if bus is None and bit_rate_index is not None:
                raise Cia309Error(ErrorCode.INTERNAL_STATE,
                                  "the network has no bus parameters to set a bit rate in")
            nodes = _node_areas(link, timeout)
            stored = self._take_stored_database(link)
            try:
                self._start_card(link, timeout)
                for node, data in nodes.items():
                    link.download_area(node, data, timeout)
                extended = _record(_read_area(stored), BUS_CAN_EXT) if stored else None
                if extended is not None:
                    link.download_area(AREA_EXTENDED, extended, timeout)
                if bus is not None:
                    if bit_rate_index is not None:
                        bus = bytes([CIA305_BIT_RATES[bit_rate_index]]) + bus[1:]
                    link.download_area(AREA_BUS, bus, timeout)
                for (b, _), data in list(link.settings.items()):
                    link.command(b, data, timeout, f"repeating msg.b {b}")
            finally:
                if stored is not None:
                    with link.mailbox_released():
                        code = DevDownload(link.number, CONFIGURATION_DOWNLOAD, stored)
                    if code != Drv.DRV_NO_ERROR:
                        raise driver_error(code, "DevDownload of the stored database")

    def _take_stored_database(self, link: Link) -> bytes | None:
        """The database stored in the card's flash, deleted there; None when there is none."""
        with link.mailbox_released():
            code, stored = upload_database(link.number)
            if code == Drv.DRV_RCS_ERROR_OFFSET + RcsF.NO_DATABASE:
                return None
            if code != Drv.DRV_NO_ERROR:
                raise driver_error(code, "upload of the stored database")
            code = delete_database(link.number)
        if code != Drv.DRV_NO_ERROR:
            raise driver_error(code, "delete of the stored database")
        return stored

    def _start_card(self, link: Link, timeout: float) -> None:
        """A warm start (the host's protocol parameters stay), then the gateway's layer-2
        state again. Call with the link held alone."""
        self._core.monitors[link.network].starting()
        try:
            with link.reader_paused():
                link.board.reset(d.WARMSTART, RESET_TIMEOUT_MS)
        except CifError as exc:
            raise driver_error(exc.code, "DevReset") from exc
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
                raise Cia309Error(ErrorCode.INTERNAL_STATE, "the network is not configured")
            nodes = _node_areas(link, timeout)
            with link.mailbox_released():
                code, stored_area = upload_database(link.number)
                stored = _read_area(stored_area) if code == Drv.DRV_NO_ERROR else None
                dbm = self._dbm(link, bus, nodes, stored)
                code = DevDownload(link.number, CONFIGURATION_DOWNLOAD, write_dbm(dbm))
            if code != Drv.DRV_NO_ERROR:
                raise driver_error(code, "DevDownload")

    def _dbm(self, link: Link, bus: bytes, nodes: dict[int, bytes],
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
            raise Cia309Error(ErrorCode.INTERNAL_STATE,
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
                raise driver_error(code, "flash directory")
            if not entries:
                raise Cia309Error(ErrorCode.INTERNAL_STATE, "no configuration is stored")
            link.settings.clear()
            link.supervision.clear()
            self._start_card(link, timeout)

    def set_heartbeat_producer(
        self, heartbeat_producer_time: int, *, network: int | None = None
    ) -> None:
        """309-1 4.5.5: the card's own heartbeat (ms, 0 = off), sent as 0x700 + its node-ID."""
        link = self._link(network)
        if not 0 <= heartbeat_producer_time <= 0xFFFF:
            raise syntax_error(f"heartbeat producer time {heartbeat_producer_time}")
        self._setting(link, COM_SET_HEARTBEAT_PRODUCER, 0,
                      struct.pack("<H", heartbeat_producer_time), "COM_Set_Heartbeat_Producer")

    def set_node_id(self, node_id: int, *, network: int | None = None) -> None:
        """309-1 4.5.6: the card's own node-ID; 102 when a configured node has it."""
        link = self._link(network)
        if not 1 <= node_id <= MAX_NODE_ID:
            raise Cia309Error(ErrorCode.UNSUPPORTED_NODE, f"node-ID {node_id}")
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
            raise syntax_error(f"EMCY COB-ID 0x{cob_id:X} is not an 11-bit identifier")
        data = NodeSwitch(node, on, cob_id).encode()
        self._setting(link, COM_SET_EMCY_CONSUMER, node, data, "COM_Set_Emcy_Consumer")

    def set_command_timeout(self, time_out: int) -> None:
        """309-1 4.5.9: this session's calls give up after ``time_out`` ms (103); 0: wait
        for the card. The card's work is not undone: a late answer is dropped."""
        if time_out < 0:
            raise syntax_error(f"command time-out {time_out}")
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
            raise driver_error(exc.code, "DevGetInfo") from exc
        _, device_number, serial_bcd = struct.unpack_from("<III", version)
        return VersionInfo(VENDOR_ID, device_number, _revision(firmware[16:32]),
                           _from_bcd(serial_bcd), GATEWAY_CLASS, PROTOCOL_VERSION)

    def set_command_size(self, size: int) -> None:
        """309-1 4.6.5: promise to accept commands up to ``size`` bytes; 600 above
        ``MAX_COMMAND_SIZE``."""
        if not 1 <= size <= MAX_COMMAND_SIZE:
            raise Cia309Error(ErrorCode.OUT_OF_MEMORY,
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
            raise driver_error(exc.code, "DevSetHostState") from exc

    def _program_control(self, link: Link, node_id: int, command: int) -> None:
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
        raise syntax_error(f"offset and length apply to strings and domains, not {data_type.value}")
    if offset < 0 or (length is not None and length < 0) or offset > LONG_SDO_LIMIT:
        raise syntax_error(f"offset {offset} / length {length}")


def _check_sdo(answer: Message, what: str) -> None:
    if answer.f == F_SDO_ABORT and len(answer.data) >= TelegramHeader.SIZE + 4:
        (code,) = struct.unpack_from("<I", answer.data, TelegramHeader.SIZE)
        raise Cia309Error.abort(code, what)
    if answer.f:
        raise card_error(answer.f, what)


def _upload_what(node: int, index: int, subindex: int) -> str:
    return f"SDO upload {index:04X}:{subindex} from node {node}"


def _upload_data(answers: list[Message], what: str) -> bytes:
    """The data of an SDO upload's answers; raises the node's abort or the card's refusal."""
    _check_sdo(answers[-1], what)
    return b"".join(answer.data[TelegramHeader.SIZE :] for answer in answers)


def _download_what(node: int, index: int, subindex: int) -> str:
    return f"SDO download {index:04X}:{subindex} to node {node}"


class SdoInFlight:
    """An SDO request sent by ``Gateway.try_sdo_upload`` or ``try_sdo_download``, its
    answer not waited for yet; ``result`` once ``on_done`` was called."""

    def __init__(self, flight: InFlight, node: int, index: int, subindex: int) -> None:
        self._flight = flight
        self._object = (node, index, subindex)
        """What an error names; its text is made only for an error."""
        self.timeout = flight.timeout
        """Seconds to wait for the answer: the session's command time-out."""

    def abandon(self) -> Cia309Error:
        """No answer within ``timeout``: the error the blocking call raises then."""
        return self._flight.abandon()


class SdoUploadInFlight(SdoInFlight):
    """An upload sent by ``Gateway.try_sdo_upload``."""

    def result(self) -> bytes:
        """The object's data; raises as ``sdo_upload`` does."""
        messages = self._flight.pending.messages  # not ``messages``: a call less per read
        if len(messages) == 1 and not messages[0].f:  # an upload's usual answer
            return messages[0].data[TelegramHeader.SIZE :]
        return _upload_data(messages, _upload_what(*self._object))


class SdoDownloadInFlight(SdoInFlight):
    """An expedited download sent by ``Gateway.try_sdo_download``."""

    def result(self) -> None:
        """Returns when the node took the value; raises as ``sdo_download`` does (the
        node's abort, the card's refusal)."""
        answer = self._flight.pending.messages[-1]
        if answer.f:
            _check_sdo(answer, _download_what(*self._object))


def _check_specifier(specifier: int | None) -> None:
    if specifier not in (None, 0):
        raise Cia309Error(ErrorCode.REQUEST_NOT_SUPPORTED,
                          f"storage specifier {specifier}: the card has one store")


def _node_areas(link: Link, timeout: float) -> dict[int, bytes]:
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


def _record(dbm: DbmFile | None, name: str) -> bytes | None:
    """The first record of table ``name``, if the database has one."""
    table = dbm.table(name) if dbm is not None else None
    return table.records[0] if table is not None and table.records else None


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
