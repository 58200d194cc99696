"""A card and a simulated network, configured on line, with its live status.

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
import time
from pathlib import Path
from types import FrameType

from rich.console import Console
from rich.live import Live

from cifemu.commands.configure import configure
from dbm_tools.builder import BuildError, build_dbm
from dbm_tools.container import write_dbm
from dbm_tools.network import Network, NetworkError, load_network
from dpm.flags import READY
from dpm.image import (
    DEFAULT_DPM_DIR,
    MAX_DEV_BOARDS,
    CardDirectory,
    UnsafePathError,
    dpm_dir,
    image_path,
)
from dpm.layout import HOST_FLAGS
from host_api import driver as d
from host_api import status as status_cli
from host_api.board import Board, CifError
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload
from host_api.driver import COLDSTART
from host_api.liveness import firmware_liveness
from host_api.network_view import remember_network
from host_api.online import ConfigurationError

EXAMPLE_NETWORK = Path(__file__).parents[1] / "examples" / "demo.toml"
START_TIMEOUT_S = 15.0
NETWORK_WAIT_S = 10.0


def _ready(image: bytes | None) -> bool:
    return image is not None and bool(image[HOST_FLAGS] & READY)


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
            card.wait(timeout=10)
            for path in _board_files(directory, args.board) - before:
                path.unlink(missing_ok=True)
            if created_dir and not any(directory.iterdir()):
                directory.rmdir()


def _show(args: argparse.Namespace, directory: Path, network_path: Path, network: Network,
          card: subprocess.Popen[bytes]) -> int:
    console = Console()
    board_no = args.board
    deadline = time.monotonic() + START_TIMEOUT_S
    while not _ready(status_cli.read_image(board_no, str(directory))):
        if card.poll() is not None or time.monotonic() > deadline:
            print("cifemu demo: the firmware did not start", file=sys.stderr)
            return 1
        time.sleep(0.05)
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
            console.print(f"card image {image_path(directory, board_no)}; Ctrl-C ends the demo. "
                          "In another terminal:", highlight=False)
            for sub in ("top", "status", "monitor"):
                console.print(f"  {' '.join(filter(None, [command, sub, options]))}",
                              highlight=False, markup=False, soft_wrap=True)
            counter = 0
            with Live(console=console, auto_refresh=False) as live:
                while True:
                    counter = (counter + 1) & 0xFF
                    d.DevExchangeIO(board_no, 0, bytes([counter]) * 32, 0, 0, 100)
                    snapshot = status_cli.read_image(board_no, str(directory))
                    if snapshot is not None:
                        live.update(status_cli.render(board_no, status_cli.snapshot(
                            snapshot, {node.id: node.error_control for node in network.nodes})),
                                    refresh=True)
                    time.sleep(0.2)
    except (CifError, ConfigurationError) as exc:
        print(f"cifemu demo: {exc}", file=sys.stderr)
        return 1
