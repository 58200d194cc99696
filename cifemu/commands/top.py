"""cifemu top: a live view of one card, for a terminal (also over SSH).

One row per node: address, name (from the network file or its EDS), NMT state
(from its heartbeats or guarding answers), the card's Nd_cfg / Nd_state /
Nd_diag bits, the supervision and when the node was last heard, the last
Err_Event the card reported for it (with the manual's text) and its last EMCY
(with the CiA 301 meaning of the code). Below: the process image mapped to
nodes and PDOs (hex and decimal, changes highlighted), a sparkline of one PDO's
value, the bus counters and load (frames/s and percent of the bit rate, from
the frames the card's tap shows, stuff bits counted), and an event log (Err_Event, EMCY, boot-ups,
NMT, your commands).

Keys: s start, t stop, p pre-operational, r reset the selected node; o read an
object by SDO (index and subindex in hex); v follow the next PDO's value; q quit.

The network file defaults to the one the card was last configured from with
`cifemu configure`, `cifemu firmware --configure` or `cifemu demo`.
--once prints one snapshot (after listening --sample seconds) and ends.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from rich.console import Console

from cifemu.cli_options import add_card_options
from cifemu.cli_output import fail
from dbm_tools.builder import BuildError
from dbm_tools.network import NetworkError, load_network
from dpm.image import dpm_dir, image_path
from host_api.liveness import firmware_liveness
from host_api.network_view import network_view, remembered_network
from host_api.top.feed import CardFeed
from host_api.top.model import CardModel
from host_api.top.render import snapshot

COMMAND = "top"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_card_options(parser)
    parser.add_argument("--network", type=Path, default=None, metavar="NETWORK.toml",
                        help="names, supervision and PDO map (default: the file the card was "
                             "last configured from)")
    parser.add_argument("--once", action="store_true",
                        help="print one snapshot and end (no terminal needed)")
    parser.add_argument("--sample", type=float, default=1.5, metavar="SECONDS",
                        help="with --once: listen this long to the bus first (default 1.5, "
                             "enough for one heartbeat of each node at 1 s)")
    parser.add_argument("--interval", type=float, default=0.25, metavar="SECONDS",
                        help="refresh period of the live view (default 0.25)")


def build_model(path: Path | None) -> CardModel:
    """The model of a card running ``path``'s network (an empty map without one)."""
    if path is None:
        return CardModel()
    network = load_network(path)
    return CardModel(view=network_view(network), network=network)


def run(args: argparse.Namespace) -> int:
    directory = dpm_dir(args.dpm_dir)
    if not image_path(directory, args.board).exists():
        return fail(COMMAND, f"no image at {image_path(directory, args.board)}: is `cifemu "
                    f"firmware --board {args.board}` running?", False)
    path = args.network or remembered_network(directory, args.board)
    try:
        model = build_model(path)
    except (NetworkError, BuildError, OSError) as exc:
        return fail(COMMAND, f"{path}: {exc}", False)
    feed = CardFeed(model, args.board, directory)
    feed.start()
    if feed.tap_error:
        model.log(time.time(), f"no frames: {feed.tap_error}")
    try:
        if args.once:
            deadline = time.monotonic() + args.sample
            while time.monotonic() < deadline:
                feed.poll_image()
                time.sleep(0.05)
            feed.poll_image()
            live = firmware_liveness(directory, args.board)
            title = (f"board {args.board} in {directory}: firmware pid {live.pid}" if live.alive
                     else f"board {args.board} in {directory}: firmware DEAD (last pid "
                          f"{live.pid})")
            Console().print(snapshot(model, time.time(), title))
            return 0 if live.alive else 3
        from host_api.top.app import TopApp  # Textual's import cost only for the live view

        TopApp(model, feed, args.board, directory, args.interval).run()
        return 0
    finally:
        feed.stop()
