"""The pytest plugin ``cifemu``: the emulated card as a fixture in a user's own test suite.

Installed with the package (the ``pytest11`` entry point ``cifemu``), so a suite that has
cifemu installed gets, without a conftest:

- the fixture ``cif_card``: a firmware process of its own, on an image directory of its
  own (a short temporary directory, since the card's sockets live there; its log and
  flash are in the test's ``tmp_path``: tests never share a card, also under xdist), with the
  simulated network of the test's ``cif_network`` marker, which the card configures
  itself from on line (``--simulate --configure``) unless the marker leaves that to the
  program under test. ``$CIF_DPM_DIR`` points at that directory for the test,
  so ``host_api.driver.DevOpenDriver()``, libcif programs and ``cifemu legacy`` find it
  without being told. The fixture yields a ``CifCard``;
- the marker ``cif_network(path_or_dict, board=0, configure=True)``;
- a recording of each test's card (``cifemu record``'s, attached at each start): for a
  failed test its transcript is a report section, for a passed one it is removed unless
  the marker ``cif_record(path=None)`` keeps it;
- for a failed test, report sections with the card's side of it: the firmware's log,
  a final ``cifemu status --json`` snapshot and the transcript of what the hosts did
  and saw (``dpm.transcript``, as ``cifemu replay`` compares it).

Why a process and not a thread in the test's own process: the host program under test
must meet the card as it would meet the real one, through the image and the doorbell
from outside, and a card that hangs or dies must not take the test process with it.
docs/pytest-plugin.md is the user's guide.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Generator, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from dbm_tools.network import Network, NetworkError, load_network
from dpm import flags as fl
from dpm import session as s
from dpm.faults import ActiveFault
from dpm.image import MAX_DEV_BOARDS, image_path
from dpm.layout import HOST_FLAGS, TASK2_STATE
from dpm.record_socket import Attachment, RecordingError, attach
from dpm.task2 import TASK_AREA_SIZE, ComDiagnostics
from dpm.transcript import transcript as transcript_of
from host_api import faults
from host_api.ready import StartError, wait_ready
from host_api.status import health, read_image, snapshot

NETWORK_MARKER = "cif_network"
RECORD_MARKER = "cif_record"
START_TIMEOUT_S = 60.0
"""Seconds a starting card may go without CPU time before its start counts as stuck
(``host_api.ready.wait_ready``, which also fails a start that spends ``START_CPU_S`` of
CPU there without READY). How long a start takes on a loaded machine is not bounded: the
wait follows the firmware's CPU time and ends as soon as READY shows."""
OPERATING_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 30.0
"""SIGTERM stops a card cleanly in milliseconds; after this the process group is killed."""
POLL_S = 0.01
LOG_TAIL_LINES = 200
"""The firmware log lines a failure report shows; the whole log stays in its file."""
TRANSCRIPT_LINES = 200
"""The transcript lines a failure report shows; the whole session stays in its directory."""


class CardError(RuntimeError):
    """The card did not do what the test asked of it (start, reach data exchange);
    the message says what it showed instead, with the end of the firmware's log."""


@dataclass
class CifCard:
    """One emulated card a test runs its host program against.

    ``board`` and ``directory`` (the image directory, also ``$CIF_DPM_DIR`` during the
    test) are what a host program needs; ``network`` is the description the card
    simulates (None: a card out of the box, no nodes, not configured), and configures
    itself from on line at each start when ``configure`` is true; ``log`` is the
    firmware's stdout and stderr. ``record_into`` (None: no recording) is where each
    start's recording goes: that directory, then ``<name>-2``, ``<name>-3`` ... after
    restarts; ``sessions`` lists them.
    """

    board: int
    directory: Path
    flash: Path
    log: Path
    network: Network | None = field(default=None, repr=False)
    configure: bool = True
    record_into: Path | None = None
    sessions: list[Path] = field(default_factory=list)
    recording_problem: str | None = None
    """Why a recording ended early (the card died under it), None when none did."""
    _process: subprocess.Popen[bytes] | None = field(default=None, repr=False)
    _attachment: Attachment | None = field(default=None, repr=False)

    @property
    def image(self) -> Path:
        return image_path(self.directory, self.board)

    @property
    def pid(self) -> int:
        """The firmware's pid (the last one, once stopped)."""
        if self._process is None:
            raise CardError(f"board {self.board} was never started")
        return self._process.pid

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def start(self, timeout: float = START_TIMEOUT_S) -> None:
        """Start the firmware and return once it is READY (not yet configured: see
        ``wait_until_operating``). Its own session, so that ``stop`` ends everything it
        started; its log is appended to, so a restart keeps the earlier run's lines."""
        if self.running:
            raise CardError(f"board {self.board} runs already (pid {self.pid})")
        self.directory.mkdir(parents=True, exist_ok=True)
        command = [sys.executable, "-m", "cifemu", "firmware", "--board", str(self.board),
                   "--dpm-dir", str(self.directory), "--flash", str(self.flash),
                   "--log-level", "INFO"]
        if self.network is not None:
            assert self.network.path is not None
            command += ["--simulate", str(self.network.path)]
            if self.configure:
                command.append("--configure")
        with self.log.open("ab") as log:
            self._process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=log,
                                             stderr=log, start_new_session=True)
        try:
            wait_ready(self._process, self.directory, self.board, timeout)
            if self.record_into is not None:
                self._record()
        except (StartError, CardError) as exc:
            self.stop()
            raise CardError(f"board {self.board}: {exc}\n{self.log_tail()}") from None

    def _record(self) -> None:
        """Attach a recording to the card that just started, into the next session."""
        assert self.record_into is not None
        into = self.record_into
        if self.sessions:
            into = into.with_name(f"{into.name}-{len(self.sessions) + 1}")
        try:
            self._attachment = attach(self.image, self.board, into)
        except RecordingError as exc:
            raise CardError(f"cannot record it: {exc}") from None
        self.sessions.append(into)

    def stop_recording(self) -> None:
        """End the running recording, if one runs: its session is then complete. The card
        records again after its next start."""
        attachment, self._attachment = self._attachment, None
        if attachment is None:
            return
        try:
            summary = attachment.detach()
        except RecordingError as exc:
            self.recording_problem = str(exc)
            return
        if not summary.complete:
            self.recording_problem = (f"the card's session writer failed: {attachment.session}"
                                      " ends early (see the firmware log)")

    def records(self) -> list[s.Record]:
        """Every event recorded of this card during the test, its sessions in order
        (docs/recording.md). Ends the running recording first."""
        self.stop_recording()
        records: list[s.Record] = []
        for session in self.sessions:
            records += s.decode_events((session / s.EVENTS).read_text(encoding="ascii"))
        return records

    def transcript(self) -> list[str]:
        """The recorded sessions as ``cifemu replay`` compares them: one decoded line per
        step (``dpm.transcript``). Ends the running recording first."""
        return [str(line) for line in transcript_of(self.records())]

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> int | None:
        """Stop the firmware (SIGTERM, SIGKILL after ``timeout``) and whatever else runs
        in its process group; its exit status, None when it was never started. A
        recording ends first, complete."""
        process = self._process
        if process is None:
            return None
        self.stop_recording()
        if process.returncode is None:  # not reaped: its pid still names its group
            self._signal_group(signal.SIGTERM)
            if not self._exited(timeout):
                self._signal_group(signal.SIGKILL)
            self._signal_group(signal.SIGKILL)  # the rest of the group, before the reaping
        return process.wait()

    def _exited(self, timeout: float) -> bool:
        """Whether the firmware exits within ``timeout``, left unreaped (WNOWAIT): a reaped
        pid may be reused, and a signal to its group then reaches a stranger's processes."""
        assert self._process is not None
        deadline = time.monotonic() + timeout
        while os.waitid(os.P_PID, self._process.pid,
                        os.WEXITED | os.WNOHANG | os.WNOWAIT) is None:
            if time.monotonic() > deadline:
                return False
            time.sleep(POLL_S)
        return True

    def restart(self, timeout: float = START_TIMEOUT_S) -> None:
        """Stop the card and start it again: a power cycle. With ``configure`` the card
        configures itself on line anew, as after the first start."""
        self.stop()
        self.start(timeout)

    def _signal_group(self, signum: int) -> None:
        assert self._process is not None
        with contextlib.suppress(ProcessLookupError):  # the group has ended already
            os.killpg(self._process.pid, signum)

    def fault(self, kind: str, *, for_ms: int | None = None, code: int = 0,
              delay_ms: int = 0, offset: int = 0, bit: int = 0,
              hang: bool = False) -> list[ActiveFault]:
        """Inject a card-side fault (docs/faults.md, ``host_api.faults.inject``): the faults
        in force afterwards. Each ends by itself after ``for_ms``, on ``clear_faults``, or
        when the card stops."""
        return faults.inject(kind, self.board, self.directory, for_ms=for_ms, code=code,
                             delay_ms=delay_ms, offset=offset, bit=bit, hang=hang)

    def clear_faults(self) -> list[ActiveFault]:
        """End every fault in force (a hanging card comes back by a cold start)."""
        return faults.clear(self.board, self.directory)

    def diagnostics(self) -> ComDiagnostics:
        """Task2State as the image holds it now, read without opening the board: the
        fixture never takes a host's place (a DevOpenDriver here would be the test
        process's one driver)."""
        image = self._image()
        return ComDiagnostics.decode(image[TASK2_STATE:TASK2_STATE + TASK_AREA_SIZE])

    def _image(self) -> bytes:
        image = read_image(self.board, str(self.directory))
        if image is None:
            raise CardError(f"board {self.board}: no image at {self.image}")
        return image

    def wait_until_operating(self, timeout: float = OPERATING_TIMEOUT_S) -> ComDiagnostics:
        """Wait until every active node of the network is in Nd_state (data exchange)
        and the card shows COM, and return Task2State then. COM too: the card raises it
        a moment after the nodes' bits, and until then a host's DevExchangeIO gets -21.
        Raises CardError naming the missing nodes and the card's Err_Event when
        ``timeout`` passes, or at once when the firmware exits."""
        if self.network is None:
            raise CardError(f"board {self.board} has no network: mark the test with "
                            f"@pytest.mark.{NETWORK_MARKER}(...)")
        nodes = [node.id for node in self.network.nodes if node.active]
        deadline = time.monotonic() + timeout
        while True:
            if not self.running:
                raise CardError(f"board {self.board}: the firmware (pid {self.pid}) is not "
                                f"running\n{self.log_tail()}")
            image = self._image()
            diag = ComDiagnostics.decode(image[TASK2_STATE:TASK2_STATE + TASK_AREA_SIZE])
            missing = sorted(set(nodes) - set(diag.operating()))
            if not missing and image[HOST_FLAGS] & fl.COM:
                return diag
            if time.monotonic() > deadline:
                error = (f"Err_Event {diag.bErr_event} at {diag.bErr_rem_adr}: {diag.err_text}"
                         if diag.bErr_event else "no Err_Event")
                what = (f"node(s) {missing} not in data exchange" if missing
                        else "every node in data exchange, but COM clear")
                raise CardError(f"board {self.board}: after {timeout} s {what} (CAN_state "
                                f"{diag.can_state_name}, Nd_state {diag.operating()}, {error})")
            time.sleep(POLL_S)

    def status(self) -> dict[str, Any]:
        """What ``cifemu status --json`` prints for this card."""
        image = read_image(self.board, str(self.directory))
        if image is None:
            return {"board": self.board, "error": f"no image at {self.image}"}
        return {"board": self.board, **snapshot(image),
                "health": health(self.directory, self.board)}

    def transcript_tail(self, lines: int = TRANSCRIPT_LINES) -> str:
        """The end of the transcript for a report, naming the sessions to replay."""
        try:
            steps = self.transcript()
        except (OSError, s.SessionError) as exc:
            return f"(no transcript: {exc})"
        names = ", ".join(str(session) for session in self.sessions)
        head = [f"{len(steps)} steps recorded in {names} (cifemu replay SESSION plays them "
                "against a card)"]
        if self.recording_problem is not None:
            head.append(f"(the recording ended early: {self.recording_problem})")
        if len(steps) > lines:
            head.append(f"({len(steps) - lines} earlier step(s) left out)")
        return "\n".join(head + steps[-lines:])

    def log_tail(self, lines: int = LOG_TAIL_LINES) -> str:
        """The end of the firmware's log, saying where the rest is."""
        try:
            text = self.log.read_text(errors="replace").splitlines()
        except OSError as exc:
            return f"(no firmware log: {exc.strerror})"
        if len(text) <= lines:
            return "\n".join(text)
        return "\n".join([f"({len(text) - lines} earlier line(s) in {self.log})",
                          *text[-lines:]])


# --- the network of a test ---------------------------------------------------------------

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def _toml_string(text: str) -> str:
    escaped = "".join(
        "\\" + ch if ch in '"\\' else f"\\u{ord(ch):04x}" if ord(ch) < 0x20 or ch == "\x7f"
        else ch for ch in text)
    return f'"{escaped}"'


def _toml_value(value: object, where: str) -> str:
    """A TOML value, tables inline: a network description has only strings, numbers,
    booleans, arrays and tables (tomli-w is not a dependency for this much)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return repr(value) if math.isfinite(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, str):
        return _toml_string(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v, f"{where}[{n}]") for n, v in enumerate(value)) + "]"
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{_toml_key(k, where)} = {_toml_value(v, f'{where}.{k}')}"
                               for k, v in value.items()) + "}"
    raise NetworkError(f"{where}: a {type(value).__name__} has no TOML form")


def _toml_key(key: object, where: str) -> str:
    if not isinstance(key, str):
        raise NetworkError(f"{where}: key {key!r} is not a string")
    return key if _BARE_KEY.fullmatch(key) else _toml_string(key)


def network_toml(description: Mapping[str, Any]) -> str:
    """A network description given as a dict ({"bus": {...}, "node": [{...}, ...]}, the
    file's own structure) as the TOML text of that file."""
    return "".join(f"{_toml_key(key, 'file')} = {_toml_value(value, key)}\n"
                   for key, value in description.items())


@dataclass(frozen=True)
class _Marked:
    """What a test's ``cif_network`` marker asks for (no marker: no network, board 0)."""

    network: Network | None = None
    board: int = 0
    configure: bool = True


def _marked(item: pytest.Item, directory: Path) -> _Marked:
    """The test's ``cif_network`` marker read; a mistake in it fails the test's set-up
    with the key it gets wrong, no traceback."""
    marker = item.get_closest_marker(NETWORK_MARKER)
    if marker is None:
        return _Marked()
    usage = f"@pytest.mark.{NETWORK_MARKER}(path_or_dict, board=0, configure=True)"
    if len(marker.args) != 1 or set(marker.kwargs) - {"board", "configure"}:
        pytest.fail(f"{usage}: got args {marker.args}, kwargs {marker.kwargs}", pytrace=False)
    board = marker.kwargs.get("board", 0)
    if not isinstance(board, int) or isinstance(board, bool) or not (
            0 <= board < MAX_DEV_BOARDS):
        pytest.fail(f"{usage}: board = {board!r} is not 0..{MAX_DEV_BOARDS - 1}", pytrace=False)
    configure = marker.kwargs.get("configure", True)
    if not isinstance(configure, bool):
        pytest.fail(f"{usage}: configure = {configure!r} is not True or False", pytrace=False)
    spec = marker.args[0]
    try:
        if isinstance(spec, Mapping):
            path = directory / "network.toml"
            path.write_text(network_toml(spec))
        elif isinstance(spec, str | os.PathLike):
            path = Path(item.path).parent / spec  # relative to the test file; absolute kept
        else:
            pytest.fail(f"{usage}: a path or a dict, not a {type(spec).__name__}",
                        pytrace=False)
        return _Marked(load_network(path), board, configure)
    except NetworkError as exc:
        pytest.fail(f"{NETWORK_MARKER}: {exc}", pytrace=False)


def _recording(item: pytest.Item, home: Path) -> tuple[Path, bool]:
    """Where the test's card records (``home/session`` unless its ``cif_record`` marker
    names a directory, relative to the test file) and whether the marker keeps it."""
    marker = item.get_closest_marker(RECORD_MARKER)
    if marker is None:
        return home / "session", False
    usage = f"@pytest.mark.{RECORD_MARKER}(path=None)"
    spec = marker.kwargs.get("path", marker.args[0] if marker.args else None)
    if len(marker.args) > 1 or set(marker.kwargs) - {"path"} or (marker.args and marker.kwargs):
        pytest.fail(f"{usage}: got args {marker.args}, kwargs {marker.kwargs}", pytrace=False)
    if spec is None:
        return home / "session", True
    if not isinstance(spec, str | os.PathLike):
        pytest.fail(f"{usage}: path is a directory, not a {type(spec).__name__}",
                    pytrace=False)
    return Path(item.path).parent / spec, True


# --- pytest's side -----------------------------------------------------------------------

CARD = pytest.StashKey[CifCard]()
"""The test's card, for the failure report."""
FAILED = pytest.StashKey[bool]()
"""Whether a phase of the test failed: its recording is kept for the report's reader."""


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", f"{NETWORK_MARKER}(path_or_dict, board=0, configure=True): the simulated "
        "network of the cif_card fixture's card (a network description file, relative to "
        "the test file, or its contents as a dict), its board number, and whether the card "
        "configures itself from it on line (False: the host program under test does)")
    config.addinivalue_line(
        "markers", f"{RECORD_MARKER}(path=None): keep the recorded session of the cif_card "
        "fixture's card: in path (a directory to create, relative to the test file; after a "
        "restart path-2 ...), else in tmp_path/cifemu/session. Unmarked, it is kept only "
        "when the test fails")


@pytest.fixture
def cif_card(request: pytest.FixtureRequest, tmp_path: Path,
             monkeypatch: pytest.MonkeyPatch) -> Iterator[CifCard]:
    """A running emulated card of the test's own; stopped afterwards, also on failure."""
    home = tmp_path / "cifemu"
    home.mkdir()
    marked = _marked(request.node, home)
    record_into, keep = _recording(request.node, home)
    # The image directory holds the card's sockets, whose paths may not pass 107 bytes: a
    # short directory of its own, not one under pytest's deep tmp_path.
    images = Path(tempfile.mkdtemp(prefix="cifemu-"))
    request.addfinalizer(lambda: shutil.rmtree(images, ignore_errors=True))
    card = CifCard(marked.board, images, home / "flash", home / "firmware.log",
                   marked.network, marked.configure, record_into)
    monkeypatch.setenv("CIF_DPM_DIR", str(card.directory))
    failure = None
    try:
        card.start()
    except CardError as exc:  # its message has the log: no report section to repeat it
        failure = str(exc)
    if failure is not None:  # outside the handler: pytest would show the message twice
        pytest.fail(failure, pytrace=False)
    request.node.stash[CARD] = card
    try:
        yield card
    finally:
        card.stop()
        if not keep and not request.node.stash.get(FAILED, False):
            for session in card.sessions:  # a passed test's recording served its purpose
                shutil.rmtree(session, ignore_errors=True)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]
                              ) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    """A failed test that had a card gets the card's side: its log, its final state and
    the transcript of its recording (which then ends: the card has written it all)."""
    del call
    report: pytest.TestReport = yield
    if report.failed:
        item.stash[FAILED] = True
    card = item.stash.get(CARD, None)
    if card is not None and report.failed:
        name = f"cifemu board {card.board}"
        report.sections.append((f"{name}: firmware log", card.log_tail()))
        report.sections.append((f"{name}: status", json.dumps(card.status(), indent=2)))
        if card.sessions:
            report.sections.append((f"{name}: transcript", card.transcript_tail()))
    return report
