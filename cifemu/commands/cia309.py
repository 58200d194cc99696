"""cifemu 309: the CiA 309-3 ASCII gateway on the card's networks (network N = board N-1).

  cifemu 309 serve [--host 127.0.0.1] [--port 60000] [--board N | --net N ...]
                   [--dialect canopennode|lely] [--read-only] [--max-clients N] [--max-line N]
                   [--idle-timeout S] [--line-timeout S] [--max-output N]
  cifemu 309 exec '[1] 4 read 0x1017 0 u16'     one request to a running server
  cifemu 309 exec --direct '4 read 0x1017 0 u16'  ... or to a gateway in this process
  cifemu 309 shell [--direct]                    interactive, with history

A request without [<sequence>] gets one. "exec" prints the answer and exits 1 when
it is an ERROR. Requests are as CANopenNode's cocomm and Lely's coctl write them
("help" lists them); answers and event lines follow --dialect.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import errno
import importlib
import json
import math
import re
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from platformdirs import user_state_path

from dpm.errors import Drv
from dpm.image import MAX_DEV_BOARDS
from dpm.message import Message
from host_api.board import CifError
from host_api.cia309.datatypes import Dialect
from host_api.cia309.formatters import format_event
from host_api.cia309.framing import DEFAULT_MAX_LINE, LineFramer
from host_api.cia309.gateway import Gateway
from host_api.cia309.model import Cia309Error, Event
from host_api.cia309.server import (
    DEFAULT_HOST,
    DEFAULT_IDLE_TIMEOUT,
    DEFAULT_LINE_TIMEOUT,
    DEFAULT_MAX_CLIENTS,
    DEFAULT_MAX_OUTPUT,
    DEFAULT_PORT,
    Client,
    Dispatcher,
    LssFactory,
    LssServices,
    Server,
    ServerConfig,
    new_event_loop,
    serve,
)

PROMPT = "309> "
DEFAULT_TIMEOUT = 130.0
"""Seconds ``exec`` and ``shell`` wait for an answer: longer than the gateway's own wait."""
QUIET_S = 0.3
"""A multi-line answer without a sequence (``help`` in Lely's dialect) ends after this
much silence."""
HISTORY_LENGTH = 1000
_SEQUENCE = re.compile(r"\s*\[\s*(\d+)\s*\]")
_EVENT_LINE = re.compile(r"\d+ (\d+ |pdo )")
"""Lely's unsolicited lines: ``<net> <node> ...`` or ``<net> pdo ...``."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    serve_parser = sub.add_parser("serve", help="run the 309-3 TCP server",
                                  description="Serve CiA 309-3 ASCII requests on TCP.")
    _card_arguments(serve_parser)
    serve_parser.add_argument("--host", default=DEFAULT_HOST,
                              help=f"address to bind (default {DEFAULT_HOST}: this machine "
                                   "only)")
    serve_parser.add_argument("--port", type=int, default=DEFAULT_PORT,
                              help=f"TCP port (default {DEFAULT_PORT}; 0 picks a free one)")
    serve_parser.add_argument("--read-only", action="store_true",
                              help="answer 100 to writes, NMT and configuration")
    serve_parser.add_argument("--max-clients", type=_positive, default=DEFAULT_MAX_CLIENTS,
                              metavar="N", help=f"connections at once; one more ends "
                                                f"the client idle longest (default "
                                                f"{DEFAULT_MAX_CLIENTS})")
    serve_parser.add_argument("--max-line", type=_positive, default=DEFAULT_MAX_LINE,
                              metavar="N", help=f"longest request in bytes until a client "
                                                f"sets its command size (default "
                                                f"{DEFAULT_MAX_LINE})")
    serve_parser.add_argument("--idle-timeout", type=_seconds, default=DEFAULT_IDLE_TIMEOUT,
                              metavar="SECONDS", help=f"drop a client that sends nothing "
                                                      f"for SECONDS while no request of its runs "
                                                      f"(default {DEFAULT_IDLE_TIMEOUT:g}; "
                                                      f"0: never)")
    serve_parser.add_argument("--line-timeout", type=_seconds, default=DEFAULT_LINE_TIMEOUT,
                              metavar="SECONDS", help=f"drop a client whose request line is "
                                                      f"not ended SECONDS after its first byte, "
                                                      f"or that does not read its answers for "
                                                      f"SECONDS (default "
                                                      f"{DEFAULT_LINE_TIMEOUT:g}; 0: never)")
    serve_parser.add_argument("--max-output", type=_positive, default=DEFAULT_MAX_OUTPUT,
                              metavar="N", help=f"bytes of answers and events left unread "
                                                f"by all clients together; over it, drop the "
                                                f"client with the most (default "
                                                f"{DEFAULT_MAX_OUTPUT})")
    serve_parser.set_defaults(action_func=_serve)
    exec_parser = sub.add_parser("exec", help="send one request, print its answer",
                                 description="Send one request and print the answer.")
    exec_parser.add_argument("request", help="e.g. '[1] 4 read 0x1017 0 u16'")
    exec_parser.add_argument("--json", action="store_true",
                             help="print the answer, or the error, as one JSON object")
    _client_arguments(exec_parser)
    exec_parser.set_defaults(action_func=_exec)
    shell_parser = sub.add_parser("shell", help="interactive requests with history",
                                  description="Type requests; answers and events print.")
    _client_arguments(shell_parser)
    shell_parser.add_argument("--history", type=Path,
                              default=user_state_path("cifemu") / "309_history",
                              help="readline history file (default: %(default)s)")
    shell_parser.set_defaults(action_func=_shell)


def _positive(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text} is not positive")
    return value


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text} is not a number of seconds") from None
    if not (value >= 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"{text} is not a finite number of seconds >= 0")
    return value


class _NetworkMeansNet(argparse.Action):
    """``--network N``, the first spelling of ``--net N``: still taken, with a warning.

    Every other command's ``--network`` names a network description (NETWORK.toml); here it
    named a CiA 309 network number, so it became ``--net``, the 309-3 requests' ``[net]``.
    """

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: object, option_string: str | None = None) -> None:
        print("cifemu 309: --network N is deprecated, use --net N (elsewhere --network "
              "names a NETWORK.toml)", file=sys.stderr)
        setattr(namespace, self.dest, [*(getattr(namespace, self.dest, None) or []), values])


def _card_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--board", type=int, action="append", default=[],
                        choices=range(MAX_DEV_BOARDS), metavar="N",
                        help="board to serve, 0..3 (repeatable; default 0)")
    parser.add_argument("--net", type=int, action="append", default=[],
                        choices=range(1, MAX_DEV_BOARDS + 1), metavar="N",
                        help="CiA 309 network to serve, 1..4 = board N-1 (repeatable)")
    parser.add_argument("--network", type=int, action=_NetworkMeansNet, dest="net",
                        choices=range(1, MAX_DEV_BOARDS + 1), metavar="N",
                        help="deprecated spelling of --net")
    parser.add_argument("--dpm-dir", default=None, metavar="DIR",
                        help="directory of the images (default $CIF_DPM_DIR or /dev/shm/cif)")
    parser.add_argument("--dialect", type=Dialect, choices=list(Dialect),
                        default=Dialect.CANOPENNODE,
                        help="whose answers and events: canopennode (cocomm) or lely (coctl)")


def _client_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default=DEFAULT_HOST, help="the server's address")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help="the server's port")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT, metavar="SECONDS",
                        help=f"seconds to wait for an answer (default {DEFAULT_TIMEOUT:g})")
    parser.add_argument("--direct", action="store_true",
                        help="no server: run a gateway in this process on the boards below")
    _card_arguments(parser)


NO_CARD = (Drv.DRV_USR_OPEN_ERROR, Drv.DRV_USR_DEV_NUMBER_INVALID, Drv.DRV_DEV_NOT_READY)
"""Driver codes of a board no firmware serves: no image directory, no image, no READY."""


def _error_text(exc: Cia309Error | OSError, args: argparse.Namespace) -> str:
    """The one line a failed command prints, with the hint the other commands give: a
    board no firmware serves asks whether it runs, a port in use names it (not Python's
    ``[Errno 98]``)."""
    if isinstance(exc, OSError) and exc.errno == errno.EADDRINUSE and hasattr(args, "port"):
        return f"port {args.port} on {args.host} is in use; choose another with --port"
    cause = exc.__cause__
    if isinstance(cause, CifError) and cause.code in NO_CARD:
        boards = _boards(args) if hasattr(args, "board") else [0]
        board = boards[0] if len(boards) == 1 else "N"
        return f"{exc}; is `cifemu firmware --board {board}` running?"
    return str(exc)


def run(args: argparse.Namespace) -> int:
    action: Callable[[argparse.Namespace], int] = args.action_func
    try:
        return action(args)
    except (Cia309Error, OSError) as exc:
        text = _error_text(exc, args)
        if getattr(args, "json", False):
            print(json.dumps({"ok": False, "error": {"text": text}}))
        else:
            print(f"cifemu 309: {text}", file=sys.stderr)
        return 1


def _boards(args: argparse.Namespace) -> list[int]:
    boards = set(args.board) | {net - 1 for net in args.net}
    return sorted(boards) or [0]


def open_lss(gateway: Gateway) -> LssFactory | None:
    """The LSS services of ``host_api.cia309.lss`` (its ``LssMaster``, one per network, fed
    by the gateway's mailbox reader), when that module is there; else LSS answers 100."""
    try:
        module = importlib.import_module("host_api.cia309.lss")
    except ImportError:
        return None
    master = getattr(module, "LssMaster", None)
    if master is None:
        return None
    masters: dict[int, LssServices] = {}
    lock = threading.Lock()

    def services(network: int) -> LssServices:
        with lock:
            if network not in masters:
                def transact(message: Message) -> Message:
                    return gateway.transact(message, network=network)

                masters[network] = master(gateway.board(network=network),
                                          indications=gateway.layer2_indications(
                                              network=network),
                                          transact=transact)
            return masters[network]

    return services


# --------------------------------------------------------------------------- serve


def _serve(args: argparse.Namespace) -> int:
    config = ServerConfig(args.host, args.port, args.dialect, args.read_only,
                          args.max_clients, args.max_line, args.idle_timeout,
                          args.line_timeout, args.max_output)
    with Gateway(_boards(args), args.dpm_dir) as gateway, \
            asyncio.Runner(loop_factory=new_event_loop) as runner:
        runner.run(_serve_until_signal(gateway, config, open_lss(gateway)))
    return 0


async def _serve_until_signal(gateway: Gateway, config: ServerConfig,
                              lss: LssFactory | None) -> None:
    """Serve until SIGTERM or SIGINT, then close every connection and the gateway."""
    task = asyncio.current_task()
    assert task is not None
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, task.cancel)

    def ready(server: Server) -> None:
        print(f"cifemu 309: {config.dialect.value} gateway on networks "
              f"{', '.join(map(str, gateway.networks))}, listening on "
              f"{config.host}:{server.port}", file=sys.stderr, flush=True)

    with contextlib.suppress(asyncio.CancelledError):
        await serve(gateway, config, lss, ready)


# --------------------------------------------------------------------------- exec and shell


def _with_sequence(request: str, sequence: int) -> tuple[str, int]:
    """The request as sent, and the sequence its answer carries."""
    match = _SEQUENCE.match(request)
    if match is not None:
        return request.strip(), int(match.group(1))
    return f"[{sequence}] {request.strip()}", sequence


class Remote:
    """A connection to a running server: sends requests, tells answers from event lines."""

    def __init__(self, host: str, port: int, timeout: float,
                 on_event: Callable[[str], None]) -> None:
        self._host, self._port = host, port
        self._address = f"{host}:{port}"
        self._timeout = timeout
        self._on_event = on_event
        self._socket = self._connect()
        self._buffer = b""
        self._closed = False

    def _connect(self) -> socket.socket:
        try:
            connection = socket.create_connection((self._host, self._port),
                                                  timeout=self._timeout)
        except OSError as exc:
            reason = exc.strerror or str(exc)
            raise ConnectionError(f"no 309-3 server at {self._address} ({reason}); start one "
                                  "with 'cifemu 309 serve'") from exc
        connection.settimeout(QUIET_S)
        return connection

    def ask(self, line: str, sequence: int) -> str:
        """Send ``line``; return its answer (every line of it).

        A connection the server ended while nothing was asked (its idle time-out, [ours])
        is opened again first: the request was not sent, so nothing is asked twice; the
        settings made with ``set`` on the old connection are gone, and a note says so.
        """
        if self._closed:
            self._socket.close()
            self._socket, self._buffer, self._closed = self._connect(), b"", False
            print(f"cifemu 309: the server at {self._address} had closed the connection; "
                  "connected again (defaults set with 'set' are gone)", file=sys.stderr)
        self._socket.sendall(line.encode("latin-1") + b"\n")
        answer: list[str] = []
        deadline = time.monotonic() + self._timeout
        while time.monotonic() < deadline:
            text = self._next_line()
            if text is None:
                if answer:
                    break  # a multi-line answer without a sequence has ended
                continue
            if not answer and _EVENT_LINE.match(text):
                self._on_event(text)
                continue
            answer.append(text)
            match = _SEQUENCE.match(text)
            if (match is not None and int(match.group(1)) == sequence) or text.endswith("\r\n"):
                break
        return "".join(answer)

    def poll_events(self) -> None:
        """Hand on event lines that came while nothing was asked."""
        while (text := self._next_line()) is not None:
            self._on_event(text)

    def _next_line(self) -> str | None:
        """One received line with its end, or None after QUIET_S without one."""
        while b"\n" not in self._buffer:
            try:
                chunk = self._socket.recv(65536)
            except TimeoutError:
                return None
            if not chunk:
                self._closed = True
                raise ConnectionError(f"the server at {self._address} closed the connection")
            self._buffer += chunk
        line, _, self._buffer = self._buffer.partition(b"\n")
        return (line + b"\n").decode("latin-1")

    def close(self) -> None:
        self._socket.close()


class _Direct:
    """A gateway in this process, answering as the server would."""

    def __init__(self, args: argparse.Namespace, on_event: Callable[[str], None]) -> None:
        self.gateway = Gateway(_boards(args), args.dpm_dir)
        self._dispatcher = Dispatcher(args.dialect, lss=open_lss(self.gateway))
        self._client = Client(self.gateway, LineFramer(DEFAULT_MAX_LINE))
        dialect = args.dialect

        def event(item: Event) -> None:
            if dialect is Dialect.LELY:
                line = format_event(item, dialect)
                if line is not None:
                    on_event(line)

        self._subscription = self.gateway.subscribe(event)

    def ask(self, line: str, sequence: int) -> str:
        del sequence
        return self._dispatcher.handle(self._client, line) or ""

    def close(self) -> None:
        self._subscription.cancel()
        self.gateway.close()


def _print_answer(text: str) -> None:
    sys.stdout.write(text.replace("\r\n", "\n"))
    if text and not text.endswith("\n"):
        sys.stdout.write("\n")
    sys.stdout.flush()


def _print_event(text: str) -> None:
    _print_answer(text)


def _connect(args: argparse.Namespace) -> Remote | _Direct:
    if args.direct:
        return _Direct(args, _print_event)
    return Remote(args.host, args.port, args.timeout, _print_event)


def _exec(args: argparse.Namespace) -> int:
    line, sequence = _with_sequence(args.request, 1)
    connection = _connect(args)
    try:
        answer = connection.ask(line, sequence)
    finally:
        connection.close()
    document = answer_document(answer)
    if args.json:
        print(json.dumps(document))
    else:
        _print_answer(answer)
    return 0 if document["ok"] else 1


_ERROR_ANSWER = re.compile(
    r"\[(\d+)\] ERROR:\s*(0x[0-9A-Fa-f]+|[0-9A-Fa-f]{8}|\d+)\s*(?:#(.*?)\.?|\((.*)\))?\s*")
"""A 309-3 error answer of either dialect: ``ERROR:101 #text.``, ``ERROR: 101 (text)``,
``ERROR:0x06020000 #text.``, ``ERROR: 06020000 (text)``."""


def answer_document(answer: str) -> dict[str, object]:
    """An answer as ``exec --json`` prints it: ``sequence`` (None for an answer without
    one, as Lely's ``help``), ``ok``, and ``answer`` (the text after the sequence) or
    ``error`` with ``code`` (a 309-3 number) or ``abort_code`` (an SDO abort), ``text`` and
    the server's ``detail`` when it gave one."""
    text = answer.replace("\r\n", "\n").rstrip("\n")
    match = _ERROR_ANSWER.fullmatch(text)
    if match is None:
        sequence = _SEQUENCE.match(text)
        body = text[sequence.end():].lstrip() if sequence else text
        return {"sequence": int(sequence.group(1)) if sequence else None, "ok": True,
                "answer": body}
    number, comment = match.group(2), match.group(3) or match.group(4) or ""
    described, _, detail = comment.partition(": ")
    error: dict[str, object] = (
        {"abort_code": int(number, 16)} if number.startswith("0x") or len(number) == 8
        else {"code": int(number)})
    error["text"] = described
    if detail:
        error["detail"] = detail
    return {"sequence": int(match.group(1)), "ok": False, "error": error}


def _shell(args: argparse.Namespace) -> int:
    import readline  # only here: it changes how input() behaves for the whole process

    history: Path = args.history
    with contextlib.suppress(OSError):
        readline.read_history_file(history)
    readline.set_history_length(HISTORY_LENGTH)
    connection = _connect(args)
    lock = threading.Lock()
    stop = threading.Event()
    if isinstance(connection, Remote):
        remote = connection

        def pump() -> None:
            while not stop.wait(QUIET_S):
                with lock, contextlib.suppress(OSError):
                    remote.poll_events()

        threading.Thread(target=pump, daemon=True, name="cia309-shell-events").start()
    sequence = 0
    try:
        while True:
            try:
                text = input(PROMPT)
            except EOFError:
                break
            if text.strip() in ("quit", "exit"):
                break
            if not text.strip():
                continue
            sequence += 1
            line, expected = _with_sequence(text, sequence)
            with lock:
                _print_answer(connection.ask(line, expected))
    except KeyboardInterrupt:
        sys.stdout.write("\n")
    finally:
        stop.set()
        connection.close()
        history.parent.mkdir(parents=True, exist_ok=True)
        readline.write_history_file(history)
    return 0
