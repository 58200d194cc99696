"""cifemu status: the card's state as a person reads it.

It maps the image read-only, so looking never disturbs a running card, and
works on a card whose firmware is down: it then says so (the firmware lock is
free; the last pid) and exits with status 3. It also shows which database the
card's last start loaded from flash. The model and its rendering are in
host_api.status.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.live import Live

from cifemu.cli_options import add_card_options
from cifemu.cli_output import fail, print_json
from dpm.image import dpm_dir, image_path
from host_api.status import GUIDE, error_controls, health, read_image, render, snapshot

EXIT_OK = 0
EXIT_DEAD = 3
"""[ours] the image is there but no firmware holds its lock (killed, crashed, stopped)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = GUIDE
    add_card_options(parser)
    parser.add_argument("--watch", action="store_true", help="refresh until Ctrl-C")
    parser.add_argument("--interval", type=float, default=0.5, metavar="SECONDS",
                        help="--watch refresh seconds")
    parser.add_argument("--json", action="store_true", help="print the decoded state as JSON")


def _full_snapshot(image: bytes, directory: Path, board: int) -> dict[str, Any]:
    return {"board": board, **snapshot(image, error_controls(directory, board)),
            "health": health(directory, board)}


def run(args: argparse.Namespace) -> int:
    console = Console()
    directory = dpm_dir(args.dpm_dir)
    image = read_image(args.board, args.dpm_dir)
    if image is None:
        where = image_path(directory, args.board)
        return fail("status", f"no image at {where}: is `cifemu firmware --board {args.board}` "
                    "running?", args.json, image=str(where))
    snap = _full_snapshot(image, directory, args.board)
    alive = EXIT_OK if snap["health"]["alive"] else EXIT_DEAD
    if args.json:
        print_json(snap)
        return alive
    if not args.watch:
        console.print(render(args.board, snap))
        return alive
    try:
        with Live(render(args.board, snap), console=console, auto_refresh=False) as live:
            while True:
                time.sleep(args.interval)
                image = read_image(args.board, args.dpm_dir) or image
                live.update(render(args.board, _full_snapshot(image, directory, args.board)),
                            refresh=True)
    except KeyboardInterrupt:
        return 0

