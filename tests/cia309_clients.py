"""Clients of the 309-3 server that the limit tests share: the server's process, a line
reader, and a well-behaved client that keeps asking at its normal rate."""

from __future__ import annotations

import re
import socket
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from tests.conftest import wait_until

READ_1000 = "1 1 read 0x1000 0 u32"
ANSWER_1000 = "983441"
"""1000h of the simulator's generic module."""
STEADY_PERIOD = 0.05
STEADY_WORST = 2.0
"""Seconds the well-behaved client may wait for one answer on a loaded two-core machine."""

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
    """A well-behaved client: one SDO read every STEADY_PERIOD, each answer checked."""

    port: int
    answered: int = 0
    worst: float = 0.0
    failures: list[str] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        wait_until(lambda: self.answered > 0 or self.failures, 10,
                   "the steady client's first answer")

    def _run(self) -> None:
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=10) as sock:
                sequence = 0
                while not self._stop.is_set():
                    sequence += 1
                    began = time.monotonic()
                    sock.sendall(f"[{sequence}] {READ_1000}\n".encode())
                    answer = read_line(sock)
                    self.worst = max(self.worst, time.monotonic() - began)
                    if answer != f"[{sequence}] {ANSWER_1000}\r\n":
                        self.failures.append(answer)
                        return
                    self.answered += 1
                    self._stop.wait(STEADY_PERIOD)
        except OSError as exc:
            self.failures.append(repr(exc))

    def stop(self, seconds: float) -> None:
        """End it and check it kept its rate over the last ``seconds``."""
        self._stop.set()
        assert self._thread is not None
        self._thread.join(10)
        assert not self.failures
        assert self.worst < STEADY_WORST
        assert self.answered >= seconds / (STEADY_PERIOD + STEADY_WORST / 10)
