"""The CiA 309-3 ASCII gateway on TCP: the text layer over the services of ``gateway``.

Layers, as pymodbus splits framer, PDU codec and transport:

* :class:`Dispatcher` turns one request line into one answer text: ``parse_request``,
  the 309-1 call on a :class:`~host_api.cia309.gateway.Gateway` session found in a table
  by the request's type, ``format_*``.
  No socket: the TCP server, ``cifemu 309 exec --direct`` and ``cifemu 309 shell
  --direct`` share it.
* :class:`Server` is the asyncio TCP server: one ``Client`` per connection with its own
  line framer, sequence and gateway session (so its own default network and node-ID,
  command time-out and command size), requests of one client answered in order, clients
  served at once, and events fanned out to every client. A line that arrives alone
  while its client waits for nothing (the usual read or write: one line, one answer) is
  answered without the client's task: an SDO upload or expedited download from the mailbox
  reader's callback on the event loop (``Server._fast_line``).

Events follow the dialect: Lely's ``coctl`` reads unsolicited lines (``1 5 BOOT_UP``,
``1 pdo 1 2 0x1 0x2``) between answers, so in that dialect every client gets them as
they happen; CANopenNode's ``cocomm`` would take such a line for its answer, so there
they go to the message log that ``log`` prints, as CANopenNode's gateway does. The log
(the last ``LOG_LINES`` events) is kept in both dialects.

Limits [ours]: 127.0.0.1 unless told otherwise; ``max_clients`` connections; lines longer
than the client's command size (``--max-line``, raised per client by ``set command_size`` up
to ``MAX_COMMAND_SIZE``) are answered with 600 and dropped, the connection stays. A slot must
not be held by a client that does nothing, or eight of them lock everyone else out:

* a new connection while every slot is taken ends the idle connection that has been idle
  longest, which sees its last answers and then the end of the connection, as after its
  idle time-out. Idle: no request of it runs or waits to be read, and it does not read its
  answers, or has not finished a request yet, or has sent and been sent nothing for
  ``IDLE_GRACE_S`` (a client between two requests keeps its slot). The new connection waits
  up to ``SLOT_WAIT_S`` for one to become idle, else it is answered ``[0] ERROR:600`` and
  closed (at once when ``max_clients`` others wait already);
* ``idle_timeout``: no byte received for this long while none of its requests runs;
* ``line_timeout``: a line begun but not ended within this long (a client sending one
  byte a second never goes idle, but never finishes a request either), or answers not read
  for this long: a client's requests are not read while more than ``WRITE_HIGH`` bytes of
  its answers wait (back-pressure), so a client that never reads holds little and is
  ended here;
* ``max_output``: the answers and events waiting for all clients together (events do not
  wait for a client to read); over it, the client with the most is ended.

The idle and line time-outs and the budget end a connection without an answer. Memory
then stays bounded: per client ``WRITE_HIGH`` plus one answer, ``READ_CHUNK`` of request
lines and its command size; in all ``max_output`` of output at most; the kernel's socket
buffers are ``SOCKET_BUFFER``. A time-out of 0 turns that time-out off.
``--read-only`` answers 100 to everything that writes to a node or the card (SDO and
PDO writes, NMT, configuration, LSS); reads, ``info version``, ``help``, ``log`` and the
client's own settings (default network and node, command time-out and size) remain.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import functools
import logging
import math
import select
import selectors
import socket
import sys
import termios
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import datetime
from typing import Any, Protocol

from dpm.cia305 import LssAddress
from host_api.cia309.datatypes import LINE_ENDS, Dialect
from host_api.cia309.formatters import (
    format_abort,
    format_empty,
    format_error,
    format_event,
    format_help,
    format_lss_address,
    format_lss_node_id,
    format_lss_number,
    format_ok,
    format_pdo_read,
    format_plain_upload,
    format_upload,
    format_version,
)
from host_api.cia309.framing import DEFAULT_MAX_LINE, LineFramer, OverlongLine
from host_api.cia309.gateway import Gateway, SdoDownloadInFlight, SdoInFlight, SdoUploadInFlight
from host_api.cia309.model import Cia309Error, ErrorCode, Event
from host_api.cia309.parser import parse_request, plain_read_line
from host_api.cia309.requests import (
    ConfigureRpdo,
    ConfigureTpdo,
    DisableGuarding,
    DisableHeartbeat,
    EnableGuarding,
    EnableHeartbeat,
    EnterPreoperational,
    GetVersion,
    Help,
    InitGateway,
    Log,
    LssActivateBitRate,
    LssAssignNodeId,
    LssCompleteConfiguration,
    LssConfigureBitRate,
    LssConfigureNodeId,
    LssFastscan,
    LssIdentifyFastscan,
    LssIdentifyNonConfigured,
    LssIdentifyRemoteSlave,
    LssInquireAddress,
    LssInquireNodeId,
    LssSlowscan,
    LssStore,
    LssSwitchGlobal,
    LssSwitchSelective,
    ParseError,
    ReadPdo,
    Request,
    ResetCommunication,
    ResetNode,
    RestoreConfiguration,
    SdoDownload,
    SdoUpload,
    SetBootUpForwarding,
    SetCommandSize,
    SetCommandTimeout,
    SetDefaultNetwork,
    SetDefaultNode,
    SetHeartbeatProducer,
    SetNodeId,
    SetSdoBlock,
    SetSdoTimeout,
    StartNode,
    StopNode,
    StoreConfiguration,
    WritePdo,
)

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 60000
DEFAULT_MAX_CLIENTS = 8
DEFAULT_IDLE_TIMEOUT = 60.0
"""[ours] seconds a connection may send nothing while it has no request running."""
DEFAULT_LINE_TIMEOUT = 10.0
"""[ours] seconds from the first byte of a request line to its line end."""
DEFAULT_MAX_OUTPUT = 1 << 20
"""[ours] bytes of answers and events that may wait, for all clients together."""
REFUSAL_FLUSH_S = 1.0
"""How long the last answers to a client that is ended (a refusal, an eviction) may take
to leave before the connection is cut anyway."""
LOG_LINES = 1000
READ_CHUNK = 4096
"""[ours] bytes of requests read at once: what a client that pipelines thousands of short
requests holds as lines while it waits for its answers to be read."""
WRITE_HIGH = 64 * 1024
"""[ours] bytes of a client's answers that may wait before its next request is read."""
WRITE_LOW = 16 * 1024
"""Reading its requests again once its waiting answers are down to this."""
IDLE_GRACE_S = 1.0
"""[ours] a client that has had an answer keeps its slot this long after its last byte or
answer, whatever new clients come: a client between two requests is not idle."""
SLOT_WAIT_S = IDLE_GRACE_S + 0.25
"""How long a new client waits for a slot (while every client is busy or in its grace)
before it is refused; at most ``max_clients`` wait."""
SLOT_POLL_S = 0.05
SOCKET_BUFFER = 64 * 1024
"""[ours] SO_SNDBUF and SO_RCVBUF of every connection (the kernel doubles them), instead of
the kernel's autotuning up to megabytes per socket."""

READ_ONLY_REQUESTS = (
    SdoUpload, ReadPdo, GetVersion, Help, Log,
    SetDefaultNetwork, SetDefaultNode, SetCommandTimeout, SetCommandSize,
)
"""What ``--read-only`` still serves: nothing here changes a node or the card."""

SdoRequest = SdoUpload | SdoDownload
SDO_REQUESTS = (SdoUpload, SdoDownload)
"""The requests the server sends from its event loop when the card can take them now
(``Server._answer``, ``Server._fast_line``)."""


LssNumbers = tuple[int, int, int, int]
"""An LSS address as the LSS services take and give it: vendor, product, revision, serial."""


class LssServices(Protocol):
    """The LSS services (309-1 4.8) of one network, as ``host_api.cia309.lss.LssMaster``
    offers them over the gateway's layer-2 access.

    The dispatcher adapts the 309-3 requests to these calls: a False from an identify or
    fastscan service and a None from ``fastscan`` are failures with 103 (no slave answered);
    a ValueError is 101; any other exception whose ``code`` is a 309-3 error number (as
    ``LssError``'s) fails the request with that number.
    """

    def switch_state_global(self, mode: int) -> None: ...

    def switch_state_selective(self, vendor: int, product: int, revision: int,
                               serial: int) -> None: ...

    def configure_node_id(self, node_id: int) -> None: ...

    def configure_bit_timing(self, table: int, index: int) -> None: ...

    def activate_bit_timing(self, switch_delay_ms: int) -> None: ...

    def store_configuration(self) -> None: ...

    def inquire_lss_number(self, lss_sub: int) -> int: ...

    def inquire_node_id(self) -> int: ...

    def identify_remote_slave(self, vendor: int, product: int, revision_low: int,
                              revision_high: int, serial_low: int, serial_high: int) -> bool: ...

    def identify_non_configured_slave(self) -> bool: ...

    def fastscan_step(self, id_number: int, bit_checked: int, lss_sub: int,
                      lss_next: int) -> bool: ...

    def fastscan(self, vendor: int | None = None, product: int | None = None,
                 revision: int | None = None, serial: int | None = None,
                 timeout: float | None = None) -> LssNumbers | None: ...

    def assign_node_id(self, address: LssNumbers, node_id: int) -> None: ...

    def complete_node_id_configuration(self, start_id: int = 2, store: bool = True,
                                       exclude: Iterable[int] = (),
                                       timeout: float | None = None) -> object: ...


LssFactory = Callable[[int], LssServices]
"""The LSS services of a network (by its number)."""

@dataclass(eq=False)
class Client:
    """One 309-3 client: its gateway session, its line framer, its last sequence number,
    and when (event-loop time) its unfinished line began."""

    gateway: Gateway
    framer: LineFramer
    last_sequence: int = 0
    line_started: float | None = None


class EventLog:
    """The last events as text lines (what ``log`` prints), in the dialect's words."""

    def __init__(self, dialect: Dialect, size: int = LOG_LINES) -> None:
        self.dialect = dialect
        self._lines: deque[str] = deque(maxlen=size)

    def add(self, event: Event) -> str | None:
        """Log the event; returns its line, or None when the dialect has none for it."""
        line = format_event(event, self.dialect, stamp=datetime.now())
        if line is not None:
            self._lines.append(line)
        return line

    def take(self) -> str:
        """Every logged line, oldest first, as one answer: lines joined by LF and closed by
        the dialect's line end, as ``help`` is, so ``cocomm`` reads it whole; empty when
        nothing was logged. The log is empty afterwards (CANopenNode)."""
        if not self._lines:
            return ""
        text = "\n".join(line.rstrip("\r\n") for line in self._lines)
        self._lines.clear()
        return text + self.dialect.line_end


@dataclass(frozen=True)
class Answered:
    """A line answered without executing a request (``Dispatcher.prepare``)."""

    text: str | None


class Dispatcher:
    """One request line in, one answer text out (None: no answer), for one client."""

    def __init__(
        self,
        dialect: Dialect = Dialect.CANOPENNODE,
        *,
        read_only: bool = False,
        lss: LssFactory | None = None,
        event_log: EventLog | None = None,
    ) -> None:
        self.dialect = dialect
        self.read_only = read_only
        self.lss = lss
        self.event_log = event_log or EventLog(dialect)

    def handle(self, client: Client, line: str | OverlongLine) -> str | None:
        """The answer to one framed line (blocking: call it from a worker thread). A
        failure of the line or the service is its ``ERROR`` answer; only a defect of the
        gateway itself raises."""
        prepared = self.prepare(client, line)
        if isinstance(prepared, Answered):
            return prepared.text
        return self.execute(client, prepared)

    def prepare(self, client: Client, line: str | OverlongLine) -> Request | Answered:
        """The request a line makes, or its answer when it makes none to execute (a line
        that does not parse, an empty one, one ``--read-only`` refuses); never blocks."""
        dialect = self.dialect
        if isinstance(line, OverlongLine):
            error = line.error()
            sequence = client.last_sequence if error.sequence is None else error.sequence
            return Answered(format_error(sequence, error.error, dialect, detail=str(error)))
        try:
            request = parse_request(line, dialect)
        except ParseError as exc:
            sequence = client.last_sequence if exc.sequence is None else exc.sequence
            return Answered(format_error(sequence, exc.error, dialect, detail=str(exc)))
        if request is None:
            return Answered(format_empty(dialect))
        client.last_sequence = request.sequence
        if self.read_only and not isinstance(request, READ_ONLY_REQUESTS):
            return Answered(format_error(request.sequence, ErrorCode.REQUEST_NOT_SUPPORTED,
                                         dialect))
        return request

    def execute(self, client: Client, request: Request) -> str:
        """The answer to a prepared request (blocking)."""
        try:
            return self._execute(client, request)
        except Cia309Error as exc:
            return self.failure(request, exc)

    def failure(self, request: Request, exc: Cia309Error) -> str:
        """The answer to a request whose service failed: the node's abort or the error."""
        if exc.abort_code is not None:
            return format_abort(request.sequence, exc.abort_code, self.dialect)
        assert exc.error is not None
        return format_error(request.sequence, exc.error, self.dialect)

    def _execute(self, client: Client, request: Request) -> str:
        handler = _SERVICES.get(type(request))
        if handler is not None:
            return handler(self, client, request)
        lss_call = _LSS_SERVICES.get(type(request))
        if lss_call is not None:
            return self._lss(client.gateway, request, lss_call)
        raise Cia309Error(ErrorCode.REQUEST_NOT_SUPPORTED, type(request).__name__)

    def _lss(self, gateway: Gateway, request: Any, call: _LssCall) -> str:
        """309-1 4.8: to the network's LSS services, when there are any (else 100)."""
        if self.lss is None:
            raise Cia309Error(ErrorCode.REQUEST_NOT_SUPPORTED, "no LSS services here")
        lss = self.lss(gateway.resolve_network(request.net))
        try:
            answer = call(lss, request, self.dialect)
        except Cia309Error:
            raise
        except ValueError as exc:
            raise Cia309Error(ErrorCode.SYNTAX_ERROR, str(exc)) from exc
        except Exception as exc:
            code = getattr(exc, "code", None)
            if isinstance(code, int) and code in set(ErrorCode):
                raise Cia309Error(ErrorCode(code), str(exc)) from exc
            raise
        if answer is False:
            raise Cia309Error(ErrorCode.TIME_OUT, "no LSS slave answered")
        if isinstance(answer, str):
            return answer
        return format_ok(request.sequence, self.dialect)


_Service = Callable[[Dispatcher, Client, Any], str]
"""How the dispatcher serves one type of request: its answer text."""


def _ok(call: Callable[[Gateway, Any], object]) -> _Service:
    """A service whose success is ``[seq] OK``."""
    def serve(dispatcher: Dispatcher, client: Client, request: Any) -> str:
        call(client.gateway, request)
        return format_ok(request.sequence, dispatcher.dialect)
    return serve


def _sdo_upload(dispatcher: Dispatcher, client: Client, request: SdoUpload) -> str:
    data = client.gateway.sdo_upload(request.index, request.subindex, network=request.net,
                                     node_id=request.node, data_type=request.dtype)
    return format_upload(request.sequence, request.dtype, data, dispatcher.dialect)


def _set_sdo_block(gateway: Gateway, request: SetSdoBlock) -> None:
    raise Cia309Error(ErrorCode.REQUEST_NOT_SUPPORTED,
                      "the card runs segmented SDO transfers only")


def _read_pdo(dispatcher: Dispatcher, client: Client, request: ReadPdo) -> str:
    values = client.gateway.read_pdo_data(request.number, network=request.net)
    network = client.gateway.resolve_network(request.net)
    return format_pdo_read(request.sequence, network, request.number, values,
                           dispatcher.dialect)


def _set_command_size(dispatcher: Dispatcher, client: Client, request: SetCommandSize) -> str:
    client.gateway.set_command_size(request.size)
    client.framer.max_line = request.size
    return format_ok(request.sequence, dispatcher.dialect)


def _get_version(dispatcher: Dispatcher, client: Client, request: GetVersion) -> str:
    return format_version(request.sequence, client.gateway.get_version(network=request.net),
                          dispatcher.dialect)


def _help(dispatcher: Dispatcher, client: Client, request: Help) -> str:
    return format_help(request.topic, dispatcher.dialect)


def _log(dispatcher: Dispatcher, client: Client, request: Log) -> str:
    return dispatcher.event_log.take() or format_empty(dispatcher.dialect) or ""


_SERVICES: dict[type[Request], _Service] = {
    SdoUpload: _sdo_upload,
    SdoDownload: _ok(lambda g, r: g.sdo_download(r.index, r.subindex, r.data, network=r.net,
                                                  node_id=r.node)),
    StartNode: _ok(lambda g, r: g.start_node(r.node, network=r.net)),
    StopNode: _ok(lambda g, r: g.stop_node(r.node, network=r.net)),
    EnterPreoperational: _ok(lambda g, r: g.set_node_to_preoperational(r.node, network=r.net)),
    ResetNode: _ok(lambda g, r: g.reset_node(r.node, network=r.net)),
    ResetCommunication: _ok(lambda g, r: g.reset_communication(r.node, network=r.net)),
    EnableGuarding: _ok(lambda g, r: g.enable_node_guarding(
        r.guard_time, r.lifetime_factor, network=r.net, node_id=r.node)),
    DisableGuarding: _ok(lambda g, r: g.disable_node_guarding(network=r.net, node_id=r.node)),
    EnableHeartbeat: _ok(lambda g, r: g.start_heartbeat_consumer(
        r.consumer_time, network=r.net, node_id=r.node)),
    DisableHeartbeat: _ok(lambda g, r: g.disable_heartbeat_consumer(network=r.net,
                                                                    node_id=r.node)),
    SetSdoTimeout: _ok(lambda g, r: g.configure_sdo_timeout(r.timeout_ms, network=r.net)),
    SetSdoBlock: _ok(_set_sdo_block),
    ConfigureRpdo: _ok(lambda g, r: g.configure_rpdo(
        r.number, r.cob_id, r.transmission_type, r.mappings, network=r.net)),
    ConfigureTpdo: _ok(lambda g, r: g.configure_tpdo(
        r.number, r.cob_id, r.transmission_type, r.mappings, inhibit_time=r.inhibit_time,
        event_timer=r.event_timer, sync_start_value=r.sync_start, network=r.net)),
    ReadPdo: _read_pdo,
    WritePdo: _ok(lambda g, r: g.write_pdo_data(r.number, r.values, network=r.net)),
    InitGateway: _ok(lambda g, r: g.initialize_gateway(r.bit_rate_index, network=r.net)),
    StoreConfiguration: _ok(lambda g, r: g.store_configuration(r.specifier, network=r.net)),
    RestoreConfiguration: _ok(lambda g, r: g.restore_configuration(r.specifier,
                                                                   network=r.net)),
    SetHeartbeatProducer: _ok(lambda g, r: g.set_heartbeat_producer(r.producer_time,
                                                                    network=r.net)),
    SetNodeId: _ok(lambda g, r: g.set_node_id(r.node_id, network=r.net)),
    SetBootUpForwarding: _ok(lambda g, r: g.set_bootup_forwarding(r.enabled, network=r.net)),
    SetDefaultNode: _ok(lambda g, r: g.set_default_node_id(r.node_id, network=r.net)),
    SetDefaultNetwork: _ok(lambda g, r: g.set_default_network(r.network)),
    SetCommandTimeout: _ok(lambda g, r: g.set_command_timeout(r.timeout_ms)),
    SetCommandSize: _set_command_size,
    GetVersion: _get_version,
    Help: _help,
    Log: _log,
}
"""The 309-1 service (and its answer) of each request the parser makes, but LSS's."""


_LssCall = Callable[[LssServices, Any, Dialect], str | bool | None]
"""One LSS request on a network's LSS services: an answer text, False when no slave
answered (103), or None / True for ``[seq] OK``."""


def _lss_inquire_address(lss: LssServices, request: LssInquireAddress, dialect: Dialect) -> str:
    if request.lss_sub is not None:
        return format_lss_number(request.sequence, lss.inquire_lss_number(request.lss_sub),
                                 dialect)
    numbers = [lss.inquire_lss_number(sub) for sub in range(4)]
    return format_lss_address(request.sequence, LssAddress(*numbers), dialect)


def _lss_identify_remote(lss: LssServices, request: LssIdentifyRemoteSlave,
                         dialect: Dialect) -> bool:
    selection = request.selection
    return lss.identify_remote_slave(
        selection.vendor_id, selection.product_code, selection.revision_low,
        selection.revision_high, selection.serial_low, selection.serial_high)


def _lss_identify_fastscan(lss: LssServices, request: LssIdentifyFastscan,
                           dialect: Dialect) -> str:
    vendor, product, revision, serial = (
        value if mask == 0xFFFF_FFFF else None
        for value, mask in zip(_numbers(request.known), _numbers(request.mask), strict=True))
    timeout = None if request.timeout_ms is None else request.timeout_ms / 1000.0
    found = lss.fastscan(vendor, product, revision, serial, timeout=timeout)
    if found is None:
        raise Cia309Error(ErrorCode.TIME_OUT, "no unconfigured LSS slave answered")
    return format_lss_address(request.sequence, LssAddress(*found), dialect)


def _lss_complete(lss: LssServices, request: LssCompleteConfiguration, dialect: Dialect) -> None:
    if any(criterion.scan != 0 for criterion in request.criteria):
        raise Cia309Error(ErrorCode.REQUEST_NOT_SUPPORTED,
                          "lss_allnodes scans every LSS number")
    timeout = None if request.timeout_ms is None else request.timeout_ms / 1000.0
    lss.complete_node_id_configuration(
        2 if request.first_node_id is None else request.first_node_id,
        True if request.store is None else request.store, timeout=timeout)


def _lss_slowscan(lss: LssServices, request: LssSlowscan, dialect: Dialect) -> None:
    raise Cia309Error(ErrorCode.REQUEST_NOT_SUPPORTED, type(request).__name__)


_LSS_SERVICES: dict[type[Request], _LssCall] = {
    LssSwitchGlobal: lambda lss, r, _: lss.switch_state_global(int(r.configuration)),
    LssSwitchSelective: lambda lss, r, _: lss.switch_state_selective(*_numbers(r.address)),
    LssConfigureNodeId: lambda lss, r, _: lss.configure_node_id(r.node_id),
    LssConfigureBitRate: lambda lss, r, _: lss.configure_bit_timing(r.table_selector,
                                                                    r.table_index),
    LssActivateBitRate: lambda lss, r, _: lss.activate_bit_timing(r.switch_delay_ms),
    LssStore: lambda lss, r, _: lss.store_configuration(),
    LssInquireAddress: _lss_inquire_address,
    LssInquireNodeId: lambda lss, r, dialect: format_lss_node_id(
        r.sequence, lss.inquire_node_id(), dialect),
    LssIdentifyRemoteSlave: _lss_identify_remote,
    LssIdentifyNonConfigured: lambda lss, r, _: lss.identify_non_configured_slave(),
    LssFastscan: lambda lss, r, _: lss.fastscan_step(r.id_number, r.bit_checked, r.lss_sub,
                                                     r.lss_next),
    LssIdentifyFastscan: _lss_identify_fastscan,
    LssSlowscan: _lss_slowscan,
    LssAssignNodeId: lambda lss, r, _: lss.assign_node_id(_numbers(r.address), r.node_id),
    LssCompleteConfiguration: _lss_complete,
}
"""The LSS services (309-1 4.8) of each LSS request."""


def _numbers(address: LssAddress) -> LssNumbers:
    return (address.vendor, address.product, address.revision, address.serial)


@dataclass(frozen=True)
class ServerConfig:
    """What ``cifemu 309 serve`` is told."""

    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    dialect: Dialect = Dialect.CANOPENNODE
    read_only: bool = False
    max_clients: int = DEFAULT_MAX_CLIENTS
    max_line: int = DEFAULT_MAX_LINE
    idle_timeout: float = DEFAULT_IDLE_TIMEOUT
    line_timeout: float = DEFAULT_LINE_TIMEOUT
    max_output: int = DEFAULT_MAX_OUTPUT


class _Protocol(asyncio.StreamReaderProtocol):
    """asyncio's stream protocol, counting the bytes received: a client whose request has
    arrived but has not been read yet is not idle, and must not lose its slot.

    While the server serves the client, ``data_received`` is the server's fast path
    (``Server._fast_line``, bound to the connection by ``functools.partial`` on the
    instance, so the transport calls it with no frame of this class's between): a line it
    answers never reaches the stream, nor the client's task; what it does not take it hands
    to ``stream_received``, this class's ``data_received``."""

    received = 0

    def data_received(self, data: bytes) -> None:
        self.received += len(data)
        super().data_received(data)

    stream_received = data_received


@dataclass(eq=False)
class _Connection:
    """A client's connection as the server keeps it: what slot eviction and the output
    budget look at."""

    client: Client
    writer: asyncio.StreamWriter
    transport: asyncio.WriteTransport
    """The writer's (looked up once: the writer's property is a Python call on every
    read's path)."""
    protocol: _Protocol
    last_active: float
    """Event-loop time of its last byte received or its last answer written."""
    consumed: int = 0
    """Bytes taken from the stream so far (``protocol.received`` minus this are waiting)."""
    serving: bool = False
    """One of its requests runs."""
    draining: bool = False
    """Its requests wait until it reads its answers."""
    answered: bool = False
    """It has had an answer."""
    reading: bool = False
    """Its task waits for its next bytes, every line before them served."""
    fast: SdoRequest | None = None
    """An SDO request of it that the fast path sent and has not answered yet."""
    fast_flight: SdoInFlight | None = None
    """``fast``'s flight."""
    fast_deadline: float = 0.0
    """When (event-loop time) ``fast`` is given up. These three are the connection's, not an
    object's made per request: a Python call less on every read's path."""
    settled: asyncio.Future[None] | None = None
    """What its task waits on until ``fast`` is answered, made when it has to wait."""
    fast_timer: asyncio.TimerHandle | None = None
    """Gives up ``fast`` at its deadline: one timer for the reads that follow, moved on
    when it runs (``Server._fast_due``), not one scheduled and cancelled per read."""
    fast_timer_due: float = 0.0
    """When ``fast_timer`` runs (its ``when()``, a Python call on every read's path)."""

    def waiting_input(self) -> bool:
        """Bytes of it have arrived that the server has not read: in the stream, or still
        in the kernel (a new connection's first request before its first read)."""
        if self.protocol.received > self.consumed:
            return True
        sock = self.writer.get_extra_info("socket")
        if sock is None:
            return False
        try:
            queued = fcntl.ioctl(sock.fileno(), termios.FIONREAD, bytes(4))
        except OSError:
            return False
        return int.from_bytes(queued, sys.byteorder) > 0

    def idle(self, now: float) -> bool:
        """May lose its slot to a new client: nothing of it runs or waits to be read, and
        it does not read its answers, or it has not finished a request yet, or nothing came
        from it or went to it for IDLE_GRACE_S (a client between two requests keeps its
        slot)."""
        if self.serving:
            return False
        if self.draining:
            return True
        if self.waiting_input():
            return False
        return not self.answered or now - self.last_active >= IDLE_GRACE_S


class Server:
    """The asyncio TCP server; ``start`` binds, ``serve_forever`` runs, ``close`` ends.

    ``start`` raises OSError when the address cannot be bound (port in use, no such
    address); nothing a client sends raises: each failure is a 309-3 answer or a drop.
    """

    def __init__(self, gateway: Gateway, config: ServerConfig,
                 lss: LssFactory | None = None) -> None:
        self.gateway = gateway
        self.config = config
        self.dispatcher = Dispatcher(config.dialect, read_only=config.read_only, lss=lss)
        self._format_plain_upload = functools.partial(
            format_plain_upload, config.dialect is Dialect.LELY, LINE_ENDS[config.dialect])
        """``format_upload`` of an integer or hex value in C, else None (``_sdo_answer``)."""
        self._connections: list[_Connection] = []
        self._ending: set[asyncio.WriteTransport] = set()
        """Connections ended after their last answers, until those have left."""
        self._newcomers = 0
        """New connections waiting for a slot."""
        self._executor = ThreadPoolExecutor(max_workers=config.max_clients,
                                            thread_name_prefix="cia309-client")
        self._server: asyncio.Server | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread = 0
        """The thread the loop runs on (``start``'s)."""
        self._subscription = gateway.subscribe(self._on_event)
        self._deferred: list[tuple[_Connection, bytes]] = []
        """Fast answers written just before the loop's next wait (``_write_deferred``)."""
        self._before_wait: Callable[[Callable[[], None]], None] | None = None
        """``WakeClockLoop.before_wait`` of the loop the server runs on; None on another."""
        self._read_back: Callable[[], None] = _nothing
        """Gives the mailboxes back to the gateway's reader threads (``Gateway.read_on``)."""

    @property
    def port(self) -> int:
        """The bound port (useful after binding port 0)."""
        assert self._server is not None and self._server.sockets
        return int(self._server.sockets[0].getsockname()[1])

    async def start(self) -> None:
        loop = self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        if isinstance(loop, WakeClockLoop):
            self._before_wait = loop.before_wait

        def protocol() -> _Protocol:
            return _Protocol(asyncio.StreamReader(limit=READ_CHUNK, loop=loop),
                             self._serve_client, loop=loop)

        self._server = await loop.create_server(protocol, self.config.host, self.config.port)
        self._read_back = self.gateway.read_on(loop)
        for sock in self._server.sockets:  # accepted connections inherit them
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER)
        log.info("CiA 309-3 gateway (%s) on %s:%d", self.config.dialect.value,
                 self.config.host, self.port)

    async def serve_forever(self) -> None:
        assert self._server is not None
        await self._server.serve_forever()

    async def close(self) -> None:
        self._subscription.cancel()
        for connection in self._connections:
            flight = connection.fast_flight
            if connection.fast is not None and flight is not None:
                connection.fast = None
                flight.abandon()
        self._read_back()
        if self._server is not None:
            self._server.close()
        for connection in list(self._connections):
            connection.transport.abort()
        for transport in list(self._ending):
            transport.abort()
        if self._server is not None:
            await self._server.wait_closed()
        self._executor.shutdown(wait=False, cancel_futures=True)

    def _on_event(self, event: Event) -> None:
        """From the gateway's dispatcher thread: over to the event loop."""
        if self._loop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._broadcast, event)

    def _broadcast(self, event: Event) -> None:
        line = self.dispatcher.event_log.add(event)
        if line is None or self.config.dialect is not Dialect.LELY:
            return
        data = line.encode("latin-1")
        for connection in list(self._connections):
            self._write(connection, data)

    def _write(self, connection: _Connection, data: bytes) -> None:
        """Queue ``data`` for the client; then, while the output waiting for all clients
        (ended ones whose last answers still leave included) is over ``max_output``, cut the
        connection with the most (``abort``: ``close`` would keep its queue until it reads).
        Fast answers held for the loop's wait go first, so a client's lines keep their
        order."""
        if self._deferred:
            self._write_deferred()
        transport = connection.transport
        if transport.is_closing():
            return
        transport.write(data)
        if not transport.get_write_buffer_size():
            return  # all sent at once: the output waiting did not grow, nothing to count
        while (total := self._output()) > self.config.max_output:
            largest = max((other.transport for other in self._connections),
                          key=_waiting, default=None)
            ending = max(self._ending, key=_waiting, default=None)
            if largest is None or (ending is not None and _waiting(ending) > _waiting(largest)):
                assert ending is not None
                self._ending.discard(ending)
                ending.abort()
                continue
            owner = next(other for other in self._connections
                         if other.transport is largest)
            self._end(owner, f"{_waiting(largest)} bytes of output it does not read "
                             f"({total} for all clients)", flush=False)

    def _output(self) -> int:
        """Bytes of output waiting, for all clients together."""
        return (sum(_waiting(other.transport) for other in self._connections)
                + sum(_waiting(transport) for transport in self._ending))

    def _end(self, connection: _Connection, why: str, *, flush: bool) -> None:
        """Free the client's slot now and end its connection: after its waiting output
        (``flush``, for at most REFUSAL_FLUSH_S) or at once."""
        if self._deferred:
            self._write_deferred()  # its last answers before the end
        with contextlib.suppress(ValueError):
            self._connections.remove(connection)
        log.info("dropping %s: %s", _peer(connection.writer), why)
        transport = connection.transport
        if not flush:
            transport.abort()
            return
        transport.close()
        self._ending.add(transport)

        def cut() -> None:
            self._ending.discard(transport)
            transport.abort()

        asyncio.get_running_loop().call_later(REFUSAL_FLUSH_S, cut)

    def _take_slot(self) -> bool:
        """Make room for a new client when every slot is taken, by ending the idle client
        idle longest; False when none is idle."""
        if len(self._connections) < self.config.max_clients:
            return True
        now = asyncio.get_running_loop().time()
        idle = [connection for connection in self._connections if connection.idle(now)]
        if not idle:
            return False
        longest = min(idle, key=lambda connection: connection.last_active)
        self._end(longest, f"idle longest ({now - longest.last_active:.1f} s) when a new "
                           "client came", flush=not longest.draining)
        return True

    async def _wait_for_slot(self) -> bool:
        """A slot for a new client, within SLOT_WAIT_S (a client idle for less than
        IDLE_GRACE_S may become idle enough); False when none came or too many wait."""
        if self._take_slot():
            return True
        if self._newcomers >= self.config.max_clients:
            return False
        self._newcomers += 1
        try:
            deadline = asyncio.get_running_loop().time() + SLOT_WAIT_S
            while asyncio.get_running_loop().time() < deadline:
                await asyncio.sleep(SLOT_POLL_S)
                if self._take_slot():
                    return True
            return False
        finally:
            self._newcomers -= 1

    def _read_timeout(self, connection: _Connection, now: float) -> float | None:
        """How long the next read may wait: what is left of the line-assembly time while a
        line is unfinished, else of the idle time-out since its last byte or answer (None:
        no limit); the whole idle time-out while the fast path serves it (it is not idle,
        and is looked at again then)."""
        config = self.config
        client = connection.client
        if client.framer.partial and config.line_timeout > 0:
            assert client.line_started is not None
            return max(0.0, client.line_started + config.line_timeout - now)
        if config.idle_timeout <= 0:
            return None
        if connection.fast is not None:
            return config.idle_timeout
        return max(0.0, connection.last_active + config.idle_timeout - now)

    def _active(self, connection: _Connection, now: float) -> bool:
        """Its read timed out, but bytes of it arrived that its task has not read yet, or
        the fast path served it meanwhile (or serves it now): the idle time runs from its
        last byte or answer, which its task did not see.

        Bytes waiting first: a loop turn that finds the client's bytes and the read's due
        time-out together (a turn that comes late, behind a busy client) delivers the bytes
        to the stream and the time-out to the task, which then never reads them; that
        ended a client whose request had arrived as idle (the early drops of
        tests/test_cia309_limits.py). Its task reads them now, and looks at the line
        time-out again after them."""
        if connection.protocol.received > connection.consumed:
            return True
        if connection.client.framer.partial:
            return False
        return (connection.fast is not None
                or now - connection.last_active < self.config.idle_timeout)

    async def _drain(self, connection: _Connection) -> bool:
        """Back-pressure: while more than WRITE_HIGH bytes of answers wait, wait for the
        client to read them down to WRITE_LOW, for at most the line time-out (else the idle
        time-out); False when it did not."""
        config = self.config
        if _waiting(connection.transport) <= WRITE_HIGH:
            return True
        timeout = config.line_timeout or config.idle_timeout or None
        connection.draining = True
        try:
            await asyncio.wait_for(connection.writer.drain(), timeout)
        except TimeoutError:
            return False
        finally:
            connection.draining = False
        return True

    async def _serve_client(self, reader: asyncio.StreamReader,
                            writer: asyncio.StreamWriter) -> None:
        if not await self._wait_for_slot():
            writer.write(format_error(0, ErrorCode.OUT_OF_MEMORY,
                                      self.config.dialect).encode("latin-1"))
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(_close(writer), REFUSAL_FLUSH_S)
            writer.transport.abort()
            return
        loop = asyncio.get_running_loop()
        protocol = writer.transport.get_protocol()
        assert isinstance(protocol, _Protocol)
        writer.transport.set_write_buffer_limits(WRITE_HIGH, WRITE_LOW)
        if hasattr(writer.transport, "max_size"):
            # asyncio's selector transport receives into a new bytes object of max_size
            # (256 KiB) for every read: above glibc's mmap threshold, that was an mmap, an
            # mremap and a munmap per request line (system calls, each a ptrace round trip
            # under User-Mode Linux). READ_CHUNK is what the task reads at once anyway.
            writer.transport.max_size = READ_CHUNK
        client = Client(self.gateway.session(), LineFramer(self.config.max_line))
        connection = _Connection(client, writer, writer.transport, protocol, loop.time())
        self._connections.append(connection)
        protocol.data_received = functools.partial(  # type: ignore[method-assign]
            self._fast_line, connection)
        try:
            while connection in self._connections:
                connection.reading = True
                try:  # asyncio.timeout, not wait_for: no task of its own for every read
                    async with asyncio.timeout(self._read_timeout(connection, loop.time())):
                        data = await reader.read(READ_CHUNK)
                except TimeoutError:
                    if self._active(connection, loop.time()):
                        continue
                    what = "line unfinished" if client.framer.partial else "idle"
                    self._end(connection, f"{what} for too long", flush=False)
                    break
                finally:
                    connection.reading = False
                await self._settled(connection)
                if not data:
                    break
                connection.consumed += len(data)
                connection.last_active = loop.time()
                lines = client.framer.feed(data)
                for line in lines:
                    if connection not in self._connections:
                        break  # ended while its answers waited to be read
                    connection.serving = True
                    try:
                        answer = await self._answer(client, line)
                    finally:
                        connection.serving = False
                    connection.last_active = _fresh_time(loop)
                    connection.answered = True
                    if writer.is_closing():
                        break
                    if answer:
                        self._write(connection, answer.encode("latin-1"))
                    if not await self._drain(connection):
                        self._end(connection, "does not read its answers", flush=False)
                        break
                # A line's time runs from its first byte, or from when the server is done
                # with the lines before it: time spent serving a batch is not the client's.
                if not client.framer.partial:
                    client.line_started = None
                elif lines or client.line_started is None:
                    client.line_started = loop.time()
        except ConnectionError:
            log.debug("a client went away")
        finally:
            with contextlib.suppress(AttributeError):
                del protocol.data_received  # the class's again
            with contextlib.suppress(ValueError):
                self._connections.remove(connection)
            if not writer.transport.is_closing():
                writer.transport.abort()

    async def _answer(self, client: Client, line: str | OverlongLine) -> str | None:
        """The answer to one line: an SDO upload or expedited download from the event loop
        itself, when the card can take it now (``_send_sdo``); every other request in a
        worker thread, as the gateway's calls block.

        Why those apart: they are the requests a 309-3 client repeats most, and a worker
        thread costs each two thread switches (to the worker, back to the event loop), each
        of which waits for the interpreter lock. The server reads the mailbox on this loop
        (``Gateway.read_on``), so the card's ring wakes the loop, which resolves the answer
        at once; a gateway read by another loop's or its own thread wakes this loop
        (``Gateway.try_sdo_upload``)."""
        dispatcher = self.dispatcher
        prepared = dispatcher.prepare(client, line)
        if isinstance(prepared, Answered):
            return prepared.text
        loop = self._loop
        assert loop is not None
        if isinstance(prepared, SDO_REQUESTS):
            answered: asyncio.Future[None] = loop.create_future()
            try:
                flight = _send_sdo(client.gateway, prepared,
                                   functools.partial(self._on_loop, _resolve, answered))
            except Cia309Error as exc:
                return dispatcher.failure(prepared, exc)
            if flight is not None:
                # A timer of its own, not asyncio.timeout: no Timeout object and no
                # rescheduling per read for the one wait that nearly never runs out.
                timer = loop.call_later(flight.timeout, _time_out, answered)
                try:
                    await answered
                except TimeoutError:
                    return dispatcher.failure(prepared, flight.abandon())
                except BaseException:  # cancelled: the server closes
                    flight.abandon()
                    raise
                finally:
                    timer.cancel()
                return self._sdo_answer(prepared, flight)
        return await loop.run_in_executor(self._executor, dispatcher.execute, client, prepared)

    def _on_loop(self, action: Callable[..., None], *args: Any) -> None:
        """A flight's ``on_done``, bound to ``action`` and its arguments by
        ``functools.partial`` (made per read without a Python call): runs ``action(*args)``
        on this server's event loop, at once when the mailbox is read there
        (``Gateway.read_on``), else handed to the loop by the thread that read it."""
        if threading.get_ident() == self._loop_thread:
            action(*args)
            return
        assert self._loop is not None
        with contextlib.suppress(RuntimeError):  # the loop closed: nobody waits
            self._loop.call_soon_threadsafe(action, *args)

    def _sdo_answer(self, request: SdoRequest, flight: SdoInFlight) -> str:
        """The answer line to a finished SDO request: an upload's value or a download's
        ``OK`` (the texts the blocking services give, ``_SERVICES``), or the error it ended
        in."""
        dialect = self.dispatcher.dialect
        try:
            if isinstance(flight, SdoUploadInFlight):
                data = flight.result()
                return (self._format_plain_upload(request.sequence, request.dtype, data)
                        or format_upload(request.sequence, request.dtype, data, dialect))
            assert isinstance(flight, SdoDownloadInFlight)
            flight.result()
            return format_ok(request.sequence, dialect)
        except Cia309Error as exc:
            return self.dispatcher.failure(request, exc)

    # --- the fast path: a line answered without its client's task --------------------------

    def _fast_line(self, connection: _Connection, data: bytes) -> None:
        """The client's protocol's ``data_received`` while it is served: answer ``data`` as
        it arrives, when it is one whole line that needs no thread: an SDO upload or
        expedited download the card takes now (``_send_sdo``), answered from the mailbox's
        reader when the card answers, or a line answered without a request (an empty one,
        one that does not parse, a write ``--read-only`` refuses). Otherwise, with nothing
        taken, to the stream (``_Protocol.stream_received``): the client's task reads it
        as before.

        Only while the task waits for bytes with every earlier line answered and nothing of
        the client's output waiting, so the answers keep their order and back-pressure
        stays the task's. Why: a client that waits for each answer (cocomm, the
        benchmarks) cost the task two wake-ups per read (the bytes, then the answer), each
        an extra turn of the event loop, a poll and asyncio's timers and futures around the
        read; under User-Mode Linux each system call is a ptrace round trip of the host
        (docs/benchmarks.md, issue 22).

        A plain read (``plain_read_line``) is parsed in C and sent to the gateway's upload
        at once: the framer's, the dispatcher's and the parser's five Python calls per read
        (issue 22); every other line takes ``prepare``."""
        if (not connection.reading or connection.fast is not None
                or connection.protocol.received != connection.consumed
                or connection.transport.get_write_buffer_size()):
            connection.protocol.stream_received(data)
            return
        client = connection.client
        framer = client.framer
        dispatcher = self.dispatcher
        upload = plain_read_line(data, framer.max_line) if framer.between_lines else None
        flight: SdoInFlight | None
        try:
            if upload is not None:
                client.last_sequence = upload.sequence  # as ``prepare``
                prepared: SdoRequest = upload
                flight = client.gateway.try_sdo_upload(
                    upload.index, upload.subindex,
                    functools.partial(self._fast_done, connection, upload),
                    network=upload.net, node_id=upload.node)
            else:
                line = framer.whole_line(data)
                if line is None:
                    connection.protocol.stream_received(data)
                    return
                request = dispatcher.prepare(client, line)  # again by the task if not taken
                if isinstance(request, Answered):
                    self._fast_answer(connection, request.text)
                    return
                if not isinstance(request, SDO_REQUESTS):
                    connection.protocol.stream_received(data)
                    return
                prepared = request
                flight = _send_sdo(client.gateway, prepared,
                                   functools.partial(self._fast_done, connection, prepared))
        except Cia309Error as exc:
            self._fast_answer(connection, dispatcher.failure(prepared, exc))
            return
        if flight is None:  # it would wait: the task's worker thread makes the call
            connection.protocol.stream_received(data)
            return
        loop = self._loop
        assert loop is not None
        connection.fast = prepared
        connection.fast_flight = flight
        connection.last_active = now = loop.time()
        connection.fast_deadline = deadline = now + flight.timeout
        connection.serving = True
        timer = connection.fast_timer
        if timer is None or connection.fast_timer_due > deadline:  # a time-out made shorter
            if timer is not None:
                timer.cancel()
            connection.fast_timer = loop.call_at(deadline, self._fast_due, connection)
            connection.fast_timer_due = deadline

    def _fast_done(self, connection: _Connection, request: SdoRequest) -> None:
        """A fast request's flight's ``on_done``: its answer written, on this server's loop
        (``_on_loop`` when another thread read the mailbox: one Python call less per read
        when the loop read it, ``Gateway.read_on``)."""
        if threading.get_ident() != self._loop_thread:
            self._on_loop(self._fast_done, connection, request)
            return
        if connection.fast is not request:
            return  # given up (time-out, the server closing)
        flight = connection.fast_flight
        assert flight is not None
        self._fast_answer(connection, self._sdo_answer(request, flight))

    def _fast_due(self, connection: _Connection) -> None:
        """The fast path's timer: gives up the request out now when its time has run out,
        else waits on for the one out then; ends when none is out. Under User-Mode Linux
        each clock read is a system call, and a timer per read took one more."""
        loop = self._loop
        assert loop is not None
        connection.fast_timer = None
        request = connection.fast
        if request is None:
            return
        if loop.time() < connection.fast_deadline:
            connection.fast_timer_due = connection.fast_deadline
            connection.fast_timer = loop.call_at(connection.fast_deadline, self._fast_due,
                                                 connection)
            return
        flight = connection.fast_flight
        assert flight is not None
        self._fast_answer(connection, self.dispatcher.failure(request, flight.abandon()))

    def _fast_answer(self, connection: _Connection, text: str | None) -> None:
        """A fast line's answer: written, and the task let go on when it waits for it."""
        assert self._loop is not None
        connection.fast = None
        connection.serving = False
        connection.last_active = self._loop.time()
        connection.answered = True
        if text:
            before_wait = self._before_wait
            if before_wait is None:
                self._write(connection, text.encode("latin-1"))
            else:  # written just before the loop's wait (``_write_deferred``)
                if not self._deferred:
                    before_wait(self._write_deferred)
                self._deferred.append((connection, text.encode("latin-1")))
        settled, connection.settled = connection.settled, None
        if settled is not None and not settled.done():
            settled.set_result(None)

    def _write_deferred(self) -> None:
        """The fast answers of the loop's turn, written when it ends, just before the loop's
        wait (``_fast_answer``; at once on a loop that is not a ``WakeClockLoop``); another
        write in the turn writes them first (``_write``).

        Why: an answer wakes its client, which then waits for what the loop still does in
        that turn: a client in the same process (the benchmark's, an embedding
        application's) for the interpreter lock, which the loop gives up only in its wait
        (the benchmark's client slept 1.03-1.77 times per read, 1.00-1.06 with the answer
        written last; issue 22); under User-Mode Linux (one CPU) for the CPU, where the
        woken client may preempt the loop. The rest of the turn (the mailbox's and the
        state flags' looks, asyncio's return to its wait) is a few Python calls; the
        answers of one turn leave in the order they were made."""
        deferred, self._deferred = self._deferred, []
        for connection, data in deferred:
            self._write(connection, data)

    async def _settled(self, connection: _Connection) -> None:
        """Until the fast path's request of this client is answered (its task read more)."""
        if connection.fast is None:
            return
        assert self._loop is not None
        if connection.settled is None:
            connection.settled = self._loop.create_future()
        await connection.settled


class _WakeSelector(selectors.EpollSelector):
    """Linux's selector, reading the clock once on each return from its wait
    (``wake_time``, ``WakeClockLoop``'s time), and calling ``before_wait`` before it.

    Its ``select`` is ``EpollSelector.select`` written out (CPython 3.11-3.13: its epoll
    object ``_selector`` and its map ``_fd_to_key``), not called: the base's ``select`` and
    its ``_key_from_fd`` per ready file were two of the loop's Python calls per turn, four
    per 309-3 read (issue 22)."""

    def __init__(self) -> None:
        super().__init__()
        self.wake_time = time.monotonic()
        self.before_wait: list[Callable[[], None]] = []

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        callbacks = self.before_wait
        if callbacks:
            called = callbacks[:]
            callbacks.clear()
            for callback in called:
                try:
                    callback()
                except Exception:  # the loop's wait must go on, as asyncio's callbacks do
                    log.exception("a callback before the event loop's wait failed")
        if timeout is None:
            timeout = -1
        elif timeout <= 0:
            timeout = 0
        else:  # epoll has a resolution of 1 ms: round up, to wait at least ``timeout``
            timeout = math.ceil(timeout * 1e3) * 1e-3
        keys = self._fd_to_key  # type: ignore[attr-defined]
        ready = []
        try:
            events = self._selector.poll(timeout, max(len(keys), 1))  # type: ignore[attr-defined]
        except InterruptedError:
            events = []
        self.wake_time = time.monotonic()
        for fd, event in events:
            key = keys.get(fd)
            if key is not None:
                mask = ((selectors.EVENT_WRITE if event & ~select.EPOLLIN else 0)
                        | (selectors.EVENT_READ if event & ~select.EPOLLOUT else 0))
                ready.append((key, mask & key.events))
        return ready


class WakeClockLoop(asyncio.SelectorEventLoop):
    """An event loop that reads the clock once per wake-up: ``time`` is the clock's reading
    on the last return from the selector's wait.

    Why: asyncio reads the clock before each wait (the time-out to the next timer) and
    after it (which timers are due), and the server once per request and once per
    answer, six readings per 309-3 read. Under User-Mode Linux each is a system call (no
    vDSO), a ptrace round trip of the host (issue 22). Here the reading after the wait
    serves the callbacks that run on that wake-up and the time-out of the next wait: a
    timer set by a callback counts from the wake-up (early by what ran before it in that
    turn), and the next wait is long by what the turn's callbacks ran. Both are short: the
    loop's callbacks do not block (the gateway's blocking calls run in worker threads), and
    a callback that loops over many lines (a client's task with pipelined requests) reads
    the clock anew for each (``fresh_time``), so no timer is set from a reading older than
    one line. asyncio asks for the time after every wait, so reading it there, not when
    first asked, reads it no more often.

    ``time`` is the selector's attribute read by C (``functools.partial`` of ``getattr``),
    not a method: asyncio asks it twice per turn and the server twice per read, six Python
    frames per 309-3 read on the loop's thread, where each Python call costs 1-2 us of
    the thread's CPU (issue 22, docs/benchmarks.md)."""

    def __init__(self) -> None:
        selector = _WakeSelector()
        super().__init__(selector)
        self._wake_selector = selector
        self.before_wait: Callable[[Callable[[], None]], None] = selector.before_wait.append
        """Call a callback once, at the end of this turn: just before the loop's next wait,
        after every callback ready now (``Server._write_deferred``); a C call."""
        self.time = functools.partial(getattr, selector, "wake_time")  # type: ignore[method-assign]

    def fresh_time(self) -> float:
        """The clock read now; ``time`` returns this reading until the next wake-up."""
        selector = self._wake_selector
        selector.wake_time = now = time.monotonic()
        return now


def _fresh_time(loop: asyncio.AbstractEventLoop) -> float:
    """The loop's time read now: on a ``WakeClockLoop`` not the reading of its wake-up."""
    return loop.fresh_time() if isinstance(loop, WakeClockLoop) else loop.time()


def new_event_loop() -> asyncio.AbstractEventLoop:
    """The event loop a server runs on (``WakeClockLoop``), for ``asyncio.Runner``."""
    return WakeClockLoop()


def _nothing() -> None:
    pass


def _send_sdo(gateway: Gateway, request: SdoRequest, on_done: Callable[[], None]
              ) -> SdoInFlight | None:
    """The request sent without waiting (``Gateway.try_sdo_upload``, ``try_sdo_download``),
    ``on_done`` called once the card answered; None when it would wait (or is a download
    longer than one message): a worker thread then makes the blocking call."""
    if isinstance(request, SdoUpload):
        return gateway.try_sdo_upload(request.index, request.subindex, on_done,
                                      network=request.net, node_id=request.node)
    return gateway.try_sdo_download(request.index, request.subindex, request.data, on_done,
                                    network=request.net, node_id=request.node)


def _resolve(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)


def _time_out(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_exception(TimeoutError())


def _waiting(transport: asyncio.WriteTransport) -> int:
    """Bytes of output waiting for the client to read them."""
    return transport.get_write_buffer_size()


async def _close(writer: asyncio.StreamWriter) -> None:
    writer.close()
    with contextlib.suppress(ConnectionError):
        await writer.wait_closed()


def _peer(writer: asyncio.StreamWriter) -> str:
    peer = writer.get_extra_info("peername")
    return f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else "a client"


class BackgroundServer:
    """A server on an event-loop thread of its own, for a program that is not asyncio
    (an embedding application, the tests, the benchmark); ``close`` ends it. Raises
    OSError as ``Server.start`` does."""

    def __init__(self, gateway: Gateway, config: ServerConfig,
                 lss: LssFactory | None = None) -> None:
        self._loop = new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True,
                                        name="cia309-server")
        self._thread.start()
        self.server = Server(gateway, config, lss)
        asyncio.run_coroutine_threadsafe(self.server.start(), self._loop).result()
        self.port = self.server.port

    def close(self) -> None:
        asyncio.run_coroutine_threadsafe(self.server.close(), self._loop).result()
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join()
        self._loop.close()


async def serve(gateway: Gateway, config: ServerConfig, lss: LssFactory | None = None,
                ready: Callable[[Server], None] | None = None) -> None:
    """Run a server until cancelled; ``ready`` is called once it listens."""
    server = Server(gateway, config, lss)
    await server.start()
    if ready is not None:
        ready(server)
    try:
        await server.serve_forever()
    finally:
        await server.close()
