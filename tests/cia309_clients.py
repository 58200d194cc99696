"""Clients of the 309-3 server that the limit tests share: the server's process, a line
reader, and a well-behaved client that keeps asking at its normal rate."""

from __future__ import annotations

import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from tests import commands
from tests.conftest import Card, LoadClock, ended, wait_until
from tests.gateway_cards import start

READ_1000 = "1 1 read 0x1000 0 u32"
ANSWER_1000 = "983441"
"""1000h of the simulator's generic module."""
STEADY_PERIOD = 0.05
STEADY_WORST = 2.0
"""Seconds the well-behaved client may wait for one answer, in the time the server, the
card and the client could run (``LoadClock``): at a load of 19 the answers took 2.4-5.5 s
of wall time while seven clients that never read were dropped."""

@dataclass
class Server:
    proc: subprocess.Popen[str]
    port: int

    def rss(self) -> int:
        """The server's resident memory in bytes."""
        status = Path(f"/proc/{self.proc.pid}/status").read_text()
        match = re.search(r"VmRSS:\s+(\d+) kB", status)
        assert match is not None
        return int(match.group(1)) * 1024


def read_line(sock: socket.socket) -> str:
    data = b""
    while not data.endswith(b"\n"):
        chunk = sock.recv(1)
        if not chunk:
            break
        data += chunk
    return data.decode("latin-1")


@dataclass
class Steady:
    """A well-behaved client: one SDO read every STEADY_PERIOD, each answer checked.

    ``idle_limit``: the silence after which the server may end a connection (its idle
    time-out; ``IDLE_GRACE_S`` when a new client needs the slot), on the wall clock, as a
    server's must be. A loaded machine can keep this client from sending for longer: at a
    load of 11-13 the limit tests' client asked 13 times in 11 s beside the attackers, and
    the server rightly dropped it as idle ("idle for too long" in its log), which failed the
    test at teardown (``failures == ['']`` or a connection reset). A connection that ends
    when more than ``idle_limit`` passed between this client's last two requests is then
    opened again (``idle_drops``); the server's idle time counts from the last byte or
    answer, never before the request, so one that ends sooner is still a failure. None: no
    drop is excused."""

    port: int
    idle_limit: float | None = None
    answered: int = 0
    worst: float = 0.0
    idle_drops: int = 0
    failures: list[str] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        wait_until(lambda: self.answered > 0 or self.failures, 10,
                   "the steady client's first answer")

    def _run(self) -> None:
        sequence = 0
        while not self._stop.is_set():
            sent: float | None = None  # when this connection's last request went out
            silent = 0.0
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=10) as sock:
                    while not self._stop.is_set():
                        sequence += 1
                        now = time.monotonic()
                        clock = LoadClock(now)
                        silent, sent = (0.0 if sent is None else now - sent), now
                        sock.sendall(f"[{sequence}] {READ_1000}\n".encode())
                        answer = read_line(sock)
                        self.worst = max(self.worst, clock.elapsed())
                        if answer == "" and self._idle(silent):
                            break
                        if answer != f"[{sequence}] {ANSWER_1000}\r\n":
                            self.failures.append(answer)
                            return
                        self.answered += 1
                        self._stop.wait(STEADY_PERIOD)
            except OSError as exc:  # a reset, or a send to a connection the server ended
                if self._idle(silent):
                    continue
                self.failures.append(repr(exc))
                return

    def _idle(self, silent: float) -> bool:
        """Whether a connection that ended after ``silent`` seconds without a request of this
        client's was the server's to end; counted."""
        if self.idle_limit is None or silent <= self.idle_limit:
            return False
        self.idle_drops += 1
        return True

    def stop(self, clock: LoadClock) -> None:
        """End it and check it kept its rate since ``clock`` started, in the time the test's
        processes could run (a loaded machine slows the rate in wall time)."""
        self._stop.set()
        assert self._thread is not None
        assert ended(self._thread, 10), "the steady client did not stop"
        assert not self.failures
        assert self.worst < STEADY_WORST
        assert self.answered >= clock.elapsed() / (STEADY_PERIOD + STEADY_WORST / 10)


@contextmanager
def serving(directory: Path, *options: str) -> Iterator[Server]:
    """A read-only ``cifemu 309 serve`` process with ``options`` on a card that simulates
    one generic node, yielded once node 1 answers through it; stopped with SIGTERM after."""
    card: Card = start(directory, 0, "[[node]]\nid = 1\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "cifemu", "309", "serve", "--board", "0", "--dpm-dir",
         str(directory), "--port", "0", "--read-only", *options],
        stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        stderr = proc.stderr
        lines: queue.SimpleQueue[str] = queue.SimpleQueue()

        def pump() -> None:
            for line in stderr:
                lines.put(line)

        threading.Thread(target=pump, daemon=True).start()
        wait_until(lambda: not lines.empty(), 20, "cifemu 309 serve's first line")
        match = re.search(r"listening on 127\.0\.0\.1:(\d+)", lines.get())
        assert match is not None
        running = Server(proc, int(match.group(1)))
        wait_until(lambda: ask_once(running.port, READ_1000) == f"[1] {ANSWER_1000}", 15,
                   "node 1 answering through the server")
        yield running
        assert proc.poll() is None, "the server died"
    finally:
        proc.send_signal(signal.SIGTERM)
        assert commands.wait(proc, 20) == 0
        card.stop()


def ask_once(port: int, request: str) -> str:
    """One request on a connection of its own; the answer line without its line end."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        sock.sendall(f"[1] {request}\n".encode())
        return read_line(sock).rstrip("\r\n")
