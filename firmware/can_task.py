"""The CAN task (msg.rx 3): every CAN-task message of the seed manual.

Message handlers live here; the CANopen services they drive live in
``firmware.can`` (the master, one handler per node, the controller). Handlers
that must wait on the bus (SDO) run in a worker and post their answer later,
so the device loop never blocks on the network.
"""

from __future__ import annotations

import logging
import struct
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from dbm_tools.parameters import BusParameterSet, ExtendedBusParameterSet, NodeParameterSet
from dbm_tools.validate import (
    check_bus_parameters,
    check_extended_bus_parameters,
    check_node_parameters,
)
from dpm import message
from dpm.com import (
    DownloadRequest,
    NmtRequest,
    NodeDiagnosis,
    NodeStatus,
    NodeSwitch,
    SdoTimeoutRequest,
    StartSeqRequest,
    UploadRequest,
    configuration_answer,
    decode_layer2_frames,
    decode_rx_filters,
    decode_transparent,
    decode_word,
    encode_sdo_abort,
    encode_start_seq_confirm,
    node_diag_answer,
)
from dpm.commands import (
    AREA_BUS,
    AREA_EXTENDED,
    COM_BOOTUP_FORWARDING,
    COM_CFGRX_LAYER2,
    COM_DOWNLOAD,
    COM_END_SEQ,
    COM_NMT_MODULE_PROTOCOL,
    COM_NODE_DIAG,
    COM_RESET_ERR_EVENT,
    COM_SDO_UP_DOWNLOAD,
    COM_SEND_CANMSG_TRANSPARENT,
    COM_SET_EMCY_CONSUMER,
    COM_SET_GUARDING,
    COM_SET_HEARTBEAT_CONSUMER,
    COM_SET_HEARTBEAT_PRODUCER,
    COM_SET_NODE_ID,
    COM_SET_SDO_TIMEOUT,
    COM_START_SEQ,
    COM_TX_CAN_LAYER2,
    COM_UPLOAD,
    DOWNLOAD_AREA_SIZE,
    GET_CONFIGURATION,
    LONG_SDO_LIMIT,
    MAX_LEN_DATA_UNIT,
    NMT_COMMANDS,
    SDO_MAX_DATA,
)
from dpm.errors import CanF
from dpm.message import Ext, Message, MessageError, TelegramHeader, Tfc
from dpm.task2 import CanState, GlobalBits
from firmware import card_info
from firmware.can.bus import INTERFACE_ERRORS, BusConfig
from firmware.can.master import Master
from firmware.can.node import NodeHandler, State
from firmware.can.sdo import HostSdoTransfer, SdoResult
from firmware.task import Task

if TYPE_CHECKING:
    from firmware.whole_card import WholeCard

log = logging.getLogger(__name__)


@dataclass
class _Sequence:
    """A sequenced node download in the 1000-byte download area (COM_Start_Seq)."""

    area: int
    timeout_ms: int
    buffer: bytearray
    last: float
    length: int = 0

    def expired(self, now: float) -> bool:
        """Seed 5.2.3: more than Timeout ms since the sequence's last message (0: never)."""
        return bool(self.timeout_ms) and (now - self.last) * 1000 > self.timeout_ms


class CanTask(Task):
    number = message.Task.CAN
    name = "CAN"

    def __init__(self, device: WholeCard, config: BusConfig | None = None) -> None:
        """``device`` is the whole card only for the facts the controller publishes beside
        the image (``card_info``); the master and the handlers see a ``Card``."""
        super().__init__(device)
        self.master = Master(device, config or BusConfig(), lambda: card_info.publish(device))
        self.node_data: dict[int, bytes] = {}
        self.bus_data: bytes | None = None
        self.from_flash = False
        """The running configuration came from the database in flash (``StoredDatabase``)."""
        self.run_withdrawn = False
        """[ours] "delete database" took RUN away until the next start or bus parameter set
        (``RcsTask._withdraw_run``)."""
        self.fatal: str | None = None
        """Why the controller could not be opened: the card runs with FAT (``open``)."""
        self.extended_data: bytes | None = None
        self._sequence: _Sequence | None = None
        self.handlers.update({
            COM_START_SEQ: self.com_start_seq,
            COM_DOWNLOAD: self.com_download,
            COM_END_SEQ: self.com_end_seq,
            COM_UPLOAD: self.com_upload,
            COM_NODE_DIAG: self.com_node_diag,
            COM_SDO_UP_DOWNLOAD: self.com_sdo_up_download,
            COM_NMT_MODULE_PROTOCOL: self.com_nmt_module_protocol,
            COM_SEND_CANMSG_TRANSPARENT: self.com_send_canmsg_transparent,
            COM_RESET_ERR_EVENT: self.com_reset_err_event,
            COM_CFGRX_LAYER2: self.com_cfgrx_layer2,
            COM_TX_CAN_LAYER2: self.com_tx_can_layer2,
            GET_CONFIGURATION: self.get_configuration,
            COM_SET_SDO_TIMEOUT: self.com_set_sdo_timeout,
            COM_SET_GUARDING: self.com_set_guarding,
            COM_SET_HEARTBEAT_CONSUMER: self.com_set_heartbeat_consumer,
            COM_SET_EMCY_CONSUMER: self.com_set_emcy_consumer,
            COM_SET_HEARTBEAT_PRODUCER: self.com_set_heartbeat_producer,
            COM_SET_NODE_ID: self.com_set_node_id,
            COM_BOOTUP_FORWARDING: self.com_bootup_forwarding,
        })
        self._long_download: dict[int, tuple[TelegramHeader, bytearray]] = {}

    # --- life cycle ---------------------------------------------------------------------------

    def open(self) -> None:
        """Connect the controller; one that cannot be opened leaves the card up with FAT.

        Seed 4.3: FAT, "because of heavy internal error, no further bus communication is
        possible". A host then sees a faulty card, not a dead one: READY without RUN, FAT in
        Task2State's global bits after every start, and [ours] f 200 ("DEVICE is not
        configured") for every CAN-task command.
        """
        try:
            self.master.open()
        except INTERFACE_ERRORS as exc:
            if self.master.config.exit_on_error:
                raise
            cfg = self.master.config
            self.fatal = (f"cannot open CAN interface {cfg.interface!r} channel "
                          f"{cfg.channel!r}: {exc}")
            log.error("%s; the card stays up with FAT set (no bus communication)", self.fatal)

    def close(self) -> None:
        self.master.close()

    def handle(self, msg: Message) -> Message | None:
        if self.fatal is not None:
            return msg.answer(f=CanF.NOT_CONFIGURED)  # FAT: no bus to configure or use
        return super().handle(msg)

    def reset(self, cold: bool) -> None:
        del cold
        if self.fatal is not None:
            self.device.set_global_bit(GlobalBits.FAT, True)  # after every start's clear
        self.master.reset()
        self.node_data.clear()
        self.bus_data = None
        self.extended_data = None
        self.from_flash = False
        self.run_withdrawn = False
        self._sequence = None
        self._long_download.clear()

    @property
    def configured(self) -> bool:
        return self.master.nmt.running

    def can_state(self) -> CanState:
        return self.master.can_state()

    def next_indication(self) -> Message | None:
        return self.master.layer2.next_indication()

    # --- the configuration entry points (also used at start-up from flash) ---------------------

    def download_node(self, address: int, data: bytes) -> int:
        """Check and take one node parameter data set; 0 or the seed's msg.f."""
        errors = [f for f in check_node_parameters(data, address) if f.severity == "error"]
        if errors:
            return errors[0].number
        if address in self.node_data or (address == self.master.ext.bNodeID and address):
            return CanF.DOUBLE_ADDRESS  # a second data set never replaces the first unseen
        params = NodeParameterSet.decode(data)
        self.node_data[address] = bytes(data)
        self.master.configure_node(address, params)
        return 0

    def download_extended(self, data: bytes) -> int:
        errors = [f for f in check_extended_bus_parameters(data) if f.severity == "error"]
        if errors:
            return errors[0].number
        ext = ExtendedBusParameterSet.decode(data)
        if ext.bNodeID and ext.bNodeID in self.node_data:
            return CanF.DOUBLE_ADDRESS
        self.extended_data = bytes(data)
        self.master.ext = ext
        return 0

    def download_bus(self, data: bytes) -> int:
        """The bus parameter data set; a good one starts the network."""
        errors = [f for f in check_bus_parameters(data) if f.severity == "error"]
        if errors:
            return errors[0].number
        self.bus_data = bytes(data)
        self.run_withdrawn = False
        self.master.start_network(BusParameterSet.decode(data))
        return 0

    # --- COM_Start_Seq / COM_Download / COM_End_Seq / COM_Upload -----------------------------

    def com_start_seq(self, msg: Message) -> Message:
        """Seed 5.2.3. Every answer, an error too, has the table's msg.ln 1 with
        Max_Len_Data_Unit 240: the table gives ln and d[0] as fixed values and only f as
        variable, so a host that reads d[0] whatever f says finds 240 there."""
        confirm = encode_start_seq_confirm(MAX_LEN_DATA_UNIT)
        if self.from_flash:
            return msg.answer(f=CanF.FLASH_DATABASE_RUNS, data=confirm)
        try:
            request = StartSeqRequest.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER, data=confirm)
        area = request.area
        if not 1 <= area <= 126:
            return msg.answer(f=CanF.AREA_CODE, data=confirm)
        self._sequence = _Sequence(area, request.timeout_ms, bytearray(DOWNLOAD_AREA_SIZE),
                                   time.monotonic())
        return msg.answer(data=confirm)

    def com_download(self, msg: Message) -> Message:
        if self.from_flash:
            return msg.answer(f=CanF.FLASH_DATABASE_RUNS)
        try:
            request = DownloadRequest.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        area, offset, data = request.area, request.offset, request.data
        if area == AREA_BUS:
            return msg.answer(f=self.download_bus(data))
        if area == AREA_EXTENDED:
            return msg.answer(f=self.download_extended(data))
        if not 1 <= area <= 126:
            return msg.answer(f=CanF.AREA_CODE)
        seq = self._sequence
        now = time.monotonic()
        if seq is not None and seq.expired(now):
            # Seed 5.2.3: the time-out ends the sequence; what comes after it for another
            # node is a download of its own, not a sequence error. Its own node hears 48.
            self._sequence = None
            if area == seq.area:
                return msg.answer(f=CanF.TIMEOUT)
            seq = None
        if seq is None:
            if offset:
                return msg.answer(f=CanF.SEQUENCE)  # an offset needs COM_Start_Seq first
            if len(data) > DOWNLOAD_AREA_SIZE:
                return msg.answer(f=CanF.BUFFER_LENGTH)
            return msg.answer(f=self.download_node(area, data))
        if area != seq.area:
            return msg.answer(f=CanF.SEQUENCE)
        if offset + len(data) > DOWNLOAD_AREA_SIZE:
            return msg.answer(f=CanF.BUFFER_LENGTH)
        seq.buffer[offset : offset + len(data)] = data
        seq.length = max(seq.length, offset + len(data))
        seq.last = now
        return msg.answer()

    def com_end_seq(self, msg: Message) -> Message:
        if self.from_flash:
            return msg.answer(f=CanF.FLASH_DATABASE_RUNS)
        seq, self._sequence = self._sequence, None
        if seq is None:
            return msg.answer(f=CanF.SEQUENCE)
        if seq.expired(time.monotonic()):
            return msg.answer(f=CanF.TIMEOUT)  # it expires with no message at all, too
        if seq.length < 2:
            return msg.answer(f=CanF.INCOMPLETE)
        (total,) = struct.unpack_from("<H", seq.buffer, 0)
        if total > seq.length or total < 2:
            return msg.answer(f=CanF.INCOMPLETE)
        return msg.answer(f=self.download_node(seq.area, bytes(seq.buffer[:total])))

    def com_upload(self, msg: Message) -> Message:
        try:
            request = UploadRequest.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.PARAMETER_FAULT)
        area, offset, length = request.area, request.offset, request.length
        if area == AREA_BUS:
            stored = self.bus_data
        elif 1 <= area <= 126:
            stored = self.node_data.get(area)
        else:
            return msg.answer(f=CanF.AREA_CODE)
        if stored is None:
            return msg.answer(f=CanF.LOCAL_RESOURCE)
        if not 1 <= length <= MAX_LEN_DATA_UNIT:
            return msg.answer(f=CanF.PARAMETER_FAULT)
        if offset > len(stored):
            return msg.answer(f=CanF.BUFFER_LENGTH)
        return msg.answer(data=stored[offset : offset + length])

    # --- diagnosis ------------------------------------------------------------------------------

    def com_node_diag(self, msg: Message) -> Message:
        try:
            head = TelegramHeader.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        address = head.device_adr
        if not 1 <= address <= 127:
            return msg.answer(f=CanF.NODE_DIAG_ADDRESS)
        handler = self.master.nodes.get(address)
        raw = (handler.read_diagnosis() if handler
               else NodeDiagnosis(status=NodeStatus.DEACTIVATED).encode())
        self.device.set_node_bit("abNd_diag", address, False)
        return msg.answer(data=node_diag_answer(head, raw))

    def com_reset_err_event(self, msg: Message) -> Message:
        """Clear TOUT, EVE and the four counters (seed 5.2.12); never an error."""
        self.device.reset_counters()
        self.device.set_global_bit(GlobalBits.TOUT | GlobalBits.EVE, False)
        return msg.answer()

    def get_configuration(self, msg: Message) -> Message:
        """The node's DESCRIPT record without its first byte (docs/dbm.md section 2)."""
        try:
            head = TelegramHeader.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        descript = self.device.descript_records()
        if descript is None:
            return msg.answer(f=CanF.NO_DESCRIPT_TABLE)
        record = descript.get(head.device_adr)
        if record is None:
            return msg.answer(f=CanF.NO_DESCRIPT_RECORD)
        return msg.answer(data=configuration_answer(head, record))

    # --- SDO -----------------------------------------------------------------------------------

    def com_sdo_up_download(self, msg: Message) -> Message | None:
        try:
            head = TelegramHeader.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        address = head.device_adr
        if not 1 <= address <= 127:
            return msg.answer(f=CanF.FAULTY_PARAMETER, data=msg.data[:8])
        if head.function not in (Tfc.READ, Tfc.WRITE):
            return msg.answer(f=CanF.SDO_FUNCTION, data=msg.data[:8])
        if not self.master.nmt.running or self.master.bus is None:
            return msg.answer(f=CanF.NOT_CONFIGURED, data=msg.data[:8])
        if head.function == Tfc.WRITE and len(head.payload) != head.data_cnt:
            return msg.answer(f=CanF.SDO_BUFFER, data=msg.data[:8])
        # [ours] Only e 4, 8 and 0x0C mark a long transfer (docs/card-commands.md), and an
        # upload gets several answers only when asked with e 4: a request as the seed writes
        # it (e 0) gets the seed's single answer, and other bits in e change nothing.
        long_upload = head.function == Tfc.READ and msg.e == Ext.FIRST
        if msg.e in (Ext.FIRST, Ext.CONT, Ext.LAST) and not long_upload:
            if head.function != Tfc.WRITE:
                return msg.answer(f=CanF.SEQUENCE, data=msg.data[:8])
            gathered = self._gather(msg, head)
            if isinstance(gathered, Message):
                return gathered
            head = gathered
        handler = self.master.nodes.get(address)
        if handler is not None and handler.state is State.BOOTING:
            return msg.answer(f=CanF.NODE_BUSY, data=msg.data[:8])
        client = self.master.sdo.channel(address)
        if not client.lock.acquire(blocking=False):
            return msg.answer(f=CanF.SDO_FUNCTION, data=msg.data[:8])
        if handler is not None:
            handler.host_sdo = True  # seed 5.2.8: the node's RX-PDOs wait meanwhile

        def done(result: SdoResult) -> None:
            if handler is not None:
                handler.host_sdo = False
            client.lock.release()
            self._answer_sdo(msg, head, result, long_upload)

        self.master.sdo.start_host(HostSdoTransfer(
            self.master.bus, address, head.data_adr, head.data_idx,
            None if head.function == Tfc.READ else head.payload,
            client.sdo.RESPONSE_TIMEOUT, done))
        return None

    def _gather(self, msg: Message, head: TelegramHeader) -> Message | TelegramHeader:
        """One part of a long SDO download: an answer now, or the whole request at the end."""
        sequence = msg.e & Ext.SEQ_MASK
        address = head.device_adr
        key = (head.device_adr, head.data_adr, head.data_idx)
        if sequence == Ext.FIRST:
            self._long_download[address] = (head, bytearray(head.payload))
        else:
            first = self._long_download.get(address)
            if first is None or (first[0].device_adr, first[0].data_adr, first[0].data_idx) != key:
                self._long_download.pop(address, None)
                return msg.answer(f=CanF.SEQUENCE, data=msg.data[:8])
            first[1].extend(head.payload)
        data = self._long_download[address][1]
        if len(data) > LONG_SDO_LIMIT:
            self._long_download.pop(address, None)
            return msg.answer(f=CanF.BUFFER_LENGTH, data=msg.data[:8])
        if sequence != Ext.LAST:
            head.data_cnt = 0
            head.payload = b""
            return msg.answer(data=head.encode())
        del self._long_download[address]
        return TelegramHeader(head.device_adr, 0, head.data_adr, head.data_idx, 0, 0,
                              Tfc.WRITE, bytes(data))

    def _answer_sdo(self, msg: Message, head: TelegramHeader, result: SdoResult,
                    long_upload: bool) -> None:
        """The answer to a finished host transfer (several messages for a long upload)."""
        answer_head = TelegramHeader(head.device_adr, 0, head.data_adr, head.data_idx, 0, 0,
                                     head.function)
        if result.timed_out:
            answer = msg.answer(f=CanF.NO_RESPONSE, data=answer_head.encode())
        elif result.abort is not None:
            answer = msg.answer(f=CanF.SDO_ABORT, data=encode_sdo_abort(answer_head, result.abort))
        elif head.function == Tfc.READ and len(result.data) > LONG_SDO_LIMIT:
            answer = msg.answer(f=CanF.SDO_BUFFER, data=answer_head.encode())
        elif head.function == Tfc.READ and len(result.data) > SDO_MAX_DATA:
            if not long_upload:  # seed 5.2.8: one answer of at most 247 bytes, else f 51
                answer = msg.answer(f=CanF.SDO_BUFFER, data=answer_head.encode())
            else:
                self._post_long_upload(msg, answer_head, result.data)
                return
        else:
            if head.function == Tfc.READ:
                answer_head.data_cnt = len(result.data)
                answer_head.payload = result.data
            answer = msg.answer(data=answer_head.encode())
        self.device.post(answer)

    def _post_long_upload(self, msg: Message, head: TelegramHeader, data: bytes) -> None:
        """More than one message of upload data: first, continue ..., last (msg.e)."""
        parts = [data[i : i + SDO_MAX_DATA] for i in range(0, len(data), SDO_MAX_DATA)]
        for n, part in enumerate(parts):
            e = Ext.FIRST if n == 0 else Ext.LAST if n == len(parts) - 1 else Ext.CONT
            head.data_cnt = len(part)
            head.payload = part
            self.device.post(msg.answer(data=head.encode(), e=e))

    # --- our own commands for the CiA 309 gateway (docs/card-commands.md) ------------------------

    def _node_switch(self, msg: Message, ln: int) -> Message | tuple[NodeHandler, int, int]:
        """Parse d[0] node, d[1] 0 off / 1 on, d[2..3] u16: the node, on, value; or an error."""
        try:
            request = NodeSwitch.decode(msg.data, guarding=ln == 5)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if not 1 <= request.node <= 127:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if not self.master.nmt.running:
            return msg.answer(f=CanF.NOT_CONFIGURED)
        handler = self.master.nodes.get(request.node)
        if handler is None:
            return msg.answer(f=CanF.LOCAL_RESOURCE)
        return handler, int(request.on), request.value

    def com_set_sdo_timeout(self, msg: Message) -> Message:
        try:
            request = SdoTimeoutRequest.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if request.node > 127 or request.timeout_ms == 0:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if request.node and self.master.bus is None:
            return msg.answer(f=CanF.NOT_CONFIGURED)
        self.master.sdo.set_timeout(request.node, request.timeout_ms / 1000.0)
        return msg.answer()

    def com_set_guarding(self, msg: Message) -> Message | None:
        parsed = self._node_switch(msg, 5)
        if isinstance(parsed, Message):
            return parsed
        handler, on, guard_time = parsed
        factor = msg.data[4]
        if on and not guard_time:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        guard_time = guard_time if on else 0
        writes = [(0x100C, struct.pack("<H", guard_time)), (0x100D, bytes([factor]))]
        if on:
            writes.insert(0, (0x1017, b"\0\0"))  # CiA 301: guarding only without heartbeat
        self.master.executor.submit(self._configure_error_control, msg, handler, writes,
                                    False, guard_time, factor)
        return None

    def com_set_heartbeat_consumer(self, msg: Message) -> Message:
        parsed = self._node_switch(msg, 4)
        if isinstance(parsed, Message):
            return parsed
        handler, on, consumer_time = parsed
        if on and not consumer_time:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        handler.set_supervision(True, consumer_time if on else 0, 0)
        return msg.answer()

    def _configure_error_control(self, msg: Message, handler: NodeHandler,
                                 writes: list[tuple[int, bytes]], heartbeat: bool,
                                 time_ms: int, factor: int) -> None:
        channel = self.master.sdo.channel(handler.address)
        answer = msg.answer()
        with channel.lock:
            try:
                for index, value in writes:
                    channel.sdo.download(index, 0, value)
            except SdoAbortedError as exc:
                answer = msg.answer(f=CanF.SDO_ABORT, data=struct.pack("<I", exc.code))
            except SdoCommunicationError:
                answer = msg.answer(f=CanF.NO_RESPONSE)
        if answer.f == 0:
            handler.set_supervision(heartbeat, time_ms, factor)
        self.device.post(answer)

    def com_set_emcy_consumer(self, msg: Message) -> Message:
        parsed = self._node_switch(msg, 4)
        if isinstance(parsed, Message):
            return parsed
        handler, on, cob_id = parsed
        if cob_id > 0x7FF:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        handler.set_emcy_consumer((cob_id or 0x80 + handler.address) if on else None)
        return msg.answer()

    def com_set_heartbeat_producer(self, msg: Message) -> Message:
        try:
            self.master.ext.usProducerHeartbeatTime = decode_word(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        self.master.wake()  # the master's heartbeat starts, stops or changes its period
        return msg.answer()

    def com_set_node_id(self, msg: Message) -> Message:
        if msg.ln != 1 or not 1 <= msg.data[0] <= 127:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if msg.data[0] in self.master.nodes:
            return msg.answer(f=CanF.DOUBLE_ADDRESS)
        self.master.ext.bNodeID = msg.data[0]
        self.master.wake()  # the master's heartbeat may start now
        return msg.answer()

    def com_bootup_forwarding(self, msg: Message) -> Message:
        if msg.ln != 1 or msg.data[0] not in (0, 1):
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        self.master.layer2.bootup_forwarding = bool(msg.data[0])
        return msg.answer()

    # --- NMT, transparent CAN, layer 2 ---------------------------------------------------------

    def com_nmt_module_protocol(self, msg: Message) -> Message:
        try:
            request = NmtRequest.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if request.command not in NMT_COMMANDS or request.node > 127:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if not self.master.nmt.running:
            return msg.answer(f=CanF.NOT_CONFIGURED)
        self.master.nmt.host_nmt(request.command, request.node)
        return msg.answer()

    def com_send_canmsg_transparent(self, msg: Message) -> Message:
        try:
            frame = decode_transparent(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        dlc = frame.length_code  # a remote frame carries the data bytes as given, as before
        if not self.master.bus_send_raw(frame.ident, frame.data[: min(dlc, 8)], frame.rtr,
                                        frame.extended, dlc):
            return msg.answer(f=CanF.TIMEOUT)
        return msg.answer()

    def com_cfgrx_layer2(self, msg: Message) -> Message:
        try:
            idents = decode_rx_filters(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        if any(self.master.cob_id_in_use(i) for i in idents):
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        self.master.layer2.filters.update(idents)
        return msg.answer()

    def com_tx_can_layer2(self, msg: Message) -> Message | None:
        """Up to 127 frames, each 2 identifier bytes plus DLC data bytes; no answer."""
        try:
            frames = decode_layer2_frames(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        for frame in frames:
            self.master.bus_send_raw(frame.ident, frame.payload, frame.rtr, False,
                                     frame.length_code)
        return None
