"""309-3 reads on vcan0: ``cifemu 309 serve`` against CANopenNode's own gateway, one client.

A ``make bench-vcan`` phase (issue 22: the card's gateway should read at least as fast as
CANopenNode's). One CANopenNode device (``canopend``, node 4) sits on vcan0; the same
client, in this process, reads its 1000h over TCP through two gateways on the same bus:

* ``cifemu``: ``cifemu 309 serve`` (CANopenNode dialect, a process of its own) in front of
  the card (``cifemu firmware`` on vcan0, configured with a network whose node 4 is that
  device): client -> server -> mailbox -> card -> vcan0 -> device and back;
* ``canopennode``: a second ``canopend``, node 1, with its 309-3 gateway on a TCP port
  (``-c tcp-PORT``): client -> canopend -> vcan0 -> device and back.

The client sends ``[n] 4 read 0x1000 0 u32`` and reads the answer line; the two take turns
in batches (``measure_alternating``), so both see the same machine. Then each side reads
again alone while the CPU time of every process on the path is counted (inside
``tools/vcan-vm`` the guest has one CPU, so CPU per read is what bounds the rate), and,
where ``cocomm`` is present, CANopenNode's own client reads the same object through each
gateway from a command file (one connection, one line after another).

CANopenNode is not part of this project: ``canopend`` and ``cocomm`` are looked for in
``$CIFEMU_CANOPENNODE/bin`` (default ``~/.cache/cifemu/canopennode/bin``), then on PATH.
Without ``canopend`` the phase says so in its JSON, with the steps that build it
(docs/benchmarks.md, "CANopenNode beside the project").

    python -m bench.canopennode [--count N] [--warmup N]     (on a Linux with vcan0)
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import can

from bench.can.card import SimCard, configure, wait_operating
from bench.common import (
    STARTUP_TIMEOUT,
    emit,
    latency_stats,
    measure_alternating,
    progress,
    ratio,
    scratch_root,
    stop_process,
)
from bench.cpu import CpuSample
from dbm_tools.network import parse_network
from dpm.cia301 import ERROR_CONTROL_BASE, SDO_REQUEST_BASE, SDO_RESPONSE_BASE
from host_api.board import Board
from host_api.ready import wait_ready

CHANNEL = "vcan0"
BOARD = 0
DEVICE_NODE = 4
"""The CANopenNode device both gateways read."""
GATEWAY_NODE = 1
"""CANopenNode's gateway is a device too; its node-ID is one the card's network leaves free."""
COUNT = 2000
WARMUP = 100
BATCH = 250
"""Reads per turn of each gateway: a few hundred milliseconds each inside User-Mode Linux."""
CPU_READS = 500
"""Reads per side while the CPU time of each process on the path is counted."""
COCOMM_READS = 500
COCOMM_ROUNDS = 3
COCOMM_TIMEOUT_S = 60.0
"""One run of 500 reads takes about a second; a run that hangs is a failed one."""
CANOPENNODE_DIR = Path(os.environ.get(
    "CIFEMU_CANOPENNODE",
    Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "cifemu" / "canopennode"))
"""Where CANopenNode's Linux application is built, outside this repository; its programs are
looked for in ``bin`` under it first, then on PATH."""
_SOURCE = "~/.cache/cifemu/canopennode/CANopenLinux"
BUILD_STEPS = (
    f"git clone https://github.com/CANopenNode/CANopenLinux {_SOURCE}",
    f"git -C {_SOURCE} submodule update --init",
    f"make -C {_SOURCE}",
    f"make -C {_SOURCE}/cocomm",
    "mkdir -p ~/.cache/cifemu/canopennode/bin",
    f"cp {_SOURCE}/canopend {_SOURCE}/cocomm/cocomm ~/.cache/cifemu/canopennode/bin/",
)
"""docs/benchmarks.md's steps, one command each (read the fetched code's defaults first:
``canopend -c tcp-PORT`` listens on every address, which inside ``tools/vcan-vm`` is the
guest's loopback alone)."""
REQUEST = f"{DEVICE_NODE} read 0x1000 0 u32"
SAVE = bytes([0x23, 0x10, 0x10, 0x01]) + b"save"
"""SDO download of "save" into 1010h sub 1: CANopenNode stores its defaults. Started without
its storage files a CANopenLinux device sends EMCY 5000h, sets its error register and
refuses OPERATIONAL; restarted (the card's Reset Node) with them it is a clean device."""
BOOT_UP_TIMEOUT_S = 10.0
PORT_TIMEOUT_S = 30.0
"""Until a gateway accepts connections: the server is an interpreter start away (about a
second inside User-Mode Linux, more on a loaded host)."""
ANSWER_TIMEOUT_S = 10.0
FIRMWARE_START_S = 4 * STARTUP_TIMEOUT
"""Until the card is READY, and again until its node is up: inside User-Mode Linux on a host
at load 34-39 the benchmarks' usual 15 s and 20 s were not enough for either."""
MAX_STARTS = 50
"""A device that keeps ending (no vcan0, say) is not started for ever."""
LISTENING = re.compile(rb"listening on [^ ]+:(\d+)")


def program(name: str) -> str | None:
    """``canopend`` or ``cocomm``: in ``CANOPENNODE_DIR/bin``, else on PATH."""
    found = CANOPENNODE_DIR / "bin" / name
    return str(found) if found.is_file() and os.access(found, os.X_OK) else shutil.which(name)


def missing() -> dict[str, Any] | None:
    """The phase's JSON when ``canopend`` cannot be found, else None."""
    if program("canopend") is not None:
        return None
    return {"skipped": f"canopend not found in {CANOPENNODE_DIR / 'bin'} or on PATH; "
                       "build CANopenNode's Linux application beside the project "
                       "(docs/benchmarks.md, 'CANopenNode beside the project'), never into "
                       "this repository",
            "build": list(BUILD_STEPS)}


@dataclass
class Restarting:
    """A ``canopend`` kept running: an NMT Reset Node ends CANopenLinux's process (a device
    reboots), and the card resets each node as it boots it."""

    argv: list[str]
    log: IO[bytes]
    starts: int = 0
    exit_codes: list[int] = field(default_factory=list)
    _proc: subprocess.Popen[bytes] | None = None
    _stopping: bool = False
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            with self._lock:
                if self._stopping or self.starts >= MAX_STARTS:
                    return
                self._proc = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL,
                                              stdout=self.log, stderr=subprocess.STDOUT)
                self.starts += 1
                proc = self._proc
            self.exit_codes.append(proc.wait())

    @property
    def pid(self) -> int | None:
        with self._lock:
            return None if self._proc is None or self._proc.poll() is not None else self._proc.pid

    def stop(self) -> None:
        with self._lock:
            self._stopping = True
            proc = self._proc
        if proc is not None:
            stop_process(proc)
        if self._thread is not None:
            self._thread.join(5.0)


def wait_boot_up(bus: can.BusABC, node: int, timeout: float = BOOT_UP_TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = bus.recv(0.1)
        if (msg is not None and msg.arbitration_id == ERROR_CONTROL_BASE + node
                and bytes(msg.data) == b"\0"):
            return
    raise RuntimeError(f"no boot-up from the CANopenNode device {node} within {timeout} s")


def store_defaults(bus: can.BusABC, node: int, timeout: float = BOOT_UP_TIMEOUT_S) -> None:
    """1010h sub 1 = "save" by a raw SDO download; RuntimeError unless the device confirms."""
    bus.send(can.Message(arbitration_id=SDO_REQUEST_BASE + node, data=SAVE, is_extended_id=False))
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = bus.recv(0.1)
        if msg is None or msg.arbitration_id != SDO_RESPONSE_BASE + node:
            continue
        if msg.data[0] == 0x60:
            return
        raise RuntimeError(f"the device refused to store its defaults: {bytes(msg.data).hex()}")
    raise RuntimeError(f"the device did not answer the store request within {timeout} s")


class LineClient:
    """The one 309-3 client of both gateways: a request line, its answer line."""

    def __init__(self, port: int) -> None:
        self._socket = socket.create_connection(("127.0.0.1", port), timeout=ANSWER_TIMEOUT_S)
        self._socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sequence = 0
        self.first_answer: str | None = None

    def read(self) -> int:
        """0 for a value, 1 for an error or a wrong sequence, 2 for a closed connection."""
        self._sequence = self._sequence % 1_000_000 + 1
        prefix = f"[{self._sequence}] "
        self._socket.sendall(f"{prefix}{REQUEST}\n".encode())
        answer = b""
        while not answer.endswith(b"\r\n"):
            chunk = self._socket.recv(256)
            if not chunk:
                return 2
            answer += chunk
        text = answer.decode(errors="replace")
        if self.first_answer is None:
            self.first_answer = text.strip()
        return 0 if text.startswith(prefix) and "ERROR" not in text else 1

    def close(self) -> None:
        self._socket.close()


def wait_port(port: int, timeout: float = PORT_TIMEOUT_S) -> None:
    """Until 127.0.0.1:``port`` accepts a connection (which is closed again at once)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise RuntimeError(f"nothing listens on port {port} after {timeout} s") from None
            time.sleep(0.05)


def free_port() -> int:
    """A port free now on 127.0.0.1, for canopend, which takes no port 0."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def start_server(directory: Path, log: Path) -> tuple[subprocess.Popen[bytes], int]:
    """``cifemu 309 serve`` on board 0 of ``directory``, on a port the kernel picks."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "cifemu", "309", "serve", "--board", str(BOARD), "--dpm-dir",
         str(directory), "--port", "0"],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    assert proc.stderr is not None
    stderr = proc.stderr
    found: list[int] = []
    ready = threading.Event()

    def drain() -> None:
        with log.open("wb") as out:
            for line in iter(stderr.readline, b""):
                out.write(line)
                out.flush()
                match = LISTENING.search(line)
                if match and not found:
                    found.append(int(match.group(1)))
                    ready.set()
        ready.set()

    threading.Thread(target=drain, daemon=True).start()
    if not ready.wait(PORT_TIMEOUT_S) or not found:
        stop_process(proc)
        raise RuntimeError(f"cifemu 309 serve did not listen: {log.read_text(errors='replace')}")
    return proc, found[0]


def network_description() -> str:
    """The card's network: the CANopenNode device as node 4 (its 1000h is 0; its PDOs are
    off, so the generic module's PDOs the card maps are ignored by it), unsupervised, as
    CANopenNode's gateway leaves it: with a heartbeat, a loaded host made the card miss it,
    reset the device and retry its boot 30 times in one run, in the middle of the reads.
    Without the boot's guard step: a node without error control is one with guarding off,
    and the card would write 100Ch/100Dh, which this device lacks (its boot would fail)."""
    return "\n".join(["[bus]", "host_watchdog_ms = 0", "[[node]]", f"id = {DEVICE_NODE}",
                      'name = "canopend"', "device_type = 0", 'error_control = "none"',
                      'boot = ["reset", "device", "sync", "emcy", "sdo", "start", "pdo"]']
                     ) + "\n"


def cpu_window(client: LineClient, reads: int, pids: dict[str, int | None]) -> dict[str, Any]:
    """``reads`` reads by one client alone, with what each process on the path spent per
    read meanwhile: CPU time (``/proc/PID/stat``), and per thread its CPU time and its
    wake-ups (voluntary context switches, each one a hand-over that inside User-Mode Linux
    costs a round through the host's ptrace)."""
    live = {name: pid for name, pid in pids.items() if pid is not None}
    before = {name: CpuSample.take(pid) for name, pid in live.items()}
    start = time.perf_counter_ns()
    failures = sum(client.read() != 0 for _ in range(reads))
    wall = time.perf_counter_ns() - start
    after = {name: CpuSample.take(pid) for name, pid in live.items()}

    def per_read(value: float) -> float:
        return round(value / reads, 2)

    processes: dict[str, dict[str, Any]] = {}
    for name, pid in live.items():
        old, new = before[name], after[name]
        threads: list[dict[str, Any]] = [
            {"thread": "main" if tid == pid else f"tid {tid}",
             "cpu_us": per_read((ns - old.threads.get(tid, 0)) / 1e3),
             "wakeups": per_read(new.wakeups.get(tid, 0) - old.wakeups.get(tid, 0))}
            for tid, ns in new.threads.items()]
        processes[name] = {"cpu_us": per_read((new.stat_ns - old.stat_ns) / 1e3),
                           "wakeups": round(sum(t["wakeups"] for t in threads), 2),
                           "threads": sorted(threads, key=lambda t: -t["cpu_us"])}
    return {"reads": reads, "failures": failures,
            "wall_us_per_read": round(wall / reads / 1e3, 1),
            "cpu_us_per_read_total": round(sum(p["cpu_us"] for p in processes.values()), 1),
            "wakeups_per_read_total": round(sum(p["wakeups"] for p in processes.values()), 1),
            "per_read": processes}


def cocomm_rounds(cocomm: str, ports: dict[str, int], directory: Path) -> dict[str, Any]:
    """CANopenNode's own client, ``cocomm -f`` with ``COCOMM_READS`` lines, on each gateway in
    turn: reads/s over the whole run (the process's start included, a few ms); a run that
    fails or hangs counts in ``failed_runs`` instead."""
    commands = directory / "reads.txt"
    commands.write_text("".join(f"[{n}] {REQUEST}\n" for n in range(1, COCOMM_READS + 1)))
    rates: dict[str, list[float]] = {name: [] for name in ports}
    failures = dict.fromkeys(ports, 0)
    first_failure: dict[str, str] = {}
    for _ in range(COCOMM_ROUNDS):
        for name, port in ports.items():
            start = time.perf_counter()
            try:
                done = subprocess.run([cocomm, "-t", "127.0.0.1", "-p", str(port), "-o", "flat",
                                       "-f", str(commands)], stdin=subprocess.DEVNULL,
                                      capture_output=True, timeout=COCOMM_TIMEOUT_S, check=False)
            except subprocess.TimeoutExpired:
                failures[name] += 1
                first_failure.setdefault(name, f"no end within {COCOMM_TIMEOUT_S} s")
                continue
            elapsed = time.perf_counter() - start
            # -o flat: "[n] 0" and its CR LF for each answer, all on stdout
            if (done.returncode != 0 or done.stdout.count(b"\r\n") != COCOMM_READS
                    or b"ERROR" in done.stdout):
                failures[name] += 1
                first_failure.setdefault(name, f"exit {done.returncode}: "
                                               f"{(done.stderr + done.stdout)[:200]!r}")
                continue
            rates[name].append(round(COCOMM_READS / elapsed, 1))
    return {"reads_per_run": COCOMM_READS,
            "reads_per_s": rates,
            "failed_runs": failures,
            "first_failure": first_failure,
            "ratio_best": ratio(max(rates["cifemu"], default=0.0),
                                max(rates["canopennode"], default=0.0))}


@contextmanager
def card_on_vcan(directory: Path) -> Iterator[SimCard]:
    """The card on vcan0, configured with ``network_description`` and its node up."""
    text = network_description()
    stderr_path = directory / "firmware.stderr"
    with stderr_path.open("wb") as stderr:
        proc = subprocess.Popen(
            [sys.executable, "-m", "cifemu", "firmware", "--board", str(BOARD), "--dpm-dir",
             str(directory), "--log-level", "WARNING", "--interface", "socketcan", "--channel",
             CHANNEL, "--flash", str(directory / "flash")],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=stderr)
    card = SimCard(directory, proc, None, stderr_path)
    try:
        wait_ready(proc, directory, BOARD, FIRMWARE_START_S)
        card.board = Board(BOARD, directory, timeout=5000).open()
        configure(card, parse_network(text))
        try:
            wait_operating(BOARD, 1, FIRMWARE_START_S)
        except RuntimeError as exc:
            raise RuntimeError(f"{exc}; the firmware log: {card.log()}") from None
        card.board.close()  # the server is the card's one host from here on
        card.board = None
        yield card
    finally:
        card.stop()


def run(count: int = COUNT, warmup: int = WARMUP) -> dict[str, Any]:
    """The phase's JSON: both gateways' figures and their ratio, or why they are absent."""
    absent = missing()
    if absent is not None:
        progress(f"309-3 against CANopenNode: {absent['skipped']}")
        return absent
    try:
        return _run(count, warmup)
    except (RuntimeError, OSError, subprocess.SubprocessError) as exc:
        progress(f"309-3 against CANopenNode: {exc}")
        return {"failed": str(exc)}


def _run(count: int, warmup: int) -> dict[str, Any]:
    canopend = program("canopend")
    assert canopend is not None
    with tempfile.TemporaryDirectory(prefix="cifemu-bench-309-", dir=scratch_root()) as tmp:
        directory = Path(tmp)
        for name in ("device", "gateway"):
            (directory / name).mkdir()
        with (directory / "device.log").open("wb") as device_log, \
                (directory / "gateway.log").open("wb") as gateway_log:
            device = Restarting([canopend, CHANNEL, "-i", str(DEVICE_NODE), "-s",
                                 f"{directory / 'device'}/"], device_log)
            gateway_port = free_port()
            gateway = Restarting([canopend, CHANNEL, "-i", str(GATEWAY_NODE), "-s",
                                  f"{directory / 'gateway'}/", "-c", f"tcp-{gateway_port}"],
                                 gateway_log)
            try:
                progress(f"309-3 against CANopenNode: canopend as node {DEVICE_NODE} on vcan0")
                with can.Bus(interface="socketcan", channel=CHANNEL) as bus:
                    device.start()
                    wait_boot_up(bus, DEVICE_NODE)
                    store_defaults(bus, DEVICE_NODE)
                return _measure(directory, device, gateway, gateway_port, count, warmup)
            except RuntimeError as exc:
                device_log.flush()
                tail = (directory / "device.log").read_bytes()[-300:]
                return {"failed": str(exc), "device_starts": device.starts,
                        "device_log_tail": tail.decode(errors="replace")}
            finally:
                gateway.stop()
                device.stop()


def _measure(directory: Path, device: Restarting, gateway: Restarting, gateway_port: int,
             count: int, warmup: int) -> dict[str, Any]:
    progress("309-3 against CANopenNode: the card on vcan0, configured with the device")
    with card_on_vcan(directory) as card:
        server, port = start_server(directory, directory / "server.stderr")
        clients: list[LineClient] = []
        try:
            gateway.start()  # after the card's boot: its NMT would reset this one too
            wait_port(gateway_port)
            clients = [LineClient(port), LineClient(gateway_port)]
            cif, con = clients
            progress(f"309-3 against CANopenNode: {count} reads of 1000h through each "
                     f"gateway, in turns of {BATCH}")
            cif_m, con_m = measure_alternating([cif.read, con.read], count, warmup,
                                               frozenset({0}), BATCH)
            pids = {"client (this process)": os.getpid(), "canopend device": device.pid}
            progress("309-3 against CANopenNode: CPU time per read, each gateway alone")
            cpu = {"cifemu": cpu_window(cif, CPU_READS, {**pids, "cifemu firmware": card.pid,
                                                          "cifemu 309 serve": server.pid}),
                   "canopennode": cpu_window(con, CPU_READS,
                                             {**pids, "canopend gateway": gateway.pid})}
            for client in clients:  # canopend serves one connection at a time
                client.close()
            clients = []
            cocomm = program("cocomm")
            by_cocomm: dict[str, Any] = {"skipped": "cocomm not found"}
            if cocomm is not None:
                progress(f"309-3 against CANopenNode: cocomm -f, {COCOMM_READS} reads, "
                         f"{COCOMM_ROUNDS} rounds each")
                by_cocomm = cocomm_rounds(cocomm, {"cifemu": port, "canopennode": gateway_port},
                                          directory)
        finally:
            for client in clients:
                client.close()
            stop_process(server)
        firmware_log = card.log()
    return {
        "what": f"309-3 '[n] {REQUEST}' over TCP, answer line read, one client in this "
                "process; the device is CANopenNode's canopend on vcan0",
        "count": count,
        "warmup": warmup,
        "batch": BATCH,
        "cifemu": _figures(cif_m.per_second, cif_m.latencies_ns, cif_m.failures,
                           cif.first_answer),
        "canopennode": _figures(con_m.per_second, con_m.latencies_ns, con_m.failures,
                                con.first_answer),
        "ratio": {"reads_per_s": ratio(cif_m.per_second, con_m.per_second),
                  "p50": ratio(latency_stats(cif_m.latencies_ns)["p50"],
                               latency_stats(con_m.latencies_ns)["p50"])},
        "cpu": cpu,
        "cocomm": by_cocomm,
        "device_starts": device.starts,
        "gateway_starts": gateway.starts,
        "firmware_log": firmware_log,
        "canopend": program("canopend"),
    }


def _figures(per_s: float, latencies_ns: list[int], failures: int,
             answer: str | None) -> dict[str, Any]:
    return {"reads_per_s": round(per_s, 1), "latency_us": latency_stats(latencies_ns),
            "failures": failures, "first_answer": answer}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.canopennode", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=COUNT, help=f"reads each (default {COUNT})")
    parser.add_argument("--warmup", type=int, default=WARMUP,
                        help=f"reads each before timing (default {WARMUP})")
    args = parser.parse_args(argv)
    emit(run(args.count, args.warmup))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
