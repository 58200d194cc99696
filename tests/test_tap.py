"""The frame tap never loses a frame unseen: a slow reader is told how many it lost, and where.

The card's serving side (``firmware.can.tap.TapPublisher``) runs here in the test's
process on a real socket beside a real image path, so a burst is as fast as the card's
own and its size is known exactly; the end-to-end test runs a firmware on ``shm`` and
``cifemu monitor`` stopped with SIGSTOP while the card passes a burst.
"""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest

from dpm.image import image_path
from dpm.tap import TapSubscriber, decode_frame, tap_address
from firmware.can.tap import TapPublisher
from host_api.monitor.tap_bus import QUEUE_FRAMES, TapBus
from host_api.top.model import CardModel
from host_api.top.render import bus_text
from tests import commands
from tests.conftest import ROOT, ended, start_card, wait_until

BURST_ID = 0x181
HELLO_ID = 0x701


def frame(ident: int, number: int) -> can.Message:
    return can.Message(arbitration_id=ident, is_extended_id=False,
                       data=number.to_bytes(8, "little"))


def number_of(msg: can.Message) -> int:
    return int.from_bytes(msg.data, "little")


@pytest.fixture
def card_tap(tmp_path: Path) -> Iterator[tuple[TapPublisher, Path]]:
    image = image_path(tmp_path, 0)
    publisher = TapPublisher(tap_address(image))
    yield publisher, image
    publisher.close()


def subscribed(publisher: TapPublisher, has_frame: object) -> None:
    """Offer hello frames until the reader got one: the card learns a subscriber only while
    it publishes (at most every 0.1 s)."""
    count = 0

    def hello() -> bool:
        nonlocal count
        publisher.publish(frame(HELLO_ID, count), received=True)
        count += 1
        return bool(has_frame())  # type: ignore[operator]

    wait_until(hello, 20, "the tap's first frame to the reader")


def quiet_tap_bus(publisher: TapPublisher, image: Path) -> TapBus:
    """A ``TapBus`` the card sends to, with the hellos that showed it already read."""
    bus = TapBus(image)
    try:
        subscribed(publisher, lambda: bus.recv(0.05) is not None)
        while bus.recv(0.05) is not None:
            pass
    except BaseException:
        bus.shutdown()
        raise
    return bus


def burst(publisher: TapPublisher, sent: int) -> None:
    """Offer frames 0..sent-1 at the card's full speed, as its bus thread would."""
    for number in range(sent):
        publisher.publish(frame(BURST_ID, number), received=False)


def read_to_the_last(read: Callable[[], list[int]], sent: int, timeout: float = 30) -> list[int]:
    """The burst's frame numbers ``read`` gives, in order, up to its last frame's."""
    numbers: list[int] = []

    def last_came() -> bool:
        numbers.extend(read())
        return bool(numbers) and numbers[-1] == sent - 1

    wait_until(last_came, timeout, "the burst's last frame")
    return numbers


def test_a_paused_subscriber_is_told_exactly_how_many_frames_it_lost(
        card_tap: tuple[TapPublisher, Path]) -> None:
    """The reader reads nothing until the whole burst is offered (it is paused on that
    condition, not on time); then it reads to the burst's last frame. Before batches and
    sequence numbers it got 11 datagrams' worth and was never told of the rest."""
    publisher, image = card_tap
    reader = TapSubscriber(image)
    try:
        got: list[can.Message] = []

        def read_some() -> bool:
            batch = reader.recv(0.05)
            got.extend(decode_frame(f)[0] for f in (batch.frames if batch else []))
            return bool(got)

        subscribed(publisher, read_some)
        while (batch := reader.recv(0.05)) is not None:  # the hellos still queued
            assert batch.lost == 0
        lost_before = reader.lost
        sent = 20_000
        burst(publisher, sent)

        def read_batch() -> list[int]:
            batch = reader.recv(0.05)
            return [number_of(decode_frame(f)[0]) for f in (batch.frames if batch else [])]

        numbers = read_to_the_last(read_batch, sent)
    finally:
        reader.close()
    assert lost_before == 0
    assert numbers == sorted(numbers) and len(set(numbers)) == len(numbers)
    assert 0 < reader.lost == sent - len(numbers)


def test_a_tap_bus_at_normal_speed_loses_nothing(card_tap: tuple[TapPublisher, Path]) -> None:
    """A burst of 4,000 frames at the card's full speed while a python-can user reads as
    usual: all arrive and nothing is reported lost. The old tap kept 10 datagrams of one
    frame each for a reader the scheduler had not run yet."""
    publisher, image = card_tap
    bus = quiet_tap_bus(publisher, image)
    try:
        sent = 4_000
        burst(publisher, sent)

        def read_frame() -> list[int]:
            msg = bus.recv(0.05)
            return [number_of(msg)] if msg is not None and msg.arbitration_id == BURST_ID else []

        assert read_to_the_last(read_frame, sent) == list(range(sent))
        assert bus.lost_frames == 0
    finally:
        bus.shutdown()


def test_a_tap_bus_user_who_stops_reading_gets_a_warning_and_the_count(
        card_tap: tuple[TapPublisher, Path], caplog: pytest.LogCaptureFixture) -> None:
    """``Bus.recv`` is not called while more frames come than the bus and the card keep;
    then every frame ``recv`` returns plus ``lost_frames`` is the burst, and the log says
    how many were lost."""
    publisher, image = card_tap
    bus = quiet_tap_bus(publisher, image)
    try:
        sent = 2 * QUEUE_FRAMES + 10_000
        burst(publisher, sent)
        with caplog.at_level(logging.WARNING, logger="host_api.monitor.tap_bus"):
            def read_any() -> list[int]:
                msg = bus.recv(0.05)
                return [] if msg is None else [number_of(msg)]

            received = len(read_to_the_last(read_any, sent, 60))
        assert 0 < bus.lost_frames == sent - received
        warned = [r.getMessage() for r in caplog.records if "frames lost" in r.getMessage()]
        assert warned and warned[-1].endswith(f"; {bus.lost_frames} so far")
        assert "tap reader too slow" in warned[0]
    finally:
        bus.shutdown()


def test_top_shows_the_frames_its_tap_reader_lost() -> None:
    """``cifemu top``'s feed hands ``TapBus.lost_frames`` to its model: the bus line says
    its frames/s undercount, the event log says when."""
    model = CardModel()
    assert "lost" not in bus_text(model.bus(1000.0))
    model.on_frames_lost(7, 1000.0)
    model.on_frames_lost(5, 1001.0)
    assert bus_text(model.bus(1001.0)).endswith("  12 frames lost (tap reader too slow)")
    assert [e.split(" ", 1)[1] for e in model.new_events(0)] == [
        "7 frames lost (tap reader too slow)", "5 frames lost (tap reader too slow)"]


def test_the_monitor_stopped_during_a_burst_shows_the_frames_it_lost(tmp_path: Path) -> None:
    """A firmware on ``shm`` receives a burst of 10,000 frames while ``cifemu monitor`` is
    stopped (SIGSTOP); the test's own tap reader paces the burst so that the card and
    the ``shm`` ring keep up and no frame is lost before the tap. Once continued, the
    monitor shows frames and "lost" records that add up to the burst exactly, its --log
    marks the gap, and stderr has the total."""
    channel = f"tap{os.getpid()}"
    card = start_card(tmp_path, 0, "--interface", "shm", "--channel", channel)
    log_file = tmp_path / "trace.log"
    sender = can.Bus(interface="shm", channel=channel)
    own = TapBus(card.path)
    watching = subprocess.Popen(
        [sys.executable, "-m", "cifemu", "monitor", "--dpm-dir", str(tmp_path), "--json",
         "--log", str(log_file), "--duration", "300"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert watching.stdout is not None and watching.stderr is not None
    stdout = watching.stdout
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(stdout.readline, "")),
                              daemon=True)
    reader.start()
    try:
        hello = 0

        def monitor_heard_hello() -> bool:
            nonlocal hello
            sender.send(frame(HELLO_ID, hello))
            hello += 1
            return any(f'"can_id": {HELLO_ID}' in line for line in list(lines))

        wait_until(monitor_heard_hello, 60, "the monitor's first frame from the tap")
        watching.send_signal(signal.SIGSTOP)
        sent, chunk = 10_000, 500
        seen = -1
        for start in range(0, sent, chunk):
            for number in range(start, start + chunk):
                sender.send(frame(BURST_ID, number))

            def chunk_passed(last: int = start + chunk - 1) -> bool:
                nonlocal seen
                while (msg := own.recv(0.01)) is not None:
                    if msg.arbitration_id == BURST_ID:
                        seen = number_of(msg)
                return seen == last

            wait_until(chunk_passed, 60, f"burst frame {start + chunk - 1} on the tap")
        assert own.lost_frames == 0  # the card passed every frame on
        watching.send_signal(signal.SIGCONT)
        wait_until(lambda: any(f'"data": "{(sent - 1).to_bytes(8, "little").hex()}"' in line
                               for line in list(lines)), 60, "the burst's last frame shown")
        watching.send_signal(signal.SIGINT)
        commands.wait(watching, 30)
        assert ended(reader, 30), "the monitor's output was not read to its end"
        err = watching.stderr.read()
    finally:
        if watching.poll() is None:
            watching.send_signal(signal.SIGCONT)
            watching.kill()
            watching.wait()
        own.shutdown()
        sender.shutdown()
        card.stop()
    records = [json.loads(line) for line in lines]
    first = next(n for n, r in enumerate(records) if r.get("can_id") == BURST_ID)
    after_hellos = records[max(n for n, r in enumerate(records[:first])
                               if r.get("can_id") == HELLO_ID) + 1:]
    shown = [r for r in after_hellos if r.get("can_id") == BURST_ID]
    lost = sum(int(r["lost"]) for r in after_hellos if r["kind"] == "lost")
    assert watching.returncode == 0, err
    assert 0 < lost == sent - len(shown), (lost, len(shown))
    assert all(r["text"] == f"{r['lost']} frames lost (tap reader too slow)"
               for r in records if r["kind"] == "lost")
    assert f"{lost} frames lost in all (tap reader too slow)" in err
    # candump's format: python-can writes an error frame's identifier as CAN_ERR_FLAG with
    # a class of its own, and keeps byte 1, CAN_ERR_CRTL_RX_OVERFLOW
    gaps = re.findall(r" 2000[0-9A-F]{4}#0001000000000000$", log_file.read_text(), re.M)
    assert len(gaps) == sum(r["kind"] == "lost" for r in records), "a gap unmarked in --log"
