"""cifemu reset: restart a running card, as SyCon's "Reset device" does.

DevReset with COLDSTART (--cold, the default), WARMSTART (--warm) or BOOTSTART (--boot),
then the card's own signs that it is back: READY, and RUN where a database is stored in
its flash (the card starts it). A cold start also forgets the host's protocol parameters
(Task2Parameter); a warm start keeps them (seed chapter 2). Either start forgets an
on-line configuration (`cifemu configure`), which lives only until the next start.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from cifemu.cli_options import add_card_options
from cifemu.cli_output import fail, print_json
from dpm.errors import Drv
from dpm.flags import COM, READY, RUN
from host_api.next_steps import card_options

if TYPE_CHECKING:
    from host_api.board import Board

COMMAND = "reset"
RESET_TIMEOUT_MS = 10_000
"""How long DevReset may take to see READY again (a card started with --reset-delay)."""
RUN_WAIT_S = 5.0
"""[ours] How long a card with a stored database is given to start it (RUN) after READY."""
POLL_S = 0.02
STARTS = ("cold", "warm", "boot")
"""The DevReset modes (COLDSTART, WARMSTART, BOOTSTART) by the option that chooses them."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    kind = parser.add_mutually_exclusive_group()
    for name in STARTS:
        kind.add_argument(f"--{name}", dest="start", action="store_const", const=name,
                          help=f"DevReset {name.upper()}START"
                          + (" (the default)" if name == "cold" else ""))
    parser.set_defaults(start="cold")
    add_card_options(parser)
    parser.add_argument("--json", action="store_true",
                        help="print the outcome as one JSON object")


def flag_names(flags: int) -> list[str]:
    return [name for name, bit in (("READY", READY), ("RUN", RUN), ("COM", COM)) if flags & bit]


def host_flags(board: Board) -> int:
    """bHostFlags as the driver reads it (DRIVERINFO)."""
    from host_api.driver import DRIVERINFO, GET_DRIVER_INFO

    return int(DRIVERINFO.unpack(board.info(GET_DRIVER_INFO, DRIVERINFO.size))[11])


def restart(board: Board, start: str, progress: Callable[[str], None]) -> dict[str, object]:
    """Reset the card and wait for it to come back; what it shows then."""
    from host_api.download import flash_directory
    from host_api.driver import BOOTSTART, COLDSTART, WARMSTART

    code, entries = flash_directory(board.number)
    stored = code == Drv.DRV_NO_ERROR and bool(entries)
    progress(f"{start} start (DevReset {start.upper()}START)")
    board.reset({"cold": COLDSTART, "warm": WARMSTART, "boot": BOOTSTART}[start],
                RESET_TIMEOUT_MS)
    progress("READY")
    flags = host_flags(board)
    if stored:
        progress("a database is stored in the flash: waiting for RUN")
        deadline = time.monotonic() + RUN_WAIT_S
        while not flags & RUN and time.monotonic() < deadline:
            time.sleep(POLL_S)
            flags = host_flags(board)
    return {"start": start, "database_stored": stored, "flags": flag_names(flags),
            "run": bool(flags & RUN)}


def end_line(number: int, outcome: dict[str, object], options: str) -> str:
    flags = " ".join(outcome["flags"])  # type: ignore[arg-type]
    head = f"board {number}: {outcome['start']} start done, {flags}"
    if outcome["database_stored"] and outcome["run"]:
        return f"{head}: the database from the flash runs"
    if outcome["database_stored"]:
        return (f"{head}: the database from the flash did not start (RUN missing); "
                f"`cifemu status{options}` shows the card's Err_Event")
    return (f"{head}: no database stored, the card waits for an on-line configuration "
            f"(`cifemu configure NETWORK.toml{options}`)")


def run(args: argparse.Namespace) -> int:
    from host_api.board import Board, CifError  # after parsing: --help needs no driver

    options = card_options(args.board, args.dpm_dir)
    progress: Callable[[str], None] = (
        (lambda text: None) if args.json
        else (lambda text: print(f"board {args.board}: {text}", flush=True)))
    try:
        with Board(args.board, args.dpm_dir) as board:
            outcome = restart(board, args.start, progress)
    except CifError as exc:
        hint = (f"; is `cifemu firmware{options}` running?"
                if exc.code in (Drv.DRV_USR_DEV_NUMBER_INVALID, Drv.DRV_DEV_NOT_READY,
                                Drv.DRV_DEV_RESET_TIMEOUT) else "")
        return fail(COMMAND, f"board {args.board}: {exc}{hint}", args.json,
                    driver_code=exc.code, driver_name=exc.name)
    if args.json:
        print_json({"board": args.board, **outcome})
    else:
        print(end_line(args.board, outcome, options))
    return 0 if outcome["run"] or not outcome["database_stored"] else 1
