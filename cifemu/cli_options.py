"""The options every command that addresses one card takes: which board, which directory."""

from __future__ import annotations

import argparse

from dpm.image import DEFAULT_DPM_DIR, MAX_DEV_BOARDS


def add_card_options(parser: argparse.ArgumentParser,
                     board_help: str = "board number 0..3 (default 0)") -> None:
    parser.add_argument("--board", type=int, default=0, choices=range(MAX_DEV_BOARDS),
                        metavar="N", help=board_help)
    parser.add_argument("--dpm-dir", default=None, metavar="DIR",
                        help=f"image directory (default $CIF_DPM_DIR or {DEFAULT_DPM_DIR})")
