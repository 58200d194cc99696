"""Frames on python-can's ``virtual`` interface handled by the thread that sends them [ours].

python-can's ``virtual`` interface puts a copy of each frame into every other station's
queue, in the sender's thread; the station's receive thread then wakes for it and waits
for the interpreter lock, which the sender holds until its own next wait. With
``--simulate`` the card and its nodes share one process, and each such hand-over cost an
expedited host SDO a thread wake-up (50-150 µs here, issue 22). An ``InlineQueue`` lets
the sender run the station's frame handlers itself when the station's receive thread has
nothing to do, and queues the frame for the thread as before otherwise.

Two kinds of station use it. The card's controller (``firmware.can.bus``) takes every
frame that finds it idle. A simulated network (``firmware.sim.network``) takes only the
frames its sender asked to have answered at once (``answered_here``): the card's host SDO
requests; every other frame, from any thread, waits for the nodes' own thread as before,
so that no other path of the card runs node code in its threads. Both send through a
``CopyingVirtualBus``, which gives the other stations the copies python-can's ``virtual``
gives them, made for less.
"""

from __future__ import annotations

import queue
import threading
import time
from types import TracebackType
from typing import Protocol

import can
from can.interfaces.virtual import VirtualBus


class Dispatcher(Protocol):
    """The station's side: its frame handlers, run by a sender's thread."""

    def try_dispatch(self, msg: can.Message) -> bool:
        """Handle ``msg`` in the calling thread unless a frame is being handled or the
        calling thread may not run the handlers; False: not done, the frame is queued."""


class _Asked(threading.local):
    """Per thread: whether it is inside ``answered_here``, and the frames it reserved."""

    def __init__(self) -> None:
        self.depth = 0
        self.reserved: list[tuple[InlineQueue, can.Message]] = []


_asked = _Asked()


class _AnsweredHere:
    """Frames sent inside ``with answered_here:`` to an ``asked_only`` station are handled by
    this thread when the block ends, if that station is idle then (else by its own thread,
    in the order sent).

    At the end, not inside the send: python-can's ``virtual`` puts the frame into one
    station after the other, and the card traces a sent frame once the send returns; an
    answer handled inside the send would come before its request in the card's trace and
    at the stations after the node. A frame reserved this way counts as taken from the
    station's queue meanwhile, so frames sent after it by other threads wait behind it.

    One object for every thread (its state is ``_asked``'s, per thread), entered by a
    ``with`` without a call: a generator-based context manager cost the device loop six
    Python calls per host SDO request, this two (issue 22)."""

    def __enter__(self) -> None:
        _asked.depth += 1

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 traceback: TracebackType | None) -> None:
        state = _asked
        state.depth -= 1
        if not state.depth:
            reserved = state.reserved
            while reserved:
                station, msg = reserved.pop(0)
                station.deliver_reserved(msg)


answered_here = _AnsweredHere()


new_message = object.__new__
"""A ``can.Message`` without its constructor, whose slots the caller sets, every one."""


class CopyingVirtualBus(VirtualBus):
    """A ``virtual`` station whose ``send`` gives each other station its copy without
    ``copy.deepcopy``: the same copies, made for less.

    python-can's ``send`` deep-copies the frame for every other station on the channel,
    through ``copy``'s machinery and ``can.Message``'s constructor: 4-6 µs and four Python
    calls a frame here, twice per expedited host SDO (the card's request and the
    simulated node's answer) in the card's device loop (issue 22). This one makes the
    same copy (a deep copy with the time stamp, channel and direction of the reception,
    its slots set one by one in ``send``, not in a function of its own: a Python call
    less per frame) and gives it to the stations as python-can does: the
    sender's own station only when it receives its own messages, every station tried,
    ``CanOperationError`` when one was full. Installed on a station by ``install``."""

    @classmethod
    def install(cls, bus: can.BusABC) -> None:
        """Make ``bus``, a ``VirtualBus`` (its subclasses keep their own ``send``), one of
        these, in place: python-can's ``can.Bus`` made the object."""
        if type(bus) is VirtualBus:
            bus.__class__ = cls

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not self._open:
            self._check_if_open()  # raises python-can's error for a closed bus
        timestamp = msg.timestamp if self.preserve_timestamps else time.time()
        own = self.queue
        channel = self.channel_id
        full = False
        for station in self.channel:
            if station is own and not self.receive_own_messages:
                continue
            copy: can.Message = new_message(can.Message)
            copy.timestamp = timestamp
            copy.arbitration_id = msg.arbitration_id
            copy.is_extended_id = msg.is_extended_id
            copy.is_remote_frame = msg.is_remote_frame
            copy.is_error_frame = msg.is_error_frame
            copy.channel = channel
            copy.dlc = msg.dlc
            copy.data = bytearray(msg.data)
            copy.is_fd = msg.is_fd
            copy.is_rx = station is not own
            copy.bitrate_switch = msg.bitrate_switch
            copy.error_state_indicator = msg.error_state_indicator
            try:
                station.put(copy, True, timeout)
            except queue.Full:
                full = True
        if full:
            raise can.CanOperationError("Could not send message to one or more recipients")


class InlineQueue(queue.Queue[can.Message]):
    """A ``virtual`` station's receive queue whose frame, when the receive thread is idle,
    is handled by the thread that sends it.

    Still one frame at a time, in the order sent: a sender handles its frame only when no
    frame waits in the queue or has been taken from it and not yet handled (``_taken``,
    kept under the queue's own mutex) and the dispatcher's ``try_dispatch`` finds none being
    handled; otherwise the frame is queued for the thread as before. The receive thread
    reports each frame it has handled (``dispatched``). A station that receives its own
    messages keeps the thread (its own sends would run its handlers inside them).
    """

    _dispatcher: Dispatcher
    _taken: int
    """Frames taken from the queue (by the receive thread, or reserved by ``answered_here``)
    and not handled yet."""
    _asked_only: bool

    @classmethod
    def install(cls, station: queue.Queue[can.Message], dispatcher: Dispatcher, *,
                asked_only: bool = False) -> InlineQueue:
        """Make the station's own queue object an ``InlineQueue``, in place, under its
        mutex: python-can's ``send`` may hold the object already, and frames in it stay.
        ``asked_only``: only frames sent inside ``answered_here``."""
        with station.mutex:
            station.__class__ = cls
            inline: InlineQueue = station  # type: ignore[assignment]
            inline._dispatcher = dispatcher
            inline._taken = 0
            inline._asked_only = asked_only
        return inline

    def put(self, item: can.Message, block: bool = True, timeout: float | None = None) -> None:
        if self._asked_only:
            if _asked.depth:
                with self.mutex:
                    reserved = not self.queue and not self._taken
                    if reserved:
                        self._taken += 1
                if reserved:
                    _asked.reserved.append((self, item))
                    return
        else:
            with self.mutex:
                idle = not self.queue and not self._taken
            if idle and self._dispatcher.try_dispatch(item):
                return
        super().put(item, block, timeout)

    def deliver_reserved(self, item: can.Message) -> None:
        """A frame reserved in ``answered_here``: handled here, or else first in the queue
        (frames sent after it by other threads wait behind it)."""
        if self._dispatcher.try_dispatch(item):
            self.dispatched()
            return
        with self.mutex:
            self.queue.appendleft(item)
            self._taken -= 1
            self.unfinished_tasks += 1
            self.not_empty.notify()

    def _get(self) -> can.Message:
        self._taken += 1  # under the mutex: Queue.get holds it
        return super()._get()

    def dispatched(self) -> None:
        """A frame taken from the queue (or reserved) has been handled."""
        with self.mutex:
            self._taken -= 1
