"""The card's CAN controller: a python-can bus, its counters, its trace.

Every frame the master sends goes through ``CanBus.send``, so the Task2State
counters and the optional trace see all of them, including the ones canopen's
SDO client sends. The exception is a SYNC from a timer outside the interpreter
(``send_periodic``): it comes back through the receive path into the trace,
and a controller that fails to send it reports that in error frames. Received
frames are dispatched by identifier to the services that subscribed, and fed to
canopen's network for its SDO clients.

The receive thread (``_Receiver``) is the controller's own, not python-can's
``Notifier``: the Notifier returns from ``recv`` every 100 ms to see whether it
should stop, ten wake-ups a second of a card with nothing to do. This one blocks
until a frame comes, and power-off wakes it (issue 22). It also keeps deadlines that
only the frames it takes move later (``Deadlines``: the heartbeat consumers'): its wait
ends at the earliest, and ``on_deadline`` tells the master when one came.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import functools
import json
import logging
import math
import os
import queue
import select
import socket
import subprocess
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import can
import canopen
from can.interfaces.socketcan import constants as socketcan_constants
from can.interfaces.socketcan.socketcan import build_can_frame, dissect_can_frame

from dpm._quicklock import Lock as QuickLock
from dpm.cia301 import SDO_REQUEST_BASE, SDO_RESPONSE_BASE
from firmware.can.tap import TapPublisher
from firmware.errors import BusSetupError
from firmware.frames import (
    CAN_ERR_BUSOFF,
    CAN_ERR_CRTL,
    CAN_ERR_CRTL_ACTIVE,
    CAN_ERR_CRTL_LIMITS,
    CAN_ERR_CRTL_RX_WARNING,
    CAN_ERR_CRTL_TX_WARNING,
    CAN_ERR_RESTARTED,
    SDO_FRAME_LENGTH,
)
from firmware.inline import CopyingVirtualBus, InlineQueue, new_message

log = logging.getLogger(__name__)

INTERFACE_ERRORS = (can.CanError, OSError, ValueError, ImportError, NotImplementedError,
                    TypeError)
"""What python-can raises when an interface or channel cannot be opened (TypeError: an
option, ``--bus-option``, that the interface's class does not take)."""

SEND_TIMEOUT = 0.020
"""Seed 4.3: each CAN message is supervised to be sent within 20 ms."""
FrameCallback = Callable[[can.Message], None]
REOPEN_S = 1.0
"""[ours] How often a controller whose transport failed tries to open it again."""

HIDDEN_CLOSE_INTERFACES = ("socketcand",)
"""Bridge clients whose ``recv`` hides a closed connection: python-can's socketcand client
reads nothing from a connection its server closed and returns no frame, again and again,
without raising; only a later ``send`` fails. The controller looks at the connection
itself (``check_link``)."""
LINK_CHECK_S = 0.1
"""[ours] How often the card looks at such a connection while nothing fails: a link lost
while the card sends nothing is a bus-off within this."""

TCP_BRIDGE_INTERFACES = ("socketcand", "remote")
"""Bridge clients on one TCP connection (python-can's socketcand client, python-can-remote's
websocket), on which the card sets short keep-alive probes (``keep_alive``)."""
KEEPALIVE_IDLE_S = 2
"""[ours] A bridge's connection that carried nothing for this long is probed (TCP
keep-alive; the system's default waits two hours)."""
KEEPALIVE_INTERVAL_S = 1
"""[ours] The time between two unanswered keep-alive probes."""
KEEPALIVE_PROBES = 3
"""[ours] Unanswered probes after which the system ends the connection."""
LINK_DEAD_S = KEEPALIVE_IDLE_S + KEEPALIVE_INTERVAL_S * KEEPALIVE_PROBES
"""[ours] How long a bridge's peer may stay silent before the system ends the connection and
the card reports a bus-off: a pulled cable or a dead router, which close nothing. Also the
time the card's frames may wait unacknowledged (TCP_USER_TIMEOUT): keep-alive probes go only
over a connection with nothing to send, and a card that sends PDOs, SYNC or its heartbeat
seldom has nothing; without it the system would retransmit for many minutes
(net.ipv4.tcp_retries2)."""

NO_REMOTE_FRAME_INTERFACES = ("socketcand",)
"""Interfaces that cannot send a remote frame: socketcand's ``< send >`` has no RTR flag, and
python-can's client writes a remote frame as data it does not have (the daemon drops that
line as a syntax error, or, for a length of 0, puts a data frame on the bus). The card sends
none there and counts each in Msg_Time_Out [ours]: guarding and RTR-requested PDOs fail
visibly, not silently."""

PERIODIC_OUTSIDE_INTERFACES = ("socketcan", "shm")
"""Interfaces whose ``send_periodic`` keeps time outside this interpreter: SocketCAN's
broadcast manager in the kernel, ``shm``'s timer process. Elsewhere it is a thread."""
ECHOING_INTERFACES = ("udp_multicast",)
"""Transports that hand a sender its own frames back; the controller drops them."""
FIXED_RATE_INTERFACES = ("virtual", "shm", "udp_multicast", "socketcan")
"""Interfaces whose bit rate the card cannot set: a SocketCAN link's is the kernel's (``ip
link set can0 type can bitrate N``, as root), an ``shm`` channel's its first station's, and
``virtual`` and ``udp_multicast`` have none. Where the link's rate is known, the card
compares its Baud_rate with it (``link_bitrate``)."""
IP_TIMEOUT_S = 2.0
"""How long reading a SocketCAN link's rate from ``ip`` may take; a look at the rate waits
for a lookup under way as long, and more for the start of ``ip`` itself (``LinkRate``)."""
SELECTABLE_INTERFACES = ("socketcan", "udp_multicast")
"""Interfaces whose ``fileno`` is readable exactly while a frame waits (one frame per
datagram, nothing buffered in Python): the receive thread waits on it with ``select``,
beside a pipe that its ``stop`` writes."""
RECV_IDLE_S = 1.0
"""How long the receive thread waits in ``recv`` on ``virtual`` and ``shm``, whose waits its
``stop`` ends at once: a net for a wake-up frame that a software filter (``can_filters``)
dropped. An idle controller's thread wakes this often (it woke every 100 ms with
python-can's ``Notifier``)."""
RECV_POLL_S = 0.1
"""How long the receive thread waits in ``recv`` on an interface it has no other way to wake
(a bridge's client, a vendor's driver): python-can's ``Notifier`` waited as long, and the
card's power-off waits at most this for the thread."""
LINGER_S = 0.001
"""[ours] While boot-ups are under way (``CanBus.lingering``), how long the receive thread
that found no frame waits before it looks once more, unseen by the senders, before it sleeps
until one rings it: the answers of many nodes' boot steps that come meanwhile are taken in
one wake-up (each about 150 us of CPU) and their next requests sent together, at most this
much later (issue 22). Only while frames come close together (``DENSE_S``): a frame
alone would cost the look's wake-up on top of its own. Not on a ``virtual`` bus whose senders
dispatch a frame that finds the thread idle themselves (``InlineQueue``)."""
DENSE_S = 0.002
"""[ours] Frames stamped less than this apart come close together (``LINGER_S``)."""
TAKE_RECEIVED_MAX = 4096
"""[ours] The most frames the receive thread takes at once before the master judges a late
node (``_Receiver.take_then``): a second and more of a busy 1 Mbit/s bus."""
RECEIVER_JOIN_S = 5.0
"""How long ``_Receiver.stop`` waits for the thread and for a frame a sender's thread is
handling (python-can's ``Notifier.stop``'s default); a frame handler that takes longer is
left to end on its own."""


def bitrate_of_link(details: object) -> int | None:
    """``bittiming.bitrate`` of ``ip -details -json link show dev X``'s answer.

    The kernel reports a CAN link's bit timing over netlink (``IFLA_CAN_BITTIMING``) and
    ``ip`` prints it under ``linkinfo.info_data.bittiming``. None for a link without bit
    timing (``vcan``, whose info_kind is "vcan") or an answer of another shape.
    """
    try:
        rate = details[0]["linkinfo"]["info_data"]["bittiming"]["bitrate"]  # type: ignore[index]
    except (KeyError, IndexError, TypeError):
        return None
    return rate if isinstance(rate, int) and rate > 0 else None


def stream_of(bus: can.BusABC) -> socket.socket | None:
    """The TCP connection of a bridge client: the one TCP socket among the bus object's
    attributes (python-can's socketcand client holds it in a private one, python-can-remote
    in ``socket``, so it is found by its type, not by a name that may change); None when
    there is not exactly one."""
    found = [value for value in vars(bus).values()
             if isinstance(value, socket.socket) and value.type == socket.SOCK_STREAM
             and value.family in (socket.AF_INET, socket.AF_INET6)]
    return found[0] if len(found) == 1 else None


def keep_alive(stream: socket.socket) -> None:
    """Probe a bridge's TCP connection so that a silent peer ends it within ``LINK_DEAD_S``.

    A peer that goes without a word (a cable pulled, a router gone, the remote machine's
    power cut) sends no FIN and no RST: the connection stays open, the card's frames go into
    it unanswered, and the host sees only the nodes' lost heartbeats until TCP gives up. With
    these options the system ends the connection itself; the client's next ``recv`` (or
    ``check_link``'s look) fails with ETIMEDOUT and the card reports the bus-off and reopens,
    as for a closed connection. An option the system refuses leaves the link working, only
    without the bound: one log line says so."""
    try:
        stream.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        stream.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE, KEEPALIVE_IDLE_S)
        stream.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL, KEEPALIVE_INTERVAL_S)
        stream.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT, KEEPALIVE_PROBES)
        stream.setsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT, LINK_DEAD_S * 1000)
    except OSError as exc:
        log.warning("no TCP keep-alive on the bridge's connection (%s): a link cut without a "
                    "closed connection shows only as lost heartbeats until TCP gives up", exc)


def stream_failure(stream: socket.socket) -> Exception | None:
    """Why a connection is gone, without taking a byte from it: its server closed it (a
    peek reads nothing) or the system reports an error (reset, timed out); None while it
    is up, whether or not a frame waits."""
    try:
        if stream.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT):
            return None
    except BlockingIOError:
        return None
    except OSError as exc:
        return exc
    return can.CanOperationError("the server closed the connection")


def socketcan_bitrate(channel: str) -> int | None:
    """The rate the kernel runs SocketCAN link ``channel`` at; None where it reports none.

    Read through iproute2's ``ip -json`` rather than a netlink library: one well-kept
    program every SocketCAN machine has, for one number. No ``ip``, or an ``ip`` that
    fails, is "unknown", never an error: the card then has nothing to compare.
    """
    try:
        done = subprocess.run(["ip", "-details", "-json", "link", "show", "dev", channel],
                              capture_output=True, text=True, timeout=IP_TIMEOUT_S, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if done.returncode != 0:
        return None
    try:
        return bitrate_of_link(json.loads(done.stdout))
    except ValueError:
        return None


class LinkRate:
    """A SocketCAN link's rate, read once per opening of the controller, in a thread.

    ``ip`` takes about a second inside User-Mode Linux, and the looks at the rate came from
    the device loop: a bus parameter download looked twice (vcan) to three times (a CAN
    link) and the card's facts once more, and the loop answered nothing meanwhile, not even
    COM_Shared_Memory. The kernel changes a CAN link's rate only while the link is down,
    which the card meets as a failed transport and opens anew (``CanBus.on_error``), with
    a new look. [ours] A rate changed while the card neither sends nor reopens shows at the
    card's next start or reopening, not at the next bus parameter set.
    """

    def __init__(self, channel: str) -> None:
        self._rate: int | None = None
        self._known = threading.Event()
        threading.Thread(target=self._look, args=(channel,), name="can-link-rate",
                         daemon=True).start()

    def _look(self, channel: str) -> None:
        try:
            self._rate = socketcan_bitrate(channel)
        finally:
            self._known.set()

    def get(self) -> int | None:
        """The rate; only a look right after the opening waits, for the lookup under way
        (at most ``IP_TIMEOUT_S`` and the start of ``ip``; None: unknown)."""
        self._known.wait(2 * IP_TIMEOUT_S)
        return self._rate


CAN_ERR_CRTL_WARNINGS = CAN_ERR_CRTL_RX_WARNING | CAN_ERR_CRTL_TX_WARNING


class ErrorEscalation:
    """Which error frames are a new overstep of the controller's error limits.

    Seed 4.3: Bus_Error_Cnt is the "number of detected bus error limit oversteps". A
    controller whose error counters climb reports each limit it passes in an error frame of
    its own (SocketCAN: warning, then error-passive), but both belong to one overstep: the
    error-passive report right after a warning report is no new one. Every warning report is:
    the counters were below the limit before it, whether or not the controller said so (not
    every driver reports the return to error-active). An overstep ends when the controller
    reports itself error-active again, goes bus-off (Bus_Off_Cnt counts that) or restarts.
    """

    def __init__(self) -> None:
        self._beyond = False
        """Whether the counters are past a limit since the controller last said they were not."""

    def update(self, msg: can.Message) -> bool:
        """Feed every error frame in order; True for one that is a new overstep."""
        error_class = msg.arbitration_id
        status = msg.data[1] if len(msg.data) > 1 else 0
        if error_class & (CAN_ERR_BUSOFF | CAN_ERR_RESTARTED) or (
                error_class & CAN_ERR_CRTL and status & CAN_ERR_CRTL_ACTIVE):
            self._beyond = False
            return False
        if error_class & CAN_ERR_CRTL and status & CAN_ERR_CRTL_LIMITS:
            new = bool(status & CAN_ERR_CRTL_WARNINGS) or not self._beyond
            self._beyond = True
            return new
        return False


class _MasterNetwork(canopen.Network):
    """canopen's network whose sends go through the card's controller."""

    def __init__(self, owner: CanBus) -> None:
        super().__init__(owner.bus)
        self._owner = owner

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._owner.send(can_id, bytes(data), remote=remote)


@dataclass
class BusConfig:
    """How the card reaches its CAN bus (command line of ``cifemu firmware``)."""

    interface: str = "virtual"
    channel: str = "cifemu"
    bitrate: int | None = None
    trace: Path | None = None
    tap: bytes | None = None
    """The socket of the frame tap (``dpm.tap``), beside the image [ours]."""
    exit_on_error: bool = False
    """A controller that cannot be opened ends the firmware, instead of the seed's card
    staying up with FAT set (``cifemu firmware --exit-on-bus-error``)."""
    options: dict[str, Any] = field(default_factory=dict)
    """Keyword arguments for ``can.Bus`` beyond interface, channel and bit rate
    (``--bus-option``, ``--bus-config``, the network description's ``[bus] options``): a
    socketcand host and port, ``receive_own_messages`` ... Kept with the controller, which
    opens the interface again with them (a new Baud_rate, a lost link)."""


class Deadlines(Protocol):
    """Deadlines that the frames the receive thread takes only move later
    (``firmware.can.supervision.HeartbeatWatch``)."""

    def due(self) -> float:
        """The earliest (monotonic seconds; inf: none)."""

    def take(self, now: float) -> bool:
        """Drop those that came by ``now``; True when one did."""


class _NoDeadlines:
    """The receive thread's deadlines before anyone gives it some: none."""

    def due(self) -> float:
        return math.inf

    def take(self, now: float) -> bool:
        del now
        return False


class _Receiver:
    """The controller's receive thread: waits until a frame comes or ``stop`` wakes it.

    How it waits depends on what can wake the interface's ``recv``:

    - ``SELECTABLE_INTERFACES``: ``select`` on the bus's descriptor and on a pipe that
      ``stop`` writes, without a time-out, then ``recv(0)``;
    - ``virtual`` and ``shm``: ``recv(RECV_IDLE_S)``; ``stop`` hands the station a frame of
      its own (``VirtualBus.queue``, ``ShmBus.loop_back``), which ends the wait and which
      the thread drops. (A ``recv`` that only returned None would not do: python-can's
      ``recv`` waits on until its time-out.) On ``virtual``, a frame that finds the
      thread idle is dispatched by its sender's thread instead (``InlineQueue``);
    - any other: ``recv(RECV_POLL_S)``, as python-can's ``Notifier``.

    While boot-ups are under way and frames come close together (``LINGER_S``), a thread
    that finds no frame looks once more a moment later before it waits to be rung.

    Every wait ends by the earliest of the controller's ``deadlines`` too; once one came
    (frames may keep the thread awake past it), the controller's ``on_deadline`` is called.

    A frame that arrives while it stops is dropped, as the Notifier drops the frames after
    its last ``recv``. An exception from the interface or a frame handler goes to the
    controller's ``on_error``, as the Notifier's did; then the thread ends: ``on_error``
    opens the interface again with a new receiver, or the controller is closing.
    """

    def __init__(self, bus: can.BusABC, interface: str, listener: CanBus) -> None:
        self._bus = bus
        self._listener = listener
        self._stopping = False
        self._wake_frame = can.Message(arbitration_id=0, is_extended_id=False)
        """What ``stop`` hands a ``virtual`` or ``shm`` station (known by identity)."""
        self._fd = -1
        self._wake_w = -1
        """The pipe's end that ``stop`` writes (``SELECTABLE_INTERFACES``)."""
        self._hand_over: Callable[[can.Message], None] | None = None
        self._dispatching = QuickLock()
        """Held while a frame is dispatched, by this thread or by a sender (``InlineQueue``):
        the frame handlers never run twice at once. Taken per frame received: a lock that
        reads no clock when free (``dpm._quicklock``, issue 22)."""
        self._inline: InlineQueue | None = None
        self._last_stamp = 0.0
        self._dense = False
        """The last frame came less than ``DENSE_S`` after the one before (``_linger``)."""
        self._after_taking: Callable[[], None] | None = None
        """Set by ``take_then``: called by this thread once the frames received are taken."""
        self._take: Callable[[], can.Message | None] = functools.partial(bus.recv, 0)
        """Takes the frame ``select`` found: ``recv(0)``, or on SocketCAN without software
        filters the frame read straight from the socket (``socketcan_take``)."""
        if interface in SELECTABLE_INTERFACES:
            with contextlib.suppress(NotImplementedError, OSError):
                self._fd = bus.fileno()
            self._take = socketcan_take(bus) or self._take
        if self._fd >= 0:
            self._wake_r, self._wake_w = os.pipe2(os.O_CLOEXEC | os.O_NONBLOCK)
            # Closed with the object, which the thread holds while it runs: never a
            # descriptor that the thread may still select on.
            weakref.finalize(self, _close_pipe, self._wake_r, self._wake_w)
        elif interface == "virtual" and isinstance(getattr(bus, "queue", None), queue.Queue):
            if not getattr(bus, "receive_own_messages", True):
                self._inline = InlineQueue.install(bus.queue, self)  # type: ignore[attr-defined]
            self._hand_over = bus.queue.put_nowait  # type: ignore[attr-defined]
        elif callable(getattr(bus, "loop_back", None)):
            self._hand_over = bus.loop_back  # type: ignore[attr-defined]
        self._timeout = RECV_IDLE_S if self._hand_over is not None else RECV_POLL_S
        self._thread = threading.Thread(target=self._run, name="can-receive", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        listener = self._listener
        try:
            while not self._stopping:
                due = listener.deadlines.due()
                msg = self._next(due)
                if msg is not None:
                    stamp = msg.timestamp
                    self._dense = stamp - self._last_stamp < DENSE_S
                    self._last_stamp = stamp
                    self._dispatch(msg)
                callback = self._after_taking
                if callback is not None:
                    self._after_taking = None
                    self._take_received()
                    callback()
                # no clock read per frame while there are no deadlines (a system call each
                # under User-Mode Linux, issue 22)
                if (due < math.inf and due <= (now := time.monotonic())
                        and listener.deadlines.take(now)):
                    listener.on_deadline()
        except Exception as exc:  # the transport failed, or a frame handler did
            if not self._stopping:
                listener.on_error(exc)

    def _dispatch(self, msg: can.Message) -> None:
        try:
            if msg is not self._wake_frame:
                with self._dispatching:
                    if not self._stopping:
                        self._listener.on_message_received(msg)
        finally:
            if self._inline is not None:
                self._inline.dispatched()

    def _take_received(self) -> None:
        """Dispatch the frames received by now, without waiting for more (``take_then``);
        at most ``TAKE_RECEIVED_MAX``, so that a bus faster than the card cannot hold it."""
        for _ in range(TAKE_RECEIVED_MAX):
            if self._stopping or (
                    self._fd >= 0 and not select.select((self._fd,), (), (), 0)[0]):
                return
            msg = self._take()
            if msg is None:
                return
            self._dispatch(msg)

    def take_then(self, callback: Callable[[], None]) -> None:
        """Have this thread dispatch every frame received by now, then call ``callback``
        (from any thread; ``Master._verdict_waits``)."""
        self._after_taking = callback
        if self._wake_w >= 0:
            with contextlib.suppress(BlockingIOError):  # full: the thread is awake anyway
                os.write(self._wake_w, b"t")
        elif self._hand_over is not None:
            with contextlib.suppress(queue.Full):  # a full queue wakes the thread anyway
                self._hand_over(self._wake_frame)

    def try_dispatch(self, msg: can.Message) -> bool:
        """Dispatch ``msg`` in the calling thread, a sender's, unless a frame is being
        dispatched (``InlineQueue.put`` has seen that none waits). False: not done.

        The senders are other stations of this process: a simulated node's thread, or the
        card's own device loop when a simulated node answered its host SDO request there
        (``firmware.inline.answered_here``). The card's frame handlers take only the card's
        own locks, never a sender's: a node's thread holding its network's lock waits for
        no card thread, and the device loop's ``_turn`` is only ever tried
        (``Device.hand_over``)."""
        if msg is self._wake_frame or not self._dispatching.acquire(blocking=False):
            return False
        try:
            if not self._stopping:
                self._listener.on_message_received(msg)
        except Exception as exc:  # as in the thread: the controller's failure, not the sender's
            if not self._stopping:
                self._listener.on_error(exc)
        finally:
            self._dispatching.release()
        return True

    def _next(self, due: float) -> can.Message | None:
        """The next frame, or None when the wait ended without one (``stop``, a time-out,
        ``due``)."""
        if self._dense and self._inline is None and self._listener.lingering():
            msg = self._linger(due)
            if msg is not None:
                return msg
        if self._fd >= 0:
            wait = None if math.isinf(due) else max(0.0, due - time.monotonic())
            ready = select.select((self._fd, self._wake_r), (), (), wait)[0]
            if self._wake_r in ready and not self._stopping:  # take_then's: read, or spin
                with contextlib.suppress(BlockingIOError):
                    os.read(self._wake_r, 64)
            return self._take() if self._fd in ready else None
        if math.isinf(due):
            return self._bus.recv(self._timeout)
        return self._bus.recv(max(0.0, min(self._timeout, due - time.monotonic())))

    def _linger(self, due: float) -> can.Message | None:
        """A frame received by now; else, ``LINGER_S`` (or until ``due``) later, one received
        by then (None: none came, the thread waits to be rung). The thread sleeps unmarked,
        so no sender rings it: the frames that come meanwhile cost one wake-up."""
        msg = self._take_now()
        if msg is not None or self._stopping:
            return msg
        rest = LINGER_S if math.isinf(due) else min(LINGER_S, due - time.monotonic())
        if rest > 0:
            time.sleep(rest)
        return self._take_now()

    def _take_now(self) -> can.Message | None:
        """A frame received by now, without waiting."""
        if self._fd >= 0:
            return self._take() if select.select((self._fd,), (), (), 0)[0] else None
        return self._bus.recv(0)

    def stop(self) -> None:
        """End the thread: wake it, and wait for it and for a frame that a sender's thread is
        handling (``try_dispatch``), unless called from the thread itself (by a frame handler
        or ``on_error``). Once this returns no frame handler runs, and none starts.

        A sender's thread is no thread of the controller's, and nothing else waits for it:
        with ``--simulate`` a simulated node's thread that handled its answer to a boot step
        went on while the card powered off, and sent the next request on the closed bus and
        counted its Msg_Time_Out in the unmapped image ("frame handler failed on 0x581",
        ValueError: mmap closed). Both waits end within ``RECEIVER_JOIN_S`` together: a
        handler that takes longer is left to end on its own, as before."""
        if self._stopping:
            return
        self._stopping = True
        if self._wake_w >= 0:
            os.write(self._wake_w, b"s")  # the pipe has room: take_then's bytes are read
        if self._hand_over is not None:
            with contextlib.suppress(queue.Full):  # a full queue wakes the thread anyway
                self._hand_over(self._wake_frame)
        if threading.current_thread() is not self._thread:
            deadline = time.monotonic() + RECEIVER_JOIN_S
            self._thread.join(RECEIVER_JOIN_S)
            # ``try_dispatch`` looks at ``_stopping`` under this lock: a sender that took it
            # first ends its frame before this returns, one that takes it later handles none
            if self._dispatching.acquire(timeout=max(0.0, deadline - time.monotonic())):
                self._dispatching.release()


class _IoVec(ctypes.Structure):
    _fields_ = (("iov_base", ctypes.c_void_p), ("iov_len", ctypes.c_size_t))


class _MsgHdr(ctypes.Structure):
    """struct msghdr (recvmsg(2)): no name asked for."""

    _fields_ = (("msg_name", ctypes.c_void_p), ("msg_namelen", ctypes.c_uint32),
                ("msg_iov", ctypes.POINTER(_IoVec)), ("msg_iovlen", ctypes.c_size_t),
                ("msg_control", ctypes.c_void_p), ("msg_controllen", ctypes.c_size_t),
                ("msg_flags", ctypes.c_int))


class _TimestampCmsg(ctypes.Structure):
    """The one control message asked for: struct cmsghdr, then SO_TIMESTAMPNS's struct
    timespec, as the kernel lays them out on a 64-bit Linux (32 bytes)."""

    _fields_ = (("cmsg_len", ctypes.c_size_t), ("cmsg_level", ctypes.c_int),
                ("cmsg_type", ctypes.c_int), ("tv_sec", ctypes.c_int64),
                ("tv_nsec", ctypes.c_int64))


_libc_recvmsg = None


def _recvmsg() -> Any:
    """libc's recvmsg through ctypes (which releases the interpreter lock while it waits)."""
    global _libc_recvmsg
    if _libc_recvmsg is None:
        call = ctypes.CDLL(None, use_errno=True).recvmsg
        call.argtypes = (ctypes.c_int, ctypes.POINTER(_MsgHdr), ctypes.c_int)
        call.restype = ctypes.c_ssize_t
        _libc_recvmsg = call
    return _libc_recvmsg


def socketcan_take(bus: can.BusABC) -> Callable[[], can.Message | None] | None:
    """For a SocketCAN bus without software filters: a call that reads the frame waiting on
    its socket (after ``select`` said one is there) with one ``recvmsg`` that asks for no
    sender's address, as python-can's ``recv(0)`` reads it but without its ``time.time()``
    and second ``select`` with a zero time-out, and without the interface's name that
    Python's ``socket.recvmsg`` looks up for every frame (an ``ioctl(SIOCGIFNAME)``): each a
    system call of about 30 us inside User-Mode Linux, which has no vDSO (issue 22). The
    frame's time stamp is the kernel's (SO_TIMESTAMPNS, which python-can's bus asked for).
    None for any other bus (a bus on every interface, channel "", whose frames name theirs;
    a socket python-can set up otherwise; a 32-bit build): ``recv(0)`` it is."""
    sock = getattr(bus, "socket", None)
    if (not isinstance(bus, can.interfaces.socketcan.SocketcanBus) or bus.filters
            or not isinstance(sock, socket.socket) or not bus.channel
            or ctypes.sizeof(_TimestampCmsg) != 32
            or not sock.getsockopt(socket.SOL_SOCKET, socketcan_constants.SO_TIMESTAMPNS)):
        return None
    channel = bus.channel
    recvmsg = _recvmsg()
    fd = sock.fileno()
    frame = ctypes.create_string_buffer(socketcan_constants.CANFD_MTU)
    control = _TimestampCmsg()
    control_size = ctypes.sizeof(control)
    vector = _IoVec(ctypes.cast(frame, ctypes.c_void_p), len(frame))
    header = _MsgHdr(None, 0, ctypes.pointer(vector), 1,
                     ctypes.cast(ctypes.byref(control), ctypes.c_void_p), 0, 0)
    header_ref = ctypes.byref(header)
    stamped = (socket.SOL_SOCKET, socketcan_constants.SO_TIMESTAMPNS)
    c = socketcan_constants

    def take() -> can.Message | None:
        while True:  # again after a signal (EINTR), as python-can's recv does
            header.msg_controllen = control_size
            got = recvmsg(fd, header_ref, 0)
            if got >= 0:
                break
            error = ctypes.get_errno()
            if error != errno.EINTR:  # python-can's recv raises the same
                raise can.CanOperationError(f"Error receiving: {os.strerror(error)}", error)
        raw = frame.raw[:got]
        can_id, dlc, flags, data = dissect_can_frame(raw)
        stamp = (control.tv_sec + control.tv_nsec * 1e-9
                 if header.msg_controllen >= control_size
                 and (control.cmsg_level, control.cmsg_type) == stamped else time.time())
        extended = bool(can_id & c.CAN_EFF_FLAG)
        return can.Message(
            timestamp=stamp, channel=channel,
            arbitration_id=can_id & (0x1FFFFFFF if extended else 0x7FF),
            is_extended_id=extended, is_remote_frame=bool(can_id & c.CAN_RTR_FLAG),
            is_error_frame=bool(can_id & c.CAN_ERR_FLAG), is_fd=got == c.CANFD_MTU,
            is_rx=not header.msg_flags & socket.MSG_DONTROUTE,
            bitrate_switch=bool(flags & c.CANFD_BRS),
            error_state_indicator=bool(flags & c.CANFD_ESI), dlc=dlc, data=data)

    return take


def socketcan_send(bus: can.BusABC) -> Callable[[can.Message], bool] | None:
    """For a SocketCAN bus: a call that writes a frame to its socket if the socket takes it
    at once (True), else False with nothing sent, and ``send`` goes python-can's way, which
    waits up to its time-out. python-can's ``send`` reads the clock twice (``time.time()``,
    its ``select``), makes a logger's child (a lock, one more clock reading under CPython
    3.11) and calls ``select`` before the write: four clock readings and a system call more
    per frame, about 150 us inside User-Mode Linux (issue 22)."""
    sock = getattr(bus, "socket", None)
    if not isinstance(bus, can.interfaces.socketcan.SocketcanBus) or not isinstance(
            sock, socket.socket) or bus.channel == "":
        return None

    def send(msg: can.Message) -> bool:
        try:
            return sock.send(build_can_frame(msg), socket.MSG_DONTWAIT) > 0
        except (BlockingIOError, InterruptedError):
            return False
        except OSError as exc:
            if exc.errno == errno.ENOBUFS:  # the queue is full: python-can's send waits
                return False
            raise can.CanOperationError(f"Failed to transmit: {exc.strerror}",
                                        exc.errno) from exc

    return send


def _close_pipe(*fds: int) -> None:
    for fd in fds:
        os.close(fd)


class CanBus(can.Listener):
    """One CAN controller on one python-can bus."""

    def __init__(self, interface: str = "virtual", channel: str = "cifemu",
                 bitrate: int | None = None, trace: Path | None = None,
                 tap: bytes | None = None, options: Mapping[str, Any] | None = None) -> None:
        kwargs: dict[str, Any] = dict(options or {})
        self.sets_bitrate = interface not in FIXED_RATE_INTERFACES
        """Whether ``set_bitrate`` changes the controller's rate (else it compares)."""
        if bitrate is not None and (self.sets_bitrate or interface == "shm"):
            kwargs["bitrate"] = bitrate  # on shm: the channel's rate, if the card opens it first
        if interface == "shm":
            kwargs.setdefault("timer_process", True)  # see send_periodic
        self.interface = interface
        self.channel = channel
        self._link: socket.socket | None = None
        """The connection ``check_link`` watches (``HIDDEN_CLOSE_INTERFACES`` only)."""
        self._fast_send: Callable[[can.Message], bool] | None = None
        """``socketcan_send``'s call for the bus ``_open`` opened last, else None."""
        self.bus = self._open(kwargs)
        self._open_kwargs = kwargs
        self._link_rate = LinkRate(channel) if interface == "socketcan" else None
        self._bitrate = bitrate if self.sets_bitrate else None
        self.network = _MasterNetwork(self)
        # Copy-on-write: subscribing replaces a tuple, so the receive thread reads
        # them without a lock.
        self._subscribers: dict[int, tuple[FrameCallback, ...]] = {}
        self._catch_all: tuple[FrameCallback, ...] = ()
        self._dispatch: dict[int, tuple[FrameCallback, ...]] = {}
        """Per 11-bit identifier with subscribers: the catch-all callbacks, then its own, as
        one tuple made when a subscription changes, not per received frame (``_redispatch``,
        ``_dispatch_one``)."""
        self._lock = QuickLock()
        """Taken twice per host SDO transfer (``lend_sdo_responses``): no clock reading
        when free (``dpm._quicklock``, issue 22)."""
        self._trace_lock = threading.Lock()
        """The trace is written by the receive thread and by every sending thread."""
        self._echoes: deque[tuple[int, bytes, bool]] | None = (
            deque(maxlen=256) if interface in ECHOING_INTERFACES else None)
        self._rx_overflows_seen = 0
        self._lent: dict[int, FrameCallback] = {}
        """SDO response identifiers lent to a client of the card's own, kept from canopen's
        network (``lend_sdo_responses``)."""
        self.on_error_frame: Callable[[can.Message], None] = lambda msg: None
        self.on_send_timeout: Callable[[], None] = lambda: None
        self.on_link_back: Callable[[], None] = lambda: None
        """Called once a lost link is open again (``on_error``), from the reopening thread."""
        self.deadlines: Deadlines = _NoDeadlines()
        """What the receive thread keeps besides frames (see ``_Receiver``)."""
        self.lingering: Callable[[], bool] = lambda: False
        """Whether answers are due from many nodes at once (boot-ups under way): the
        receive thread then takes them in batches (``LINGER_S``)."""
        self.on_deadline: Callable[[], None] = lambda: None
        """Called from the receive thread when one of ``deadlines`` came, and from whichever
        thread finds the transport failed: no receive thread keeps them until it is back
        (``receiving``)."""
        self._trace: can.Listener | None = can.Logger(str(trace)) if trace else None
        self.record: Callable[[can.Message, bool], None] | None = None
        """A recording's frame hook (``firmware.recorder``; frame, received), set and
        cleared while the card runs: every frame the trace sees."""
        self._tap = TapPublisher(tap) if tap else None
        self._lost = False
        """The transport failed; a thread is opening it again (``on_error``). A bool, not a
        ``threading.Event``: nothing waits for it, and ``send`` reads it for every frame,
        where ``Event.is_set`` is a Python call (issue 22)."""
        self.off_bus = False
        """[ours] The fault "bus-off" (firmware/faults.py): the controller neither sends
        nor receives (``set_bus_off``)."""
        self._closed = threading.Event()
        self._refused_remote = False
        """Whether the one log line about a remote frame not sent is written."""
        self._receiver = _Receiver(self.bus, interface, self)

    # --- receiving ----------------------------------------------------------------------

    def subscribe(self, can_id: int, callback: FrameCallback) -> None:
        with self._lock:
            self._subscribers[can_id] = (*self._subscribers.get(can_id, ()), callback)
            self._dispatch_one(can_id)

    def unsubscribe(self, can_id: int, callback: FrameCallback) -> None:
        with self._lock:
            callbacks = list(self._subscribers.get(can_id, ()))
            if callback in callbacks:
                callbacks.remove(callback)
                self._subscribers[can_id] = tuple(callbacks)
                self._dispatch_one(can_id)

    def _dispatch_one(self, can_id: int) -> None:
        """Put ``can_id``'s new tuple into ``_dispatch`` (under ``_lock``), one item: the
        receive thread reads either its old tuple or its new one, never half of one.
        Making the whole table anew for each change cost a card start with 127 nodes
        (some 600 subscriptions, each undone first) a quadratic 35-80 ms of CPU (issue 22)."""
        callbacks = self._subscribers.get(can_id, ())
        if callbacks:
            self._dispatch[can_id] = self._catch_all + callbacks
        else:
            self._subscribers.pop(can_id, None)
            self._dispatch.pop(can_id, None)

    def _redispatch(self) -> None:
        """Make ``_dispatch`` anew (under ``_lock``) and swap it in whole, when the catch-all
        callbacks change every entry: the receive thread reads either the old table or the
        new one, never half of one."""
        catch_all = self._catch_all
        self._dispatch = {ident: catch_all + callbacks
                          for ident, callbacks in self._subscribers.items() if callbacks}

    def lend_sdo_responses(self, can_id: int, client: FrameCallback) -> None:
        """Give ``can_id``'s frames to ``client`` after its subscribers, and keep them from
        canopen's network, until ``take_back_sdo_responses``.

        A host SDO transfer or a boot step answers from its own client; canopen's client
        for that node is idle meanwhile (the channel lock) and would only queue every
        response, without bound, until its next request. One entry for both, not a
        subscription and a hold: those cost each transfer six Python calls and four
        tuples and sets made anew (issue 22). The channel lock lets one client at a time
        borrow a node's responses.
        """
        with self._lock:
            self._lent[can_id] = client

    def take_back_sdo_responses(self, can_id: int, client: FrameCallback) -> None:
        """``can_id``'s frames go to canopen's network again, unless another client has
        borrowed them since."""
        with self._lock:
            if self._lent.get(can_id) == client:
                del self._lent[can_id]

    def subscribe_all(self, callback: FrameCallback) -> None:
        """Every received frame (layer-2 access, transparent reception)."""
        with self._lock:
            self._catch_all = (*self._catch_all, callback)
            self._redispatch()

    def on_message_received(self, msg: can.Message) -> None:
        if self.off_bus and not msg.is_error_frame:
            return  # off the bus: the controller hears nothing
        if self._trace is not None:
            with self._trace_lock:
                self._trace.on_message_received(msg)
        record = self.record
        if record is not None:
            record(msg, True)
        if self._tap is not None:
            self._tap.publish(msg, received=True)
        if msg.is_error_frame:
            self.on_error_frame(msg)
            return
        if self._echoes is not None and self._is_echo(msg):
            return
        ident = msg.arbitration_id
        if msg.is_extended_id:
            callbacks, client = self._catch_all, None
        else:
            callbacks = self._dispatch.get(ident, self._catch_all)
            client = self._lent.get(ident)  # before the callbacks: its last answer ends the loan
        for callback in callbacks:
            try:
                callback(msg)
            except Exception:
                log.exception("frame handler failed on 0x%X", ident)
        if client is not None:
            try:
                client(msg)
            except Exception:
                log.exception("frame handler failed on 0x%X", ident)
            return
        # canopen's network serves only the SDO clients (answers on 0x581..0x5FF). A
        # response of another length never reaches them: canopen unpacks fixed offsets
        # (struct.error on a short abort) or takes a short one for data. The node
        # handler, subscribed above, reports it as Err_Event 38 when its boot-up times out.
        if (SDO_RESPONSE_BASE < ident < SDO_REQUEST_BASE and not msg.is_extended_id
                and not msg.is_remote_frame
                and len(msg.data) == SDO_FRAME_LENGTH):
            self.network.notify(ident, msg.data, msg.timestamp)

    def on_error(self, exc: Exception) -> None:
        """The transport failed under the receive or a sending thread, or ``check_link``
        found its connection closed: a bridge's link is gone (python-can-remote raises from
        ``recv`` and ``send``; python-can's socketcand client only from ``send``, its
        ``recv`` returns nothing from a closed connection). No error frame tells it.

        [ours] The host sees a bus-off (Bus_Off_Cnt, EVE): the controller is off the bus.
        The interface is opened again every ``REOPEN_S`` until it is back; then
        ``on_link_back`` (the master sends every running node's outputs again) and the
        nodes' supervision do the rest. The receive thread ends after it reports a
        failure (``_Receiver``); the reopening thread waits for it."""
        with self._lock:  # the receive thread and every sending thread may get here
            if self._lost or self._closed.is_set():
                return
            self._lost = True
        log.warning("CAN interface %s channel %s failed (%s: %s); opening it again every "
                    "%.0f s", self.interface, self.channel, type(exc).__name__, exc, REOPEN_S)
        self.on_error_frame(can.Message(is_error_frame=True, arbitration_id=CAN_ERR_BUSOFF))
        self.on_deadline()  # the receive thread ends: its deadlines go back to the master
        threading.Thread(target=self._reopen, name="can-reopen", daemon=True).start()

    def take_then(self, callback: Callable[[], None]) -> None:
        """Call ``callback`` once the receive thread has taken every frame received by now,
        at once when none runs (``receiving``; the master judges a late node after,
        ``Master._verdict_waits``)."""
        if self.receiving:
            self._receiver.take_then(callback)
        else:
            callback()

    @property
    def receiving(self) -> bool:
        """Whether a receive thread runs and keeps ``deadlines`` (not while a lost link is
        opened again, nor after ``shutdown``)."""
        return not (self._lost or self._closed.is_set())

    @property
    def watches_link(self) -> bool:
        """Whether ``check_link`` has a connection to look at on this interface."""
        return self.interface in HIDDEN_CLOSE_INTERFACES

    def check_link(self) -> None:
        """Report a bridge connection its server closed while the card sends nothing, as
        ``on_error`` reports a transport that raises (a bus-off, then reopening). For
        ``HIDDEN_CLOSE_INTERFACES``, whose ``recv`` does not tell it; the card calls this
        every ``LINK_CHECK_S``. Elsewhere it does nothing."""
        link = self._link
        if link is None or self._lost:
            return
        failure = stream_failure(link)
        if failure is not None and link is self._link:  # not a socket a reopening replaced
            self.on_error(failure)

    def _open(self, kwargs: dict[str, Any]) -> can.BusABC:
        """Open the interface; for a bridge on TCP, find its connection to probe
        (``keep_alive``) and, for one that hides a closed connection, to watch."""
        bus = can.Bus(interface=self.interface, channel=self.channel, **kwargs)
        if self.interface == "virtual":
            CopyingVirtualBus.install(bus)  # each frame sent copied without ``copy.deepcopy``
        if self.interface in TCP_BRIDGE_INTERFACES:
            stream = stream_of(bus)
            if stream is None:
                log.warning("%s: no TCP connection found; a link cut without a closed "
                            "connection shows only as lost heartbeats%s", self.interface,
                            ", a closed one only when a frame cannot be sent"
                            if self.interface in HIDDEN_CLOSE_INTERFACES else "")
            else:
                keep_alive(stream)
            if self.interface in HIDDEN_CLOSE_INTERFACES:
                self._link = stream
        self._fast_send = socketcan_send(bus)
        return bus

    def set_bus_off(self, off: bool) -> None:
        """[ours] The fault "bus-off": the controller reports bus-off and leaves the bus
        (``off``), or reports its restart and joins it again. Each report is the error
        frame a SocketCAN controller delivers (CAN_ERR_BUSOFF, CAN_ERR_RESTARTED), taken
        as received: the trace, the tap and the master's counters see it as they would a
        real one."""
        if off:
            self.on_message_received(can.Message(
                timestamp=time.time(), is_error_frame=True, arbitration_id=CAN_ERR_BUSOFF,
                channel=self.channel, dlc=8, data=bytes(8)))
            self.off_bus = True
        else:
            self.off_bus = False
            self.on_message_received(can.Message(
                timestamp=time.time(), is_error_frame=True, arbitration_id=CAN_ERR_RESTARTED,
                channel=self.channel, dlc=8, data=bytes(8)))

    def _reopen(self) -> None:
        self._receiver.stop()
        with contextlib.suppress(Exception):  # the transport is gone: closing it may fail too
            self.bus.shutdown()
        while not self._closed.wait(REOPEN_S):
            try:
                bus = self._open(self._open_kwargs)
            except Exception as exc:  # whatever the transport raises while it is away
                log.debug("CAN interface %s still away: %s", self.interface, exc)
                continue
            self.bus = bus
            if self._link_rate is not None:
                self._link_rate = LinkRate(self.channel)  # its rate may have changed meanwhile
            self._receiver = _Receiver(bus, self.interface, self)
            self._lost = False
            log.warning("CAN interface %s channel %s is back", self.interface, self.channel)
            self.on_link_back()
            return

    def _is_echo(self, msg: can.Message) -> bool:
        """A frame this controller sent itself, looped back by the transport."""
        assert self._echoes is not None
        key = (msg.arbitration_id, bytes(msg.data), msg.is_remote_frame)
        with self._lock:
            if key in self._echoes:
                self._echoes.remove(key)
                return True
        return False

    # --- sending ---------------------------------------------------------------------------

    def send(self, can_id: int, data: bytes = b"", remote: bool = False,
             extended: bool | None = None, dlc: int | None = None) -> bool:
        """Send one frame; False (and Msg_Time_Out counted) when it could not go out.

        [ours] Off the bus (``set_bus_off``) nothing goes out and nothing is counted: the
        controller is not waiting for an acknowledge, it knows it is off. A lost link not
        open again (``on_error``) counts every frame: the client it had may take one without
        a word (python-can-remote's closed websocket drops it), and the frame is lost."""
        if self.off_bus:
            return False
        if self._lost:
            self.on_send_timeout()
            return False
        if remote and self.interface in NO_REMOTE_FRAME_INTERFACES:
            if not self._refused_remote:
                self._refused_remote = True
                log.warning("%s cannot send remote frames: 0x%X and every later one not "
                            "sent (Msg_Time_Out); supervise nodes by heartbeat",
                            self.interface, can_id)
            self.on_send_timeout()
            return False
        # python-can's constructor's work, its slots set here: the call with its keywords
        # costs every frame the card sends a Python call, two per host SDO (issue 22)
        msg: can.Message = new_message(can.Message)
        msg.timestamp = time.time()
        msg.arbitration_id = can_id
        msg.is_extended_id = can_id > 0x7FF if extended is None else extended
        msg.is_remote_frame = remote
        msg.is_error_frame = False
        msg.channel = self.channel  # the trace labels sent frames as received ones
        msg.dlc = dlc if dlc is not None else len(data)
        msg.data = bytearray() if remote else bytearray(data)
        msg.is_fd = False
        msg.is_rx = False
        msg.bitrate_switch = False
        msg.error_state_indicator = False
        if self._echoes is not None:
            with self._lock:
                self._echoes.append((can_id, bytes(msg.data), remote))
        try:
            fast = self._fast_send
            if fast is None or not fast(msg):
                self.bus.send(msg, timeout=SEND_TIMEOUT)
        except can.CanError as exc:
            log.warning("frame 0x%X not sent: %s", can_id, exc)
            self.on_send_timeout()
            return False
        except Exception as exc:  # a bridge's transport gone (WebsocketClosed, OSError ...)
            self.on_error(exc)
            self.on_send_timeout()
            return False
        if self._trace is not None:
            with self._trace_lock:
                self._trace.on_message_received(msg)
        record = self.record
        if record is not None:
            record(msg, False)
        if self._tap is not None:
            self._tap.publish(msg, received=False)
        return True

    def send_periodic(self, can_id: int, period: float) -> can.broadcastmanager.CyclicSendTaskABC:
        """An empty frame every ``period`` from a timer outside this interpreter.

        Only for ``PERIODIC_OUTSIDE_INTERFACES``: a thread here would wait for the
        interpreter lock as the caller's own would. The frames do not pass
        ``send``; they come back through the receive path (and so into the trace)
        as a frame from another sender does. Raises ``BusSetupError`` on any other
        interface.
        """
        if self.interface not in PERIODIC_OUTSIDE_INTERFACES:
            raise BusSetupError(f"{self.interface} has no cyclic sending outside the interpreter")
        msg = can.Message(arbitration_id=can_id, is_extended_id=False, data=b"")
        return self.bus.send_periodic(msg, period)

    def take_rx_overflows(self) -> int:
        """Frames the interface lost since the last call (at least 1: an overflow was reported).

        SocketCAN reports an overflow without a count; the ``shm`` interface
        counts in ``rx_overflows``.
        """
        total = int(getattr(self.bus, "rx_overflows", 0))
        lost, self._rx_overflows_seen = total - self._rx_overflows_seen, total
        return max(1, lost)

    @property
    def bitrate(self) -> int | None:
        """The rate the controller runs at: the card's where it sets it, else the link's
        where that is known (``link_bitrate``); None: unknown."""
        return self._bitrate if self.sets_bitrate else self.link_bitrate()

    @property
    def takes_bitrate(self) -> bool:
        """Whether the seed's Baud_rate means something here: the controller takes it, or
        the link's rate is known, so that ``set_bitrate`` can tell a rate it does not run."""
        return self.sets_bitrate or self.link_bitrate() is not None

    def link_bitrate(self) -> int | None:
        """The rate of a link whose rate the card cannot set, where it is known.

        SocketCAN: what the kernel reported for the link when the controller opened it
        (``LinkRate``; None for ``vcan``, which has no bit timing). ``shm``: the channel's
        rate [ours], set by its first station opened with one. ``virtual`` and
        ``udp_multicast``: None, they have no rate.
        """
        if self._link_rate is not None:
            return self._link_rate.get()
        rate = getattr(self.bus, "bitrate", None) if self.interface == "shm" else None
        return rate if isinstance(rate, int) else None

    def set_bitrate(self, bitrate: int) -> None:
        """Run the controller at ``bitrate``: live where the interface can (slcan's
        ``set_bitrate``), else by closing it and opening it again. Only where
        ``takes_bitrate``; raises what python-can raises for a rate it cannot set, and the
        controller keeps its old one then.

        On a link whose rate the card cannot set (``FIXED_RATE_INTERFACES``), a rate other
        than the link's raises ``CanOperationError``: the host asked for a rate the bus
        does not run, which the seed reports as Err_Event 56 (5.2.5.4.1, "baudrate out of
        range"), not as every node's failure to answer a few seconds later.
        """
        if not self.sets_bitrate:
            link = self.link_bitrate()
            if link is not None and link != bitrate:
                raise can.CanOperationError(
                    f"{self.interface} channel {self.channel} runs at {link} bit/s, which the "
                    f"card cannot change")
            return
        setter = getattr(self.bus, "set_bitrate", None)
        if callable(setter):
            setter(bitrate)
        else:
            self._receiver.stop()
            self._link = None  # closed on purpose: no lost link for check_link
            self.bus.shutdown()
            kwargs = {**self._open_kwargs, "bitrate": bitrate}
            self.bus = self._open(kwargs)
            self._open_kwargs = kwargs
            self._receiver = _Receiver(self.bus, self.interface, self)
        self._bitrate = bitrate

    def shutdown(self) -> None:
        self._closed.set()
        self._receiver.stop()
        if self._trace is not None:
            self._trace.stop()
        if self._tap is not None:
            self._tap.close()
        self.bus.shutdown()
