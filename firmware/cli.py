"""``cifemu firmware``: run one emulated card in the foreground."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from types import FrameType

from dpm.image import DEFAULT_DPM_DIR, MAX_DEV_BOARDS, BoardBusyError
from firmware.device import Device


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--board", type=int, default=0, choices=range(MAX_DEV_BOARDS),
                        metavar="N", help="board number 0..3 (default 0)")
    parser.add_argument("--dpm-dir", default=None,
                        help=f"directory of the image board<N>.dpm "
                             f"(default $CIF_DPM_DIR or {DEFAULT_DPM_DIR})")
    parser.add_argument("--reset-delay", type=float, default=0.0, metavar="SECONDS",
                        help="emulate a real card's slow start (default 0: milliseconds)")
    parser.add_argument("--log-level", default="INFO",
                        choices=["DEBUG", "INFO", "WARNING", "ERROR"])


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s: %(message)s")
    try:
        device = Device(args.board, args.dpm_dir, reset_delay=args.reset_delay)
    except BoardBusyError as exc:
        print(f"cifemu firmware: board {args.board} refused: {exc}", file=sys.stderr)
        return 1

    def on_signal(signum: int, frame: FrameType | None) -> None:
        del signum, frame
        device.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    logging.getLogger("firmware").info("board %d serving %s", args.board, device.path)
    device.run()
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m firmware", description=__doc__)
    add_arguments(parser)
    return run(parser.parse_args(argv))
