"""The boot-up of one node: reset, identify, configure by SDO (seed 4.2, bitConfigNdState).

Why a module of its own: the boot-up is the one part of a node handler that waits (on
SDO answers, on the boot-up message), and the one part that writes the node's object
dictionary. It decides nothing about the node's state: it ends with no event, and the
handler puts the node into operation, or with the seed's Err_Event, which the handler
reports. The frames it owns are the node's boot-up message (as an answer to its reset)
and the SDO responses whose length the SDO client never sees.

It is driven by frames, not by a waiting thread (issue 22): each step is started by the
frame that answers the one before (an SDO response, the boot-up message), in the bus
thread, or by the master's thread when a time-out comes; so the sequences of many nodes
are in flight together (``BOOTS_IN_FLIGHT``) and none costs a thread switch per answer.
A blocking client in a pool of 32 worker threads took 1.3-1.6 times as long as canopen
for 127 nodes.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Protocol

import can
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError, SdoError

from dbm_tools.parameters import ConfigNdState, NodeParameterSet
from dpm.cia301 import COB_ID_SYNC, EMCY_BASE, ERROR_CONTROL_BASE, SDO_RESPONSE_BASE
from dpm.com import NodeDiagnosis, NodeStatus
from dpm.commands import NMT_RESET_NODE as NMT_RESET
from dpm.commands import NMT_START
from dpm.errors import NodeEvent
from firmware.can.bus import CanBus
from firmware.can.sdo import HostSdoTransfer, SdoChannels, SdoResult
from firmware.frames import SDO_FRAME_LENGTH

log = logging.getLogger("firmware.can.node")
"""The node handler's log, as before the boot-up had a module of its own."""

BOOTUP_TIMEOUT = 3.0
"""[ours] seconds a reset node has to answer: its boot-up message, or 1000h read."""
RESET_GRACE = 1.0
"""[ours] seconds the card waits after a reset for a boot-up message before it reads 1000h."""
HEARTBEAT_PRODUCER = 0x1017
"""CiA 301's producer heartbeat time, which only the node's own heartbeat depends on."""
BOOTS_IN_FLIGHT = 64
"""[ours] boot-ups under way at once; the others wait their turn (``BootSlots``). Twice the
32 of the card's former pool of boot threads, so that 32 silent nodes (3 s each) hold up
no other node; not all 127, whose requests at once a machine at load 28 answered late."""


class BootSlots:
    """At most ``BOOTS_IN_FLIGHT`` boot-ups under way; the others start in their order as
    slots come free."""

    def __init__(self, limit: int = BOOTS_IN_FLIGHT) -> None:
        self._limit = limit
        self._running = 0
        self._waiting: collections.deque[Callable[[], bool]] = collections.deque()
        self._lock = threading.Lock()

    def take(self, start: Callable[[], bool]) -> None:
        """Call ``start`` in a free slot, now or when one comes free; it returns False when
        it did not start after all (a newer boot-up of its node came meanwhile), which
        frees the slot at once."""
        with self._lock:
            if self._running >= self._limit:
                self._waiting.append(start)
                return
            self._running += 1
        if not start():
            self.free()

    def busy(self) -> bool:
        """Whether a boot-up is under way (``CanBus.lingering``)."""
        return self._running > 0

    def free(self) -> None:
        """A boot-up ended: the next waiting one starts in its slot."""
        while True:
            with self._lock:
                if not self._waiting:
                    self._running -= 1
                    return
                start = self._waiting.popleft()
            if start():
                return


class BootLink(Protocol):
    """What a boot-up uses of the network besides the node's SDO channel."""

    @property
    def closing(self) -> bool: ...

    @property
    def sync_cob_id(self) -> int: ...

    @property
    def global_start(self) -> bool: ...

    @property
    def nodes_stopped(self) -> bool:
        """Auto-clear or HOST_NOT_READY stopped the network: a boot-up starts no node."""

    def send_nmt(self, command: int, node: int) -> None: ...


class BootFailure(Exception):
    """The boot-up ended with the seed's Err_Event ``event`` (seed 4.3)."""

    def __init__(self, event: int) -> None:
        super().__init__(event)
        self.event = event


class UnknownSdoResponse(SdoCommunicationError):
    """An answer the SDO client could not take (``SdoResult.failed``): an unknown command
    specifier, a toggle bit not alternated, another object's answer. The node did answer,
    not as CiA 301 has it: 37, never a time-out to wait out or call silence."""


@dataclass(frozen=True)
class Sdo:
    """A step: read (``value`` None) or write one object; the sequence gets the value read,
    or ``SdoAbortedError`` / ``SdoCommunicationError`` thrown in, as canopen's client raised
    them before."""

    index: int
    subindex: int
    value: bytes | None = None


@dataclass(frozen=True)
class BootUp:
    """A step: wait up to ``timeout`` seconds for the boot-up message; the sequence gets
    whether it came."""

    timeout: float


Steps = Generator[Sdo | BootUp, bytes | bool | None, None]


class _GraceTimer:
    """The wait for a boot-up message, watched by the master's thread (``SdoChannels.watch``)
    like an SDO time-out: it ends the wait unless the message ended it first."""

    def __init__(self, timeout: float, expire: Callable[[_GraceTimer], None]) -> None:
        self.deadline = time.monotonic() + timeout
        self._expire = expire
        self.finished = False

    def check(self, now: float) -> float:
        if self.finished:
            return math.inf
        if now >= self.deadline:
            self.finished = True
            self._expire(self)
            return math.inf
        return self.deadline


@dataclass
class _Run:
    """One boot-up under way (``BootSequence.start``)."""

    bus: CanBus
    channels: SdoChannels
    timeout: float
    release: Callable[[], None]
    current: Callable[[], bool]
    done: Callable[[int | None], None]
    steps: Steps
    ended: bool = False

    def end(self) -> None:
        """Give the SDO channel (and the boot slot) back, once."""
        if not self.ended:
            self.ended = True
            self.release()


class InForce(Protocol):
    """The node's error control as it is now (``ErrorControl``): the configured one until
    the host switches it at run time (COM_Set_Guarding, COM_Set_Heartbeat_Consumer)."""

    heartbeat: bool
    guard_time: int
    life_time_factor: int


class BootSequence:
    """The boot steps of one node, as its bitConfigNdState leaves them to the card."""

    def __init__(self, address: int, params: NodeParameterSet, diag: NodeDiagnosis,
                 link: BootLink, control: InForce) -> None:
        self.address = address
        self.params = params
        self.diag = diag
        self.link = link
        self._control = control
        """[ours] The error control the GUARD step writes: the one in force, so a node lost
        after a run-time switch comes back supervised as the host asked, not as configured."""
        self._booted = False
        """The boot-up message answering the last reset came. A flag, not an Event: nothing
        waits on it, and 127 Events (a Condition each) cost a start 3-9 ms before READY."""
        self._reset_at = 0.0
        """Wall-clock time (as frames are stamped) of the last NMT reset the card sent it."""
        self._sdo_length_error = False
        """An SDO response of another length than 8 came since the boot-up began. The
        SDO client never sees it, and times out: Err_Event 38."""
        self._lock = threading.Lock()
        self._pending: object | None = None
        """The step under way (an SDO transfer's token or a grace timer): its end, and only its,
        advances the sequence; ``_lock`` lets the first of two ends (the boot-up message
        and the grace timer) win."""
        self._run: _Run | None = None

    def attach(self, bus: CanBus) -> None:
        bus.subscribe(SDO_RESPONSE_BASE + self.address, self._on_sdo_response)

    def detach(self, bus: CanBus) -> None:
        bus.unsubscribe(SDO_RESPONSE_BASE + self.address, self._on_sdo_response)

    @property
    def reset_at(self) -> float:
        """Wall-clock time of the last NMT reset the card sent the node (0: none yet)."""
        return self._reset_at

    def arm(self) -> None:
        """A boot-up begins: a boot-up message from now on may answer its reset."""
        self._booted = False

    def booted_up(self, stamp: float | None) -> None:
        """The node's boot-up message. One sent before our reset (at power-on, say) must
        not pass for its answer: the node would still be resetting when the first SDO
        request comes."""
        if stamp is None or stamp >= self._reset_at:
            self._booted = True
            with self._lock:
                timer = self._pending
                if not isinstance(timer, _GraceTimer):
                    return
                self._pending = None
                timer.finished = True
            self._advance(True)

    def start(self, bus: CanBus, channels: SdoChannels, timeout: float, reset_sent: bool,
              release: Callable[[], None], current: Callable[[], bool],
              done: Callable[[int | None], None]) -> None:
        """Begin every step the node's bitConfigNdState does not skip, each SDO request
        waiting ``timeout`` seconds for its answer, with the node's SDO channel taken:
        ``release`` gives it back, once, when the sequence ends (``stop`` too, for a start
        that failed unforeseen). ``done`` gets None when all steps
        succeeded, else the Err_Event the seed gives the failure, from the thread of the
        last answer (or time-out); never when ``current`` turned False (a newer boot-up of
        the node replaced this one), which the sequence asks before each step."""
        self._sdo_length_error = False
        self._run = _Run(bus, channels, timeout, release, current, done,
                         self._steps(self.params.bitConfigNdState, reset_sent))
        self._advance(None)

    def _advance(self, answer: bytes | bool | None, error: SdoError | None = None) -> None:
        """Give the sequence the answer to its last step (or throw ``error`` in) and start
        the next step; a step that needs no wait (a boot-up message already there) is
        answered in the same loop."""
        run = self._run
        assert run is not None
        while True:
            if not run.current():
                run.end()
                return
            try:
                step = run.steps.throw(error) if error is not None else run.steps.send(answer)
            except StopIteration:
                self._end(run, None)
                return
            except BootFailure as failure:
                self._end(run, failure.event)
                return
            except SdoError as exc:
                self._end(run, self._failure(exc))
                return
            error = None
            if isinstance(step, BootUp):
                if self._booted:
                    answer = True
                    continue
                timer = _GraceTimer(step.timeout, self._grace_over)
                with self._lock:
                    self._pending = timer
                run.channels.watch(timer)
                if self._booted:  # came between the look and the timer
                    self.booted_up(None)
                return
            token = object()
            transfer = HostSdoTransfer(run.bus, self.address, step.index, step.subindex,
                                       step.value, run.timeout,
                                       functools.partial(self._answered, token))
            with self._lock:
                self._pending = token
            run.channels.start_host(transfer)
            return

    @staticmethod
    def _end(run: _Run, event: int | None) -> None:
        """The channel back first: the handler may start the node's next boot-up at once."""
        run.end()
        run.done(event)

    def stop(self) -> None:
        """The start failed unforeseen: give the channel back if the sequence has not."""
        if self._run is not None:
            self._run.end()

    def _grace_over(self, timer: _GraceTimer) -> None:
        with self._lock:
            if self._pending is not timer:
                return
            self._pending = None
        self._advance(False)

    def _answered(self, token: object, result: SdoResult) -> None:
        """An SDO step's end, in the bus thread (or the master's, at its time-out): the
        first of the two, if both come (``token`` is the step's)."""
        with self._lock:
            if self._pending is not token:
                return
            self._pending = None
        if result.failed:
            self._advance(None, UnknownSdoResponse(result.failed))
        elif result.timed_out:
            self._advance(None, SdoCommunicationError("No SDO response received"))
        elif result.abort is not None:
            self._advance(None, SdoAbortedError(result.abort))
        else:
            self._advance(result.data)

    def _failure(self, exc: SdoError) -> int:
        """The Err_Event of an SDO step the sequence did not handle itself."""
        if isinstance(exc, SdoAbortedError):
            log.info("node %d: configuration aborted 0x%08X", self.address, exc.code)
            self.diag.status |= NodeStatus.PRM_FAULT
            return self._responded(NodeEvent.NO_RESPONSE)
        if isinstance(exc, UnknownSdoResponse):
            log.info("node %d: unknown configuration answer: %s", self.address, exc)
            return self._responded(NodeEvent.UNKNOWN_SDO_RESPONSE)
        if self._sdo_length_error:
            # The node did answer, with a frame the controller kept from the client.
            log.info("node %d: configuration answers of a length other than 8", self.address)
            return self._responded(NodeEvent.SDO_LENGTH)
        log.info("node %d: no configuration answer: %s", self.address, exc)
        return self._responded(NodeEvent.NO_RESPONSE, answered=False)

    def _responded(self, event: int, answered: bool = True) -> int:
        """No_Response ("node not responding", seed 5.2.7 Nodestatus_1) as this boot-up's
        failure ``event`` found the node: set when it failed for the node's silence, cleared
        when the node answered, however wrongly (an abort, 35, 36, 37, 38). [ours] The seed
        does not say when the bit clears; it says whether the node responds, so the latest
        attempt decides. Before, a silent attempt's bit stayed through a later one the node
        answered wrongly, and Nd_diag said both "did not answer" and "answered wrongly"."""
        if answered:
            self.diag.status &= ~NodeStatus.NO_RESPONSE
        else:
            self.diag.status |= NodeStatus.NO_RESPONSE
        return event

    def _steps(self, skip: int, reset_sent: bool) -> Steps:
        # ``.value``: an IntFlag operand makes each test build a flag object (3 us each,
        # some 10 a node; issue 22).
        params = self.params
        link = self.link
        if link.closing:
            raise BootFailure(NodeEvent.NO_RESPONSE)
        if reset_sent or not skip & ConfigNdState.RESET.value:
            if not reset_sent:
                self._booted = False
                self._reset_at = time.time()
                link.send_nmt(NMT_RESET, self.address)
            deadline = time.monotonic() + BOOTUP_TIMEOUT
            if not (yield BootUp(RESET_GRACE)):
                yield from self._identify(deadline)
        if not skip & ConfigNdState.DEVICE.value:
            raw = yield Sdo(0x1000, 0)
            assert isinstance(raw, bytes)
            if len(raw) < 4:
                raise BootFailure(self._responded(NodeEvent.UNKNOWN_SDO_RESPONSE))
            device_type = int.from_bytes(raw[:4], "little")
            self.diag.profile = device_type & 0xFFFF
            self.diag.add_info = device_type >> 16
            # [ours] a configured 0 means "any": a host may not know one of the two.
            if params.usDevProfNum and params.usDevProfNum != self.diag.profile:
                self.diag.status |= NodeStatus.PRM_FAULT
                raise BootFailure(self._responded(NodeEvent.PROFILE_MISMATCH))
            if params.usAddTypeInfo and params.usAddTypeInfo != self.diag.add_info:
                self.diag.status |= NodeStatus.PRM_FAULT
                raise BootFailure(self._responded(NodeEvent.DEVICE_TYPE_MISMATCH))
        control = self._control
        if not skip & ConfigNdState.GUARD.value:
            if control.heartbeat:
                if control.guard_time:
                    # [ours] the node produces at half the master's consumer time.
                    yield from self._write_producer_time(
                        struct.pack("<H", max(1, control.guard_time // 2)))
            else:
                if control.guard_time:
                    # CiA 301: a node that produces heartbeats does not answer guarding;
                    # switch its producer off (a node without 1017h may refuse: fine).
                    with contextlib.suppress(SdoAbortedError):
                        yield Sdo(HEARTBEAT_PRODUCER, 0, b"\0\0")
                yield from self._write_guarding(0x100C, struct.pack("<H", control.guard_time))
                yield from self._write_guarding(
                    0x100D, struct.pack("<B", control.life_time_factor))
                yield from self._write_cob_id(0x100E, params.usCobIDGuard,
                                              ERROR_CONTROL_BASE + self.address)
        if not skip & ConfigNdState.SYNC.value:
            yield from self._write_cob_id(0x1005, link.sync_cob_id, COB_ID_SYNC)
        if not skip & ConfigNdState.EMCY.value:
            yield from self._write_cob_id(0x1014, params.usCobIDEmcy, EMCY_BASE + self.address)
        if not skip & ConfigNdState.SDO.value:
            for entry in params.atSdoCfgData:
                value = bytes(entry.abSdoValue[: entry.bLength])
                if (entry.usIndex, entry.bSubindex) == (HEARTBEAT_PRODUCER, 0):
                    if control.guard_time and not control.heartbeat:
                        # [ours] guarded: the GUARD step switched its heartbeat off, and a
                        # node that produced one again would answer no guarding (CiA 301).
                        log.info("node %d: SDO list's 1017h left out: the node is guarded",
                                 self.address)
                        continue
                    yield from self._write_producer_time(value)
                else:
                    yield Sdo(entry.usIndex, entry.bSubindex, value)
        if (not skip & ConfigNdState.START.value and not link.global_start
                and not link.nodes_stopped):
            link.send_nmt(NMT_START, self.address)

    def _identify(self, deadline: float) -> Steps:
        """A reset node that sent no boot-up message: read 1000h until it answers.

        The seed's card does not react to boot-up events (appendix: "Bootup Protocol, no
        reaction on Bootup Events of a Node"); its boot-up is "simple, reading object 1000H".
        So a node of CiA 301 before 4.0, which sends none, boots as well; a boot-up message
        only spares the wait. Only a time-out is tried again: no answer within
        ``BOOTUP_TIMEOUT`` of the reset is 34 with No_Response. A node that answered, in a
        frame of the wrong length (38) or one the client cannot take (37), is judged at once
        as in any other step (``_failure``); before, it too was 34 with No_Response after
        3 s, and a node answering 37 at once was asked again and again for those 3 s.
        """
        while True:
            if self.link.closing:
                raise BootFailure(NodeEvent.NO_RESPONSE)
            try:
                yield Sdo(0x1000, 0)
                return
            except UnknownSdoResponse:
                raise
            except SdoCommunicationError:
                if self._sdo_length_error or time.monotonic() >= deadline:
                    raise

    def _write_producer_time(self, value: bytes) -> Steps:
        """1017h, the node's producer heartbeat time: from the GUARD step or the SDO list.

        [ours] The card only consumes heartbeats (seed 5.2.5.1.1: with HRTBT, usGuardTime
        is the time "the DEVICE will wait as Consumer"); what rate the node produces at is
        the node's. So for a node whose heartbeat the card consumes, a refused write of 1017h
        is no configuration failure, wherever the write comes from: the node produces at its
        own rate, and supervision judges that (too slow, or none at all, is 30). For any other
        node, a 1017h entry of the SDO list is the host's like every other: refused, 34 with
        Prm_Fault.
        """
        try:
            yield Sdo(HEARTBEAT_PRODUCER, 0, value)
        except SdoAbortedError as exc:
            if not (self._control.heartbeat and self._control.guard_time):
                raise
            log.info("node %d: 1017h refused (0x%08X); it produces at its own rate",
                     self.address, exc.code)

    def _write_guarding(self, index: int, value: bytes) -> Steps:
        """100Ch (guard time) or 100Dh (life time factor), written by the GUARD step.

        [ours] With a guard time of 0 the node is not guarded at all, and the write only
        switches its life guarding off. CiA 301 lets a node that produces heartbeats do
        without both objects (a CANopenNode device has neither): a refusal of that write
        is no configuration failure, since a node without them guards nothing. With a guard
        time, a refusal fails the configuration (34, Prm_Fault): the card would guard a
        node that does not answer.
        """
        try:
            yield Sdo(index, 0, value)
        except SdoAbortedError as exc:
            if self._control.guard_time:
                raise
            log.info("node %d: %04Xh refused (0x%08X); it is not guarded",
                     self.address, index, exc.code)

    def _write_cob_id(self, index: int, cob_id: int, default: int) -> Steps:
        """A COB-ID the boot-up writes: 100Eh (usCobIDGuard), 1005h (the SYNC COB-ID), 1014h
        (usCobIDEmcy); seed 4.2 and 5.2.5.1.1: written "into the node object directory during
        its startup".

        [ours] The seed does not say what a refusal means. CiA 301 lets a node do without
        these objects (100Eh before 4.0 only, 1014h only with EMCY, 1005h only with SYNC) or
        keep them read-only, and such a node uses the predefined connection set's identifier:
        so it may refuse the write of that default (700h + node-ID, 80h, 80h + node-ID),
        which it uses anyway. Any other value it must take, or its configuration fails (34,
        Prm_Fault): the card would send or expect frames the node does not.
        """
        try:
            yield Sdo(index, 0, struct.pack("<I", cob_id))
        except SdoAbortedError as exc:
            if cob_id != default:
                raise
            log.info("node %d: %04Xh refused (0x%08X); it uses the default %03Xh",
                     self.address, index, exc.code, default)

    def _on_sdo_response(self, msg: can.Message) -> None:
        """Notes a response of the wrong length; the SDO client never sees it."""
        if not msg.is_remote_frame and len(msg.data) != SDO_FRAME_LENGTH:
            log.info("node %d: SDO response of %d bytes", self.address, len(msg.data))
            self._sdo_length_error = True
