"""What recording costs per event, counted, not timed (issue 22, docs/recording.md).

The device loop calls the recorder's hooks on every message, answer and flag change, and
the recorder's drain thread takes what they queued every 50 ms, under the interpreter lock
the loop needs. A user sees this as the recording card's latency and CPU per call; these
tests count what the machine's load does not change: the Python objects an event leaves
for the drain thread to pack and free, the system calls of the hooks, and the bytes each
event puts through the pipe and the spool. A real ``Recorder`` with its writer process on
a real mapped image and a ledger as host_api writes it; the hooks are called as the
device loop calls them (firmware/device.py), the session it writes is read back.
"""

from __future__ import annotations

import mmap
import os
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import pytest

from dpm import flags as fl
from dpm import session as s
from dpm.commands import COM_SHARED_MEMORY
from dpm.image import CardDirectory, lock_path
from dpm.layout import DPM_SIZE, SND_PD, TASK2_PARAMETER, TASK2_STATE, TASK_STATE_SIZE
from dpm.ledger import END, LedgerLine
from dpm.message import Message, Task
from firmware import recorder as recorder_module
from firmware.process_image import ProcessImage
from firmware.recorder import Recorder
from host_api.locks import LEDGER_BYTES

HOST_PID = 4321
ROUND_TRIPS = 2000
EVENTS_PER_ROUND_TRIP = 4
"""The DevFlags change that brings the message, the message (with its DEVACK), its answer
(with its HOSTCOM), the DevFlags change that takes the answer (HOSTACK)."""
LINES_PER_ROUND_TRIP = 6
"""The writer makes two lines of a message and of an answer (their HostFlags toggles)."""


@dataclass
class Recording:
    recorder: Recorder
    mm: mmap.mmap
    image: ProcessImage
    session: Path
    spool: int
    """The test's own descriptor of the spool: its size once the writer read it back."""


@pytest.fixture
def recording(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Recording]:
    """A recorder whose drain thread waits until ``close``: what the hooks queue stays
    queued, to be counted."""
    monkeypatch.setattr(recorder_module, "DRAIN_S", 3600.0)
    monkeypatch.setattr(recorder_module, "PIECE", 1001)  # pieces that end inside events
    image_dir = tmp_path / "cif"
    image_dir.mkdir(mode=0o750)
    line = LedgerLine(HOST_PID, 77, 5, COM_SHARED_MEMORY, Task.PLC, Task.USER, 0, 1).encode()
    ledger = (line.encode() + END).ljust(LEDGER_BYTES, b"\0")  # as host_api leaves it
    lock_path(image_dir, 0, "transaction").write_bytes(ledger)
    session = tmp_path / "session"
    session.mkdir()
    fds = [os.open(session / name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
           for name in (s.EVENTS, s.CAN_LOG)]
    spool = os.open(session, os.O_TMPFILE | os.O_RDWR, 0o600)
    files = CardDirectory(image_dir)
    mm = mmap.mmap(-1, DPM_SIZE)
    image = ProcessImage(mm)
    try:
        recorder = Recorder(0, fds[0], fds[1], spool, "virtual")
        for fd in fds:
            os.close(fd)
        recorder.start(files, mm, image)
        yield Recording(recorder, mm, image, session, spool)
    finally:
        os.close(spool)
        files.close()


def _messages() -> tuple[bytes, bytes]:
    """A COM_Shared_Memory request as the card copies DevMbx (the whole slot) and its
    answer as the card encodes it."""
    request = Message(rx=Task.PLC, tx=Task.USER, b=COM_SHARED_MEMORY, nr=5, data=bytes(8))
    raw = request.encode()
    return raw + bytes(288 - len(raw)), request.answer(data=bytes(range(16))).encode()


def _round_trips(rec: Recorder, count: int, raw: bytes, answer: bytes) -> None:
    """``count`` mailbox round trips, the hooks in the device loop's order."""
    dev = host = 0
    for n in range(count):
        now = float(n)
        dev ^= fl.DEVCOM
        rec.dev_flags(dev, now)  # the turn that takes the message
        rec.put(raw, host, host ^ fl.DEVACK)
        host ^= fl.DEVACK
        rec.answer(answer, host, host ^ fl.HOSTCOM)
        host ^= fl.HOSTCOM
        rec.settle()
        dev ^= fl.HOSTACK
        rec.dev_flags(dev, now)  # the turn after the host took the answer
        rec.settle()


def _syscalls() -> tuple[int, int]:
    """This process's read and write system calls so far (all its threads)."""
    fields = dict(line.split(": ") for line in Path("/proc/self/io").read_text().splitlines())
    return int(fields["syscr"]), int(fields["syscw"])


def test_a_queued_event_holds_no_python_object_and_makes_no_system_call(
        recording: Recording) -> None:
    """While events wait for the drain they are bytes in one buffer: at most one Python
    object per 20 events stays allocated (a tuple, a float and the bytes of each, 2.5
    blocks an event on 9aa3708, all of which the drain thread marshalled and freed), and a
    round trip makes one system call, the ledger's read (the put's pid), none of them a
    write."""
    raw, answer = _messages()
    _round_trips(recording.recorder, 10, raw, answer)  # the ledger opened, buffers grown
    own = [b - a for a, b in zip(_syscalls(), _syscalls(), strict=True)]  # reading /proc
    blocks = sys.getallocatedblocks()
    before = _syscalls()
    _round_trips(recording.recorder, ROUND_TRIPS, raw, answer)
    kept = (sys.getallocatedblocks() - blocks) / (ROUND_TRIPS * EVENTS_PER_ROUND_TRIP)
    reads, writes = (now - then - calls
                     for now, then, calls in zip(_syscalls(), before, own, strict=True))
    recording.recorder.close()
    assert recording.recorder.complete
    assert kept <= 0.05, f"{kept:.2f} Python objects kept per queued event"
    assert reads <= ROUND_TRIPS, f"{reads / ROUND_TRIPS:.2f} reads per round trip"
    assert writes == 0, f"{writes} writes while {ROUND_TRIPS} round trips were queued"


def test_a_round_trip_puts_few_bytes_through_the_spool_and_all_of_it_is_written(
        recording: Recording) -> None:
    """A mailbox round trip of a 16-byte request and its 24-byte answer takes at most 240
    bytes of the spool (its four events, the ledger's line and Task2State; 748 on 9aa3708:
    the ledger's read of 512 bytes went in whole, and marshal's framing); every event
    comes out of the writer, in pieces that end inside events."""
    raw, answer = _messages()
    _round_trips(recording.recorder, ROUND_TRIPS, raw, answer)
    recording.recorder.close()
    assert recording.recorder.complete
    per_round_trip = os.fstat(recording.spool).st_size / ROUND_TRIPS
    assert per_round_trip <= 240, f"{per_round_trip:.0f} spool bytes per round trip"
    records = s.decode_events((recording.session / s.EVENTS).read_text())
    assert recording.recorder.events == len(records) == ROUND_TRIPS * LINES_PER_ROUND_TRIP
    kinds = [r.kind for r in records[:LINES_PER_ROUND_TRIP]]
    assert kinds == [s.DEV_FLAGS, s.HOST_FLAGS, s.PUT, s.ANSWER, s.HOST_FLAGS, s.DEV_FLAGS]
    put, answered = records[2], records[3]
    assert put.pid == answered.pid == HOST_PID
    assert put.msg is not None and put.msg.encode() == raw[: len(put.msg.encode())]
    assert answered.msg is not None and answered.msg.encode() == answer
    assert records[-1].t == ROUND_TRIPS - 1


def _exchange(recording: Recording, before: int, after: int) -> None:
    """A process-data handshake as the device loop makes it: the process image's exchange,
    the PDACK toggle, the end of the turn."""
    recording.image.cycle()
    recording.recorder.host_flags(before, after)
    recording.recorder.settle()


def test_exchanges_starts_and_frames_come_out_as_the_card_saw_them(
        recording: Recording) -> None:
    """The other events' packing: an exchange that changed the areas and one that did not
    (a PDACK toggle while READY), a start with its Task2Parameter, a HostFlags change of
    its own, and frames (``can.log``)."""
    rec, mm = recording.recorder, recording.mm
    mm[TASK2_PARAMETER : TASK2_PARAMETER + s.PARAMETER_SIZE] = bytes(range(s.PARAMETER_SIZE))
    mm[TASK2_STATE] = 0x42
    rec.dev_flags(fl.INIT, 1.0)  # a start: its parameter recorded
    rec.host_flags(0, fl.READY)
    mm[SND_PD + 3] = 0xA5  # the host's outputs
    recording.image.write_inputs(7, b"\x5a")  # the bus's inputs
    _exchange(recording, fl.READY, fl.READY | fl.PDACK)
    _exchange(recording, fl.READY | fl.PDACK, fl.READY)  # unchanged
    for n in range(3):
        rec.frame(can.Message(arbitration_id=0x180 + n, is_extended_id=False, data=[n],
                              timestamp=10.0 + n), n == 1)
    rec.close()
    assert rec.complete and rec.frames == 3
    records = s.decode_events((recording.session / s.EVENTS).read_text())
    assert [r.kind for r in records] == [s.DEV_FLAGS, s.HOST_FLAGS, s.HOST_FLAGS, s.EXCHANGE,
                                         s.HOST_FLAGS, s.EXCHANGE]
    assert records[0].parameter == bytes(range(s.PARAMETER_SIZE))
    assert (records[0].before, records[0].after) == (0, fl.INIT)
    assert records[3].changes == {"SndPd": [(3, b"\xa5")], "RcvPd": [(7, b"\x5a")]}
    assert records[5].changes == {} and records[5].state[0] == 0x42
    assert (records[4].before, records[4].after) == (fl.READY | fl.PDACK, fl.READY)
    log = (recording.session / s.CAN_LOG).read_text().splitlines()
    assert [line.split()[2] for line in log] == ["180#00", "181#01", "182#02"]
    assert log[1].endswith(" R") and log[0].endswith(" T")


def test_an_exchange_records_every_change_of_the_areas_and_copies_no_unchanged_one(
        recording: Recording) -> None:
    """The recorder copies the areas only at an exchange the process image marked
    (``ProcessImage.exchanged_changes``): every way the areas change between two exchanges
    still comes out (the host's SndPd, the bus's inputs, a COM_Shared_Memory write into the
    send area, which changes the card's copy and the image at once, a flipped input bit),
    and each unchanged exchange costs 27 bytes of spool instead of 7 KiB."""
    rec, mm, image = recording.recorder, recording.mm, recording.image
    ready, acked = fl.READY, fl.READY | fl.PDACK
    steps: list[Callable[[], object]] = [
        lambda: mm.__setitem__(SND_PD + 1, 0x11),
        lambda: None,
        lambda: image.write_inputs(2, b"\x22"),
        lambda: None,
        lambda: image.write_send_area(5, b"\x55"),
        lambda: image.flip_inputs(2, 0x01, once=True),
        lambda: None,  # the flip is over: the true bit again
        lambda: None,
    ]
    sizes = []
    for n, step in enumerate(steps):
        step()
        size = len(rec._queue)  # what one exchange queued
        _exchange(recording, *((ready, acked) if n % 2 == 0 else (acked, ready)))
        sizes.append(len(rec._queue) - size)
    rec.close()
    assert rec.complete
    exchanges = [r.changes for r in s.decode_events((recording.session / s.EVENTS).read_text())
                 if r.kind == s.EXCHANGE]
    assert exchanges == [{"SndPd": [(1, b"\x11")]}, {}, {"RcvPd": [(2, b"\x22")]}, {},
                         {"SndPd": [(5, b"\x55")]}, {"RcvPd": [(2, b"\x23")]},
                         {"RcvPd": [(2, b"\x22")]}, {}]
    unchanged = s.SPOOL_EXCHANGE.size + TASK_STATE_SIZE
    assert [size == unchanged for size in sizes] == [False, True, False, True, False, False,
                                                    False, True]



def test_the_hosts_pd_toggle_is_queued_with_its_exchange_and_in_the_turns_order(
        recording: Recording) -> None:
    """The host's PD toggle that asks for an exchange is held until the end of the turn and
    queued with the exchange in one append (one event's bytes fewer to pack); the session
    still has its DevFlags line, at the turn's time, before the PDACK toggle and the
    exchange. A toggle whose turn did not exchange is written at the turn's end; one
    followed by another event of its turn (an answer) comes before it."""
    rec, image = recording.recorder, recording.image
    _, answer = _messages()
    ready, acked = fl.READY, fl.READY | fl.PDACK
    rec.dev_flags(fl.PDCOM, 1.0)  # the turn that exchanges
    size = len(rec._queue)  # nothing queued until the turn's end
    image.cycle()
    rec.host_flags(ready, acked)
    assert len(rec._queue) == size
    rec.settle()
    rec.dev_flags(0, 2.0)  # a toggle, no exchange in its turn
    rec.settle()
    rec.dev_flags(fl.PDCOM, 3.0)  # a toggle, then an answer in the same turn
    rec.answer(answer, acked, acked ^ fl.HOSTCOM)
    rec.settle()
    rec.close()
    assert rec.complete
    records = s.decode_events((recording.session / s.EVENTS).read_text())
    assert [r.kind for r in records] == [s.DEV_FLAGS, s.HOST_FLAGS, s.EXCHANGE, s.DEV_FLAGS,
                                         s.DEV_FLAGS, s.ANSWER, s.HOST_FLAGS]
    assert [(r.before, r.after) for r in records if r.kind == s.DEV_FLAGS] == [
        (0, fl.PDCOM), (fl.PDCOM, 0), (0, fl.PDCOM)]
    assert [r.t for r in records if r.kind == s.DEV_FLAGS] == [1.0, 2.0, 3.0]
    assert (records[1].before, records[1].after) == (ready, acked)
    assert records[2].state == recording.mm[TASK2_STATE : TASK2_STATE + TASK_STATE_SIZE]
