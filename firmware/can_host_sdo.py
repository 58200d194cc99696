"""COM_SDO_Up_Download: the host's SDO transfers through the card, long ones too.

Why a module of its own: it is the one CAN-task message whose answer comes later, from the
SDO channel's worker, and the one that gathers a request over several messages (seed 5.2.8;
the long transfers with msg.e in docs/card-commands.md). It owns the parts of a long
download while they come in; the transfer on the bus is ``firmware.can.sdo``'s.
"""

from __future__ import annotations

import logging
from functools import partial
from typing import TYPE_CHECKING

from dpm._quicklock import Lock
from dpm.cia301 import NODE_ID_MAX
from dpm.com import encode_sdo_abort
from dpm.commands import COM_SDO_UP_DOWNLOAD, LONG_SDO_LIMIT, SDO_MAX_DATA
from dpm.errors import F_INTERNAL_ERROR, CanF
from dpm.layout import MSG_HEADER_SIZE
from dpm.message import (
    HEADER,
    TELEGRAM_HEADER,
    Ext,
    Message,
    TelegramHeader,
    Tfc,
    encode_answer,
)
from firmware.can.node import State
from firmware.can.sdo import HostSdoTransfer, SdoResult
from firmware.card import Card
from firmware.task import Handler

if TYPE_CHECKING:
    from firmware.can.master import Master
    from firmware.can.node import NodeHandler

log = logging.getLogger(__name__)

_REQUEST_MIN = MSG_HEADER_SIZE + TELEGRAM_HEADER.size
_HEAD = slice(MSG_HEADER_SIZE, _REQUEST_MIN)
"""A request's telegram header, which a refusal carries back."""
_PAYLOAD = slice(_REQUEST_MIN, None)
_READ = int(Tfc.READ)
_WRITE = int(Tfc.WRITE)
_FIRST = int(Ext.FIRST)
_LONG_PARTS = frozenset((Ext.FIRST, Ext.CONT, Ext.LAST))
_BOOTING = State.BOOTING


class HostSdo:
    """COM_SDO_Up_Download over the master's SDO channels; answers go out by ``Card.post``.

    [ours] A request and its answers are handled as the mailbox's bytes: the turn in C
    hands them over so (``native_request``), and a ``Message`` with its decode, its
    telegram header object, its answer and their encodes cost that path seven Python calls
    per transfer (issue 22); the Python turn's request (``com_sdo_up_download``) is encoded
    once to join it, and the answers go to ``Card.post`` as bytes (``firmware.card.Answer``).

    A request of the turn in C gets a number; while that turn's call is under way
    (``_open``), the answers of its transfer are kept for it (``_kept``: a simulated node of
    this process answers in the loop's thread, ``firmware.inline``), later ones are posted
    as usual. One slot for every request, not an object per request (issue 22); the lock
    puts the call's end and a late answer from another thread in one order."""

    def __init__(self, card: Card, master: Master) -> None:
        self.card = card
        self.master = master
        self._long_download: dict[int, tuple[TelegramHeader, bytearray]] = {}
        self._numbers = 0
        """The last number given to a request of the turn in C (the Python turn's are 0)."""
        self._open = -1
        """The number of the request whose ``native_request`` call is under way; -1: none."""
        self._kept: list[bytes] = []
        """The answers that came for it during the call."""
        self._kept_lock = Lock()

    def handlers(self) -> dict[int, Handler]:
        return {COM_SDO_UP_DOWNLOAD: self.com_sdo_up_download}

    def reset(self) -> None:
        """A start forgets the parts of every long download."""
        self._long_download.clear()

    def com_sdo_up_download(self, msg: Message) -> Message | None:
        answer = self._request(msg.encode(), 0)
        return None if answer is None else Message.decode(answer)

    def native_request(self, raw: bytes) -> bytes | None:
        """A COM_SDO_Up_Download the device loop's turn in C took (``firmware/_mailbox.c``:
        a CAN-task message of this command with msg.e 0 or 4 from the host it serves)
        [ours]: the same handling as the Python turn's (``com_sdo_up_download``, with
        ``Task.handle``'s f on a failure), without that turn. Returns the answer's bytes for
        the host mailbox, or None when the answer comes later, or comes in several messages:
        those are posted, as the Python turn's would be. A part posted after the one
        returned cannot overtake it: the turn in C writes it while it holds the device's
        turn lock, and ``Device.hand_over`` delivers nothing into a host mailbox that is
        not free."""
        self._numbers = self._open = number = self._numbers + 1
        try:
            answer = self._request(raw, number)
        except Exception:
            log.exception("task CAN failed on command %d", raw[6])
            answer = encode_answer(raw, f=F_INTERNAL_ERROR)
        with self._kept_lock:
            self._open = -1
            kept = self._kept
            if answer is None and len(kept) == 1:
                return kept.pop()
            for late in kept:
                self.card.post(late)
            kept.clear()
        return answer

    def _give(self, number: int, answer: bytes) -> None:
        """An answer to request ``number``: kept while its ``native_request`` call is under
        way, else posted (under the lock: after the ones the call's end posts)."""
        with self._kept_lock:
            if number == self._open:
                self._kept.append(answer)
            else:
                self.card.post(answer)

    def _request(self, raw: bytes, number: int) -> bytes | None:
        """The request ``raw`` (header and msg.ln data bytes) numbered ``number``: its
        answer now, or None when its transfer answers (``_give``).

        The checks in the seed's order, each refusal's telegram header copied only for the
        refusal, and the numbers compared as module globals (an enum member read through
        its class costs a look-up more): a host SDO read runs these in the device loop's
        thread on every transfer (issue 22)."""
        if len(raw) < _REQUEST_MIN:
            return encode_answer(raw, f=CanF.FAULTY_PARAMETER)
        address, _, index, subindex, count, _, function = TELEGRAM_HEADER.unpack_from(
            raw, MSG_HEADER_SIZE)
        if not 1 <= address <= NODE_ID_MAX:
            return encode_answer(raw, f=CanF.FAULTY_PARAMETER, data=raw[_HEAD])
        if function != _READ and function != _WRITE:
            return encode_answer(raw, f=CanF.SDO_FUNCTION, data=raw[_HEAD])
        master = self.master
        if not master.nmt.running or master.bus is None:
            return encode_answer(raw, f=CanF.NOT_CONFIGURED, data=raw[_HEAD])
        payload = None
        if function == _WRITE:
            payload = raw[_PAYLOAD]
            if len(payload) != count:
                return encode_answer(raw, f=CanF.SDO_BUFFER, data=raw[_HEAD])
        # [ours] Only e 4, 8 and 0x0C mark a long transfer (docs/card-commands.md), and an
        # upload gets several answers only when asked with e 4: a request as the seed writes
        # it (e 0) gets the seed's single answer, and other bits in e change nothing.
        e = raw[7]
        long_upload = function == _READ and e == _FIRST
        if e in _LONG_PARTS and not long_upload:
            if function != _WRITE:
                return encode_answer(raw, f=CanF.SEQUENCE, data=raw[_HEAD])
            gathered = self._gather(raw, e, TelegramHeader.decode(raw[MSG_HEADER_SIZE:]))
            if isinstance(gathered, bytes):
                return gathered
            payload = bytes(gathered)
        handler = master.nodes.get(address)
        if handler is not None and handler.state is _BOOTING:
            return encode_answer(raw, f=CanF.NODE_BUSY, data=raw[_HEAD])
        client = master.sdo.channel(address)
        if not client.lock.acquire(blocking=False):
            return encode_answer(raw, f=CanF.SDO_FUNCTION, data=raw[_HEAD])
        if handler is not None:
            handler.host_sdo = True  # seed 5.2.8: the node's RX-PDOs wait meanwhile
        transfer = HostSdoTransfer(
            master.bus, address, index, subindex, payload, client.sdo.RESPONSE_TIMEOUT,
            partial(self._answer_sdo, number, raw, long_upload, client.lock, handler),
            answered_here=True)
        # ``SdoChannels.start_host`` written out: a Python call less per transfer (issue 22)
        transfer.start()
        if not transfer.finished:  # answered in ``start`` (``answered_here``): nothing to watch
            master.sdo.watch(transfer)
        return None

    def _gather(self, raw: bytes, e: int, head: TelegramHeader) -> bytes | bytearray:
        """One part of a long SDO download: the answer to it now (``bytes``), or the whole
        download's data after its last part (the ``bytearray`` it was gathered in)."""
        sequence = e & Ext.SEQ_MASK
        address = head.device_adr
        head8 = raw[MSG_HEADER_SIZE : MSG_HEADER_SIZE + TELEGRAM_HEADER.size]
        key = (head.device_adr, head.data_adr, head.data_idx)
        if sequence == Ext.FIRST:
            self._long_download[address] = (head, bytearray(head.payload))
        else:
            first = self._long_download.get(address)
            if first is None or (first[0].device_adr, first[0].data_adr, first[0].data_idx) != key:
                self._long_download.pop(address, None)
                return encode_answer(raw, f=CanF.SEQUENCE, data=head8)
            first[1].extend(head.payload)
        data = self._long_download[address][1]
        if len(data) > LONG_SDO_LIMIT:
            self._long_download.pop(address, None)
            return encode_answer(raw, f=CanF.BUFFER_LENGTH, data=head8)
        if sequence != Ext.LAST:
            head.data_cnt = 0
            head.payload = b""
            return encode_answer(raw, data=head.encode())
        del self._long_download[address]
        return data

    def _answer_sdo(self, number: int, raw: bytes, long_upload: bool, channel: Lock,
                    handler: NodeHandler | None, result: SdoResult) -> None:
        """The answer to the finished host transfer asked by ``raw`` (several messages for a
        long upload); the node's channel (``channel``, its lock) and RX-PDOs (``handler``)
        are free again first. One bound method given to the transfer (a ``partial``), not a
        closure that calls it: a Python call less per transfer (issue 22)."""
        if handler is not None:
            handler.host_sdo = False
        channel.release()
        address, _, index, subindex, _, _, function = TELEGRAM_HEADER.unpack_from(
            raw, MSG_HEADER_SIZE)
        data = result.data
        if (function == _READ and not result.timed_out and result.abort is None
                and len(data) <= SDO_MAX_DATA):
            # the usual answer, an upload's data in one message, packed here: a call of
            # ``encode_answer`` more per transfer otherwise
            body = TELEGRAM_HEADER.pack(address, 0, index, subindex, len(data), 0, function) + data
            answer = HEADER.pack(raw[1], raw[0], len(body), raw[3], raw[6], 0, 0, 0) + body
            with self._kept_lock:  # ``_give`` written out: a Python call less (issue 22)
                if number == self._open:
                    self._kept.append(answer)
                else:
                    self.card.post(answer)
            return
        head = TelegramHeader(address, 0, index, subindex, 0, 0, function)
        if result.timed_out:
            answer = encode_answer(raw, f=CanF.NO_RESPONSE, data=head.encode())
        elif result.abort is not None:
            answer = encode_answer(raw, f=CanF.SDO_ABORT, data=encode_sdo_abort(head, result.abort))
        elif function == Tfc.READ and len(data) > LONG_SDO_LIMIT:
            answer = encode_answer(raw, f=CanF.SDO_BUFFER, data=head.encode())
        elif function == Tfc.READ:  # more than one message holds
            if not long_upload:  # seed 5.2.8: one answer of at most 247 bytes, else f 51
                answer = encode_answer(raw, f=CanF.SDO_BUFFER, data=head.encode())
            else:
                self._post_long_upload(number, raw, head, data)
                return
        else:  # a download's confirmation
            answer = encode_answer(raw, data=head.encode())
        self._give(number, answer)

    def _post_long_upload(self, number: int, raw: bytes, head: TelegramHeader,
                          data: bytes) -> None:
        """More than one message of upload data: first, continue ..., last (msg.e)."""
        parts = [data[i : i + SDO_MAX_DATA] for i in range(0, len(data), SDO_MAX_DATA)]
        for n, part in enumerate(parts):
            e = Ext.FIRST if n == 0 else Ext.LAST if n == len(parts) - 1 else Ext.CONT
            head.data_cnt = len(part)
            head.payload = part
            self._give(number, encode_answer(raw, data=head.encode(), e=e))
