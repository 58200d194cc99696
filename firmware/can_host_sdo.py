"""COM_SDO_Up_Download: the host's SDO transfers through the card, long ones too.

Why a module of its own: it is the one CAN-task message whose answer comes later, from the
SDO channel's worker, and the one that gathers a request over several messages (seed 5.2.8;
the long transfers with msg.e in docs/card-commands.md). It owns the parts of a long
download while they come in; the transfer on the bus is ``firmware.can.sdo``'s.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING

from dpm._quicklock import Lock
from dpm.cia301 import NODE_ID_MAX
from dpm.com import encode_sdo_abort
from dpm.commands import COM_SDO_UP_DOWNLOAD, LONG_SDO_LIMIT, SDO_MAX_DATA
from dpm.errors import F_INTERNAL_ERROR, CanF
from dpm.message import TELEGRAM_HEADER, Ext, Message, MessageError, TelegramHeader, Tfc
from firmware.can.node import State
from firmware.can.sdo import HostSdoTransfer, SdoResult
from firmware.card import Card
from firmware.task import Handler

if TYPE_CHECKING:
    from firmware.can.master import Master
    from firmware.can.node import NodeHandler

log = logging.getLogger(__name__)

Post = Callable[[Message], None]
"""Where a transfer's answer goes: ``Card.post``, or a ``_Kept`` of the turn in C."""


class _Kept:
    """The answer of a request the device loop's turn in C handed over (``native_request``)
    [ours]: kept for that turn when the transfer ends inside the call (a simulated node of
    this process answers in the loop's thread, ``firmware.inline``), posted as usual when it
    ends later, from another thread. Whichever side pops the answer owns it (``list.pop`` is
    atomic), so an answer that comes while the call returns is neither lost nor given twice."""

    __slots__ = ("_answers", "_closed", "_post")

    def __init__(self, post: Post) -> None:
        self._post = post
        self._answers: list[Message] = []
        self._closed = False

    def __call__(self, answer: Message) -> None:
        answers = self._answers
        answers.append(answer)
        if self._closed:
            try:
                answer = answers.pop()
            except IndexError:  # the call took it meanwhile
                return
            self._post(answer)

    def take(self) -> Message | None:
        """The answer, if the transfer ended inside the call; from now on answers are posted."""
        self._closed = True
        try:
            return self._answers.pop()
        except IndexError:
            return None


class HostSdo:
    """COM_SDO_Up_Download over the master's SDO channels; answers go out by ``Card.post``."""

    def __init__(self, card: Card, master: Master) -> None:
        self.card = card
        self.master = master
        self._long_download: dict[int, tuple[TelegramHeader, bytearray]] = {}

    def handlers(self) -> dict[int, Handler]:
        return {COM_SDO_UP_DOWNLOAD: self.com_sdo_up_download}

    def reset(self) -> None:
        """A start forgets the parts of every long download."""
        self._long_download.clear()

    def com_sdo_up_download(self, msg: Message) -> Message | None:
        return self._request(msg, self.card.post)

    def native_request(self, raw: bytes) -> bytes | None:
        """A COM_SDO_Up_Download the device loop's turn in C took (``firmware/_mailbox.c``:
        a CAN-task message of this command with msg.e 0 from the host it serves) [ours]: the
        same handling as the Python turn's (``com_sdo_up_download``, with ``Task.handle``'s
        f on a failure), without that turn. Returns the answer's bytes for the host mailbox,
        or None when the answer comes later (posted, as the Python turn's would be)."""
        msg = Message.decode(raw)
        kept = _Kept(self.card.post)
        try:
            answer = self._request(msg, kept)
        except Exception:
            log.exception("task CAN failed on command %d", msg.b)
            answer = msg.answer(f=F_INTERNAL_ERROR)
        if answer is None:
            answer = kept.take()
            if answer is None:
                return None
        return answer.encode()

    def _request(self, msg: Message, post: Post) -> Message | None:
        try:
            head = TelegramHeader.decode(msg.data)
        except MessageError:
            return msg.answer(f=CanF.FAULTY_PARAMETER)
        address = head.device_adr
        if not 1 <= address <= NODE_ID_MAX:
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
        self.master.sdo.start_host(HostSdoTransfer(
            self.master.bus, address, head.data_adr, head.data_idx,
            None if head.function == Tfc.READ else head.payload,
            client.sdo.RESPONSE_TIMEOUT,
            partial(self._answer_sdo, post, msg, head, long_upload, client.lock, handler),
            answered_here=True))
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

    def _answer_sdo(self, post: Post, msg: Message, head: TelegramHeader, long_upload: bool,
                    channel: Lock, handler: NodeHandler | None, result: SdoResult) -> None:
        """The answer to a finished host transfer (several messages for a long upload); the
        node's channel (``channel``, its lock) and RX-PDOs (``handler``) are free again
        first. One bound method given to the transfer (a ``partial``), not a closure that
        calls it: a Python call less per transfer (issue 22)."""
        if handler is not None:
            handler.host_sdo = False
        channel.release()
        function, data = head.function, result.data
        if (function == Tfc.READ and not result.timed_out and result.abort is None
                and len(data) <= SDO_MAX_DATA):
            # the usual answer, an upload's data in one message, packed at once: a header
            # object and its ``encode`` cost two Python calls more
            post(msg.answer(data=TELEGRAM_HEADER.pack(
                head.device_adr, 0, head.data_adr, head.data_idx, len(data), 0, function)
                + data))
            return
        answer_head = TelegramHeader(head.device_adr, 0, head.data_adr, head.data_idx, 0, 0,
                                     function)
        if result.timed_out:
            answer = msg.answer(f=CanF.NO_RESPONSE, data=answer_head.encode())
        elif result.abort is not None:
            answer = msg.answer(f=CanF.SDO_ABORT, data=encode_sdo_abort(answer_head, result.abort))
        elif function == Tfc.READ and len(data) > LONG_SDO_LIMIT:
            answer = msg.answer(f=CanF.SDO_BUFFER, data=answer_head.encode())
        elif function == Tfc.READ:  # more than one message holds
            if not long_upload:  # seed 5.2.8: one answer of at most 247 bytes, else f 51
                answer = msg.answer(f=CanF.SDO_BUFFER, data=answer_head.encode())
            else:
                self._post_long_upload(post, msg, answer_head, data)
                return
        else:  # a download's confirmation
            answer = msg.answer(data=answer_head.encode())
        post(answer)

    def _post_long_upload(self, post: Post, msg: Message, head: TelegramHeader,
                          data: bytes) -> None:
        """More than one message of upload data: first, continue ..., last (msg.e)."""
        parts = [data[i : i + SDO_MAX_DATA] for i in range(0, len(data), SDO_MAX_DATA)]
        for n, part in enumerate(parts):
            e = Ext.FIRST if n == 0 else Ext.LAST if n == len(parts) - 1 else Ext.CONT
            head.data_cnt = len(part)
            head.payload = part
            post(msg.answer(data=head.encode(), e=e))
