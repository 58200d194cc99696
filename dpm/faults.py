"""The fault channel's contract: card-side faults on demand [ours] (docs/faults.md).

A real card cannot be made to fail on purpose; the emulated one can, so that a host
program's reaction to a failing card can be tested. A tool (``cifemu fault``,
``host_api.faults``, the pytest plugin's ``CifCard.fault``) sends one request datagram to
the socket ``board<N>.fault`` beside the image; the firmware (``firmware.faults``)
applies it and answers with one reply datagram. A file system socket, as the doorbell and
the frame tap: the image directory's permissions decide who may inject faults
(docs/security.md).

A request is a JSON object: ``kind`` and the fields its kind takes (``FIELDS``); a reply
is ``{"ok": true, "active": [...]}`` (the faults active after the request, each with its
kind, fields and the milliseconds it has left) or ``{"ok": false, "error": "..."}``. JSON,
not a packed layout: the requests are rare, a person reads them in a trace, and a new
field does not move the others. The codec is apart from the sockets, so that the
firmware, the tools and the tests share it; ``decode_request`` refuses anything that is
not a well-formed request of a known kind with ``FaultRequestError``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dpm.errors import DpmError
from dpm.image import socket_path

WATCHDOG = "watchdog"
RCS_ERROR = "rcs-error"
STALL = "stall"
SLOW = "slow"
FLIP = "flip"
BUS_OFF = "bus-off"
DIE = "die"
CLEAR = "clear"
"""Not a fault: ends every active fault (a ``die --hang`` card comes back by a cold start)."""
LIST = "list"
"""Not a fault: asks only for the active faults."""

KINDS: dict[str, str] = {
    WATCHDOG: "the device watchdog stops: the card no longer answers the host's "
              "watchdog triggers (bHostWatchDog stays) nor supervises the host",
    RCS_ERROR: "RcsInfo.bRcsError shows CODE (1..255), as a card whose operating system "
               "reports an error; everything else runs",
    STALL: "the mailbox stalls: the card does not take messages from DevMbx for MS ms "
           "(the host's DevPutMessage finds the mailbox full, its answers do not come)",
    SLOW: "a slow card: every message the card hands the host comes MS ms late",
    FLIP: "a bit flip in an input byte: bit BIT of RcvPd byte OFFSET is inverted at the "
          "next exchange (once), or at every exchange for --for MS",
    BUS_OFF: "the CAN controller goes bus-off (Bus_Off_Cnt, EVE) and is off the bus for "
             "MS ms: nothing sent, nothing received; then it recovers",
    DIE: "the firmware dies as a card whose own watchdog fires: READY drops and the "
         "process exits; with --hang it stays, serving nothing, until the fault ends, "
         "then comes back through a cold start",
}
"""Every fault kind and what the host sees, for ``--help`` and docs/faults.md."""

FIELDS: dict[str, frozenset[str]] = {
    WATCHDOG: frozenset({"for_ms"}),
    RCS_ERROR: frozenset({"code", "for_ms"}),
    STALL: frozenset({"for_ms"}),
    SLOW: frozenset({"delay_ms", "for_ms"}),
    FLIP: frozenset({"offset", "bit", "for_ms"}),
    BUS_OFF: frozenset({"for_ms"}),
    DIE: frozenset({"hang", "for_ms"}),
    CLEAR: frozenset(),
    LIST: frozenset(),
}
"""The fields each request kind may carry; the others must keep their defaults."""

NEEDS_DURATION = frozenset({STALL, BUS_OFF})
"""Kinds whose length is their argument: a stall or a bus-off that never ends is a
``die --hang``, not what these kinds are for."""

MAX_MS = 24 * 3600 * 1000
"""The longest fault, and the longest delay of a slow card (a day) [ours]: a number beyond
it is a mistake, and a fault never outlives the firmware anyway."""
RCS_ERROR_MAX = 255
"""bRcsError is a byte; 1..249 is what a host's DevInitBoard turns into 1000 + bRcsError."""
BITS_PER_BYTE = 8
MAX_DATAGRAM = 4096
"""The largest request or reply: a reply lists at most one fault of each kind."""
DIE_EXIT_STATUS = 70
"""The firmware's exit status after the fault ``die`` (sysexits' EX_SOFTWARE, "internal
software error"): a supervisor or a test tells a card that died from one stopped cleanly
(0) or refused at its start (1)."""
REPLY_TIMEOUT_S = 5.0
"""How long a tool waits for the firmware's reply: it answers at once, but a loaded
machine may run the firmware's fault thread late."""


def fault_address(image_path: Path) -> str:
    """The fault socket of the card serving ``image_path``: ``board<N>.fault`` beside it."""
    return os.fspath(socket_path(image_path, "fault"))


class FaultRequestError(DpmError, ValueError):
    """A request that is not a well-formed fault request; the message says which field."""


@dataclass(frozen=True)
class FaultRequest:
    """One request: a fault to inject (``kind`` in ``KINDS``), ``clear`` or ``list``.

    ``for_ms``: how long the fault lasts, None until ``clear`` (for ``flip``: None is one
    exchange only). ``code``: the RCS error of ``rcs-error``; ``delay_ms``: the lateness of
    ``slow``; ``offset`` and ``bit``: the input bit of ``flip``; ``hang``: a ``die`` that
    keeps the process.
    """

    kind: str
    for_ms: int | None = None
    code: int = 0
    delay_ms: int = 0
    offset: int = 0
    bit: int = 0
    hang: bool = False

    def __post_init__(self) -> None:
        self._check()

    def _check(self) -> None:
        fields = FIELDS.get(self.kind)
        if fields is None:
            raise FaultRequestError(f"unknown fault kind {self.kind!r}: one of "
                                    + ", ".join([*KINDS, CLEAR, LIST]))
        for name in ("for_ms", "code", "delay_ms", "offset", "bit", "hang"):
            if name not in fields and getattr(self, name) != _DEFAULTS[name]:
                raise FaultRequestError(f"{self.kind} takes no {name}")
        if self.for_ms is not None:
            _in_range("for_ms", self.for_ms, 1, MAX_MS)
        elif self.kind in NEEDS_DURATION:
            raise FaultRequestError(f"{self.kind} needs its length in ms (for_ms)")
        if self.kind == RCS_ERROR:
            _in_range("code", self.code, 1, RCS_ERROR_MAX)
        if self.kind == SLOW:
            _in_range("delay_ms", self.delay_ms, 1, MAX_MS)
        if self.kind == FLIP:
            from dpm.layout import IO_AREA_SIZE  # here: `cifemu fault --help` needs no layout

            _in_range("offset", self.offset, 0, IO_AREA_SIZE - 1)
            _in_range("bit", self.bit, 0, BITS_PER_BYTE - 1)
        if not isinstance(self.hang, bool):
            raise FaultRequestError(f"hang must be true or false, not {self.hang!r}")
        if self.kind == DIE and self.for_ms is not None and not self.hang:
            raise FaultRequestError("die takes for_ms only with hang: a firmware that "
                                    "exits does not come back by itself")

    def fields(self) -> dict[str, Any]:
        """The request's own fields (those its kind takes, defaults left out)."""
        return {name: getattr(self, name) for name in sorted(FIELDS[self.kind])
                if getattr(self, name) != _DEFAULTS[name]}

    def encode(self) -> bytes:
        return json.dumps({"kind": self.kind, **self.fields()}).encode()

    def describe(self) -> str:
        """One line for a person and the firmware's log: ``slow delay_ms=200 for 1500 ms``."""
        words = [self.kind, *(k if v is True else f"{k}={v}" for k, v in self.fields().items()
                             if k != "for_ms")]
        if self.for_ms is not None:
            words.append(f"for {self.for_ms} ms")
        elif self.kind == FLIP:
            words.append("for one exchange")
        elif self.kind in KINDS:
            words.append("until cleared")
        return " ".join(words)


_DEFAULTS: dict[str, Any] = {"for_ms": None, "code": 0, "delay_ms": 0, "offset": 0, "bit": 0,
                             "hang": False}


def _in_range(name: str, value: object, low: int, high: int) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        raise FaultRequestError(f"{name} must be an integer {low}..{high}, not {value!r}")


def _json_object(data: bytes, what: str) -> dict[str, Any]:
    if len(data) > MAX_DATAGRAM:
        raise FaultRequestError(f"{what} of {len(data)} bytes is longer than {MAX_DATAGRAM}")
    try:
        value = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise FaultRequestError(f"{what} is no JSON text: {exc}") from None
    if not isinstance(value, dict):
        raise FaultRequestError(f"{what} is no JSON object")
    return value


def decode_request(data: bytes) -> FaultRequest:
    """A request datagram; FaultRequestError names what is wrong with it."""
    value = _json_object(data, "request")
    kind = value.pop("kind", None)
    if not isinstance(kind, str):
        raise FaultRequestError("request without a kind")
    unknown = set(value) - set(_DEFAULTS)
    if unknown:
        raise FaultRequestError(f"unknown field(s) {sorted(unknown)}")
    return FaultRequest(kind, **value)


@dataclass(frozen=True)
class ActiveFault:
    """A fault in force: its request and the milliseconds it has left (None: until
    ``clear``, or for a ``flip`` once, until the next exchange)."""

    request: FaultRequest
    left_ms: int | None

    def as_json(self) -> dict[str, Any]:
        return {"kind": self.request.kind, **self.request.fields(), "left_ms": self.left_ms}

    def describe(self) -> str:
        """One line for a person: ``slow delay_ms=200 for 1500 ms, 1200 ms left``."""
        if self.left_ms is None:
            return self.request.describe()
        return f"{self.request.describe()}, {self.left_ms} ms left"


def encode_reply(active: list[ActiveFault] | None = None, error: str | None = None) -> bytes:
    """The firmware's answer: the active faults, or why it refused the request."""
    if error is not None:
        return json.dumps({"ok": False, "error": error}).encode()
    return json.dumps({"ok": True, "active": [a.as_json() for a in active or []]}).encode()


def decode_reply(data: bytes) -> list[ActiveFault]:
    """The active faults of a reply; FaultRequestError with the firmware's reason when it
    refused the request, or when the reply is malformed."""
    value = _json_object(data, "reply")
    if value.get("ok") is not True:
        raise FaultRequestError(str(value.get("error", "the card refused the request")))
    active = []
    for entry in value.get("active", []):
        if not isinstance(entry, dict):
            raise FaultRequestError("reply with a malformed fault entry")
        entry = dict(entry)
        left = entry.pop("left_ms", None)
        kind = entry.pop("kind", None)
        if not isinstance(kind, str) or (left is not None and not isinstance(left, int)):
            raise FaultRequestError("reply with a malformed fault entry")
        unknown = set(entry) - set(_DEFAULTS)
        if unknown:
            raise FaultRequestError(f"reply with unknown field(s) {sorted(unknown)}")
        active.append(ActiveFault(FaultRequest(kind, **entry), left))
    return active
