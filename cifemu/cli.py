"""``cifemu``: one command for the emulated CIF CANopen master card.

  cifemu firmware   run one emulated card in the foreground
  cifemu status     show a card's flags, info areas and Task2State
  cifemu demo       start a card and watch its status until Ctrl-C
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

from firmware import cli as firmware_cli
from host_api import status as status_cli


def _demo(args: argparse.Namespace) -> int:
    """A card in a private image directory, its live status on screen."""
    directory = args.dpm_dir or tempfile.mkdtemp(prefix="cifemu-demo-")
    card = subprocess.Popen(
        [sys.executable, "-m", "firmware", "--board", "0", "--dpm-dir", directory,
         "--log-level", "WARNING"]
    )
    try:
        deadline = time.monotonic() + 10
        while status_cli.read_image(0, directory) is None:
            if card.poll() is not None or time.monotonic() > deadline:
                print("cifemu demo: the firmware did not start", file=sys.stderr)
                return 1
            time.sleep(0.05)
        print(f"card image: {directory}/board0.dpm  (Ctrl-C ends the demo)")
        watch = argparse.Namespace(board=0, dpm_dir=directory, watch=True, interval=0.5,
                                   json=False)
        return status_cli.run(watch)
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
    st = sub.add_parser("status", help="show a card's state", description=status_cli.__doc__)
    status_cli.add_arguments(st)
    st.set_defaults(func=status_cli.run)
    demo = sub.add_parser("demo", help="start a card and watch its status until Ctrl-C",
                          description=_demo.__doc__)
    demo.add_argument("--dpm-dir", default=os.environ.get("CIFEMU_DEMO_DIR"),
                      help="image directory (default: a fresh temporary one)")
    demo.set_defaults(func=_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    result: int = args.func(args)
    return result
