"""The device loop's mailbox turn in C (firmware/_mailbox.c) against its Python turn.

Why in process: the counts are of one device loop's turns, which only that process sees.
The parts are the real ones: two cards (``Device``) serving their images from their own
threads in one directory, one with the turn in C (the default) and one without, asked
through the driver API by a host in the test's thread, so every request reaches both
through the same image, flags and doorbell a host process uses.
"""

from __future__ import annotations

import mmap
import os
import random
import shutil
import subprocess
import sys
import sysconfig
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dpm import flags as fl
from dpm import session as s
from dpm.commands import COM_SDO_UP_DOWNLOAD, COM_SHARED_MEMORY
from dpm.doorbell import HostBell
from dpm.errors import Drv
from dpm.image import lock_path
from dpm.layout import DEV_FLAGS, DEV_MBX, HOST_FLAGS, IO_AREA_SIZE, PC_MBX, SND_PD
from dpm.message import MSG_MAX_SIZE, Message, Task, TelegramHeader, Tfc
from firmware import native_mailbox
from firmware.device import Device
from firmware.plc import HOST_CONTROLLED
from firmware.recorder import Recorder
from host_api.driver import (
    MSG_BUFFER_SIZE,
    DevCloseDriver,
    DevExchangeIO,
    DevExitBoard,
    DevGetMessage,
    DevInitBoard,
    DevOpenDriver,
    DevPutMessage,
)
from tests.conftest import wait_until

SOURCE = Path(__file__).parent.parent / "firmware" / "_mailbox.c"
READS = 500
"""COM_Shared_Memory reads a host makes in the turn count's test."""
PYTHON_TURNS_MAX = 60
"""The Python turns the device loop may take for them: the start of the fallback poll's back
off (eight turns) and the odd turn a wake-up of another thread costs; it took one Python turn
per read (500) before the turn in C."""


@dataclass
class Cards:
    native: Device
    python: Device
    turns: dict[int, int]
    """Python turns (``Device.service``) per board."""


def _serve(device: Device, turns: dict[int, int]) -> None:
    service = device.service

    def counted(now: float) -> None:
        turns[device.board] += 1
        service(now)

    device.service = counted  # type: ignore[method-assign]  # counts this card's turns
    device.run()


@pytest.fixture
def cards(tmp_path: Path) -> Iterator[Cards]:
    """Board 0 with the turn in C, board 1 without, the same process data in both; a host
    (this thread) has both open."""
    rng = random.Random(22)
    inputs = bytes(rng.getrandbits(8) for _ in range(IO_AREA_SIZE))
    outputs = bytes(rng.getrandbits(8) for _ in range(IO_AREA_SIZE))
    devices = [Device(board, tmp_path, flash_dir=tmp_path / f"flash{board}") for board in (0, 1)]
    devices[1].native = False
    turns = {0: 0, 1: 0}
    for device in devices:
        device.plc.image.write_inputs(0, inputs)
        device.plc.image.write_send_area(0, outputs)
    threads = [threading.Thread(target=_serve, args=(device, turns), daemon=True)
               for device in devices]
    for thread in threads:
        thread.start()
    try:
        assert DevOpenDriver(os.fspath(tmp_path)) == 0
        for board in (0, 1):
            wait_until(lambda b=board: DevInitBoard(b) == 0,  # type: ignore[misc]
                       what=f"board {board} READY")
        yield Cards(devices[0], devices[1], turns)
        for board in (0, 1):
            DevExitBoard(board)
        DevCloseDriver()
    finally:
        for device, thread in zip(devices, threads, strict=True):
            device.stop()
            thread.join(10)


def _ask(board: int, request: Message) -> Message:
    assert DevPutMessage(board, request, 1000) == 0
    rc, answer = DevGetMessage(board, MSG_BUFFER_SIZE, 1000)
    assert rc == 0 and answer is not None
    return answer


def _read(nr: int, area: int, adr: int, cnt: int, data_type: int, idx: int = 0) -> Message:
    return Message(rx=Task.PLC, tx=Task.USER, b=COM_SHARED_MEMORY, nr=nr & 0xFF,
                   data=TelegramHeader(data_area=area, data_adr=adr, data_idx=idx,
                                       data_cnt=cnt, data_type=data_type,
                                       function=Tfc.READ).encode())


def test_a_host_polling_the_image_costs_the_card_no_python_turn_per_read(cards: Cards) -> None:
    """COM_Shared_Memory reads in a row are answered by the turn in C: the device loop's
    Python turns stay far below one per read, and every answer is the image's bytes. On
    the old code every read took a Python turn (500 of 500)."""
    device = cards.native
    before = cards.turns[0]
    for nr in range(READS):
        answer = _ask(0, _read(nr, 1, nr % 64, 8, 5))
        offset = nr % 64
        assert answer.f == 0 and answer.nr == nr & 0xFF
        assert answer.data[8:] == bytes(device.plc.image.inputs[offset : offset + 8])
    python_turns = cards.turns[0] - before
    assert python_turns <= PYTHON_TURNS_MAX, f"{python_turns} Python turns for {READS} reads"
    device.bell.ring_self()  # the turn in C returns and counts what it served
    wait_until(lambda: device.native_turns >= READS - python_turns, what="the turns in C")


TELEGRAMS = st.builds(
    lambda adr, area, data_adr, idx, cnt, data_type, function, tail: TelegramHeader(
        adr, area, data_adr, idx, cnt, data_type, function, tail).encode(),
    st.integers(0, 255), st.sampled_from([0, 1, 2, 3, 127, 255]),
    st.one_of(st.integers(0, 40), st.integers(0, 0xFFFF)), st.integers(0, 17),
    st.one_of(st.integers(0, 12), st.integers(0, 255)),
    st.sampled_from([5, 6, 10, 14, 0, 7, 0x85, 0x8E, 255]),
    st.sampled_from([1, 1, 1, 0, 2, 3, 255]), st.binary(max_size=4))
REQUEST_DATA = st.one_of(TELEGRAMS, st.binary(max_size=12))


@settings(max_examples=300, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=REQUEST_DATA, nr=st.integers(0, 255), tx=st.integers(0, 255),
       e=st.sampled_from([0, 0, 2, 4]))
def test_the_turn_in_c_answers_as_the_python_turn(cards: Cards, data: bytes, nr: int, tx: int,
                                                  e: int) -> None:
    """Valid and malformed COM_Shared_Memory requests get the same answer bytes (msg.f,
    data, header) and leave the same flags from both cards; reads of the send area and
    of bits included. A request without an answer (msg.e NAK, no error) gets none."""
    request = Message(rx=Task.PLC, tx=tx, b=COM_SHARED_MEMORY, nr=nr, e=e, data=data)
    answers = []
    for board in (0, 1):
        assert DevPutMessage(board, request, 1000) == 0
        rc, answer = DevGetMessage(board, MSG_BUFFER_SIZE, 100 if e & 2 else 1000)
        answers.append((rc, answer.encode() if answer is not None else None))
    assert answers[0] == answers[1]
    assert cards.native.mm[HOST_FLAGS] == cards.python.mm[HOST_FLAGS]
    assert (cards.native.mm[SND_PD : SND_PD + IO_AREA_SIZE]
            == cards.python.mm[SND_PD : SND_PD + IO_AREA_SIZE])


FUZZ_REQUESTS = 3000


def fuzz(directory: str, module: str) -> None:
    """The sanitizers' run (in its own process, the sanitized build of the turn in C loaded
    as ``firmware._mailbox``): random and edge-case COM_Shared_Memory requests, each answer
    compared with what the PLC task's Python handler gives for the same request, on a card
    that records them for the first half; a quarter put by a host that writes the slot
    (msg.ln any) and the ledger (empty, its line, garbage, longer than the card's first
    read and than all it reads) itself, all of which the session holds; and host SDO
    requests of such bytes, compared with the CAN task's (taken in C once the recording
    ended: a recording card hands them to the Python turn); and between them the host's
    exchanges (served in C, recorded in the first half), the bus's inputs new at times."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("firmware._mailbox", module)
    assert spec is not None and spec.loader is not None
    sanitized = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sanitized)
    native_mailbox.serve = native_mailbox.configure(sanitized)
    device = Device(0, directory, flash_dir=Path(directory) / "flash")
    rng = random.Random(309)
    device.plc.image.write_inputs(0, rng.randbytes(IO_AREA_SIZE))
    thread = threading.Thread(target=device.run, daemon=True)
    thread.start()
    assert DevOpenDriver(directory) == 0
    wait_until(lambda: DevInitBoard(0) == 0, what="READY")
    session = Path(directory) / "session"
    recorder = _attach(device, session)
    host = BellHost(device)
    raw_puts = 0
    outputs = rng.randbytes(32)
    edges = [0, 1, 7, 8, 15, 16, 119, 120, 239, 240, 255, 1791, 1792, 3583, 3584, 0xFFFF]
    for nr in range(FUZZ_REQUESTS):
        if nr % 3:
            header = TelegramHeader(
                rng.randrange(256), rng.choice([0, 1, 2, 3]), rng.choice(edges),
                rng.choice([0, 7, 15, 16, 255]), rng.choice(edges) & 0xFF,
                rng.choice([5, 6, 10, 14, 0x85, 0]), rng.choice([1, 1, 0, 2, 3]))
            data = header.encode()
        else:
            data = rng.randbytes(rng.randrange(0, 24))
        if nr == FUZZ_REQUESTS // 2:
            records = _detach(device, recorder, session)  # the driver's: the firmware's pid,
            assert [r.kind for r in records].count(s.PUT) == raw_puts  # left out
            assert [r.kind for r in records].count(s.ANSWER) == raw_puts
        if nr % 8 == 1:  # an exchange (bMode 3's host-controlled mode), new inputs at times
            if nr % 24 == 1:
                device.plc.image.write_inputs(rng.randrange(IO_AREA_SIZE - 8), rng.randbytes(8))
            assert DevExchangeIO(0, 0, outputs, 0, 16, 1000)[0] == int(Drv.DRV_DEV_NO_COM_FLAG)
        if nr % 4 == 2:  # a host SDO request: the CAN task's, by sdo_turn in C (msg.e 0, 4)
            request = Message(rx=Task.CAN, tx=Task.USER, b=COM_SDO_UP_DOWNLOAD, nr=nr & 0xFF,
                              e=rng.choice([0, 0, 4]), data=data)
            answer = _ask(0, request)
            expected = device.can.handle(request)
            assert answer == expected, (request, answer, expected)
            continue
        request = Message(rx=Task.PLC, tx=Task.USER, b=COM_SHARED_MEMORY, nr=nr & 0xFF,
                          data=data)
        if nr % 4 == 3:
            ledger = rng.choice([b"", _line(HOST_PID, nr & 0xFF, request.b, request.rx,
                                            request.tx) + b"\0",
                                 b"9" * rng.randrange(513, 13_000),
                                 rng.randbytes(rng.randrange(0, 700))])
            raw = host.transact(_slot(request.rx, request.tx, request.nr, request.b, 0,
                                      rng.choice([len(data), rng.randrange(256)]), data),
                                ledger)
            raw_puts += 1
            assert raw is not None
            answer = Message.decode(raw)
            request = Message.decode(host.mm[DEV_MBX : DEV_MBX + MSG_MAX_SIZE])  # as taken
        else:
            answer = _ask(0, request)
        expected = device.plc.com_shared_memory(request)
        assert answer == expected, (request, answer, expected)
    host.close()
    device.bell.ring_self()
    # (a ring from the other host than the last returns to the Python turn, which serves it)
    wait_until(lambda: device.native_turns > FUZZ_REQUESTS // 4, what="the turns in C")
    DevExitBoard(0)
    DevCloseDriver()
    device.stop()
    thread.join(10)


def test_the_turn_in_c_under_the_sanitizers(tmp_path: Path) -> None:
    """Built with AddressSanitizer and UBSan, the turn in C answers random and edge-case
    requests (lengths 0-23, every area, counts and addresses at and past each limit) as
    the Python handler does, without a read or write out of bounds or undefined
    behaviour; host SDO requests of the same bytes (the card unconfigured: every answer
    comes from the call ``sdo_turn`` makes) too."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    runtimes = [subprocess.run([cc, f"-print-file-name={name}"], capture_output=True,
                               text=True, check=True).stdout.strip()
                for name in ("libasan.so", "libubsan.so")]
    if not all(Path(runtime).is_absolute() for runtime in runtimes):
        pytest.skip("no ASan/UBSan run-time libraries for this compiler")
    module = tmp_path / f"_mailbox{sysconfig.get_config_var('EXT_SUFFIX')}"
    subprocess.run([cc, "-shared", "-fPIC", "-std=gnu11", "-Wall", "-Wextra", "-Werror", "-g",
                    "-fsanitize=address,undefined", "-fno-sanitize-recover=all",
                    f"-I{sysconfig.get_paths()['include']}", str(SOURCE), "-o", str(module)],
                   check=True)
    env = {**os.environ, "LD_PRELOAD": " ".join(runtimes),
           "ASAN_OPTIONS": "detect_leaks=0"}
    directory = tmp_path / "dpm"
    directory.mkdir()
    done = subprocess.run(
        [sys.executable, "-c", "import sys, tests.test_native_mailbox as t; "
         "t.fuzz(sys.argv[1], sys.argv[2])", str(directory), str(module)],
        env=env, capture_output=True, text=True, timeout=300, check=False,
        cwd=Path(__file__).parent.parent)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "runtime error" not in done.stderr and "AddressSanitizer" not in done.stderr


# --- a recording card (issue 25) -----------------------------------------------------------


def _attach(device: Device, session: Path) -> Recorder:
    """A recording of ``device`` into ``session``, attached between two turns, as ``cifemu
    record`` attaches one to a running card."""
    recorder = Recorder.create(session, device.board, "test")
    recorder.start(device.files, device.mm, device.plc.image)
    assert device.record(recorder) is None
    return recorder


def _detach(device: Device, recorder: Recorder, session: Path) -> list[s.Record]:
    """The recording ended and its session written: its events."""
    assert device.record(None) is recorder
    recorder.close()
    assert recorder.complete
    return s.decode_events((session / s.EVENTS).read_text())


def test_a_recording_card_serves_the_reads_in_c_and_records_every_one(
        cards: Cards, tmp_path: Path) -> None:
    """A card that records a session answers COM_Shared_Memory reads in the turn in C as a
    plain card does (Python turns far below one per read), and its session holds every
    read and answer with the host's pid (from the ledger), in order, as the Python turn
    recorded them. On the old code a recording card took the Python turn for every read
    (500 of 500)."""
    device = cards.native
    recorder = _attach(device, tmp_path / "session")
    host = BellHost(device)
    before, served = cards.turns[0], device.native_turns
    try:
        for nr in range(READS):
            request = _read(nr, 1, nr % 64, 8, 5)
            raw = host.transact(request.encode(), _line(HOST_PID, nr & 0xFF, request.b,
                                                       request.rx, request.tx) + b"\0")
            assert raw is not None and Message.decode(raw).f == 0
    finally:
        host.close()
    python_turns = cards.turns[0] - before
    device.bell.ring_self()  # the turn in C returns and counts what it served
    wait_until(lambda: device.native_turns >= served + READS - python_turns,
               what="the turns in C")
    assert python_turns <= PYTHON_TURNS_MAX, f"{python_turns} Python turns for {READS} reads"
    records = _detach(device, recorder, tmp_path / "session")
    messages = [r for r in records if r.kind in (s.PUT, s.ANSWER)]
    assert [r.kind for r in messages] == [s.PUT, s.ANSWER] * READS
    for nr, (put, answered) in enumerate(zip(messages[::2], messages[1::2], strict=True)):
        assert put.msg is not None and answered.msg is not None
        assert put.msg == _read(nr, 1, nr % 64, 8, 5)
        offset = nr % 64
        assert answered.msg.nr == nr & 0xFF and answered.msg.data[8:] == bytes(
            device.plc.image.inputs[offset : offset + 8])
        assert put.pid == answered.pid == HOST_PID
        assert put.t <= answered.t
    times = [r.t for r in records]
    assert times == sorted(times)


class BellHost:
    """A host that writes the mailbox, the flags and the transaction ledger itself and rings
    through its own doorbell (``dpm.doorbell.HostBell``): any bytes a local user may write
    there reach the card (docs/security.md), the ledger's too, which the driver would have
    written in its own form."""

    def __init__(self, device: Device) -> None:
        self.device = device
        with open(device.path, "r+b") as image:
            self.mm = mmap.mmap(image.fileno(), 0)
        self.bell = HostBell(device.path)
        self.ledger = os.open(lock_path(device.directory, device.board, "transaction"),
                              os.O_WRONLY)

    def close(self) -> None:
        os.close(self.ledger)
        self.bell.close()
        self.mm.close()

    def transact(self, raw: bytes, ledger: bytes) -> bytes | None:
        """Put the message slot's bytes ``raw`` with ``ledger`` at the ledger's start, ring,
        and take the answer, if the card gives one."""
        mm = self.mm
        wait_until(lambda: not (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.DEV_MBX,
                   what="the device mailbox free")
        os.pwrite(self.ledger, ledger, 0)
        mm[DEV_MBX : DEV_MBX + len(raw)] = raw
        mm[DEV_FLAGS] ^= fl.DEVCOM
        self.bell.ring_device()
        wait_until(lambda: not (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.DEV_MBX,
                   what="the message taken")
        # The card's turn lock is held for the whole turn that took the message, in C or in
        # Python: once it is free, the answer is in PcMbx, or there is none (msg.e NAK).
        with self.device._turn:
            pass
        if not (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.HOST_MBX:
            return None
        answer = mm[PC_MBX : PC_MBX + 8 + mm[PC_MBX + 2]]
        mm[DEV_FLAGS] ^= fl.HOSTACK
        return answer


def _slot(rx: int, tx: int, nr: int, b: int, e: int, ln: int, data: bytes) -> bytes:
    """A message slot as a host may write it: msg.ln need not be the data's length."""
    return bytes((rx, tx, ln, nr, 0, 0, b, e)) + data[: MSG_MAX_SIZE - 8]


HOST_PID = os.getppid()
"""The pid the bell host's ledger lines name: not this process's, which is the firmware's,
whose messages a session leaves out (``cifemu firmware --configure``'s)."""


def _line(pid: int, nr: int, b: int, rx: int, tx: int) -> bytes:
    return b"%d 1 %d %d %d %d 0 0\n" % (pid, nr, b, rx, tx)


LEDGERS = st.one_of(
    st.just(b"\0"), st.binary(max_size=40),
    st.binary(min_size=600, max_size=700).map(lambda b: b.replace(b"\0", b"x")),
    st.integers(513, 13_000).map(lambda n: b"9" * n),
)
"""What a ledger may hold besides its host's line: nothing, any bytes, more than the card's
first read without ``END`` (it reads all of it then), more than all it reads."""

SETTLE_READS = 40
"""Plain reads at most after a hypothesis example's steps, until one is served in C (the
fallback poll backs off within ten turns)."""

STEPS = st.lists(st.tuples(
    st.sampled_from([int(Task.PLC)] * 4 + [200]), st.integers(0, 255), st.integers(0, 255),
    st.sampled_from([COM_SHARED_MEMORY] * 4 + [0x55]), st.sampled_from([0, 0, 2, 4]),
    st.one_of(st.none(), st.integers(0, 255)), REQUEST_DATA, st.booleans(), LEDGERS,
), min_size=1, max_size=5)


def _python_turn(cards: Cards, devices: tuple[Device, ...]) -> None:
    """A Python turn of each card, over when this returns: where a recording begins and
    ends, whether a fallback poll's turn saw the DevFlags between two steps is the machine's
    timing; this makes it a turn of each (the turn in C returns for the ring and counts what
    it served)."""
    turns = dict(cards.turns)
    for device in devices:
        device.bell.ring_self()
    wait_until(lambda: all(cards.turns[d.board] > turns[d.board] for d in devices),
               what="a Python turn of each card")
    for device in devices:
        with device._turn:
            pass


def _folded(records: list[s.Record]) -> list[tuple[object, ...]]:
    """The records without their time stamps, each run of DevFlags changes folded into one
    (from the first's ``before`` to the last's ``after``): whether a turn of the card saw the
    host's HOSTACK apart from its next DEVCOM is the machine's timing (a fallback poll between
    the two), in C as in Python."""
    folded: list[tuple[object, ...]] = []
    for r in records:
        entry: tuple[object, ...] = (r.kind, r.pid, r.msg, r.before, r.after, r.changes,
                                     r.state, r.parameter)
        if r.kind == s.DEV_FLAGS and folded and folded[-1][0] == s.DEV_FLAGS:
            entry = (*folded.pop()[:4], r.after, *entry[5:])
        folded.append(entry)
    return folded


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(steps=STEPS)
def test_the_turn_in_c_records_as_the_python_turn(
        cards: Cards, tmp_path_factory: pytest.TempPathFactory,
        steps: list[tuple[int, int, int, int, int, int | None, bytes, bool, bytes]]) -> None:
    """The same messages (valid and malformed COM_Shared_Memory requests, msg.ln other than
    the data's, other commands and tasks, NAK) with the same ledger bytes (the host's line,
    none, garbage, longer than the card's first read, longer than all it reads), put to a
    recording card with the turn in C and to one without, make the same session, field by
    field but the time stamps; and the card with the turn in C served the read that ends
    them there (on the old code a recording card served none in C)."""
    sessions = [tmp_path_factory.mktemp("session") / "s" for _ in (0, 1)]
    devices = (cards.native, cards.python)
    recorders = [_attach(device, session)
                 for device, session in zip(devices, sessions, strict=True)]
    hosts = [BellHost(device) for device in devices]
    try:
        _python_turn(cards, devices)  # each card's recording begins with DevFlags as they are
        served = cards.native.native_turns
        for rx, tx, nr, b, e, ln, data, own, ledger in steps:
            raw = _slot(rx, tx, nr, b, e, len(data) if ln is None else ln, data)
            lines = (_line(HOST_PID, nr, b, rx, tx) if own else b"") + ledger
            answers = [host.transact(raw, lines) for host in hosts]
            assert answers[0] == answers[1]
        # Then plain reads until one was served in C: a turn that records begins in Python
        # (the turn in C that waited took the card for one that does not), and so do the
        # turns after a start until the fallback poll has backed off.
        for nr in range(SETTLE_READS):
            request = _read(nr, 1, nr, 4, 5)
            lines = _line(HOST_PID, nr, request.b, request.rx, request.tx)
            python_turns = cards.turns[0]
            answers = [host.transact(request.encode(), lines) for host in hosts]
            assert answers[0] == answers[1]
            if cards.turns[0] == python_turns:  # answered without a Python turn
                break
        _python_turn(cards, devices)  # after the last HOSTACK, before the recording ends
        assert cards.native.native_turns > served, "no turn in C"
    finally:
        for host in hosts:
            host.close()
        native, python = (_detach(device, recorder, session) for device, recorder, session
                          in zip(devices, recorders, sessions, strict=True))
    assert _folded(native) == _folded(python)


# --- the process-data exchange in C (issue 25) -----------------------------------------------


EXCHANGES = 300
"""Host-controlled exchanges in the exchange test: a few with new outputs, new inputs, a
flipped input bit; the rest as a PDO loop in a steady state makes them."""


def _step_kinds(rng: random.Random) -> list[str]:
    kinds = ["same"] * EXCHANGES
    for n in rng.sample(range(EXCHANGES), 60):
        kinds[n] = rng.choice(["outputs", "inputs", "inputs", "flip"])
    return kinds


def _answered(device: Device) -> None:
    """Until ``device`` answered the host's exchange (PDACK) and ended the turn that did."""
    mm = device.mm
    wait_until(lambda: not (mm[HOST_FLAGS] ^ mm[DEV_FLAGS]) & fl.PD, what="PDACK")
    with device._turn:  # the turn that answered records after its ring, holding this
        pass


def test_the_exchange_in_c_answers_and_records_as_the_python_turn(
        cards: Cards, tmp_path: Path) -> None:
    """DevExchangeIO in the buffered host-controlled mode against a recording card with the
    turn in C and one without: every exchange gives both hosts the same inputs (new inputs
    of the bus, an input bit the fault "flip" inverts once), both cards take the same
    outputs (the CAN master's copy), and both sessions are the same, field by field but the
    time stamps. The card with the turn in C serves the exchanges that bring no new output
    there: its Python turns stay far below one per exchange (on the old code every exchange
    took one, 300 of 300)."""
    devices = (cards.native, cards.python)
    assert all(device.plc.image.mode in HOST_CONTROLLED for device in devices)
    sessions = [tmp_path / f"session{device.board}" for device in devices]
    recorders = [_attach(device, session)
                 for device, session in zip(devices, sessions, strict=True)]
    rng = random.Random(25)
    outputs = rng.randbytes(IO_AREA_SIZE)
    _python_turn(cards, devices)
    before, served = cards.turns[0], cards.native.native_turns
    try:
        for kind in _step_kinds(rng):
            if kind == "outputs":
                outputs = outputs[:8] + rng.randbytes(8) + outputs[16:]
            elif kind == "inputs":
                offset, data = rng.randrange(IO_AREA_SIZE - 8), rng.randbytes(8)
                for device in devices:  # as the bus delivers them
                    device.plc.image.write_inputs(offset, data)
            elif kind == "flip":
                offset, bit = rng.randrange(64), rng.randrange(8)
                for device in devices:  # the fault "flip", once (firmware/faults.py)
                    with device.between_turns():
                        device.plc.image.flip_inputs(offset, 1 << bit, once=True)
            # The driver hands over the outputs and takes the inputs of the exchange before
            # (the image's RcvPd), then toggles PDCOM and returns: each card's answer is
            # awaited here, so that the next step's inputs come after it on both cards.
            got = [DevExchangeIO(device.board, 0, outputs, 0, 64, 1000) for device in devices]
            assert got[0] == got[1]
            assert got[0][0] == int(Drv.DRV_DEV_NO_COM_FLAG)  # no bus configured: no COM
            for device in devices:
                _answered(device)
                assert bytes(device.plc.image.outputs) == outputs
    finally:
        python_turns = cards.turns[0] - before
        _python_turn(cards, devices)  # the turn in C returns, its turns counted
        records = [_detach(device, recorder, session) for device, recorder, session
                   in zip(devices, recorders, sessions, strict=True)]
    assert python_turns <= EXCHANGES // 3, f"{python_turns} Python turns for {EXCHANGES}"
    assert cards.native.native_turns - served >= EXCHANGES - python_turns
    assert _folded(records[0]) == _folded(records[1])
    exchanges = [r for r in records[0] if r.kind == s.EXCHANGE]
    assert len(exchanges) == EXCHANGES
    assert sum(1 for r in exchanges if r.changes) >= 40  # the outputs', inputs', flips'
