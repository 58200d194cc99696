"""``python -m bench tap``: frames a slow tap reader loses in a burst, against one frame a datagram.

The card's side runs in this process (``firmware.can.tap.TapPublisher``) and offers
a burst of ``BURST`` frames at full speed; the reader is another process that does
``cifemu monitor``'s work per frame (the CANopen meaning and the printed line) through
``TapBus``. The baseline, in the same run and alternating with it, is the tap as it
was before sequence numbers (wire version 1): one frame per datagram, sent without
waiting and dropped when the reader's queue is full, read one datagram at a time
with the same work per frame. Lost = offered - received, counted by the bench
itself; the new reader's own report (``lost_frames``) is given beside it.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import select
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from cifemu.commands.monitor import frame_line
from dpm.image import image_path
from dpm.tap import decode_frame, encode_frame, tap_address
from firmware.can.tap import TapPublisher
from host_api.monitor.codec import decode
from host_api.monitor.tap_bus import TapBus

NAME = "tap"
BURST = 10_000
ROUNDS = 5
BURST_ID = 0x181
HELLO_ID = 0x701
END_ID = 0x7FF
"""The frame after the burst; the reader ends on it and reports."""
WAIT_S = 120.0


def _work(msg: can.Message, out: io.StringIO) -> None:
    """What ``cifemu monitor`` does per frame: its meaning and its line."""
    meaning = decode(msg.arbitration_id, bytes(msg.data), extended=msg.is_extended_id,
                     remote=msg.is_remote_frame, error=msg.is_error_frame)
    out.write(frame_line(msg, meaning, True) + "\n")
    out.seek(0)


def _read_burst(receive: Callable[[], can.Message | None]) -> int:
    """Say "ready", then take frames until the end marker (or silence), saying "heard" at
    the first hello, doing the monitor's work on each burst frame; how many came."""
    out = io.StringIO()
    received = 0
    heard = False
    print("ready", flush=True)
    while True:
        msg = receive()
        if msg is None or msg.arbitration_id == END_ID:
            return received
        if msg.arbitration_id == BURST_ID:
            received += 1
            _work(msg, out)
        elif msg.arbitration_id == HELLO_ID and not heard:
            heard = True
            print("heard", flush=True)


def _read_batched(image: Path) -> dict[str, Any]:
    bus = TapBus(image, log_losses=False)
    try:
        received = _read_burst(lambda: bus.recv(WAIT_S))
        return {"received": received, "reported_lost": bus.lost_frames}
    finally:
        bus.shutdown()


def _read_single(address: bytes) -> dict[str, Any]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(address)
    sock.settimeout(WAIT_S)
    try:
        received = _read_burst(lambda: decode_frame(sock.recv(128))[0])
        return {"received": received, "reported_lost": None}
    finally:
        sock.close()


def _frame(ident: int, number: int) -> can.Message:
    return can.Message(arbitration_id=ident, is_extended_id=False, timestamp=time.time(),
                       data=number.to_bytes(8, "little"))


class _Single:
    """The version-1 tap: one frame per datagram, dropped on a full queue."""

    def __init__(self, address: bytes) -> None:
        self._address = address
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.setblocking(False)

    def publish(self, msg: can.Message, received: bool) -> None:
        with contextlib.suppress(OSError):  # the reader's queue is full: lost, unseen
            self._sock.sendto(encode_frame(msg, received), self._address)

    def close(self) -> None:
        self._sock.close()


def _round(batched: bool) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="bench-tap-") as directory:
        image = image_path(Path(directory), 0)
        address = b"\0bench-tap-" + str(time.monotonic_ns()).encode()
        publisher: TapPublisher | _Single = (TapPublisher(tap_address(image)) if batched
                                             else _Single(address))
        role = ["--batched", str(image)] if batched else ["--single", address.hex()]
        reader = subprocess.Popen([sys.executable, "-m", "bench.tap", *role],
                                  stdout=subprocess.PIPE, text=True)
        assert reader.stdout is not None
        try:
            assert reader.stdout.readline().strip() == "ready"
            hello = 0
            deadline = time.monotonic() + WAIT_S
            while not select.select([reader.stdout], [], [], 0.01)[0]:
                publisher.publish(_frame(HELLO_ID, hello), True)
                hello += 1
                if time.monotonic() > deadline:
                    raise RuntimeError("the tap reader never heard a frame")
            assert reader.stdout.readline().strip() == "heard"
            start = time.perf_counter()
            for number in range(BURST):
                publisher.publish(_frame(BURST_ID, number), True)
            offered_s = time.perf_counter() - start
            while reader.poll() is None and time.monotonic() < deadline:
                publisher.publish(_frame(END_ID, 0), True)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    reader.wait(0.01)
            result: dict[str, Any] = json.loads(reader.stdout.read())
        finally:
            if reader.poll() is None:
                reader.kill()
                reader.wait()
            publisher.close()
    result["lost"] = BURST - result["received"]
    result["burst_s"] = offered_s
    return result


def run(count: int | None = None, warmup: int | None = None) -> dict[str, Any]:
    rounds = count or ROUNDS
    batched: list[dict[str, Any]] = []
    single: list[dict[str, Any]] = []
    for _ in range(warmup or 0):
        _round(True)
    for _ in range(rounds):  # alternating: the machine's load moves
        single.append(_round(False))
        batched.append(_round(True))
    return {
        "name": NAME,
        "burst": BURST,
        "rounds": rounds,
        "batched": {"lost": [r["lost"] for r in batched],
                    "reported_lost": [r["reported_lost"] for r in batched],
                    "burst_s": [round(r["burst_s"], 4) for r in batched]},
        "baseline_one_frame_per_datagram": {
            "lost": [r["lost"] for r in single],
            "burst_s": [round(r["burst_s"], 4) for r in single]},
        "load_average": list(os.getloadavg()),
    }


def main(argv: list[str] | None = None) -> int:
    """A reader's process (``--batched IMAGE`` or ``--single ADDRESS-HEX``)."""
    parser = argparse.ArgumentParser(prog="python -m bench.tap")
    role = parser.add_mutually_exclusive_group(required=True)
    role.add_argument("--batched", type=Path, metavar="IMAGE")
    role.add_argument("--single", metavar="ADDRESS_HEX")
    args = parser.parse_args(argv)
    result = (_read_batched(args.batched) if args.batched is not None
              else _read_single(bytes.fromhex(args.single)))
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
