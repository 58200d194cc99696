"""Fuzzing the readers: every input either parses or raises DbmError, nothing else.

The normal run is a few seconds; CIFEMU_FUZZ_EXAMPLES=100000 makes a dedicated long run.
"""

from __future__ import annotations

import os
import random
import struct
from contextlib import suppress

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dbm_tools.container import DbmFile, DbmTable, read_data_area, read_dbm, write_dbm
from dbm_tools.errors import DbmError
from dbm_tools.parameters import (
    BusParameterSet,
    ExtendedBusParameterSet,
    NodeParameterSet,
    PdoData,
    SdoCfgData,
)
from dbm_tools.tables import DescriptRecord, GlobalSet, NodesRecord, ProjektRecord
from dbm_tools.validate import (
    check_bus_parameters,
    check_dbm,
    check_extended_bus_parameters,
    check_node_parameters,
)
from tests.fixtures import REAL_DBM, needs_real_dbm

REAL = REAL_DBM.read_bytes() if REAL_DBM.is_file() else b""
NODE = NodeParameterSet(
    usCobIDEmcy=0x85,
    usCobIDGuard=0x705,
    atSdoCfgData=[SdoCfgData(0x1017, 0, 2, b"\xe8\x03\0\0")],
    atPdoCfgData=[PdoData(1, 4, 0x185, 1), PdoData(0, 0x82, 0x205, 255)],
    ausInputOffsets=[4],
    ausOutputOffsets=[8],
).encode()
BUILT = write_dbm(
    DbmFile(
        [
            DbmTable("GLOBAL", [GlobalSet().encode()]),
            DbmTable("BUS_CAN_EXT", [ExtendedBusParameterSet().encode()]),
            DbmTable("NODES", [bytes([a]) + NODE for a in (5, 40, 6)] + [b"\x07"], key_length=1),
            DbmTable("BUS_CAN", [BusParameterSet().encode()]),
            DbmTable("ODD", [b"x", b"yyy"]),
            DbmTable("MANY", [bytes([i, 0, i]) for i in range(35)], key_length=2),
        ]
    )
)

EXAMPLES = int(os.environ.get("CIFEMU_FUZZ_EXAMPLES", "2000"))
"""Examples of the reader fuzz (a fifth of them on SyCon's file); the data-set fuzz gets half.
Hypothesis costs about a millisecond per example here, so this file takes a few seconds."""


def fuzz(examples: int) -> settings:
    return settings(
        max_examples=examples,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


def reseal(raw: bytes) -> bytes:
    """Fix the lengths (header, w5, w6) and w0 of a mutated file so that the deeper checks
    get exercised."""
    if len(raw) < 60 or len(raw) % 2 or len(raw) - 44 > 0xFFFF:
        return raw
    area = bytearray(raw[44:])
    area[10:14] = struct.pack("<HH", len(area) // 2, len(area) // 2)
    area[0:2] = struct.pack("<H", sum(struct.unpack(f"<{len(area) // 2 - 1}H", area[2:])) & 0xFFFF)
    return raw[:38] + struct.pack("<H", len(area)) + raw[40:44] + bytes(area)


SEEDS = st.integers(0, 2**64 - 1)
"""Mutations come from a seeded RNG, one draw per example: drawing each edit through
hypothesis cost ten times more than parsing the result. A failure still reports its seed."""


def mutate(original: bytes, seed: int) -> bytes:
    rng = random.Random(seed)
    data = bytearray(original)
    for _ in range(rng.randint(1, 6)):
        kind = rng.choice(["flip", "set", "word"] * 3 + ["cut", "insert", "delete"])
        at = rng.randrange(max(len(data), 1))
        if kind == "flip" and data:
            data[at] ^= 1 << rng.randrange(8)
        elif kind == "set" and data:
            data[at] = rng.randrange(256)
        elif kind == "word" and len(data) > at + 1:
            data[at : at + 2] = struct.pack("<H", rng.randrange(0x10000))
        elif kind == "cut":
            del data[at:]
        elif kind == "insert":
            data[at:at] = rng.randbytes(rng.randint(1, 8))
        elif kind == "delete":
            del data[at : at + rng.randint(1, 8)]
    return reseal(bytes(data)) if rng.random() < 0.5 else bytes(data)


def read_anything(raw: bytes) -> None:
    """Parse, and when that works also run the database checks, which must not raise either."""
    try:
        dbm = read_dbm(raw)
    except DbmError:
        return
    check_dbm(dbm)
    assert read_dbm(write_dbm(dbm)) == dbm


HEADER = BUILT[:44]

FILES = st.one_of(
    st.binary(max_size=600),
    st.binary(max_size=600).map(lambda raw: HEADER + raw),
    st.binary(max_size=600).map(lambda raw: reseal(HEADER + raw)),
    SEEDS.map(lambda seed: mutate(BUILT, seed)),
)
"""Random bytes, random data areas behind a valid header (some with a valid w0), and
mutations of one of our files."""


@fuzz(EXAMPLES * 4 // 5)
@given(FILES)
def test_reader(raw: bytes) -> None:
    read_anything(raw)
    with suppress(DbmError):
        read_data_area(raw[44:])


@needs_real_dbm
@fuzz(EXAMPLES // 5)
@given(SEEDS)
def test_reader_on_mutations_of_sycons_file(seed: int) -> None:
    raw = mutate(REAL, seed)
    read_anything(raw)
    with suppress(DbmError):
        read_data_area(raw[44:])


@fuzz(EXAMPLES // 2)
@given(
    st.one_of(st.binary(max_size=260), SEEDS.map(lambda seed: mutate(NODE, seed))),
    st.integers(-1, 300),
)
def test_data_sets(data: bytes, node: int) -> None:
    """Data-set decoders are exact inverses where they accept, and checks never raise."""
    check_node_parameters(data, node)
    check_bus_parameters(data[:7])
    check_extended_bus_parameters(data[:41])
    try:
        decoded = NodeParameterSet.decode(data)
    except DbmError as error:
        assert error.number in {59, 61, 64, 71, 72, 76}
    else:
        assert decoded.encode() == data
    for codec in (GlobalSet, ProjektRecord, DescriptRecord, NodesRecord):
        with suppress(DbmError):
            assert codec.decode(data).encode() == data
