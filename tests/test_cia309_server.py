"""The CiA 309-3 TCP server: raw request lines as ``cocomm`` and ``coctl`` send them, answers
and event lines byte for byte, several clients, read-only mode, limits, malformed input, LSS,
and the ``cifemu 309`` commands (serve, exec, shell under a pseudo-terminal).

Board 0 runs a simulated network (node 1 generic, node 2 the data-type device of
``tests/data/cia309_node.eds``, node 9 on the bus but not in the card, and an unconfigured LSS
slave); in-process servers of both dialects share one gateway on it. Board 1 is a card
without configuration for the ``cifemu 309 serve`` subprocess.
"""

from __future__ import annotations

import _thread
import asyncio
import base64
import json
import mmap
import os
import pty
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import FrameType

import pytest

from cifemu.commands.cia309 import Remote, open_lss
from dpm.commands import COM_SDO_UP_DOWNLOAD
from dpm.image import image_path
from dpm.layout import DEV_MBX
from dpm.message import Ext, Message
from firmware.can.sdo import DEFAULT_SDO_TIMEOUT
from host_api.cia309.datatypes import Dialect
from host_api.cia309.framing import LineFramer
from host_api.cia309.gateway import Gateway
from host_api.cia309.model import DataType
from host_api.cia309.server import BackgroundServer, ServerConfig, new_event_loop
from host_api.cia309.server import Client as CoreClient
from tests import commands
from tests.conftest import ended, wait_until, within
from tests.gateway_cards import EDS, start, wait_operating

NETWORK = f"""[[node]]
id = 1
[[node]]
id = 2
eds = "{EDS}"
[[node]]
id = 9
[[node]]
id = 255
lss = {{ vendor = 0x5678, product = 1, revision = 1, serial = 7 }}
"""
VERSION = "4409670 1250100 1.70 1 3 2.0 1.0"
"""``info version`` of board 0: vendor "CIF", ulDeviceNo, firmware 1.70, serial 1, class 3."""


class Client:
    """A raw TCP client: bytes out, bytes in, nothing interpreted."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.buffer = b""
        self.events: list[str] = []

    def send(self, data: bytes | str) -> None:
        self.sock.sendall(data.encode("latin-1") if isinstance(data, str) else data)

    def until(self, end: bytes) -> bytes:
        """Everything received up to and including ``end``."""
        while end not in self.buffer:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError(f"closed before {end!r}; got {self.buffer!r}")
            self.buffer += chunk
        at = self.buffer.index(end) + len(end)
        data, self.buffer = self.buffer[:at], self.buffer[at:]
        return data

    def ask(self, line: str, end: bytes = b"\r\n") -> str:
        self.send(line)
        return self.until(end).decode("latin-1")

    def answer(self, line: str) -> str:
        """Lely's dialect: the answer line to ``line``; event lines before it are kept in
        ``events``, as coctl prints them between answers."""
        sequence = line[: line.index("]") + 1]
        self.send(line)
        while not (text := self.until(b"\n").decode("latin-1")).startswith(sequence):
            self.events.append(text)
        return text

    def close(self) -> None:
        self.sock.close()


@pytest.fixture(scope="module")
def directory(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("cia309-server")


@pytest.fixture(scope="module")
def servers(directory: Path) -> Iterator[dict[str, BackgroundServer]]:
    """A CANopenNode server (at most 3 clients), a Lely one (without LSS) and a read-only one."""
    card = start(directory, 0, NETWORK)
    try:
        with Gateway([0], directory) as gateway:
            wait_operating(0, [1, 2])
            lss = open_lss(gateway)
            assert lss is not None
            running = {
                "canopennode": BackgroundServer(gateway, ServerConfig(port=0, max_clients=3),
                                                lss),
                "lely": BackgroundServer(gateway, ServerConfig(port=0, dialect=Dialect.LELY)),
                "read-only": BackgroundServer(gateway, ServerConfig(port=0, read_only=True), lss),
            }
            try:
                yield running
            finally:
                for server in running.values():
                    server.close()
    finally:
        card.stop()


Connect = Callable[[str], Client]
"""A new client of the named server."""


@pytest.fixture
def connect(servers: dict[str, BackgroundServer]) -> Iterator[Connect]:
    opened: list[Client] = []

    def make(name: str) -> Client:
        client = Client(servers[name].port)
        opened.append(client)
        return client

    yield make
    for client in opened:
        client.close()


def test_cocomm_requests_unchanged(connect: Connect) -> None:
    """Lines as CANopenNode's cocomm writes them ('[<n>] ' prepended, LF), answers it reads."""
    c = connect("canopennode")
    assert c.ask("[1] 2 write 0x2006 0 u16 1234\n") == "[1] OK\r\n"
    assert c.ask("[2] 2 read 0x2006 0 u16\n") == "[2] 1234\r\n"
    assert c.ask("[3] read 0x2006 0 x16\n") == "[3] 0x04D2\r\n"  # node 2 became the default
    assert c.ask("[4] 2 read 0x2345 0 u16\n") == (
        "[4] ERROR:0x06020000 #Object does not exist in the object dictionary.\r\n")
    assert c.ask('[5] 2 w 0x2009 0 vs "a ""quoted"" word"\n') == "[5] OK\r\n"
    assert c.ask("[6] 2 r 0x2009 0 vs\n") == '[6] "a ""quoted"" word"\r\n'
    assert c.ask("[7] 2 r 0x2006 0\n") == "[7] D2 04\r\n"  # no type: hex
    # cocomm -i streams a long value in 1000-byte writes, the line ends with its LF.
    data = os.urandom(8192)
    line = f"[8] 2 write 0x2000 0 d {base64.b64encode(data).decode()}\n".encode()
    for at in range(0, len(line), 1000):
        c.send(line[at : at + 1000])
    assert c.until(b"\r\n") == b"[8] OK\r\n"
    answer = c.ask("[9] 2 read 0x2000 0 d\n")
    assert answer.startswith("[9] ") and base64.b64decode(answer[4:-2]) == data
    assert c.ask("\n") == "\r\n"  # cocomm -f waits for the answer to an empty line
    helped = c.ask("[10] help datatype\n")
    assert "vs (visible string" in helped and helped.count("\r\n") == 1
    assert c.ask("[11] 1 stop\n") == "[11] OK\r\n"
    logged: list[str] = []  # CANopenNode's events go to the log that 'log' prints

    def stopped_logged() -> bool:
        logged.append(c.ask("[12] log\n"))
        return '"stopped" (4)' in logged[-1]

    wait_until(stopped_logged, 5, "node 1's state change in the log")
    assert re.fullmatch(r'\d{4}-\d\d-\d\d \d\d:\d\d:\d\d: CANopen Remote node ID = 0x01: '
                        r'NMT state changed to: "stopped" \(4\)\r\n', logged[-1])
    assert c.ask("[13] 1 start\n") == "[13] OK\r\n"


def test_coctl_requests_unchanged(connect: Connect) -> None:
    """The session of Lely's doc/coctl.md, answers and event lines as coctl reads them."""
    c = connect("lely")
    assert c.answer("[1] set network 1\n") == "[1] OK\n"
    assert c.answer("[2] set node 2\n") == "[2] OK\n"
    assert c.answer("[3] r 0x1018 0x01 u32\n") == "[3] 0x00001234\n"
    assert c.answer("[4] 1 2 w 0x2006 0 u16 0x1234\n") == "[4] OK\n"
    assert c.answer("[5] 1 2 r 0x2006 0 u16\n") == "[5] 0x1234\n"
    assert c.answer("[6] r 0x2345 0 u8\n") == (
        "[6] ERROR: 06020000 (Object does not exist in the object dictionary)\n")
    assert c.answer("[7] info version\n") == f"[7] {VERSION}\n"
    assert c.answer("[8] boot_up_indication Enable\n") == "[8] OK\n"
    assert c.answer("[9] 9 reset node\n") == "[9] OK\n"
    wait_until(lambda: "1 9 BOOT_UP\n" in c.events or c.answer("[10] info version\n") == "",
               5, "the boot-up event line")
    # Dummy mappings by type index, as coctl's set rpdo takes them.
    assert c.answer("[11] set rpdo 1 0x189 event 2 0x0005 0 0x0005 0\n") == "[11] OK\n"
    dummies = " ".join(["0x0005 0"] * 8)  # node 9's RPDO takes 8 bytes
    assert c.answer(f"[12] set tpdo 1 0x209 event 8 {dummies}\n") == "[12] OK\n"
    assert c.answer("[13] 9 start\n") == "[13] OK\n"
    assert c.answer("[14] w p 1 8 7 9 0 0 0 0 0 0\n") == "[14] OK\n"
    wait_until(lambda: "1 pdo 1 2 0x7 0x9\n" in c.events or c.answer("[15] info version\n") == "",
               5, "node 9's echo as an RPDO event line")
    assert c.answer("[16] r p 1\n") == "[16] 1 pdo 1 2 0x7 0x9\n"
    assert c.answer("[17] lss_store\n") == (
        "[17] ERROR: 100 (Request not supported)\n")  # this server has no LSS services


def test_several_clients_at_once(connect: Connect) -> None:
    clients = [connect("canopennode") for _ in range(3)]
    expected = {1: "[{}] 983441\r\n", 2: "[{}] 0\r\n"}  # 1000h of the generic module, of node 2
    for node, client in zip((1, 2, 1), clients, strict=True):
        assert client.ask(f"[1] set node {node}\n") == "[1] OK\r\n"
    failures: list[str] = []

    def work(client: Client, node: int) -> None:
        for sequence in range(2, 30):
            answer = client.ask(f"[{sequence}] read 0x1000 0 u32\n")
            if answer != expected[node].format(sequence):
                failures.append(answer)

    threads = [threading.Thread(target=work, args=(client, node))
               for node, client in zip((1, 2, 1), clients, strict=True)]
    for thread in threads:
        thread.start()
    for thread in threads:
        assert ended(thread, 30), "a client's reads did not end"
    assert not failures


def test_a_client_waiting_for_each_answer_costs_two_loop_turns_per_read(
        servers: dict[str, BackgroundServer], connect: Connect) -> None:
    """A read of a client that waits for each answer wakes the server's event loop twice:
    once for its line, once for the card's ring with the answer, which is written from
    there (not from the client's task, woken by a future; not four turns, with the mailbox
    looked at every 5 ms while the card rings). Each turn is a poll of the selector: under
    User-Mode Linux every system call is a ptrace round trip of the host (issue 22)."""
    server = servers["canopennode"]
    client = connect("canopennode")
    assert client.ask("[1] 1 read 0x1000 0 u32\n") == "[1] 983441\r\n"  # connected, warm
    loop = server.server._loop
    assert loop is not None
    selector = loop._selector  # type: ignore[attr-defined]
    polled = selector.select
    turns = 0

    def counting(timeout: float | None = None) -> list[object]:
        nonlocal turns
        turns += 1
        return polled(timeout)  # type: ignore[no-any-return]

    reads = 200
    selector.select = counting
    try:
        for n in range(2, reads + 2):
            assert client.ask(f"[{n}] 1 read 0x1000 0 u32\n") == f"[{n}] 983441\r\n"
    finally:
        del selector.select
    assert turns <= 2.25 * reads, f"{turns / reads:.2f} turns of the event loop per read"


def test_the_event_loop_writes_a_turns_fast_answers_when_the_turn_ends() -> None:
    """The server's loop runs what ``before_wait`` was given once, after every callback
    of the turn that gave it and before the loop waits again: the fast path's answers are
    written there, so a client in the same process does not wait for the interpreter lock
    while the loop finishes its turn (``Server._write_deferred``, issue 22)."""
    loop = new_event_loop()
    order: list[str] = []

    def first() -> None:
        loop.before_wait(lambda: order.append("before the wait"))  # type: ignore[attr-defined]
        order.append("first")

    async def turns() -> None:
        loop.call_soon(first)
        loop.call_soon(order.append, "second")
        await asyncio.sleep(0.01)  # a wait: the loop's selector waits
        order.append("after the wait")

    try:
        loop.run_until_complete(turns())
    finally:
        loop.close()
    assert order == ["first", "second", "before the wait", "after the wait"]


def test_a_read_reads_the_event_loops_clock_once_per_turn(
        servers: dict[str, BackgroundServer], connect: Connect,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The server's event loop reads the clock once per turn, after its wait (two readings
    per read), not six times (asyncio before and after each wait, the fast path at the
    line and at the answer): under User-Mode Linux each reading is a system call, a ptrace
    round trip of the host (issue 22). Counted are the readings the loop's thread makes
    for the loop's time; the clock itself is the real one."""
    server = servers["canopennode"]
    client = connect("canopennode")
    assert client.ask("[1] 1 read 0x1000 0 u32\n") == "[1] 983441\r\n"  # connected, warm
    loop = server.server._loop
    assert loop is not None
    loop_thread = server._thread.ident
    server_module = sys.modules[BackgroundServer.__module__].__file__
    clock = time.monotonic
    readings = 0

    def counting() -> float:
        nonlocal readings
        caller = sys._getframe(1).f_code
        if (threading.get_ident() == loop_thread and caller.co_name in ("select", "fresh_time")
                and caller.co_filename == server_module):
            readings += 1
        return clock()

    reads = 200
    monkeypatch.setattr(time, "monotonic", counting)
    for n in range(2, reads + 2):
        assert client.ask(f"[{n}] 1 read 0x1000 0 u32\n") == f"[{n}] 983441\r\n"
    monkeypatch.undo()
    assert readings <= 2.25 * reads, f"{readings / reads:.2f} clock readings per read"



def ask_profiled(loop: asyncio.AbstractEventLoop, client: Client,
                 profile: Callable[[FrameType, str, object], None], count: int,
                 request: str = "1 read 0x1000 0 u32", answer: str = "983441") -> None:
    """``count`` times ``request`` (a read of 1000h unless told) through ``client``, each
    answered ``answer``, with ``profile`` set on the server's loop thread (a profile
    function is per thread, so it is set and cleared from that thread)."""

    def profiling(on: bool) -> None:
        done = threading.Event()

        def switch() -> None:
            sys.setprofile(profile if on else None)
            done.set()

        loop.call_soon_threadsafe(switch)
        assert within(done.wait, 10)

    profiling(True)
    try:
        for n in range(2, count + 2):
            assert client.ask(f"[{n}] {request}\n") == f"[{n}] {answer}\r\n"
    finally:
        profiling(False)


def test_a_read_costs_the_loop_few_calls_of_the_gateways_own_python(
        servers: dict[str, BackgroundServer], connect: Connect) -> None:
    """A read runs at most 32 calls of ``host_api.cia309``'s Python functions on the
    server's loop thread (30.4 at branch plainc, with the plain read's line parsed and its
    answer formatted in C, the upload sent from the fast path itself and the selector's
    wait written out; 40.1 at branch fastwrite, as 40.2 before it: the dispatch of an
    SDO request to the gateway's upload or download, ``_send_sdo``, where the fast path
    made an object per read, and ``DataType.size`` a dict look-up; 39.1 on 2026-12-04
    with the loop's time read by C and the
    mailbox's flags read from the map; 46.2 on 2026-12-03 with one copy of each function
    on the path; 48.2 with the copies written out at 9aa3708, 64 before that): on this VM the loop
    thread spent 190-220 us of CPU per read, 60 % of it in the interpreter over about 125
    Python calls, and each call saved is CPU off every read (issue 22).
    Counted with a profile function on the loop's thread only; the card and the client are
    the real ones."""
    server = servers["canopennode"]
    client = connect("canopennode")
    assert client.ask("[1] 1 read 0x1000 0 u32\n") == "[1] 983441\r\n"  # connected, warm
    loop = server.server._loop
    assert loop is not None
    calls = 0

    def counting(frame: FrameType, event: str, arg: object) -> None:
        nonlocal calls
        if event == "call" and "cia309" in frame.f_code.co_filename:
            calls += 1

    reads = 200
    ask_profiled(loop, client, counting, reads)
    assert calls <= 32 * reads, f"{calls / reads:.1f} calls of host_api.cia309 per read"


def test_a_read_takes_no_thread_lock_of_cpython_and_three_clock_readings_on_the_loop(
        servers: dict[str, BackgroundServer], connect: Connect) -> None:
    """A read's DevPutMessage and DevGetMessage on the server's loop thread take their locks
    (the put and get channels, the ledger's state, the SDO channel) as ``dpm._quicklock``
    locks and read no clock for a call that does not wait: CPython 3.11's thread lock reads
    the monotonic clock in every acquire, and inside User-Mode Linux (no vDSO) each clock
    reading is a system call of about 30 us. Before: 9 acquires of thread locks and 5 clock
    readings per read, 23.6 clock_gettime calls per read in the guest (8.0 after; issue 22).
    Left: the loop's time after each of its two waits and the ledger's time stamp.
    Counted with a profile function on the loop's thread; card and client are real."""
    server = servers["canopennode"]
    client = connect("canopennode")
    assert client.ask("[1] 1 read 0x1000 0 u32\n") == "[1] 983441\r\n"  # connected, warm
    loop = server.server._loop
    assert loop is not None
    thread_locks = (_thread.LockType, _thread.RLock)
    clocks = {time.monotonic, time.monotonic_ns, time.time, time.time_ns, time.perf_counter,
              time.perf_counter_ns}
    locks = readings = 0

    def counting(frame: FrameType, event: str, arg: object) -> None:
        nonlocal locks, readings
        if event != "c_call":
            return
        if isinstance(getattr(arg, "__self__", None), thread_locks):
            name = getattr(arg, "__name__", "")
            locks += name in ("acquire", "__exit__")  # ``with`` shows only its __exit__
        elif arg in clocks:
            readings += 1

    reads = 200
    ask_profiled(loop, client, counting, reads)
    assert locks <= 0.1 * reads, f"{locks / reads:.2f} acquires of CPython thread locks per read"
    assert readings <= 3.1 * reads, f"{readings / reads:.2f} clock readings per read"


def test_a_write_that_fits_one_message_takes_no_worker_thread(
        servers: dict[str, BackgroundServer], connect: Connect) -> None:
    """A write of a value that fits one mailbox message (an expedited SDO download) of a
    client that waits for each answer is sent and answered on the server's event loop, as
    a read is (``Server._fast_line``): no ``run_in_executor``, so no worker thread and its
    two thread switches, and not the client's task either. It runs at most 42 calls of
    ``host_api.cia309``'s Python functions on the loop, as a read (40.1 at branch
    plainwrite, with the plain write of an integer parsed by one regular expression,
    ``_plain_write``; 68.3 at branch fastwrite, 28 of them the general parser's; before,
    95 on the loop, with the line parsed twice, and the worker thread's besides). A longer
    value (a segmented download: several requests) still goes to a worker thread."""
    server = servers["canopennode"]
    client = connect("canopennode")
    assert client.ask("[1] 2 write 0x2006 0 u16 7\n") == "[1] OK\r\n"  # connected, warm
    loop = server.server._loop
    assert loop is not None
    server_module = sys.modules[BackgroundServer.__module__].__file__
    counted = {"run_in_executor": 0, "_answer": 0, "cia309": 0}

    def counting(frame: FrameType, event: str, arg: object) -> None:
        if event != "call":
            return
        code = frame.f_code
        if code.co_name == "run_in_executor" or (code.co_name == "_answer"
                                                 and code.co_filename == server_module):
            counted[code.co_name] += 1
        if "cia309" in code.co_filename:
            counted["cia309"] += 1

    writes = 200
    ask_profiled(loop, client, counting, writes, "2 write 0x2006 0 u16 7", "OK")
    assert counted["run_in_executor"] == 0
    assert counted["_answer"] == 0  # the fast path's, not the client's task's
    assert counted["cia309"] <= 42 * writes, (
        f"{counted['cia309'] / writes:.1f} calls of host_api.cia309 per write")
    domain = base64.b64encode(bytes(range(256))).decode()
    ask_profiled(loop, client, counting, 1, f"2 write 0x2000 0 d {domain}", "OK")
    assert counted["run_in_executor"] == 1


WRITES = (
    "2 write 0x2006 0 u16 4321",  # OK
    "2 write 0x2345 0 u16 1",  # the node: no such object
    "2 write 0x1000 0 u32 1",  # the node: read only
    "2 write 0x2006 0 u32 1",  # the node: the length does not match
    "9 write 0x1017 0 u16 0",  # OK: node 9 is not in the card's configuration, but on the bus
    "42 write 0x1017 0 u16 0",  # no node 42 on the bus: the card's SDO time-out
    "3 2 write 0x2006 0 u16 1",  # no network 3
    "2 write 0x2006 0 u16 1234",  # OK
)


def answer_lines(client: Client, count: int, end: bytes) -> list[str]:
    """The next ``count`` answer lines; event lines (Lely's) are kept in ``events``."""
    lines: list[str] = []
    while len(lines) < count:
        line = client.until(end).decode("latin-1")
        if line.startswith("["):
            lines.append(line)
        else:
            client.events.append(line)
    return lines


@pytest.mark.parametrize("name", ["canopennode", "lely", "read-only"])
def test_writes_are_answered_alike_on_every_path(
        servers: dict[str, BackgroundServer], connect: Connect, name: str) -> None:
    """The answer to a write is the same text whichever way the server serves it: a line
    alone (the event loop's fast path), lines sent together (the client's task, which
    sends an expedited download from the loop too), and the blocking service that a worker
    thread runs for the rest (``Dispatcher.handle``): OK, the node's SDO aborts, the
    card's SDO time-out, an unserved network, no default node; in each dialect, and
    ``--read-only``'s refusal. A refused write leaves the object as it was."""
    server = servers[name].server
    gateway = server.gateway
    end = server.dispatcher.dialect.line_end.encode()
    lines = [f"[{n}] {line}" for n, line in enumerate(("write 0x2006 0 u16 1", *WRITES), 1)]
    gateway.sdo_download(0x2006, 0, (555).to_bytes(2, "little"), node_id=2)
    alone = connect(name)
    fast: list[str] = []
    for line in lines:
        alone.send(f"{line}\n")
        fast += answer_lines(alone, 1, end)
    together = connect(name)
    together.send("".join(f"{line}\n" for line in lines))
    pipelined = answer_lines(together, len(lines), end)
    session = CoreClient(gateway.session(), LineFramer())
    blocking = [server.dispatcher.handle(session, line) for line in lines]
    assert fast == pipelined == blocking
    if name == "read-only":
        assert set(fast) == {f"[{n}] ERROR:100 #Request not supported.\r\n"
                             for n in range(1, len(lines) + 1)}
        assert gateway.sdo_upload(0x2006, 0, node_id=2) == (555).to_bytes(2, "little")
        return
    expected = {
        "canopennode": ["[1] ERROR:105 #No default node set.\r\n", "[2] OK\r\n",
                        "[3] ERROR:0x06020000 #Object does not exist in the object "
                        "dictionary.\r\n",
                        "[4] ERROR:0x06010002 #Attempt to write a read only object.\r\n"],
        "lely": ["[1] ERROR: 105 (No default node set)\n", "[2] OK\n",
                 "[3] ERROR: 06020000 (Object does not exist in the object dictionary)\n",
                 "[4] ERROR: 06010002 (Attempt to write a read only object)\n"],
    }[name]
    assert fast[:4] == expected
    assert [fast[5], fast[8]] == [expected[1].replace("[2]", f"[{n}]") for n in (6, 9)]
    assert fast[6].startswith("[7] ERROR") and "103" in fast[6]  # the time-out
    assert gateway.sdo_upload(0x2006, 0, node_id=2) == (1234).to_bytes(2, "little")


READS = (
    "1 read 0x1000 0 u32",  # the benchmark's
    "1 r 4096 0 i32",
    "1 read 0x1000 0 x32",
    "1 read 0x1000 0",  # no type: hex
    "1 read 0x1000 0 hex",
    "1 read 0x1000 0 u16",  # the length does not match: hex (CANopenNode), abort (Lely)
    "1 read 0x1000 0 r32",  # formatted by the Python path
    "1 read 0x1008 0 vs",
    "2 read 0x2006 0 u16",
    "2 read 0x2345 0 u8",  # the node: no such object
    "1 2 read 0x1000 0 u32",  # network 1 given
    "3 2 read 0x1000 0 u32",  # no network 3
    "1 read 0x1000 0 u128",  # no such type
)


@pytest.mark.parametrize("name", ["canopennode", "lely", "read-only"])
def test_reads_are_answered_alike_on_every_path(
        servers: dict[str, BackgroundServer], connect: Connect, name: str) -> None:
    """The answer to a read is the same text whichever way the server serves it: a line
    alone in the plain form (parsed and answered in C, ``plain_read_line`` and
    ``format_plain_upload``), the same with white space before it (the fast path's Python
    parser), lines sent together (the client's task), and the blocking service
    (``Dispatcher.handle``); in each dialect."""
    server = servers[name].server
    end = server.dispatcher.dialect.line_end.encode()
    lines = [f"[{n}] {line}" for n, line in enumerate(READS, 1)]
    answers: dict[str, list[str]] = {"plain": [], "spaced": []}
    for way, before in (("plain", ""), ("spaced", " ")):
        alone = connect(name)
        for line in lines:
            alone.send(f"{before}{line}\n")
            answers[way] += answer_lines(alone, 1, end)
    together = connect(name)
    together.send("".join(f"{line}\n" for line in lines))
    pipelined = answer_lines(together, len(lines), end)
    session = CoreClient(server.gateway.session(), LineFramer())
    blocking = [server.dispatcher.handle(session, line) for line in lines]
    assert answers["plain"] == answers["spaced"] == pipelined == blocking
    expected = {
        "lely": ["[1] 0x000f0191\n", "[2] 983441\n", "[3] 0x000f0191\n",
                 "[4] 91 01 0F 00\n"],
    }.get(name, ["[1] 983441\r\n", "[2] 983441\r\n", "[3] 0x000F0191\r\n",
                 "[4] 91 01 0F 00\r\n"])
    assert answers["plain"][:4] == expected


def test_a_write_then_a_read_returns_the_value_written(connect: Connect) -> None:
    c = connect("canopennode")
    for n, value in enumerate((1, 65535, 0, 4660), 1):
        assert c.ask(f"[{2 * n}] 2 write 0x2006 0 u16 {value}\n") == f"[{2 * n}] OK\r\n"
        assert c.ask(f"[{2 * n + 1}] 2 read 0x2006 0 u16\n") == f"[{2 * n + 1}] {value}\r\n"


def test_pipelined_writes_keep_their_order(connect: Connect) -> None:
    """Writes each followed by a read, sent without waiting for the answers: the answers
    come in order, and each read returns the write before it. Once all in one send (the
    client's task reads them together), once a line per send (the fast path takes a line
    while nothing of the client's waits, the task the ones that arrive meanwhile)."""
    c = connect("canopennode")
    c.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    pairs = 50

    def lines(first: int) -> list[str]:
        return [line for k in range(first, first + pairs)
                for line in (f"[{2 * k}] 2 write 0x2006 0 u16 {k}\n",
                             f"[{2 * k + 1}] 2 read 0x2006 0 u16\n")]

    def answers(first: int) -> str:
        return "".join(f"[{2 * k}] OK\r\n[{2 * k + 1}] {k}\r\n"
                       for k in range(first, first + pairs))

    c.send("".join(lines(1)))
    assert c.until(f"[{2 * pairs + 1}] {pairs}\r\n".encode()).decode() == answers(1)
    for line in lines(pairs + 1):
        c.send(line)
    last = 2 * pairs
    assert c.until(f"[{2 * last + 1}] {last}\r\n".encode()).decode() == answers(pairs + 1)


def test_a_read_the_card_answers_too_late_is_a_time_out_and_the_next_is_served(
        connect: Connect) -> None:
    """The client's command time-out bounds a read or a write answered without its task
    (the fast path's timer): 103 when it runs out, long before the card's answer, also
    when it was made shorter between two reads; then the next one is answered."""
    c = connect("canopennode")
    assert c.ask("[1] set command_timeout 5000\n") == "[1] OK\r\n"
    assert c.ask("[2] 1 read 0x1000 0 u32\n") == "[2] 983441\r\n"
    assert c.ask("[3] set sdo_timeout 4000\n") == "[3] OK\r\n"
    try:
        assert c.ask("[4] set command_timeout 50\n") == "[4] OK\r\n"
        began = time.monotonic()  # node 43 is not on the bus: the card answers in 4 s
        assert c.ask("[5] 43 read 0x1000 0 u32\n") == "[5] ERROR:103 #Time-out.\r\n"
        assert time.monotonic() - began < 3
        began = time.monotonic()
        assert c.ask("[51] 44 write 0x1017 0 u16 0\n") == "[51] ERROR:103 #Time-out.\r\n"
        assert time.monotonic() - began < 3
        assert c.ask("[52] 1 write 0x1017 0 u16 0\n") == "[52] OK\r\n"
        assert c.ask("[6] set command_timeout 5000\n") == "[6] OK\r\n"
        assert c.ask("[7] 1 read 0x1000 0 u32\n") == "[7] 983441\r\n"
    finally:
        timeout = int(DEFAULT_SDO_TIMEOUT * 1000)
        assert c.ask(f"[8] set sdo_timeout {timeout}\n") == "[8] OK\r\n"


def test_every_read_asks_the_card_in_the_long_form(
        servers: dict[str, BackgroundServer], directory: Path, connect: Connect) -> None:
    """Every upload reaches the card in the long form (COM_SDO_Up_Download with msg.e 4,
    answered in parts when one message cannot hold the value), typed or not, on the fast
    path and through the blocking gateway call: the card's turn in C serves it, a value
    that fits one message with the seed's one answer at the seed's form's cost (docs/dpm.md
    section 3). From branch sdohost until branch gwlong a read of a fixed-size type was
    asked in the seed's form (msg.e 0) and again in the long form after an f 51. Read from
    the device mailbox in the image, where the request stays after the card took it (a
    message the gateway sent meanwhile, such as an event's COM_Node_Diag, is passed over)."""
    c = connect("canopennode")
    gateway = servers["canopennode"].server.gateway
    with open(image_path(directory, 0), "r+b") as file, mmap.mmap(file.fileno(), 0) as image:

        def forms(read: Callable[[int], None]) -> set[int]:
            """msg.e of the SDO requests of ten reads."""
            seen = set()
            for n in range(10):
                read(n)
                sent = Message.decode(image[DEV_MBX : DEV_MBX + 8 + image[DEV_MBX + 2]])
                if sent.b == COM_SDO_UP_DOWNLOAD:
                    seen.add(sent.e)
            return seen

        def typed(n: int) -> None:
            assert c.ask(f"[{n}] 1 read 0x1000 0 u32\n") == f"[{n}] 983441\r\n"

        def blocking(n: int) -> None:
            assert gateway.sdo_upload(0x1000, 0, node_id=1, data_type=DataType.UNSIGNED32
                                      ) == (983441).to_bytes(4, "little")

        def untyped(n: int) -> None:
            assert c.ask(f"[{n}] 1 read 0x1000 0\n") == f"[{n}] 91 01 0F 00\r\n"

        assert forms(typed) == {Ext.FIRST}
        assert forms(blocking) == {Ext.FIRST}
        assert forms(untyped) == {Ext.FIRST}


def test_a_typed_read_of_an_object_longer_than_its_type_shows_its_bytes_or_the_abort(
        servers: dict[str, BackgroundServer], connect: Connect) -> None:
    """A read as a fixed-size type of an object longer than that type on the node, one
    message long (a u16 read of 1000h's four bytes) or longer (a u32 read of a 600-byte
    DOMAIN): CANopenNode's dialect shows all the object's bytes as ``hex``, as a read
    without a type does; Lely's answers the length mismatch with abort 06070010
    (docs/cia309.md); the blocking gateway call returns all the bytes; the next read is
    served as usual."""
    gateway = servers["canopennode"].server.gateway
    data = bytes(range(256)) * 2 + bytes(88)
    gateway.sdo_download(0x2000, 0, data, node_id=2, data_type=DataType.DOMAIN)
    c = connect("canopennode")
    lely = connect("lely")
    whole = c.ask("[1] 2 read 0x2000 0 hex\n")
    assert whole.startswith("[1] ") and len(whole) > 3 * len(data)
    assert c.ask("[2] 2 read 0x2000 0 u32\n") == whole.replace("[1]", "[2]", 1)
    assert gateway.sdo_upload(0x2000, 0, node_id=2, data_type=DataType.UNSIGNED32) == data
    assert c.ask("[3] 1 read 0x1000 0 u16\n") == "[3] 91 01 0F 00\r\n"
    mismatch = ("ERROR: 06070010 (Data type does not match, length of service parameter does "
                "not match)\n")
    assert lely.answer("[4] 2 read 0x2000 0 u32\n") == f"[4] {mismatch}"
    assert lely.answer("[5] 1 read 0x1000 0 u16\n") == f"[5] {mismatch}"
    assert c.ask("[6] 1 read 0x1000 0 u32\n") == "[6] 983441\r\n"


def test_a_new_client_ends_the_one_idle_longest(connect: Connect) -> None:
    """Issue 20: over the limit of 3, a new client is served within 2 s and the client idle
    longest sees its connection end, without a line; while none is idle (each waits for a
    node that does not answer), a new client is refused with 600."""
    clients = [connect("canopennode") for _ in range(3)]
    for sequence, client in enumerate(clients, 1):  # the first is idle longest
        assert client.ask(f"[{sequence}] 1 read 0x1000 0 u32\n") == f"[{sequence}] 983441\r\n"
    began = time.monotonic()
    fourth = connect("canopennode")
    assert fourth.ask("[4] 1 read 0x1000 0 u32\n") == "[4] 983441\r\n"
    assert time.monotonic() - began < 2
    assert clients[0].sock.recv(10) == b""
    busy = [*clients[1:], fourth]
    for client in busy:  # node 42 is not on the bus: 9 SDO time-outs of 300 ms, in turn
        client.send("".join(f"[{sequence}] 42 read 0x1000 0 u32\n" for sequence in (5, 6, 7)))
    refused = connect("canopennode")
    assert refused.until(b"\r\n") == b"[0] ERROR:600 #Running out of memory.\r\n"
    assert refused.sock.recv(10) == b""
    for client in busy:
        assert client.until(b"[7] ERROR:103 #Time-out.\r\n").endswith(b"\r\n")


def test_read_only_refuses_writes_and_nmt(connect: Connect) -> None:
    c = connect("read-only")
    assert c.ask("[1] 2 read 0x2006 0 u16\n").startswith("[1] ")
    refused = "[{}] ERROR:100 #Request not supported.\r\n"
    for sequence, request in enumerate(("2 write 0x2006 0 u16 1", "2 start", "0 stop",
                                        "2 reset node", "set sdo_timeout 100", "lss_store",
                                        "set tpdo 1 0x300 event 1 0x6000 1 u8", "init 2"), 2):
        assert c.ask(f"[{sequence}] {request}\n") == refused.format(sequence)
    assert c.ask("[20] set node 1\n") == "[20] OK\r\n"
    assert c.ask("[21] info version\n") == f"[21] {VERSION}\r\n"


def test_malformed_lines_keep_the_connection(connect: Connect) -> None:
    c = connect("canopennode")
    assert c.ask("hello\n") == (
        "[0] ERROR:101 #Syntax error: a request starts with [<sequence>].\r\n")
    assert c.ask(b"\xff\xfe\x00garbage\n".decode("latin-1")).startswith("[0] ERROR:101 #")
    assert c.ask("[5] 2 read\n") == "[5] ERROR:101 #Syntax error: index missing.\r\n"
    assert c.ask("[6] 2 frobnicate\n") == (
        "[6] ERROR:100 #Request not supported: unknown command 'frobnicate'.\r\n")
    assert c.ask("[7] 200 read 0x1000 0 u8\n") == (
        "[7] ERROR:107 #Unsupported node: node 200 is not addressable.\r\n")
    assert c.ask("[8] 3 2 read 0x1000 0 u8\n") == "[8] ERROR:106 #Unsupported net.\r\n"
    assert c.ask("[9] read 0x1000 0 u8\n") == "[9] ERROR:105 #No default node set.\r\n"
    assert c.ask("[10] 42 read 0x1000 0 u32\n") == "[10] ERROR:103 #Time-out.\r\n"
    assert c.ask("[11] set sdo_block 1\n") == "[11] ERROR:100 #Request not supported.\r\n"
    assert c.ask("[12] set command_size 64\n") == "[12] OK\r\n"
    long_line = f'[13] 2 write 0x2009 0 vs "{"x" * 100}"\n'
    assert c.ask(long_line) == (
        "[13] ERROR:600 #Running out of memory: request longer than the command size.\r\n")
    assert c.ask("[14] 2 read 0x2006 0 u16\n").startswith("[14] ")  # still served
    assert c.ask("[15] set command_size 200000\n") == "[15] ERROR:600 #Running out of memory.\r\n"
    assert c.ask("[16] wait\n") == (
        "[16] ERROR:100 #Request not supported: unknown command 'wait'.\r\n")


def test_lss_requests_reach_the_lss_services(connect: Connect) -> None:
    c = connect("canopennode")
    assert c.ask("[1] lss_identity 0x5678 1 0 5 0 100\n") == "[1] OK\r\n"
    assert c.ask("[2] lss_identity 0x9999 1 0 5 0 100\n") == "[2] ERROR:103 #Time-out.\r\n"
    assert c.ask("[3] lss_ident_nonconf\n") == "[3] OK\r\n"
    assert c.ask("[4] lss_switch_sel 0x5678 1 1 7\n") == "[4] OK\r\n"
    assert c.ask("[5] lss_get_node\n") == "[5] 0xFF\r\n"
    assert c.ask("[6] lss_inquire_addr 3\n") == "[6] 0x00000007\r\n"
    assert c.ask("[7] lss_inquire_addr\n") == "[7] 0x00005678 0x00000001 0x00000001 0x00000007\r\n"
    assert c.ask("[8] lss_conf_bitrate 0 9\n") == "[8] ERROR:503 #LSS bit-rate not supported.\r\n"
    assert c.ask("[9] lss_switch_glob 0\n") == "[9] OK\r\n"


# --- cifemu 309 serve / exec / shell --------------------------------------------------------------


def cifemu(*args: str) -> list[str]:
    return [sys.executable, "-m", "cifemu", "309", *args]


def read_until(fd: int, marker: bytes, timeout: float = 10) -> bytes:
    """Bytes from a pseudo-terminal up to ``marker``."""
    data = b""
    while marker not in data:
        if not commands.readable(fd, timeout):
            raise TimeoutError(f"no {marker!r} in {data!r}")
        data += os.read(fd, 4096)
    return data


def test_cli_serve_exec_and_shell(servers: dict[str, BackgroundServer], directory: Path,
                                  tmp_path: Path) -> None:
    card = start(directory, 1, None)
    serve = subprocess.Popen(
        cifemu("serve", "--board", "1", "--dpm-dir", str(directory), "--port", "0"),
        stderr=subprocess.PIPE, text=True)
    try:
        stderr = serve.stderr
        assert stderr is not None
        lines: queue.SimpleQueue[str] = queue.SimpleQueue()

        def pump() -> None:
            for line in stderr:
                lines.put(line)

        threading.Thread(target=pump, daemon=True).start()
        wait_until(lambda: not lines.empty(), 20, "cifemu 309 serve's first line")
        match = re.search(r"listening on 127\.0\.0\.1:(\d+)", lines.get())
        assert match is not None
        port = match.group(1)
        version = VERSION.replace(" 1 3 ", " 2 3 ")  # board 1: serial 2
        done = commands.run(cifemu("exec", "--port", port, "info version"),
                            capture_output=True, text=True, timeout=30)
        assert (done.returncode, done.stdout) == (0, f"[1] {version}\n")
        done = commands.run(cifemu("exec", "--port", port, "[7] 1 read 0x1000 0 u32"),
                            capture_output=True, text=True, timeout=30)
        assert done.returncode == 1  # the network has no configuration
        assert done.stdout.startswith("[7] ERROR:102 ")
        history = tmp_path / "history"
        master, slave = pty.openpty()
        shell = subprocess.Popen(cifemu("shell", "--port", port, "--history", str(history)),
                                 stdin=slave, stdout=slave, stderr=slave,
                                 env={**os.environ, "TERM": "dumb"})
        os.close(slave)
        try:
            read_until(master, b"309> ")
            os.write(master, b"info version\r")
            assert f"[1] {version}".encode() in read_until(master, b"309> ")
            os.write(master, b"quit\r")
            assert commands.wait(shell, 20) == 0
        finally:
            os.close(master)
        assert "info version" in history.read_text()
    finally:
        serve.send_signal(signal.SIGTERM)
        assert commands.wait(serve, 20) == 0
    try:
        done = commands.run(cifemu("exec", "--direct", "--board", "1", "--dpm-dir",
                                   str(directory), "info version"),
                            capture_output=True, text=True, timeout=30)
        assert (done.returncode, done.stdout) == (0, f"[1] {version}\n")
    finally:
        card.stop()


def test_cli_net_n_is_the_309_network_and_network_n_still_works_with_a_warning(
        directory: Path) -> None:
    """Issue 21: ``--network`` names a NETWORK.toml in every other command, so the 309
    network is ``--net N`` (board N-1); the first spelling still works, and says so."""
    card = start(directory, 1, None)
    version = VERSION.replace(" 1 3 ", " 2 3 ")  # board 1: serial 2
    try:
        for option, warned in (("--net", False), ("--network", True)):
            done = commands.run(cifemu("exec", "--direct", option, "2", "--dpm-dir",
                                       str(directory), "info version"),
                                capture_output=True, text=True, timeout=30)
            assert (done.returncode, done.stdout) == (0, f"[1] {version}\n"), option
            assert ("--network N is deprecated, use --net N" in done.stderr) == warned
    finally:
        card.stop()


def test_cli_exec_answers_errors_and_json(servers: dict[str, BackgroundServer]) -> None:
    """Issue 14: ``exec help`` succeeds; a syntax error says what was wrong; ``--json``
    gives answers and errors as one object; no server names host:port and the way out."""
    port = str(servers["canopennode"].port)

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return commands.run(cifemu("exec", *args), capture_output=True, text=True, timeout=30)

    done = run("--port", port, "help")
    assert done.returncode == 0 and "Command strings start with" in done.stdout
    done = run("--port", port, "[5] 2 read")
    assert (done.returncode, done.stdout) == (1, "[5] ERROR:101 #Syntax error: index missing.\n")
    done = run("--port", port, "--json", "[5] 2 read")
    assert done.returncode == 1
    assert json.loads(done.stdout) == {"sequence": 5, "ok": False, "error": {
        "code": 101, "text": "Syntax error", "detail": "index missing"}}
    done = run("--port", port, "--json", "[6] 2 read 0x1000 0 u32")
    assert (done.returncode, json.loads(done.stdout)) == (0, {"sequence": 6, "ok": True,
                                                              "answer": "0"})
    done = run("--port", port, "--json", "[7] 2 read 0x5555 0 u32")
    assert json.loads(done.stdout)["error"] == {
        "abort_code": 0x0602_0000, "text": "Object does not exist in the object dictionary"}
    with socket.socket() as unused:  # a port nobody listens on
        unused.bind(("127.0.0.1", 0))
        free = str(unused.getsockname()[1])
    done = run("--port", free, "info version")
    assert done.returncode == 1 and not done.stdout
    assert f"127.0.0.1:{free}" in done.stderr and "cifemu 309 serve" in done.stderr
    done = run("--port", free, "--json", "info version")
    assert done.returncode == 1
    assert "cifemu 309 serve" in json.loads(done.stdout)["error"]["text"]


def test_a_request_that_arrives_with_the_idle_time_out_is_answered(
        servers: dict[str, BackgroundServer]) -> None:
    """A request whose bytes reach the server in the same turn of its event loop as the
    connection's idle time-out (the loop came late, busy with another client) is answered,
    not dropped as idle: the read's time-out reached the client's task, which had not read
    the bytes yet. The loop is held busy by a callback until the request has arrived and the
    idle time is over; two lines in one write, so the client's task reads them (not the
    fast path, which notes its bytes itself)."""
    gateway = servers["canopennode"].server.gateway
    short = BackgroundServer(gateway, ServerConfig(port=0, idle_timeout=0.3))
    client = Client(short.port)
    try:
        assert client.ask("[1] 1 read 0x1000 0 u32\n") == "[1] 983441\r\n"
        busy, sent = threading.Event(), threading.Event()

        def hold() -> None:  # the loop's thread: a client's long turn
            busy.set()
            sent.wait(10)
            time.sleep(0.5)  # the idle time-out (0.3 s after the answer) falls due meanwhile

        short._loop.call_soon_threadsafe(hold)
        assert within(busy.wait, 10)
        client.send("[2] 1 read 0x1000 0 u32\n[3] 1 read 0x1000 0 u32\n")
        sent.set()
        assert client.until(b"[3] 983441\r\n") == b"[2] 983441\r\n[3] 983441\r\n"
    finally:
        client.close()
        short.close()


def test_shell_connects_again_after_the_idle_time_out(
        servers: dict[str, BackgroundServer], capsys: pytest.CaptureFixture[str]) -> None:
    """A shell left alone longer than the server's idle time-out asks its next request on a
    new connection instead of failing."""
    gateway = servers["canopennode"].server.gateway
    short = BackgroundServer(gateway, ServerConfig(port=0, idle_timeout=0.3))
    try:
        remote = Remote("127.0.0.1", short.port, 10, lambda line: None)
        assert remote.ask("[1] 2 read 0x1000 0 u32", 1) == "[1] 0\r\n"

        def closed() -> bool:
            try:
                remote.poll_events()
            except ConnectionError:
                return True
            return False

        wait_until(closed, 5, "the server closing the idle connection")
        assert remote.ask("[2] 2 read 0x1000 0 u32", 2) == "[2] 0\r\n"
        assert "connected again" in capsys.readouterr().err
        remote.close()
    finally:
        short.close()
