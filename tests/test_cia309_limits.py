"""The 309-3 server under hostile clients: idle, slow and non-reading connections, 200 at
once, and hypothesis-generated lines, each while a well-behaved client keeps asking at its
normal rate and the server's memory stays bounded (issue 13).

The server is a real ``cifemu 309 serve`` process (its resident memory is read from
/proc) on a card that simulates one generic node, with short limits so that each test
takes a few seconds: idle and line time-outs of 1 s, 4 clients, 256 KiB of unread output.
It is read-only, so no generated line can change the node. CIFEMU_FUZZ_EXAMPLES (default
60) sets the number of generated examples; the other tests repeat their attack
CIFEMU_FUZZ_EXAMPLES // 20 times (at least 3) for a long run.
"""

from __future__ import annotations

import contextlib
import os
import queue
import socket
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from host_api.cia309.server import IDLE_GRACE_S
from tests.cia309_clients import (
    ANSWER_1000,
    READ_1000,
    Server,
    Steady,
    ask_once,
    read_line,
    serving,
)
from tests.conftest import LoadClock, taken, wait_until

EXAMPLES = int(os.environ.get("CIFEMU_FUZZ_EXAMPLES", "60"))
ROUNDS = max(3, EXAMPLES // 20)
MAX_CLIENTS = 4
IDLE_TIMEOUT_S = 1.0
LIMITS = ["--max-clients", str(MAX_CLIENTS), "--idle-timeout", str(IDLE_TIMEOUT_S),
          "--line-timeout", "1", "--max-output", str(256 * 1024)]
MEMORY_GROWTH = 8 << 20
"""Bytes the server's resident memory may grow over a test after its first round."""
FIRST_RSS: dict[str, int] = {}
"""The server's resident memory after the first generated example."""
REFUSED = b"[0] ERROR:600 #Running out of memory.\r\n"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    with serving(tmp_path_factory.mktemp("cia309-limits"), *LIMITS) as running:
        yield running


def _closed_by_server(sock: socket.socket, timeout: float) -> bool:
    """True when the server ends the connection within ``timeout`` (what it sent before
    is read and thrown away)."""
    sock.settimeout(timeout)
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            if not sock.recv(65536):
                return True
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False
    return False


@pytest.fixture
def steady(server: Server) -> Iterator[Steady]:
    client = Steady(server.port, idle_limit=min(IDLE_TIMEOUT_S, IDLE_GRACE_S))
    client.start()
    clock = LoadClock(time.monotonic())
    yield client
    client.stop(clock)


def _served(port: int) -> bool:
    """A new client gets its answer (not the refusal of a full server)."""
    try:
        return ask_once(port, READ_1000) == f"[1] {ANSWER_1000}"
    except OSError:
        return False


def _attack(server: Server, steady: Steady, connect: type[_Attacker]) -> None:
    """ROUNDS times: fill every free slot with attackers, check that the server drops
    them all and serves a new client; then the memory bound."""
    baseline = 0
    for round_ in range(ROUNDS):
        attackers = [connect(server.port) for _ in range(MAX_CLIENTS - 1)]
        try:
            with ThreadPoolExecutor(len(attackers)) as pool:  # all at once, as a pack would
                dropped = list(pool.map(lambda attacker: attacker.dropped(connect.DEADLINE),
                                        attackers))
            assert all(dropped), f"{connect.__name__} not dropped"
            wait_until(lambda: _served(server.port), 5, "a new client served")
        finally:
            for attacker in attackers:
                attacker.close()
        if round_ == 0:
            baseline = server.rss()
    assert server.rss() - baseline < MEMORY_GROWTH


class _Attacker:
    DEADLINE = 8.0
    """Seconds the server may take to drop one."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)

    def dropped(self, timeout: float) -> bool:
        return _closed_by_server(self.sock, timeout)

    def close(self) -> None:
        self.sock.close()


class _Idle(_Attacker):
    """Connects and says nothing."""


class _Slow(_Attacker):
    """Sends a request one byte a second, never finishing it in time."""

    def dropped(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        request = f"[1] {READ_1000}\n".encode()
        try:
            for byte in request[:-1]:
                self.sock.sendall(bytes([byte]))
                if _closed_by_server(self.sock, 1.0):
                    return True
                if time.monotonic() > deadline:
                    return False
        except (BrokenPipeError, ConnectionResetError):
            return True
        return False


class _NeverReads(_Attacker):
    """Asks for ``help`` (a long answer) in batches and never reads an answer. Its receive
    buffer is small, as an attacker may choose, so that the kernel does not take tens of
    megabytes of answers before the server's own queue grows."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        self.sock.settimeout(10)
        self.sock.connect(("127.0.0.1", port))

    DEADLINE = 30.0
    """The server first fills the kernel's socket buffers (megabytes) at a few thousand
    answers a second, shared by the attackers."""

    def dropped(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        batch = b"help\n" * 2000
        self.sock.settimeout(0.2)
        try:
            while time.monotonic() < deadline:
                with contextlib.suppress(TimeoutError):  # the server takes its time
                    self.sock.sendall(batch)
        except (BrokenPipeError, ConnectionResetError):
            return True
        return False


def test_idle_clients_are_dropped(server: Server, steady: Steady) -> None:
    """Issue 13, defect 3: idle connections no longer hold the server's slots."""
    _attack(server, steady, _Idle)


def test_slow_clients_are_dropped(server: Server, steady: Steady) -> None:
    """Issue 13, defect 3: a line that takes longer than the line time-out ends the client."""
    _attack(server, steady, _Slow)


def test_clients_that_never_read_are_dropped(server: Server, steady: Steady) -> None:
    """Issue 13, defects 3 and 4: a client that never reads is dropped at the output bound,
    and what it left behind is given back."""
    _attack(server, steady, _NeverReads)


def test_200_connections_at_once(server: Server, steady: Steady) -> None:
    """Every one of 200 simultaneous connections is answered or refused with 600; none
    hangs, and the steady client keeps its rate."""
    baseline = 0
    for round_ in range(max(2, ROUNDS // 3)):
        sockets = []
        try:
            for _ in range(200):  # each asks at once: a slot's idle time-out is 1 s
                sockets.append(socket.create_connection(("127.0.0.1", server.port), timeout=10))
                sockets[-1].sendall(f"[7] {READ_1000}\n".encode())
            outcomes = {read_line(sock).encode() for sock in sockets}
        finally:
            for sock in sockets:
                sock.close()
        assert outcomes <= {REFUSED, f"[7] {ANSWER_1000}\r\n".encode()}
        if round_ == 0:
            baseline = server.rss()
    assert server.rss() - baseline < MEMORY_GROWTH


LINE_BREAKS = st.sampled_from([b"\n", b"\r\n", b"\r"])
JUNK = st.one_of(
    st.binary(max_size=200),
    st.text(max_size=100).map(lambda text: text.encode("utf-8", "surrogatepass")),
    st.binary(min_size=1, max_size=4).map(lambda head: head + b"\x80\xfe\xff\xc3(\x00"),
    st.integers(16385, 70000).map(lambda size: b"[3] 1 read " + b"x" * size),
    st.sampled_from([b"[1] 1 read 0x1000 0 u32", b"[1] help", b"1 read 0x1000",
                     b"\x00\x00\x00", b"[99999999999] 1 read"]),
)


@settings(max_examples=EXAMPLES, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(lines=st.lists(st.tuples(JUNK, LINE_BREAKS), max_size=20),
       repeat=st.sampled_from([1, 1, 1, 2000]))
def test_generated_lines(server: Server, steady: Steady,
                         lines: list[tuple[bytes, bytes]], repeat: int) -> None:
    """Whatever a client writes, in one write (thousands of requests pipelined when
    ``repeat`` is 2000), the connection still answers the next well-formed request and the
    steady client keeps its rate."""
    once = b"".join(junk + end for junk, end in lines)
    payload = once * (repeat if len(once) * repeat <= 1 << 20 else 1)
    sentinel = f"[424242] {ANSWER_1000}\r\n".encode()
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
        received: queue.SimpleQueue[bytes] = queue.SimpleQueue()

        def read() -> None:
            tail = b""
            try:
                while sentinel not in tail:
                    chunk = sock.recv(1 << 20)
                    if not chunk:
                        break
                    tail = tail[-4096:] + chunk
            finally:
                received.put(tail)

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        sock.sendall(payload + f"\n[424242] {READ_1000}\n".encode())
        tail = taken(received, 60)
        assert sentinel in tail, f"no answer to the request after the junk: {tail[-200:]!r}"
    baseline = FIRST_RSS.setdefault("generated", server.rss())
    assert server.rss() - baseline < MEMORY_GROWTH
