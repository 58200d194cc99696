"""The CiA 309-1 LSS services (4.8) on the host, spoken through the card's layer-2 access.

The card has no LSS master of its own, so the host is the CiA 305 LSS master: requests go
out on 0x7E5 in COM_Tx_CAN_Layer2 (msg.b 84, which has no answer), the slaves' answers on
0x7E4 come back as COM_Rx_CAN_Layer2 indications (msg.b 83) once a COM_CfgRx_Layer2 filter
(msg.b 82) routes that identifier to the host (seed 5.3). Frame layout on both sides:
``ID.10..3 | ID.2..0 RTR DLC`` and the data bytes.

::

    with Board(0) as card:
        lss = LssMaster(card)
        for address, node_id in lss.complete_node_id_configuration(start_id=2):
            print(address, "->", node_id)

Sharing the mailbox: by default the master reads the host mailbox itself while a service
runs (and drops what is not a layer-2 indication). A program with its own mailbox reader,
such as the 309 gateway, passes ``indications`` (the next msg.b 83 message within a time-out)
and ``transact`` (a command with its answer), and the master never reads the mailbox.

Failures raise ``LssError`` with a CiA 309-3 error number: 103 when no slave answered in time,
502 / 503 / 504 / 501 when a slave answered a configure service with a CiA 305 error code
(node-ID out of range, bit timing not supported, store failed or not supported,
implementation-specific), 505 when the card refused the request or the driver call failed
(the medium to the bus failed).

Decisions [ours]:

* Time-outs: CiA 305 leaves them to the master. A service that expects an answer waits
  ``timeout`` (500 ms, as canopen's ``LssMaster``): it costs only when nobody answers. A
  single fastscan request (``fastscan_step``, 309-1 4.8.12) waits ``scan_timeout`` (50 ms):
  its silence is its answer. Through the emulated card an answer takes 0.3 ms (p50) to 2 ms
  (p99), but a loaded machine can hold a frame back for tens of milliseconds; on a real bus
  choose both to suit the slowest device.
* Each step of a scan (the reset, every bit, every confirmation) is followed, in the same
  message, by "identify non-configured remote slave", which every unconfigured slave, that
  is every slave taking part, answers (with 50h, where the step's answer is 4Fh). A slave
  answers its requests in order, so once every slave taking part has answered the marker,
  each answer of the step is in and none is left over to be read as the next step's: a
  step ends on that count, never on a time-out, and an answer a loaded machine delayed is
  neither read as a 1-bit nor taken for the next step's. A step costs a round trip instead
  of 50 ms per 1-bit.
* How many take part: the reset step's first marker answer and its duplicates within
  ``SETTLE_S`` (the answers of several slaves reach the host up to 2 ms apart through the
  emulated card). A loaded machine can hold a duplicate back longer; the scan then reads
  wrong bits and its confirmation fails. A scan that fails (a confirmation or a marker not
  answered, or no slave selected at the end) starts over, up to ``FASTSCAN_ATTEMPTS``
  scans. The failed scan's late answers are first taken and dropped for the scan's wait,
  the next scan waits twice as long, and it expects the number of slaves counted from
  every marker answer the failed scan read, late ones included.
* Several slaves may answer one identify request (outside a scan), each with its own frame:
  after a positive answer the master takes the indications of the next ``SETTLE_S`` and
  discards them, so a late duplicate is not read as the answer to the next request.
* Multi-frame requests (switch selective, identify remote slave) go in one COM_Tx_CAN_Layer2
  message, which the card sends back to back.
* The services of one master are serialised: LSS addresses the whole bus, so two interleaved
  services would corrupt each other.
"""

from __future__ import annotations

import functools
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from enum import IntEnum
from typing import Concatenate, ParamSpec, TypeVar

from dpm.cia301 import NODE_ID_MAX
from dpm.cia305 import (
    ACTIVATE_BIT_TIMING,
    CONFIGURATION,
    CONFIGURE_BIT_TIMING,
    CONFIGURE_NODE_ID,
    ERROR_IMPLEMENTATION_SPECIFIC,
    FASTSCAN,
    FASTSCAN_RESET,
    IDENTIFY_NON_CONFIGURED_REMOTE,
    IDENTIFY_NON_CONFIGURED_SLAVE,
    IDENTIFY_REMOTE_VENDOR,
    IDENTIFY_SLAVE,
    INQUIRE_NODE_ID,
    INQUIRE_VENDOR,
    LSS_ANSWER_COB_ID,
    LSS_REQUEST_COB_ID,
    STORE_CONFIGURATION,
    SWITCH_SELECTIVE_ANSWER,
    SWITCH_SELECTIVE_VENDOR,
    SWITCH_STATE_GLOBAL,
    WAITING,
    LssAddress,
)
from dpm.commands import COM_CFGRX_LAYER2, COM_RX_CAN_LAYER2, COM_TX_CAN_LAYER2
from dpm.errors import Drv
from dpm.message import Ext, Message, Task
from host_api.board import Board, CifError
from host_api.cia309.model import Cia309Error, ErrorCode

DEFAULT_TIMEOUT_S = 0.5
DEFAULT_SCAN_TIMEOUT_S = 0.05
SETTLE_S = 0.002
FASTSCAN_ATTEMPTS = 3

P = ParamSpec("P")
R = TypeVar("R")

IndicationSource = Callable[[float], Message | None]
"""The next COM_Rx_CAN_Layer2 indication (msg.b 83) within the time-out in seconds, else None;
a time-out of 0 only takes one that is already there."""
Transact = Callable[[Message], Message]
"""A command to the card and its answer (``Board.transact`` by default)."""


class LssErrorCode(IntEnum):
    """The CiA 309-3 error numbers an LSS service can fail with (the model's numbers)."""

    TIME_OUT = ErrorCode.TIME_OUT
    IMPLEMENTATION_ERROR = ErrorCode.LSS_IMPLEMENTATION_ERROR
    """LSS implementation- / manufacturer-specific error."""
    NODE_ID_NOT_SUPPORTED = ErrorCode.LSS_NODE_ID_NOT_SUPPORTED
    BIT_RATE_NOT_SUPPORTED = ErrorCode.LSS_BIT_RATE_NOT_SUPPORTED
    PARAMETER_STORING_FAILED = ErrorCode.LSS_PARAMETER_STORING_FAILED
    MEDIA_ERROR = ErrorCode.LSS_MEDIA_ERROR
    """LSS command failed because of media error (here: the card refused the request)."""


class LssError(Cia309Error):
    """An LSS service failed: ``code`` (309-3), and the slave's CiA 305 answer if it sent one."""

    def __init__(self, code: LssErrorCode, what: str, lss_error: int | None = None,
                 spec_error: int | None = None) -> None:
        self.code = code
        self.lss_error = lss_error
        """The error code of the slave's answer (CiA 305), None when there was no answer."""
        self.spec_error = spec_error
        """The answer's spec-error byte, meaningful when ``lss_error`` is 255."""
        text = f"{what}: {code.value} {code.name.lower().replace('_', ' ')}"
        if lss_error == ERROR_IMPLEMENTATION_SPECIFIC:
            text += f" (LSS error code {lss_error}, spec-error {spec_error})"
        elif lss_error is not None:
            text += f" (LSS error code {lss_error})"
        super().__init__(ErrorCode(code), text)


_CONFIGURE_ERRORS = {
    CONFIGURE_NODE_ID: LssErrorCode.NODE_ID_NOT_SUPPORTED,
    CONFIGURE_BIT_TIMING: LssErrorCode.BIT_RATE_NOT_SUPPORTED,
    STORE_CONFIGURATION: LssErrorCode.PARAMETER_STORING_FAILED,
}
"""What a CiA 305 error code other than 255 means in each configure answer."""


def _frame(cs: int, payload: bytes = b"") -> bytes:
    """One LSS request in the layer-2 format: the identifier bytes, then 8 data bytes."""
    data = bytes([cs]) + payload.ljust(7, b"\0")
    return bytes([LSS_REQUEST_COB_ID >> 3, (LSS_REQUEST_COB_ID & 7) << 5 | len(data)]) + data


def _u32(value: int) -> bytes:
    if not 0 <= value <= 0xFFFF_FFFF:
        raise ValueError(f"an LSS number is 32 bits, not {value:#x}")
    return value.to_bytes(4, "little")


def _fastscan_frame(id_number: int, bit_checked: int, lss_sub: int, lss_next: int) -> bytes:
    """The one fastscan request (CiA 305 LSS Fastscan), checked: the single step a 309
    client asks for and the composite scan's marked steps are the same request."""
    if not (0 <= bit_checked <= 31 or bit_checked == FASTSCAN_RESET):
        raise ValueError(f"BitChecked is 0..31 or 0x80, not {bit_checked}")
    if not (0 <= lss_sub <= 3 and 0 <= lss_next <= 3):
        raise ValueError("LSSSub and LSSNext are 0..3")
    return _frame(FASTSCAN, _u32(id_number) + bytes([bit_checked, lss_sub, lss_next]))


def _u8(value: int, what: str) -> bytes:
    if not 0 <= value <= 0xFF:
        raise ValueError(f"{what} is one byte, not {value}")
    return bytes([value])


def lss_answers(indication: Message) -> list[bytes]:
    """The LSS answers (0x7E4, 8 data bytes) among the frames of a layer-2 indication."""
    answers, at, d = [], 0, indication.data
    while at + 2 <= len(d):
        ident = d[at] << 3 | d[at + 1] >> 5
        rtr, dlc = d[at + 1] & 0x10, d[at + 1] & 0x0F
        size = 0 if rtr else min(dlc, 8)
        if ident == LSS_ANSWER_COB_ID and not rtr and size == 8:
            answers.append(bytes(d[at + 2 : at + 10]))
        at += 2 + size
    return answers


def _serialised(method: Callable[Concatenate[LssMaster, P], R]
                ) -> Callable[Concatenate[LssMaster, P], R]:
    """Hold the master's lock for the whole service (see the module's decisions)."""

    @functools.wraps(method)
    def run(master: LssMaster, /, *args: P.args, **kwargs: P.kwargs) -> R:
        with master._lock:
            return method(master, *args, **kwargs)

    return run


class LssMaster:
    """A CiA 305 LSS master on one card's CAN bus, one method per CiA 309-1 LSS service.

    Every service raises :class:`LssError` (a ``Cia309Error``) when it fails: 103 when no
    slave answers, 501..505 for the slave's refusal or the card's; the identify and
    fastscan services answer False or None instead when nobody answers.
    """

    def __init__(self, board: Board, indications: IndicationSource | None = None,
                 transact: Transact | None = None, timeout: float = DEFAULT_TIMEOUT_S,
                 scan_timeout: float = DEFAULT_SCAN_TIMEOUT_S) -> None:
        self.board = board
        self.timeout = timeout
        """Seconds a confirmed service waits for its answer."""
        self.scan_timeout = scan_timeout
        """Seconds ``fastscan_step`` waits: an unanswered step reads as a 1-bit."""
        self._indications = indications
        self._transact = transact or board.transact
        self._answers: deque[bytes] = deque()
        self._filter_set = False
        self._lock = threading.RLock()
        self._participants: int | None = None
        """How many slaves answer each fastscan step's marker; None until a scan knows."""
        self._scan_markers = 0
        """Marker answers (50h) read since the scan began, late ones included."""
        self._scan_steps = 0
        """Marked steps the scan sent."""

    # --- the card: filter, requests, indications ---------------------------------------

    def open(self) -> None:
        """Route 0x7E4 to the host (COM_CfgRx_Layer2); done by the first service anyway.

        The card drops its layer-2 filters when the host stops communication or the card
        restarts: call it again after either.
        """
        request = Message(rx=Task.CAN, tx=Task.USER, b=COM_CFGRX_LAYER2,
                          data=bytes([LSS_ANSWER_COB_ID & 0xFF, LSS_ANSWER_COB_ID >> 8]))
        try:
            answer = self._transact(request)
        except CifError as exc:
            raise LssError(LssErrorCode.MEDIA_ERROR, f"layer-2 filter: {exc}") from exc
        if answer.f:
            raise LssError(LssErrorCode.MEDIA_ERROR,
                           f"the card refused the layer-2 filter for 0x7E4 (msg.f {answer.f})")
        self._filter_set = True

    def _send(self, frames: list[bytes]) -> None:
        """Forget stale answers, then put the request frames on the bus in one message."""
        if not self._filter_set:
            self.open()
        self._answers.clear()
        while self._read(0.0) is not None:
            pass
        try:
            # [ours] e NAK: the card answers COM_Tx_CAN_Layer2 only when it fails, and the
            # driver's ledger then awaits no answer (``Link.send``)
            self.board.put_message(Message(rx=Task.CAN, tx=Task.USER, b=COM_TX_CAN_LAYER2,
                                           data=b"".join(frames), e=Ext.NAK))
        except CifError as exc:
            raise LssError(LssErrorCode.MEDIA_ERROR, f"COM_Tx_CAN_Layer2: {exc}") from exc

    def _read(self, timeout: float) -> Message | None:
        """The next layer-2 indication, its LSS answers queued; None at the time-out."""
        if self._indications is not None:
            msg = self._indications(timeout)
        else:
            try:
                msg = self.board.get_message(math.ceil(timeout * 1000))
            except CifError as exc:
                if exc.code in (Drv.DRV_DEV_GET_TIMEOUT, Drv.DRV_DEV_GET_NO_MESSAGE):
                    return None
                raise LssError(LssErrorCode.MEDIA_ERROR, f"DevGetMessage: {exc}") from exc
        if msg is not None and msg.b == COM_RX_CAN_LAYER2:
            answers = lss_answers(msg)
            self._scan_markers += sum(a[0] == IDENTIFY_NON_CONFIGURED_SLAVE for a in answers)
            self._answers.extend(answers)
        return msg

    def _answer(self, cs: int, timeout: float) -> bytes | None:
        """The first answer with command specifier ``cs`` within ``timeout``; others go."""
        deadline = time.monotonic() + timeout
        while True:
            while self._answers:
                answer = self._answers.popleft()
                if answer[0] == cs:
                    return answer
            remaining = deadline - time.monotonic()
            if remaining <= 0 or self._read(remaining) is None:
                return None

    def _settle(self, window: float = SETTLE_S) -> int:
        """Take and drop, for ``window``, the duplicates of an answer several slaves sent;
        how many of them were marker answers (50h).

        A fixed window: other layer-2 traffic in the indications must not prolong it.
        """
        deadline = time.monotonic() + window
        while (remaining := deadline - time.monotonic()) > 0:
            self._read(remaining)
        markers = sum(a[0] == IDENTIFY_NON_CONFIGURED_SLAVE for a in self._answers)
        self._answers.clear()
        return markers

    def _confirmed(self, what: str, frames: list[bytes], cs: int) -> bytes:
        self._send(frames)
        answer = self._answer(cs, self.timeout)
        if answer is None:
            raise LssError(LssErrorCode.TIME_OUT, f"{what}: no LSS slave answered")
        return answer

    def _configure(self, what: str, cs: int, payload: bytes = b"") -> None:
        """A configure service: its answer's error code 0, else the matching 309-3 error."""
        answer = self._confirmed(what, [_frame(cs, payload)], cs)
        error, spec = answer[1], answer[2]
        if error == ERROR_IMPLEMENTATION_SPECIFIC:
            raise LssError(LssErrorCode.IMPLEMENTATION_ERROR, what, error, spec)
        if error:
            raise LssError(_CONFIGURE_ERRORS[cs], what, error, spec)

    # --- 309-1 4.8.2 .. 4.8.12: one CiA 305 service each --------------------------------

    @_serialised
    def switch_state_global(self, mode: int) -> None:
        """4.8.2: every slave to ``WAITING`` (0) or ``CONFIGURATION`` (1); no answer."""
        if mode not in (WAITING, CONFIGURATION):
            raise ValueError(f"switch state global takes 0 (waiting) or 1 (configuration), "
                             f"not {mode}")
        self._send([_frame(SWITCH_STATE_GLOBAL, bytes([mode]))])

    @_serialised
    def switch_state_selective(self, vendor: int, product: int, revision: int,
                               serial: int) -> None:
        """4.8.3: the one slave with this LSS address to configuration state."""
        frames = [_frame(SWITCH_SELECTIVE_VENDOR + n, _u32(number))
                  for n, number in enumerate((vendor, product, revision, serial))]
        self._confirmed("switch state selective", frames, SWITCH_SELECTIVE_ANSWER)

    @_serialised
    def configure_node_id(self, node_id: int) -> None:
        """4.8.4: the pending node-ID of the slave in configuration state (255: none)."""
        self._configure("configure node-ID", CONFIGURE_NODE_ID, _u8(node_id, "a node-ID"))

    @_serialised
    def configure_bit_timing(self, table: int, index: int) -> None:
        """4.8.5: table selector 0 is the CiA 301 table (index 0 = 1 Mbit/s .. 8 = 10 kbit/s)."""
        self._configure("configure bit timing", CONFIGURE_BIT_TIMING,
                        _u8(table, "a table selector") + _u8(index, "a table index"))

    @_serialised
    def activate_bit_timing(self, switch_delay_ms: int) -> None:
        """4.8.6: the slaves in configuration state switch after the delay; no answer.

        They stay silent for twice the delay (CiA 305), so wait that long before the next
        request; a master changing its own rate does so within the delay.
        """
        if not 0 <= switch_delay_ms <= 0xFFFF:
            raise ValueError(f"the switch delay is 16 bits, not {switch_delay_ms}")
        self._send([_frame(ACTIVATE_BIT_TIMING, switch_delay_ms.to_bytes(2, "little"))])

    @_serialised
    def store_configuration(self) -> None:
        """4.8.7: the slave in configuration state stores its pending node-ID and bit timing."""
        self._configure("store configuration", STORE_CONFIGURATION)

    @_serialised
    def inquire_lss_number(self, lss_sub: int) -> int:
        """4.8.8 for one LSS number: 0 vendor-ID, 1 product code, 2 revision, 3 serial."""
        if not 0 <= lss_sub <= 3:
            raise ValueError(f"the LSS number is 0..3, not {lss_sub}")
        cs = INQUIRE_VENDOR + lss_sub
        answer = self._confirmed("inquire LSS address", [_frame(cs)], cs)
        return int.from_bytes(answer[1:5], "little")

    @_serialised
    def inquire_address(self) -> LssAddress:
        """4.8.8: the whole LSS address of the slave in configuration state."""
        return LssAddress(*(self.inquire_lss_number(n) for n in range(4)))

    @_serialised
    def inquire_node_id(self) -> int:
        """4.8.9: the active node-ID of the slave in configuration state (255: none)."""
        return self._confirmed("inquire node-ID", [_frame(INQUIRE_NODE_ID)], INQUIRE_NODE_ID)[1]

    @_serialised
    def identify_remote_slave(self, vendor: int, product: int, revision_low: int,
                              revision_high: int, serial_low: int, serial_high: int) -> bool:
        """4.8.10: whether at least one slave's address lies in the ranges (bounds included)."""
        numbers = (vendor, product, revision_low, revision_high, serial_low, serial_high)
        self._send([_frame(IDENTIFY_REMOTE_VENDOR + n, _u32(number))
                    for n, number in enumerate(numbers)])
        return self._identified(IDENTIFY_SLAVE, self.timeout)

    @_serialised
    def identify_non_configured_slave(self) -> bool:
        """4.8.11: whether at least one slave has no node-ID (FFh) and none pending."""
        self._send([_frame(IDENTIFY_NON_CONFIGURED_REMOTE)])
        return self._identified(IDENTIFY_NON_CONFIGURED_SLAVE, self.timeout)

    @_serialised
    def fastscan_step(self, id_number: int, bit_checked: int, lss_sub: int, lss_next: int,
                      timeout: float | None = None) -> bool:
        """4.8.12, one CiA 305 fastscan request: whether any unconfigured slave answered.

        A slave whose LSSPos is ``lss_sub`` answers when bits 31..``bit_checked`` of that LSS
        number equal ``id_number``'s, then takes ``lss_next`` as its LSSPos; ``bit_checked``
        0 with ``lss_next`` below ``lss_sub`` selects it. BitChecked 80h restarts every scan.
        """
        self._send([_fastscan_frame(id_number, bit_checked, lss_sub, lss_next)])
        return self._identified(IDENTIFY_SLAVE,
                                self.scan_timeout if timeout is None else timeout)

    def _identified(self, cs: int, timeout: float) -> bool:
        if self._answer(cs, timeout) is None:
            return False
        self._settle()
        return True

    # --- 309-1 4.8.12 .. 4.8.14: the composite services -----------------------------------

    @_serialised
    def fastscan(self, vendor: int | None = None, product: int | None = None,
                 revision: int | None = None, serial: int | None = None,
                 timeout: float | None = None) -> LssAddress | None:
        """Find one unconfigured slave and leave it selected (configuration state).

        None when no unconfigured slave answers. A known LSS number is confirmed in one
        step instead of being scanned in 32 (CANopenNode's "match"); a known number no
        unconfigured slave has also gives None. Each step waits for its markers' answers
        (see the module's decisions) up to ``timeout`` (default: ``self.timeout``), doubled
        for each scan that has to start over.
        """
        known = (vendor, product, revision, serial)
        wait = self.timeout if timeout is None else timeout
        self._participants = None
        for _ in range(FASTSCAN_ATTEMPTS):
            self._scan_markers = self._scan_steps = 0
            reset = self._marked_step(0, FASTSCAN_RESET, 0, 0, self.timeout)
            if not reset and self._participants is None:
                return None  # no unconfigured slave took part
            numbers: list[int] = []
            for lss_sub in range(4) if reset else ():
                value = known[lss_sub]
                if value is None:
                    value = self._scan_number(lss_sub, wait)
                    if value is None:
                        break  # a step's markers did not all come: scan again
                next_sub = (lss_sub + 1) % 4
                confirmed = self._marked_step(value, 0, lss_sub, next_sub, wait)
                if confirmed is False and known[lss_sub] is not None:
                    return None
                if not confirmed:
                    break  # an answer was lost or came late: scan again
                numbers.append(value)
            else:
                if reset and self._selected():
                    return LssAddress(*numbers)
            # answers come late here: take the failed scan's late answers for the scan's
            # wait, so that none is read in the next scan, count every marker answer it
            # read, and give the next scan more time
            self._settle(wait)
            self._participants = max(1, round(self._scan_markers / max(1, self._scan_steps)))
            wait *= 2
        raise LssError(LssErrorCode.TIME_OUT,
                       f"fastscan: no slave confirmed its address in {FASTSCAN_ATTEMPTS} scans")

    def _scan_number(self, lss_sub: int, wait: float) -> int | None:
        """LSS number ``lss_sub`` of the lowest slave still in the scan, bit by bit from bit
        31: a bit is 0 where a slave answered the step checking it, else 1. None when a
        step's markers did not all come within ``wait``."""
        value = 0
        for bit in range(31, -1, -1):
            answered = self._marked_step(value, bit, lss_sub, lss_sub, wait)
            if answered is None:
                return None
            if not answered:
                value |= 1 << bit
        return value

    def _marked_step(self, id_number: int, bit_checked: int, lss_sub: int, lss_next: int,
                     wait: float) -> bool | None:
        """One fastscan request with its marker behind it, in one message: whether a slave
        answered the request (4Fh); None when the markers' answers (50h) did not come within
        ``wait``.

        Each slave answers in order, so once every taking part has answered the marker,
        every answer of the step is in and none is left to be read as the next step's.
        Until the scan knows how many take part (``_participants``), the answers before
        the first marker's count, and the marker's duplicates that come within
        ``SETTLE_S`` give the number.
        """
        self._send([_fastscan_frame(id_number, bit_checked, lss_sub, lss_next),
                    _frame(IDENTIFY_NON_CONFIGURED_REMOTE)])
        self._scan_steps += 1
        deadline = time.monotonic() + wait
        answered, markers = False, 0
        while True:
            while self._answers:
                cs = self._answers.popleft()[0]
                if cs == IDENTIFY_NON_CONFIGURED_SLAVE:
                    markers += 1
                elif cs == IDENTIFY_SLAVE and (markers == 0 or self._participants):
                    answered = True
                if self._participants is None and markers:
                    self._participants = markers + self._settle()
                    return answered
                if self._participants and markers >= self._participants:
                    return answered
            remaining = deadline - time.monotonic()
            if remaining <= 0 or self._read(remaining) is None:
                return None

    def _selected(self) -> bool:
        """Whether a slave is in configuration state: a late answer can fake the last
        confirmation, but only the slave whose address was confirmed is selected."""
        self._send([_frame(INQUIRE_NODE_ID)])
        return self._answer(INQUIRE_NODE_ID, self.timeout) is not None

    @_serialised
    def assign_node_id(self, address: LssAddress, node_id: int, store: bool = True) -> None:
        """4.8.13: select the slave by its address, give it ``node_id``, store it (unless
        ``store`` is False) and switch every slave back to waiting.

        An unconfigured slave then starts up under the new node-ID; a configured one takes
        it at its next NMT reset communication or reset node.
        """
        self.switch_state_selective(*address)
        try:
            self.configure_node_id(node_id)
            if store:
                self.store_configuration()
        finally:
            self.switch_state_global(WAITING)

    @_serialised
    def complete_node_id_configuration(self, start_id: int = 2, store: bool = True,
                                       exclude: Iterable[int] = (),
                                       timeout: float | None = None
                                       ) -> list[tuple[LssAddress, int]]:
        """4.8.14: fastscan and assign until no unconfigured slave answers.

        Node-IDs are given in rising order from ``start_id`` (CANopenNode's default 2),
        leaving out ``exclude`` (e.g. the nodes the card already has). Returns every
        (LSS address, node-ID) assigned; each slave boots up under its node-ID.
        """
        taken = set(exclude)
        assigned: list[tuple[LssAddress, int]] = []
        node_id = start_id
        self.switch_state_global(WAITING)
        while (address := self.fastscan(timeout=timeout)) is not None:
            while node_id in taken:
                node_id += 1
            if not 1 <= node_id <= NODE_ID_MAX:
                self.switch_state_global(WAITING)
                raise LssError(LssErrorCode.NODE_ID_NOT_SUPPORTED,
                               f"no node-ID left for the slave {address}")
            try:
                self.configure_node_id(node_id)
                if store:
                    self.store_configuration()
            finally:
                self.switch_state_global(WAITING)
            assigned.append((address, node_id))
            node_id += 1
        return assigned
