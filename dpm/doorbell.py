"""The event channel beside the image [ours] (docs/dpm.md section 2).

A real card raises an interrupt when it writes HostFlags. Here the writer of a
flag byte rings the other side with a one-byte datagram on a Unix socket. The
device listens on ``board<N>.bell`` beside the image, a file system socket: the
directory's permissions (docs/security.md) keep other users from ringing it or
taking its name first, as anyone could an abstract name. Each host binds an
automatic abstract name, and the device learns it from the host's rings. A ring is only a hint:
both sides re-read the flags after every wake-up and also poll, so a lost ring
(a full queue, a host that writes the image directly) costs at most one poll
interval, never correctness. The device polls adaptively (``AdaptivePoll``): every
millisecond only while a host that writes without ringing is busy, backing off to
``DEVICE_POLL_IDLE`` when it pauses and, ``DEVICE_QUIET_AFTER`` after its last change, to
``DEVICE_POLL_QUIET``, so an idle card, and one whose hosts ring, sleeps instead of waking a
thousand (or twenty) times a second.
"""

from __future__ import annotations

import os
import select
import socket
from collections import OrderedDict
from pathlib import Path

from dpm.image import CardDirectory, socket_path

POLL_INTERVAL = 0.001
"""Seconds between a waiting host's flag polls when no ring arrives, and the device's poll
while the flags move (the 1 ms of docs/dpm.md 2)."""

DEVICE_POLL_IDLE = 0.05
"""[ours] The device's longest poll interval within ``DEVICE_QUIET_AFTER`` of the last change
by a host that never rings: the latency such a host sees for a request after a short pause
(docs/dpm.md 2)."""

DEVICE_QUIET_AFTER = 1.0
"""[ours] Seconds after a ring-less host's last change after which the device polls at
``DEVICE_POLL_QUIET``: a raw host that pauses less than this between its exchanges keeps
``DEVICE_POLL_IDLE``, and the card's own answers keep its 1 ms poll."""

DEVICE_POLL_QUIET = 0.25
"""[ours] The device's longest poll interval, reached ``DEVICE_QUIET_AFTER`` after a raw
host's last change, and the one it keeps while no raw host is about: the latency a host that
never rings sees for its first request after a long pause (docs/dpm.md 2). Each turn costs
this machine about 0.2 ms of CPU, mostly the wake-up itself: 20 turns a second
(``DEVICE_POLL_IDLE``) were 0.3-0.45 % of a core, most of an idle card's cost; 4 a second are
under 0.1 %."""

DEVICE_FAST_WINDOW = 0.05
"""Seconds after a raw host's activity (or the card's answer to it) during which the device
keeps polling every ``POLL_INTERVAL``: a raw host's next step of a handshake usually follows
within that."""

MAX_HOSTS = 64
"""Hosts the device keeps ringing; the longest silent one is dropped first."""

RING = b"\x01"
"""A plain ring (public for the device loop's turn in C, ``firmware.native_mailbox``, and the
host's, ``host_api._devflags``)."""
_RING_WANT_ACK = b"\x02"
"""A device ring that also says: more answers wait, ring me when you acknowledge."""
WANT_ACK = _RING_WANT_ACK[0]
"""``_RING_WANT_ACK``'s byte, for the host's wait in C (``host_api._devflags.wait_ring``)."""
_RING_WANT_MAILBOX = b"\x03"
"""A host ring that also says: I wait for the device mailbox, ring me when it is free. The
card rings for a message it took (DEVACK) only when a host asked so: a host that waits for
its answer would only wake for nothing, a thread hand-off per request whose answer comes
later (an SDO transfer; issue 22)."""


def device_address(image_path: Path) -> str:
    """The socket of the device serving ``image_path``: ``board<N>.bell`` beside it."""
    return os.fspath(socket_path(image_path, "bell"))


class _Endpoint:
    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.setblocking(False)

    def fileno(self) -> int:
        return self.sock.fileno()

    def close(self) -> None:
        self.sock.close()

    def _send(self, address: str | bytes, payload: bytes = RING) -> bool:
        """Ring ``address``; False when nobody listens there any more."""
        try:
            self.sock.sendto(payload, address)
        except (ConnectionRefusedError, FileNotFoundError, PermissionError):
            return False
        except OSError:
            return True  # queue full: the peer is awake anyway, or will poll
        return True

    def _drain(self) -> list[tuple[bytes, str | bytes]]:
        """The rings queued, once select said there is one: that one is read without asking
        again (a system call per wake-up saved). Asking select is cheaper than ending the
        loop on a raised BlockingIOError."""
        rings: list[tuple[bytes, str | bytes]] = []
        try:
            rings.append(self.sock.recvfrom(16))
        except BlockingIOError:  # another thread of this process took it
            return rings
        while select.select((self.sock,), (), (), 0)[0]:
            try:
                rings.append(self.sock.recvfrom(16))
            except BlockingIOError:
                break
        return rings

    def wait(self, timeout: float) -> bool:
        """Block until a ring or ``timeout`` seconds; True when rung.

        select, unlike a shared poll object, may be waited on by several threads
        of one host process at once. (A Python host's driver and the CiA 309 gateway's
        reader wait by ``host_api._devflags.wait_ring`` instead, the gateway's beside its
        wake-up pipe.)
        """
        rung = bool(select.select((self.sock,), (), (), max(0.0, timeout))[0])
        if rung:
            self._on_rings(self._drain())
            return True
        return False

    def _on_rings(self, rings: list[tuple[bytes, str | bytes]]) -> None:
        del rings


class AdaptivePoll:
    """The device's fallback poll interval: short only while a host that never rings is busy.

    A ring wakes the device at once whatever the interval; the poll only serves a host that
    writes the image without ringing (a raw host). Such a host shows itself by changing what
    hosts write (``host_wrote``) in a turn that no host's ring woke (``host_rang``). For
    ``DEVICE_QUIET_AFTER`` after that, activity of any kind (its next steps, the card's own
    answers) holds ``POLL_INTERVAL`` for ``DEVICE_FAST_WINDOW``, then the interval doubles
    each quiet turn up to ``DEVICE_POLL_IDLE``; without a raw host about it doubles on up to
    ``DEVICE_POLL_QUIET``. A host that rings never starts the 1 ms poll: its ring is what
    wakes the card, and polling after it woke the card 8-12 times per request for nothing
    (issue 22). A ringing host's change that a turn woken by something else saw before the
    ring came looks like a raw host's; the ring that follows with nothing new takes that back.

    ``waiting``: answers wait behind one the host has not acknowledged. A host acknowledges
    without ringing unless the card's last ring asked for one, and the card may have queued
    the next answer after that ring: the card looks every ``POLL_INTERVAL`` for
    ``DEVICE_FAST_WINDOW`` from then on, then backs off, as for a raw host.
    """

    def __init__(self) -> None:
        self.interval = POLL_INTERVAL
        self._fast_until = 0.0
        self._raw_until = 0.0
        self._waiting = False
        self._undo: tuple[float, float, float] | None = None
        """What a turn that took a change for a raw host's replaced: the ring that comes
        next, with nothing new, puts it back."""

    def next_interval(self, now: float, *, host_rang: bool, host_wrote: bool,
                      card_wrote: bool = False, waiting: bool = False) -> float:
        """The interval until the next poll, after a turn at ``now``. ``host_rang``: a
        host's ring woke it; ``host_wrote``: what hosts write changed since the last turn;
        ``card_wrote``: the card changed its flags; ``waiting``: see the class."""
        undo, self._undo = self._undo, None
        if host_wrote and not host_rang:
            self._undo = (self._raw_until, self._fast_until, self.interval)
            self._raw_until = now + DEVICE_QUIET_AFTER
        elif host_rang and not host_wrote and undo is not None:
            self._raw_until, self._fast_until, self.interval = undo
            return self.interval
        began_waiting, self._waiting = waiting and not self._waiting, waiting
        raw_about = now < self._raw_until
        if began_waiting or (raw_about and (host_wrote or host_rang or card_wrote)):
            self._fast_until = now + DEVICE_FAST_WINDOW
            self.interval = POLL_INTERVAL
        elif now >= self._fast_until:
            longest = DEVICE_POLL_IDLE if raw_about else DEVICE_POLL_QUIET
            self.interval = min(self.interval * 2, longest)
        return self.interval


    def settled(self, now: float) -> bool:
        """Whether a turn woken by a host's ring that changes no more than the mailbox
        leaves the interval as it is: no raw host about, no fast window, no answers
        waiting, nothing to undo, the interval at its longest. Only then may the device
        loop serve such turns without asking ``next_interval`` (``firmware.native_mailbox``)."""
        return (self._undo is None and not self._waiting and now >= self._raw_until
                and now >= self._fast_until and self.interval == DEVICE_POLL_QUIET)


class DeviceBell(_Endpoint):
    """The firmware's side: rung by hosts, rings every host it has heard from.

    Made while the firmware holds the board's lock, so a socket file already there is
    a killed firmware's and is replaced (``CardDirectory.bind``)."""

    def __init__(self, directory: CardDirectory, image_path: Path) -> None:
        super().__init__()
        self.address = device_address(image_path)
        self._directory = directory
        try:
            directory.bind(self.sock, Path(self.address))
        except BaseException:
            self.sock.close()
            raise
        self._hosts: OrderedDict[str | bytes, None] = OrderedDict()
        self.mailbox_wanted = False
        """A host rang that it waits for the device mailbox (``_RING_WANT_MAILBOX``): the
        device rings its hosts once the mailbox is free, and clears this."""
        self.host_rang = False
        """A host (not the device itself) rang since the device loop last cleared this: what
        it wrote was announced, so it needs no fallback poll (``AdaptivePoll``)."""

    def close(self) -> None:
        super().close()
        self._directory.unlink(Path(self.address).name)

    def _on_rings(self, rings: list[tuple[bytes, str | bytes]]) -> None:
        for payload, address in rings:
            if not address or address == self.address:
                continue
            self.host_rang = True
            if payload == _RING_WANT_MAILBOX:
                self.mailbox_wanted = True
            self._hosts[address] = None
            self._hosts.move_to_end(address)
            while len(self._hosts) > MAX_HOSTS:
                self._hosts.popitem(last=False)

    def native_hosts(self) -> list[bytes] | None:
        """The known hosts, the one heard from last at the end, for the device loop's turn in
        C (``firmware.native_mailbox``), or None when there is none or one is not a host's
        automatic abstract name (bytes)."""
        hosts = list(self._hosts)
        if not hosts or not all(isinstance(host, bytes) for host in hosts):
            return None
        return hosts  # type: ignore[return-value]  # all bytes: checked above

    def take_native(self, rings: list[tuple[bytes, str | bytes]],
                    dead: list[bytes]) -> None:
        """What the turn in C left for Python: the rings it took and did not serve, and the
        hosts its rings found gone (``ring_hosts`` drops them the same way)."""
        for address in dead:
            self._hosts.pop(address, None)
        self._on_rings(rings)

    def ring_self(self) -> None:
        """Wake the device loop from another thread of the firmware."""
        self._send(self.address)

    def ring_hosts(self, want_ack: bool = False) -> None:
        """Ring every known host; ``want_ack`` asks them to ring back on HOSTACK."""
        payload = _RING_WANT_ACK if want_ack else RING
        for address in list(self._hosts):
            if not self._send(address, payload):
                del self._hosts[address]


class HostBell(_Endpoint):
    """A host's side: rings the device after writing DevFlags, waits for rings.

    The socket is not connected to the device's, though a ``send`` on a connected one
    would skip the look-up of the socket file's path that ``sendto`` makes on every ring:
    Linux does not limit the queue of a datagram socket for the peer it is connected to,
    so a host that has the board open but never waits on its bell (a tool that configured
    the card, a client that only sends) kept every ring the device sent it, each charged to
    the device's send buffer; after about 280 of them the device could ring no host at all,
    and every host waited for its fallback poll (issue 22: the CiA 309 gateway, which waits
    for rings only, then answered every 250 ms). Unconnected, such a host holds at most
    ``/proc/sys/net/unix/max_dgram_qlen`` rings, and the device's rings to it alone fail.
    A device started again binds the same name, so the next ring reaches it, and it
    learns this host from that ring."""

    def __init__(self, image_path: Path) -> None:
        super().__init__()
        self.sock.bind(b"")  # Linux autobind: a unique abstract name
        self.device = device_address(image_path)
        self.device_path = os.fsencode(self.device)
        """``device`` as bytes, for the ring in C (``host_api._devflags.change_ring``)."""
        self.device_wants_ack = True
        """Whether the device's last ring asked for a ring on HOSTACK (it has
        more answers queued); starts True so nothing waits on a missed hint."""

    def _on_rings(self, rings: list[tuple[bytes, str | bytes]]) -> None:
        if rings:
            self.device_wants_ack = rings[-1][0] == _RING_WANT_ACK

    def ring_device(self, want_mailbox: bool = False) -> None:
        """Ring the device; ``want_mailbox``: and ask for a ring once the device mailbox is
        free (DevPutMessage before it sleeps on a full mailbox)."""
        # no device listens: it polls when it comes
        self._send(self.device, _RING_WANT_MAILBOX if want_mailbox else RING)
