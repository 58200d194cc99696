"""The session format's codec (dpm/session.py), without a card: every kind of record reads
back as written, a malformed line is refused with its reason, the changed bytes of an
exchange and the ledger's pid are what docs/recording.md says."""

from __future__ import annotations

import json
import re

import pytest

from dpm import flags as fl
from dpm import session as s
from dpm.ledger import LedgerLine, decode_line
from dpm.message import Message

ROUND_TRIP = [
    s.Record(s.PUT, 1.5, 1e9, 4242, msg=Message(3, 16, 74, bytes(8), nr=7)),
    s.Record(s.ANSWER, 1.6, 1e9, None, msg=Message(16, 3, 0, b"\x01", nr=7, a=74, f=3),
             state=bytes(range(64))),
    s.Record(s.HOST_FLAGS, 1.7, 1e9, before=0x80, after=0x84),
    s.Record(s.DEV_FLAGS, 1.8, 1e9, before=0, after=fl.INIT, parameter=b"\x03" + bytes(47)),
    s.Record(s.EXCHANGE, 1.9, 1e9, changes={"SndPd": [(0, b"\xa0\xa1")], "RcvPd": [(3, b"\x01")]},
             state=bytes(64)),
]


@pytest.mark.parametrize("record", ROUND_TRIP, ids=[r.kind for r in ROUND_TRIP])
def test_every_kind_of_record_reads_back_as_written(record: s.Record) -> None:
    line = s.encode_record(record)
    assert json.loads(line)["kind"] == record.kind  # plain JSON, as docs/recording.md says
    assert s.decode_record(line) == record


@pytest.mark.parametrize(("line", "error"), [
    ('{"kind":"put","t":1,"wall":1,"pid":null,"msg":{"rx":3,"tx":16,"ln":2,"nr":0,"a":0,'
     '"f":0,"b":74,"e":0,"data":"00"}}', "msg.ln is not the length"),
    ('{"kind":"put","t":1,"wall":1,"pid":null,"msg":{"rx":300,"tx":16,"ln":0,"nr":0,"a":0,'
     '"f":0,"b":74,"e":0,"data":""}}', "'rx' is not an integer 0..255"),
    ('{"kind":"host_flags","t":1,"wall":1,"pid":true,"before":0,"after":1}', "not a process id"),
    ('{"kind":"host_flags","t":"x","wall":1,"pid":null,"before":0,"after":1}', "'t' is not"),
    ('{"kind":"exchange","t":1,"wall":1,"pid":null,"changes":{"PcMbx":[]}}', "the areas"),
    ('{"kind":"exchange","t":1,"wall":1,"pid":null,"changes":{"SndPd":[[0,"zz"]]}}',
     "not [offset, hex]"),
    ("[1, 2]", "not a JSON object"),
    ("{", "not JSON"),
])
def test_a_malformed_record_is_refused_with_the_reason(line: str, error: str) -> None:
    with pytest.raises(s.SessionError, match=re.escape(error)):
        s.decode_record(line)


def test_changed_runs_are_the_bytes_that_differ() -> None:
    old = bytes(200)
    new = bytearray(old)
    new[0:2] = b"\x01\x02"  # at the start
    new[63:66] = b"\x03\x04\x05"  # across a comparison chunk's edge
    new[199] = 6  # at the end
    assert s.changed_runs(old, bytes(new)) == [(0, b"\x01\x02"), (63, b"\x03\x04\x05"),
                                               (199, b"\x06")]
    assert s.changed_runs(old, old) == []
    image = bytearray(old)
    s.apply_runs(image, s.changed_runs(old, bytes(new)))
    assert image == new


def test_the_ledger_names_the_sender_of_a_message() -> None:
    ledger = b"111 9 6 74 3 16 0 5\n222 8 7 74 3 16 0 6\n"
    assert s.ledger_pid(ledger, Message(3, 16, 74, nr=7)) == 222
    assert s.ledger_pid(ledger, Message(3, 16, 74, nr=8)) is None
    assert s.ledger_pid(b"garbage\n", Message(3, 16, 74, nr=7)) is None
    # [ours] what follows the ledger's END (a NUL) is left from a longer ledger
    assert s.ledger_pid(b"\0" + ledger, Message(3, 16, 74, nr=7)) is None


@pytest.mark.parametrize("record", ROUND_TRIP[:2], ids=[r.kind for r in ROUND_TRIP[:2]])
def test_the_writers_fast_line_is_the_codecs_line(record: s.Record) -> None:
    """The session writer encodes puts and answers from the mailbox bytes, without a Message
    (firmware/session_writer.py): the same line as the codec's, a mailbox slot's trailing
    bytes after msg.ln left out."""
    assert record.msg is not None
    slot = record.msg.encode().ljust(288, b"\xee")
    assert s.encode_message(record.kind, record.t, record.wall, record.pid, slot,
                            record.state) == s.encode_record(record)


@pytest.mark.parametrize("record", ROUND_TRIP[2:4], ids=[r.kind for r in ROUND_TRIP[2:4]])
def test_the_writers_fast_flags_line_is_the_codecs_line(record: s.Record) -> None:
    assert s.encode_flags(record.kind, record.t, record.wall, record.before, record.after,
                          record.parameter) == s.encode_record(record)


def test_a_ledger_line_round_trips_and_a_malformed_one_is_refused() -> None:
    """One format for host_api, libcif and the recorder (dpm.ledger); a line a dying host
    cut short, or a local user wrote, names nobody."""
    entry = LedgerLine(4242, 7, 9, 74, 3, 16, 1, 123456)
    assert entry.encode() == "4242 7 9 74 3 16 1 123456\n"
    assert decode_line(entry.encode()) == entry
    assert decode_line(entry.encode().encode()) == entry
    for bad in ("4242 7 9 74 3 16 1", "4242 7 256 74 3 16 0 5", "4242 7 9 74 3 16 3 5",
                "a b c d e f g h", "", "4242 7 9 74 3 16 0 5 6"):
        assert decode_line(bad) is None, bad
