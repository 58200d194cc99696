"""Property-based fuzz of the mailbox against one running card, through the host API.

Thousands of messages (random, structured COM_Shared_Memory telegrams, random messages to
the RCS and CAN tasks) go to one firmware process. Properties for each message:

- exactly one answer, with rx/tx swapped, a == b of the command, b == 0, nr echoed,
  and f != 254 (254 is the firmware's "internal error": a handler raised);
- the firmware process stays alive;
- nothing in the image changes outside the areas the message addressed (the mailboxes and
  flag bytes are the handshake's own and are ignored);
- COM_Shared_Memory follows seed manual 5.1.1: a valid command succeeds, echoes its telegram
  header and reads back what a model of both areas holds; an invalid one gets one of the
  error numbers that apply to it and no data.

CIFEMU_FUZZ_EXAMPLES sets the total number of examples (default 3000), split 40/40/20 over
the random, the COM_Shared_Memory and the RCS/CAN strategies.
"""

from __future__ import annotations

import mmap
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from hypothesis import HealthCheck, currently_in_test_context, event, example, given, settings
from hypothesis import strategies as st

from dpm.com import decode_layer2_frames
from dpm.commands import COM_TX_CAN_LAYER2
from dpm.errors import F_INTERNAL_ERROR, F_UNKNOWN_COMMAND, F_UNKNOWN_TASK
from dpm.message import Message, MessageError, Task
from host_api.driver import (
    DevCloseDriver,
    DevGetMessage,
    DevInitBoard,
    DevOpenDriver,
    DevPutMessage,
)
from tests.conftest import Card, start_card

TOTAL_EXAMPLES = max(3, int(os.environ.get("CIFEMU_FUZZ_EXAMPLES", "3000")))
RANDOM_EXAMPLES = TOTAL_EXAMPLES * 2 // 5
SHARED_MEMORY_EXAMPLES = TOTAL_EXAMPLES * 2 // 5
TASK_EXAMPLES = TOTAL_EXAMPLES - RANDOM_EXAMPLES - SHARED_MEMORY_EXAMPLES

BOARD = 0
MSG_SIZE = 288
ANSWER_TIMEOUT_MS = 5000
EXTRA_ANSWER_WAIT_MS = 2
"""How long to watch for a second answer after the first (the device answers in < 1 ms)."""
NAK = 0x02  # RCS_NAK_MSK in msg.e
KNOWN_TASKS = (0, 2, 3)  # RCS, PLC, CAN (seed manual 1.1 and 5)
USER, PLC = 16, 2
COM_SHARED_MEMORY = 17
UNKNOWN_PLC_COMMAND = 99
"""A msg.b the PLC task does not know: answered at once with F_UNKNOWN_COMMAND."""

# --- the image (docs/dpm.md section 1) ---------------------------------------------------
IMAGE_SIZE = 8192
SND_PD, RCV_PD, IO_SIZE = 0x0000, 0x0E00, 3584
IGNORED = ((0x1C00, 0x1D20), (0x1D40, 0x1E60), (0x1FFE, 0x2000))
"""DevMbx, PcMbx and the two flag bytes: the handshake itself writes them."""

# --- COM_Shared_Memory (seed manual 5.1.1) ---------------------------------------------------
TELEGRAM = struct.Struct("<BBHBBBB")
AREA_BY_FUNCTION, AREA_RECEIVE, AREA_SEND = 0, 1, 2
UINT8, UINT16, STRING, BIT = 5, 6, 10, 14
READ, WRITE = 1, 2
MAX_COUNT = {UINT8: 239, STRING: 239, UINT16: 119, BIT: 255}
MAX_ADDRESS = {UINT8: 3583, STRING: 3583, UINT16: 1791, BIT: 1791}
SHM_ERRORS = frozenset({162, 163, 165, 166, 167})
MAX_PAYLOAD = 255 - TELEGRAM.size

BYTE = st.integers(0, 255)
NOT_NAK = BYTE.map(lambda e: e & ~NAK)
# Bit 0x02 of msg.e (NAK) is cleared in every generated message: it suppresses a successful
# answer, so "exactly one answer" would not hold for it. test_nak_* covers NAK on its own.


@dataclass
class Harness:
    card: Card
    mm: mmap.mmap
    inputs: bytearray = field(default_factory=lambda: bytearray(IO_SIZE))
    """Model of the receive process data as the device holds it (written only by
    COM_Shared_Memory here: no configuration, so no bus fills it)."""


@pytest.fixture(scope="module")
def fuzz(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Harness]:
    card = start_card(Path(tmp_path_factory.mktemp("fuzz")))
    try:
        assert DevOpenDriver(card.directory) == 0
        assert DevInitBoard(BOARD) == 0
        mm = card.map()
        harness = Harness(card, mm)
        yield harness
        mm.close()
    finally:
        while DevCloseDriver() == 0:
            pass
        card.stop()


# --- the COM_Shared_Memory model ----------------------------------------------------------------


@dataclass
class Access:
    """A valid COM_Shared_Memory command: area 1/2, the bits it covers, the payload."""

    area: int
    function: int
    first_bit: int
    bits: int
    header: bytes
    payload: bytes

    @property
    def byte_range(self) -> tuple[int, int]:
        return self.first_bit // 8, (self.first_bit + self.bits + 7) // 8

    @property
    def answer_size(self) -> int:
        return (self.bits + 7) // 8


def payload_size(data_type: int, count: int) -> int | None:
    if data_type == BIT:
        return (count + 7) // 8
    if data_type in MAX_COUNT:
        return count * (2 if data_type == UINT16 else 1)
    return None


def shm_model(data: bytes) -> tuple[frozenset[int], Access | None]:
    """The error numbers that apply to a command (empty: it must succeed) and its access."""
    if len(data) < TELEGRAM.size:
        return SHM_ERRORS, None  # no telegram header at all: any of the table's errors
    _, area, adr, idx, cnt, data_type, function = TELEGRAM.unpack_from(data)
    payload = data[TELEGRAM.size :]
    errors: set[int] = set()
    first_bit = bits = 0
    if function not in (READ, WRITE):
        errors.add(167)
    if data_type not in MAX_COUNT:
        errors.add(166)
    if area not in (AREA_BY_FUNCTION, AREA_RECEIVE, AREA_SEND):
        errors.add(162)
    if data_type in MAX_COUNT:
        if not 1 <= cnt <= MAX_COUNT[data_type]:
            errors.add(165)
        if data_type == BIT:
            first_bit, bits = adr * 16 + idx, cnt
            if idx > 15:
                errors.add(163)
        else:
            width = 2 if data_type == UINT16 else 1
            first_bit, bits = adr * width * 8, cnt * width * 8
        if adr > MAX_ADDRESS[data_type] or first_bit + bits > IO_SIZE * 8:
            errors.add(163)
        if function == WRITE and len(payload) != payload_size(data_type, cnt):
            errors.add(165)
    if errors:
        return frozenset(errors), None
    if area == AREA_BY_FUNCTION:
        area = AREA_RECEIVE if function == READ else AREA_SEND
    return frozenset(), Access(area, function, first_bit, bits, data[: TELEGRAM.size], payload)


def get_bits(area: bytes | bytearray, first: int, count: int) -> bytes:
    """``count`` bits from bit ``first`` on, packed from bit 0 of the first byte."""
    value = int.from_bytes(area, "little") >> first
    return (value & ((1 << count) - 1)).to_bytes((count + 7) // 8, "little")


def put_bits(area: bytearray, first: int, count: int, packed: bytes) -> None:
    mask = ((1 << count) - 1) << first
    value = int.from_bytes(area, "little")
    value = (value & ~mask) | ((int.from_bytes(packed, "little") << first) & mask)
    area[:] = value.to_bytes(len(area), "little")


# --- one exchange and its properties ------------------------------------------------------------


def masked(image: bytes, extra: tuple[int, int] | None) -> bytearray:
    copy = bytearray(image)
    for start, end in (*IGNORED, *([extra] if extra else [])):
        copy[start:end] = bytes(end - start)
    return copy


def note(text: str) -> None:
    """Hypothesis's statistics event, when a property runs (plain tests call exchange too)."""
    if currently_in_test_context():
        event(text)


def answered(msg: Message) -> bool:
    """Whether the card answers ``msg``: a well-formed COM_Tx_CAN_Layer2 has no answer
    (seed 5.3.1), every other message has exactly one."""
    if msg.rx != Task.CAN or msg.b != COM_TX_CAN_LAYER2:
        return True
    try:
        decode_layer2_frames(msg.data)
    except MessageError:
        return True
    return False


def expect_no_answer(msg: Message) -> None:
    """The mailbox keeps order, so a command sent after ``msg`` whose answer comes first
    proves ``msg`` was not answered, without waiting for a time-out."""
    probe = Message(rx=PLC, tx=USER, b=UNKNOWN_PLC_COMMAND, nr=(msg.nr + 1) % 256)
    assert DevPutMessage(BOARD, probe, ANSWER_TIMEOUT_MS) == 0
    rc, answer = DevGetMessage(BOARD, MSG_SIZE, ANSWER_TIMEOUT_MS)
    assert rc == 0 and answer is not None, f"no answer to the probe after {msg} (rc {rc})"
    assert (answer.nr, answer.a, answer.f) == (probe.nr, probe.b, F_UNKNOWN_COMMAND), (
        f"an answer {answer} to {msg}, which has none")


def exchange(h: Harness, msg: Message) -> Message | None:
    """Send ``msg``, take its one answer (or make sure it has none), check every property."""
    mm = h.mm
    before = bytes(mm[:IMAGE_SIZE])
    assert DevPutMessage(BOARD, msg, ANSWER_TIMEOUT_MS) == 0
    answer: Message | None = None
    if answered(msg):
        rc, answer = DevGetMessage(BOARD, MSG_SIZE, ANSWER_TIMEOUT_MS)
        assert rc == 0 and answer is not None, f"no answer to {msg} (rc {rc})"
    else:
        expect_no_answer(msg)
        note("no answer: a well-formed COM_Tx_CAN_Layer2")
    rc, extra = DevGetMessage(BOARD, MSG_SIZE, EXTRA_ANSWER_WAIT_MS)
    assert rc == -18, f"a second answer {extra} to {msg} (rc {rc})"
    after = bytes(mm[:IMAGE_SIZE])
    assert h.card.proc.poll() is None, "the firmware process died"
    if answer is None:
        expected, got = masked(before, None), masked(after, None)
        assert expected == got, f"{msg} changed the image"
        return None

    assert (answer.rx, answer.tx, answer.a, answer.b, answer.nr) == (
        msg.tx, msg.rx, msg.b, 0, msg.nr), f"answer {answer} to {msg}"
    assert answer.f != F_INTERNAL_ERROR, f"internal firmware error on {msg}"
    if msg.rx not in KNOWN_TASKS:
        assert answer.f == F_UNKNOWN_TASK
    elif msg.rx == PLC and msg.b != COM_SHARED_MEMORY:
        assert answer.f == F_UNKNOWN_COMMAND

    note(f"rx {msg.rx if msg.rx in KNOWN_TASKS else 'other'}: f = {answer.f}")
    changed: tuple[int, int] | None = None
    if msg.rx == PLC and msg.b == COM_SHARED_MEMORY:
        changed = check_shared_memory(h, msg, answer, before, after)
    expected, got = masked(before, changed), masked(after, changed)
    if expected != got:
        diff = [hex(i) for i in range(IMAGE_SIZE) if expected[i] != got[i]]
        pytest.fail(f"{msg} changed the image outside its areas at {diff[:16]}")
    return answer


def check_shared_memory(
    h: Harness, msg: Message, answer: Message, before: bytes, after: bytes
) -> tuple[int, int] | None:
    """COM_Shared_Memory against the model; the image range the command may change."""
    errors, access = shm_model(msg.data)
    if access is None:
        assert answer.f in errors, f"f {answer.f} not in {sorted(errors)} for {msg}"
        assert answer.data == b"", "an error answer carries no data"
        return None
    assert answer.f == 0, f"f {answer.f} for the valid {msg}"
    assert answer.data[: TELEGRAM.size] == access.header, "the telegram header is echoed"
    base = SND_PD if access.area == AREA_SEND else RCV_PD
    note(f"valid {('', 'read', 'write')[access.function]} of area {access.area}")
    if access.function == READ:
        area = before[SND_PD : SND_PD + IO_SIZE] if access.area == AREA_SEND else h.inputs
        assert answer.data[TELEGRAM.size :] == get_bits(area, access.first_bit, access.bits)
        return None
    assert answer.ln == TELEGRAM.size, "a write answer has no data"
    if access.area == AREA_RECEIVE:
        put_bits(h.inputs, access.first_bit, access.bits, access.payload)
    else:
        send = bytearray(before[SND_PD : SND_PD + IO_SIZE])
        put_bits(send, access.first_bit, access.bits, access.payload)
        start, end = access.byte_range
        assert after[SND_PD + start : SND_PD + end] == send[start:end], "the write landed"
    start, end = access.byte_range
    return base + start, base + end


# --- strategies ---------------------------------------------------------------------------------

random_messages = st.builds(
    Message,
    rx=BYTE,
    tx=BYTE,
    b=BYTE,
    data=st.binary(max_size=255),
    nr=BYTE,
    a=BYTE,
    f=BYTE,
    e=NOT_NAK,
)

task_messages = st.builds(
    Message,
    rx=st.sampled_from((0, 3)),
    tx=st.one_of(st.just(USER), BYTE),
    b=BYTE,
    data=st.binary(max_size=255),
    nr=BYTE,
    a=BYTE,
    f=BYTE,
    e=NOT_NAK,
)


@st.composite
def shared_memory_messages(draw: st.DrawFn) -> Message:
    """COM_Shared_Memory commands: half of them plausible (known type, function and area,
    a count in range, addresses biased to the end of the area), the rest random."""
    plausible = draw(st.booleans())
    if plausible:
        data_type = draw(st.sampled_from(sorted(MAX_COUNT)))
        function = draw(st.sampled_from((READ, WRITE)))
        area = draw(st.sampled_from((AREA_BY_FUNCTION, AREA_RECEIVE, AREA_SEND)))
        count = draw(st.integers(1, MAX_COUNT[data_type]))
        idx = draw(st.one_of(st.integers(0, 15), st.integers(0, 15), BYTE))
        top = MAX_ADDRESS[data_type]
        adr = draw(st.one_of(st.integers(0, top), st.integers(top - 260, top + 2)))
    else:
        data_type = draw(st.one_of(st.sampled_from(sorted(MAX_COUNT)), BYTE))
        function = draw(st.one_of(st.sampled_from((READ, WRITE)), BYTE))
        area = draw(st.one_of(st.sampled_from((0, 1, 2)), BYTE))
        count = draw(BYTE)
        idx = draw(BYTE)
        adr = draw(st.one_of(st.integers(0, 3600), st.integers(0, 0xFFFF)))
    header = TELEGRAM.pack(draw(BYTE), area, adr, idx, count, data_type, function)
    size = payload_size(data_type, count)
    if function == WRITE and size is not None and size <= MAX_PAYLOAD and draw(st.booleans()):
        payload = draw(st.binary(min_size=size, max_size=size))
    elif function == READ and draw(st.booleans()):
        payload = b""
    else:
        payload = draw(st.binary(max_size=MAX_PAYLOAD))
    data = header + payload
    if not plausible and draw(st.integers(0, 9)) == 0:
        data = data[: draw(st.integers(0, TELEGRAM.size - 1))]  # a truncated header
    return Message(
        rx=PLC,
        tx=draw(st.one_of(st.just(USER), BYTE)),
        b=COM_SHARED_MEMORY,
        data=data,
        nr=draw(BYTE),
        a=draw(BYTE),
        f=draw(BYTE),
        e=draw(NOT_NAK),
    )


def fuzz_settings(examples: int) -> settings:
    return settings(
        max_examples=examples,
        deadline=None,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    )


# --- the properties -----------------------------------------------------------------------------


@fuzz_settings(RANDOM_EXAMPLES)
@given(msg=random_messages)
def test_random_messages(fuzz: Harness, msg: Message) -> None:
    exchange(fuzz, msg)


@fuzz_settings(SHARED_MEMORY_EXAMPLES)
@given(msg=shared_memory_messages())
def test_shared_memory_messages(fuzz: Harness, msg: Message) -> None:
    exchange(fuzz, msg)


@fuzz_settings(TASK_EXAMPLES)
@given(msg=task_messages)
@example(msg=Message(rx=Task.CAN, tx=USER, b=COM_TX_CAN_LAYER2, data=bytes([0x30, 0x22, 1, 2])))
def test_rcs_and_can_task_messages(fuzz: Harness, msg: Message) -> None:
    exchange(fuzz, msg)


@pytest.mark.parametrize(("data", "has_answer"), [
    (bytes([0x30, 0x22, 0x01, 0x02, 0xE0, 0x31]), False),  # two frames: no answer (seed 5.3.1)
    (bytes([0x30, 0x22, 0x01]), True),                      # a frame cut short: f 55
    (b"", True),                                            # no frame at all: f 55
])
def test_layer2_transmission_is_answered_only_when_malformed(
        fuzz: Harness, data: bytes, has_answer: bool) -> None:
    msg = Message(rx=Task.CAN, tx=USER, b=COM_TX_CAN_LAYER2, data=data, nr=0x5C)
    assert answered(msg) == has_answer
    answer = exchange(fuzz, msg)
    assert (answer is not None) == has_answer
    if answer is not None:
        assert answer.f == 55


def shm(nr: int, area: int, adr: int, function: int, payload: bytes = b"", e: int = 0) -> Message:
    header = TELEGRAM.pack(0, area, adr, 0, max(len(payload), 1), UINT8, function)
    return Message(rx=PLC, tx=USER, b=COM_SHARED_MEMORY, data=header + payload, nr=nr, e=e)


def test_nak_suppresses_only_successful_answers(fuzz: Harness) -> None:
    """msg.e bit 0x02: no answer on success, the error answer still comes."""
    # a successful write with NAK: executed, never answered
    assert DevPutMessage(BOARD, shm(0xA1, AREA_SEND, 3000, WRITE, b"\x5a", NAK), 1000) == 0
    # an unknown command with NAK: the error answer still comes; it is the first answer
    assert DevPutMessage(BOARD, Message(rx=PLC, tx=USER, b=99, nr=0xA2, e=NAK), 1000) == 0
    rc, answer = DevGetMessage(BOARD, MSG_SIZE, ANSWER_TIMEOUT_MS)
    assert rc == 0 and answer is not None
    assert (answer.nr, answer.a, answer.f) == (0xA2, 99, F_UNKNOWN_COMMAND)
    # a successful read with NAK: no answer either; the next answer is the plain read's
    assert DevPutMessage(BOARD, shm(0xA3, AREA_SEND, 3000, READ, e=NAK), 1000) == 0
    assert DevPutMessage(BOARD, shm(0xA4, AREA_SEND, 3000, READ), 1000) == 0
    rc, answer = DevGetMessage(BOARD, MSG_SIZE, ANSWER_TIMEOUT_MS)
    assert rc == 0 and answer is not None
    assert (answer.nr, answer.f, answer.data[TELEGRAM.size :]) == (0xA4, 0, b"\x5a")
    rc, _ = DevGetMessage(BOARD, MSG_SIZE, 20)
    assert rc == -18, "no answer may follow"
    assert fuzz.mm[SND_PD + 3000] == 0x5A
