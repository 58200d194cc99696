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

from cifemu.cli_options import add_card_options
from cifemu.cli_output import fail, print_json
from dpm.image import dpm_dir, image_path

EXIT_OK = 0
EXIT_DEAD = 3
"""[ours] the image is there but no firmware holds its lock (killed, crashed, stopped)."""


GUIDE = """\
How to read the screen (the card's names, spelt as in its manual and driver):

HostFlags, DevFlags
  The image's last two bytes. HostFlags are written by the card for the host,
  DevFlags by the host for the card. A flag in CAPITALS is set, in lower case
  it is clear.
  READY     the card's firmware is alive (clear while it starts or is down)
  RUN       the card holds a configuration (from its flash or sent on line)
  COM       the card communicates on the bus: the network runs
  NOTREADY  (host) the host is not ready: the card halts the bus, zeroes outputs
  INIT      (host) warm start requested; RESET: cold start requested
  HOSTCOM/HOSTACK   card-to-host mailbox: a message waits while the two differ
  DEVCOM/DEVACK     host-to-card mailbox: full while the two differ
  PDCOM/PDACK       process-data handshake; STATECOM/STATEACK: the state field
  SPCCOM/SPCACK     special control, a level the card mirrors

Task2State, the card's view of the network (one bit per node-ID in Nd_*)
  CAN_state  OFFLINE: not configured, no bus traffic. STOP: configured, but
             the network is halted (host not ready, host watchdog). CLEAR:
             auto-clear stopped every node after one was lost. OPERATE: the
             network runs.
  Nd_cfg     nodes configured in the master (listed by node-ID)
  Nd_state   nodes in data exchange (OPERATIONAL, PDOs flowing) whose guarding
             or heartbeat reports no error; valid only in OPERATE
  Nd_diag    nodes with diagnostics waiting (an error or an EMCY): the host
             reads them with COM_Node_Diag (msg.b 66)
  error      Err_Event at Err_Node_adr (device = the card itself), e.g. 30
             guarding (or heartbeat) failed, 31 the node left OPERATIONAL, 34 no answer while
             configuring it, 35/36 profile/device type (1000h) differs, 212
             faulty database, 220 host watchdog expired
  global bits  CTRL parameter error, ACLR auto-clear, NEXC a node not in data
             exchange, FAT fatal, EVE bus errors, NRDY host not ready, TOUT a
             frame could not be sent

Common msg.f numbers (the error in a mailbox answer; DevDownload: 1000 + f)
  0 no error            3 SDO abort by the node     17 node does not answer
  19 node still booting 20 no such node configured  21 parameter fault
  54 busy (one SDO per node at a time)              55 faulty parameter
  57 sequence error     60..76 data checks of a configuration
  152 unknown command   200 card not configured (the network does not run)

The full reference: docs/dpm.md sections 1, 2 and 5.
"""
"""``--help``'s guide to the screen; the model and its rendering (``host_api.status``) load
only when the command runs, so ``--help`` costs no numpy or Rich."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = GUIDE
    add_card_options(parser)
    parser.add_argument("--watch", action="store_true", help="refresh until Ctrl-C")
    parser.add_argument("--interval", type=float, default=0.5, metavar="SECONDS",
                        help="--watch refresh seconds")
    parser.add_argument("--json", action="store_true", help="print the decoded state as JSON")


def _full_snapshot(image: bytes, directory: Path, board: int) -> dict[str, Any]:
    from host_api.status import error_controls, health, snapshot

    return {"board": board, **snapshot(image, error_controls(directory, board)),
            "health": health(directory, board)}


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.live import Live

    from host_api.status import read_image, render

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

