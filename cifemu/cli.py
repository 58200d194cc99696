"""``cifemu``: one command for the emulated CIF CANopen master card.

  cifemu firmware   run one emulated card in the foreground
  cifemu sim        run a network description's simulated nodes on a CAN bus
  cifemu status     show a card's flags, info areas and Task2State
  cifemu dbm        DBM files (show, check, build, diff) and a card's stored database
                    (download, upload, delete, dir)
  cifemu demo       a card, a simulated network, on-line configuration, live status
  cifemu 309        the CiA 309-3 ASCII gateway (serve, exec, shell)
  cifemu libcif     flags that compile a C program against libcif (--cflags --libs)
  cifemu legacy     run an unchanged legacy binary against the card (/dev/cif preloaded)
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rich.console import Console
from rich.live import Live

from cifemu import libcif as libcif_cli
from dbm_tools import cli as dbm_cli
from dbm_tools.builder import build_dbm
from dbm_tools.container import write_dbm
from dbm_tools.network import load_network
from dpm.flags import READY
from dpm.layout import HOST_FLAGS
from firmware import cli as firmware_cli
from firmware.sim import cli as sim_cli
from host_api import driver as d
from host_api import legacy as legacy_cli
from host_api import status as status_cli
from host_api.board import Board
from host_api.cia309 import cli as cia309_cli
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload
from host_api.driver import COLDSTART
from host_api.online import configure_online


def _ready(image: bytes | None) -> bool:
    return image is not None and bool(image[HOST_FLAGS] & READY)


EXAMPLE_NETWORK = Path(__file__).with_name("examples") / "demo.toml"


def _demo(args: argparse.Namespace) -> int:
    """A card and a simulated network, configured on line, with its live status."""
    directory = args.dpm_dir or tempfile.mkdtemp(prefix="cifemu-demo-")
    network = args.network or EXAMPLE_NETWORK
    card = subprocess.Popen(
        [sys.executable, "-m", "firmware", "--board", "0", "--dpm-dir", directory,
         "--flash", str(Path(directory) / "flash"), "--simulate", str(network),
         "--log-level", "WARNING"]
    )
    console = Console()
    try:
        deadline = time.monotonic() + 15
        while not _ready(status_cli.read_image(0, directory)):
            if card.poll() is not None or time.monotonic() > deadline:
                print("cifemu demo: the firmware did not start", file=sys.stderr)
                return 1
            time.sleep(0.05)
        with Board(0, directory) as board:
            if args.from_dbm:
                database = write_dbm(build_dbm(load_network(network)))
                console.print(f"downloading a DBM of {len(database)} bytes built from {network}")
                if DevDownload(0, CONFIGURATION_DOWNLOAD, database) != 0:
                    print("cifemu demo: the card refused the database", file=sys.stderr)
                    return 1
                board.reset(COLDSTART)  # the card starts from its flash
            else:
                configure_online(board, load_network(network),
                                 lambda step: console.print(f"configuring: {step}"))
            console.print(f"card image {directory}/board0.dpm; Ctrl-C ends the demo")
            counter = 0
            with Live(console=console, auto_refresh=False) as live:
                while True:
                    counter = (counter + 1) & 0xFF
                    d.DevExchangeIO(0, 0, bytes([counter]) * 32, 0, 0, 100)
                    snapshot = status_cli.read_image(0, directory)
                    if snapshot is not None:
                        live.update(status_cli.render(0, status_cli.snapshot(snapshot)),
                                    refresh=True)
                    time.sleep(0.2)
    except KeyboardInterrupt:
        return 0
    finally:
        card.terminate()
        card.wait(timeout=10)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cifemu", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    fw = sub.add_parser("firmware", help="run one emulated card in the foreground",
                        description=firmware_cli.__doc__)
    firmware_cli.add_arguments(fw)
    fw.set_defaults(func=firmware_cli.run)
    sim = sub.add_parser("sim", help="run a network description's simulated nodes on a CAN bus",
                         description=sim_cli.__doc__,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    sim_cli.add_arguments(sim)
    sim.set_defaults(func=sim_cli.run)
    st = sub.add_parser("status", help="show a card's state", description=status_cli.__doc__)
    status_cli.add_arguments(st)
    st.set_defaults(func=status_cli.run)
    dbm = sub.add_parser("dbm", help="DBM files: show, check, build, diff, download, upload",
                         description=dbm_cli.__doc__,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    dbm_cli.add_arguments(dbm)
    dbm.set_defaults(func=dbm_cli.run)
    cia309 = sub.add_parser("309", help="CiA 309-3 ASCII gateway: serve, exec, shell",
                            description=cia309_cli.__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    cia309_cli.add_arguments(cia309)
    cia309.set_defaults(func=cia309_cli.run)
    libcif = sub.add_parser("libcif", help="compiler and linker flags for C programs (libcif)",
                            description=libcif_cli.__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    libcif_cli.add_arguments(libcif)
    libcif.set_defaults(func=libcif_cli.run)
    legacy = sub.add_parser("legacy", help="run a legacy binary with /dev/cif served by the card",
                            description=legacy_cli.__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    legacy_cli.add_arguments(legacy)
    legacy.set_defaults(func=legacy_cli.run)
    demo = sub.add_parser("demo", help="a card, simulated nodes, live status (Ctrl-C ends)",
                          description=_demo.__doc__)
    demo.add_argument("--dpm-dir", default=os.environ.get("CIFEMU_DEMO_DIR"),
                      help="image directory (default: a fresh temporary one)")
    demo.add_argument("--from-dbm", action="store_true",
                      help="build a DBM from the network, download it into the card's flash and "
                           "cold-start the card from it, instead of configuring it on line")
    demo.add_argument("--network", type=Path, default=None,
                      help=f"network description to simulate (default: {EXAMPLE_NETWORK.name}, "
                           "four generic I/O modules)")
    demo.set_defaults(func=_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    result: int = args.func(args)
    return result
