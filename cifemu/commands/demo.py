"""A card and a simulated network, configured on line, shown as top's live view.

The card's image goes where every other command looks by default ($CIF_DPM_DIR
or /dev/shm/cif), so `cifemu status`, `cifemu top`, `cifemu monitor` and
`cifemu 309 serve` find it without options while the demo runs. The demo
refuses to start beside a firmware that already serves the board, keeps its
flash in a temporary directory, and removes every file it created when it ends
(Ctrl-C or SIGTERM) [ours].
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from types import FrameType

from rich.console import Console, Group

from cifemu.commands.configure import configure
from dbm_tools.builder import BuildError, build_dbm
from dbm_tools.container import write_dbm
from dbm_tools.network import Network, NetworkError, load_network
from dpm.image import (
    DEFAULT_DPM_DIR,
    MAX_DEV_BOARDS,
    CardDirectory,
    UnsafePathError,
    dpm_dir,
    image_path,
)
from host_api import driver as d
from host_api import status as status_cli
from host_api.board import Board, CifError
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload
from host_api.driver import COLDSTART
from host_api.liveness import firmware_liveness
from host_api.network_view import network_view, remember_network
from host_api.online import ConfigurationError
from host_api.ready import StartError, wait_ready
from host_api.top.app import TopApp
from host_api.top.feed import CardFeed
from host_api.top.model import CardModel
from host_api.top.render import natural_width, nodes_table

EXAMPLE_NETWORK = Path(__file__).parents[1] / "examples" / "demo.toml"
NETWORK_WAIT_S = 10.0
FIRST_TABLE_S = 1.5
"""How long the demo listens before its first node table off a terminal: one heartbeat
of each of the example's nodes (1 s)."""


def _board_files(directory: Path, board: int) -> set[Path]:
    """The image and the lock files of one board (firmware's and the driver's)."""
    return {p for p in directory.glob(f"board{board}.*") if p.is_file()}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--board", type=int, default=0, choices=range(MAX_DEV_BOARDS),
                        metavar="N", help="board number 0..3 (default 0)")
    parser.add_argument("--dpm-dir", default=None, metavar="DIR",
                        help="image directory (default $CIF_DPM_DIR or /dev/shm/cif, where "
                             "status, top, monitor and 309 look)")
    parser.add_argument("--from-dbm", action="store_true",
                        help="build a DBM from the network, download it into the card's flash and "
                             "cold-start the card from it, instead of configuring it on line")
    parser.add_argument("--network", type=Path, default=None, metavar="NETWORK.toml",
                        help=f"network description to simulate (default: {EXAMPLE_NETWORK.name}, "
                             "four generic I/O modules)")


def command_for_another_terminal(directory: Path, board: int) -> tuple[str, str]:
    """The cifemu command and the options that reach this demo's card from a second terminal.

    `make demo` runs .venv/bin/cifemu without putting .venv/bin on $PATH, so a bare
    `cifemu` there is "command not found": the hint names the script by its absolute path
    unless $PATH finds this very one. The board and a directory other than the default go
    along, since the second terminal has neither this one's options nor its $CIF_DPM_DIR.
    """
    script = Path(sys.executable).parent / "cifemu"
    found = shutil.which("cifemu")
    if found is not None and script.exists() and Path(found).resolve() == script.resolve():
        words = ["cifemu"]
    elif script.exists():
        words = [str(script.absolute())]
    else:
        words = [sys.executable, "-m", "cifemu"]
    command = shlex.join(words)
    options = []
    if board != 0:
        options += ["--board", str(board)]
    if directory.absolute() != Path(DEFAULT_DPM_DIR):
        options += ["--dpm-dir", str(directory.absolute())]
    return command, shlex.join(options)


def _on_sigterm(signum: int, frame: FrameType | None) -> None:
    del signum, frame
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    directory = dpm_dir(args.dpm_dir)
    network_path = args.network or EXAMPLE_NETWORK
    try:
        network = load_network(network_path)
        build_dbm(network)  # a description the card would refuse never reaches it
    except (NetworkError, BuildError, OSError) as exc:
        print(f"cifemu demo: {network_path}: {exc}", file=sys.stderr)
        return 1
    live = firmware_liveness(directory, args.board)
    if live.alive:
        print(f"cifemu demo: board {args.board} in {directory} is already served by "
              f"process {live.pid}; stop that firmware, or give the demo another --board "
              "or --dpm-dir", file=sys.stderr)
        return 1
    created_dir = not directory.exists()
    try:  # mode 02770 whatever the umask, and refused when another user could plant files
        CardDirectory(directory, create=True).close()
    except UnsafePathError as exc:
        print(f"cifemu demo: {exc}", file=sys.stderr)
        return 1
    before = _board_files(directory, args.board)
    signal.signal(signal.SIGTERM, _on_sigterm)
    with tempfile.TemporaryDirectory(prefix="cifemu-demo-flash-") as flash:
        card = subprocess.Popen(
            [sys.executable, "-m", "cifemu", "firmware", "--board", str(args.board),
             "--dpm-dir", str(directory), "--flash", flash, "--simulate", str(network_path),
             "--log-level", "WARNING"]
        )
        try:
            return _show(args, directory, network_path, network, card)
        except KeyboardInterrupt:
            return 0
        finally:
            card.terminate()
            try:
                card.wait(timeout=10)
            except subprocess.TimeoutExpired:  # stopped (SIGSTOP) or hung: not left behind
                card.kill()
                card.wait()
            for path in _board_files(directory, args.board) - before:
                path.unlink(missing_ok=True)
            if created_dir and not any(directory.iterdir()):
                directory.rmdir()


def _show(args: argparse.Namespace, directory: Path, network_path: Path, network: Network,
          card: subprocess.Popen[bytes]) -> int:
    console = Console()
    board_no = args.board
    try:  # for as long as its start advances: a loaded machine takes 10-20 s of wall time
        wait_ready(card, directory, board_no)
    except StartError as exc:
        print(f"cifemu demo: the firmware did not start: {exc}", file=sys.stderr)
        return 1
    try:
        with Board(board_no, directory) as board:
            if args.from_dbm:
                database = write_dbm(build_dbm(network))
                console.print(f"downloading a DBM of {len(database)} bytes built from "
                              f"{network_path}")
                if DevDownload(board_no, CONFIGURATION_DOWNLOAD, database) != 0:
                    print("cifemu demo: the card refused the database", file=sys.stderr)
                    return 1
                board.reset(COLDSTART)  # the card starts from its flash
                remember_network(directory, board_no, network_path)
            else:
                configure(board, network, NETWORK_WAIT_S,
                          lambda step: console.print(f"configuring: {step}"))
            command, options = command_for_another_terminal(directory, board_no)
            ends = "q in the view" if sys.stdout.isatty() else "Ctrl-C"  # Textual takes Ctrl-C
            console.print(f"card image {image_path(directory, board_no)}; {ends} ends the demo. "
                          "In another terminal:", highlight=False, soft_wrap=True)
            hints = [" ".join(filter(None, [command, sub, options]))
                     for sub in ("top", "status", "monitor")]
            for hint in hints:
                console.print(f"  {hint}", highlight=False, markup=False, soft_wrap=True)
            sys.stdout.flush()
            _watch(board_no, directory, network_path, network, console, hints)
    except (CifError, ConfigurationError) as exc:
        print(f"cifemu demo: {exc}", file=sys.stderr)
        return 1
    return 0


def _watch(board_no: int, directory: Path, network_path: Path, network: Network,
           console: Console, hints: list[str]) -> None:
    """What a CANopen engineer looks at first: ``top``'s nodes (names, NMT states, EMCY
    texts), live with its keys on a terminal (c: the card's own bits); off a terminal, the
    node table once the nodes have been heard, then each event as a line. Meanwhile the
    host writes a counter into the outputs, so the process image moves."""
    model = CardModel(view=network_view(network), network=network)
    feed = CardFeed(model, board_no, directory)
    stop = threading.Event()
    writer = threading.Thread(target=_count_outputs, args=(board_no, stop), daemon=True)
    feed.start()
    writer.start()
    try:
        if sys.stdout.isatty():
            errors = {node.id: node.error_control for node in network.nodes}

            def card_view() -> Group | None:
                image = status_cli.read_image(board_no, str(directory))
                return (status_cli.render(board_no, status_cli.snapshot(image, errors))
                        if image is not None else None)

            for hint in hints:  # the lines above vanish behind the view: its log keeps them
                model.log(time.time(), f"in another terminal: {hint}")
            TopApp(model, feed, board_no, directory, card_view=card_view).run()
            return
        _print_lines(model, feed, network_path, console)
    finally:
        stop.set()
        writer.join(timeout=2)
        feed.stop()


def _count_outputs(board_no: int, stop: threading.Event) -> None:
    counter = 0
    while not stop.wait(0.2):
        counter = (counter + 1) & 0xFF
        d.DevExchangeIO(board_no, 0, bytes([counter]) * 32, 0, 0, 100)


def _print_lines(model: CardModel, feed: CardFeed, network_path: Path,
                 console: Console) -> None:
    """The demo in a pipe or a file: the node table after one heartbeat period, then every
    event (EMCY, Err_Event, boot-up, NMT) as a line of its own, each flushed."""
    deadline = time.monotonic() + FIRST_TABLE_S
    while time.monotonic() < deadline:
        feed.poll_image()
        time.sleep(0.05)
    table = nodes_table(model, time.time())
    table.title = f"nodes of {network_path.name}"
    Console(width=natural_width(Group(table))).print(table)
    sys.stdout.flush()
    seen = 0
    while True:
        feed.poll_image()
        for line in model.new_events(seen):
            console.print(line, highlight=False, markup=False, soft_wrap=True)
            seen += 1
        sys.stdout.flush()
        time.sleep(0.1)
