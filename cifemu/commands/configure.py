"""cifemu configure: configure a running card on line from a network description.

Sends every node's parameter set, the extended bus parameters and the bus
parameters to the CAN task (COM_Start_Seq / COM_Download / COM_End_Seq, seed
chapter 7), then waits until every configured node is in data exchange
(Nd_state) or the card reports an error (Err_Event), and watches a supervised
network one supervision period longer: a node that refuses OPERATIONAL after its
start is an error, not a success. Nothing is stored in the
card's flash: a reset forgets this configuration (use `cifemu dbm download`
for one that survives).

A refusal is shown with the CAN task's msg.f number and the manual's text for
it; a card error with its Err_Event number and text.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cifemu.cli_options import add_card_options
from cifemu.cli_output import fail, print_json
from dbm_tools.builder import BuildError, build_dbm
from dbm_tools.network import Network, NetworkError, load_network
from dbm_tools.validate import check_dbm
from dpm.errors import ERR_NODE_DEVICE, CanF, Drv
from dpm.image import dpm_dir
from dpm.task2 import ComDiagnostics
from host_api.board import Board, CifError
from host_api.liveness import firmware_liveness
from host_api.network_view import remember_network
from host_api.next_steps import configure_refusal
from host_api.online import ConfigurationError, configure_online

COMMAND = "configure"
POLL_S = 0.05
START_WAIT_S = 10.0
"""How long a card whose firmware runs may take to come up READY (a start from flash,
``--reset-delay``)."""
SETTLE_S = 1.0
"""[ours] How long, beyond the longest supervision period of the network, configure keeps
watching once every node is in Nd_state. The card sets a node's bit as soon as it has
started it; only the node's next heartbeat or guarding answer tells whether it runs (a
node may stay PRE-OPERATIONAL: CANopenNode's devices do while their error register is
set), and the card gives a started node half a second before it counts that as Err_Event
31. One period plus this covers both."""


def msg_f_text(f: int) -> str:
    """The manual's text of a CAN-task msg.f number (the one place this module looks it up)."""
    return CanF.text_of(f)


def supervision_s(network: Network) -> float:
    """The longest time the card may take to learn that an active node stopped: its
    heartbeat consumer time, or guard time times life time factor; 0 when none is
    supervised (the builder's usGuardTime and bLifeTimeFactor, seed 5.2.6)."""
    periods = [0.0]
    for node in network.nodes:
        if not node.active:
            continue
        if node.error_control == "heartbeat":
            periods.append(node.heartbeat_ms / 1000.0)
        elif node.error_control == "guarding":
            periods.append(node.guard_time_ms * max(1, node.life_time_factor) / 1000.0)
    return max(periods)


def wait_for_network(board: Board, nodes: list[int], timeout_s: float,
                     progress: Callable[[str], None], settle_s: float = 0.0) -> ComDiagnostics:
    """Poll Task2State until every node has been in Nd_state for ``settle_s``, an
    Err_Event shows, or ``timeout_s`` passes before every node got there."""
    deadline = time.monotonic() + timeout_s
    seen: set[int] = set()
    all_since: float | None = None
    while True:
        diag = board.diagnostics()
        running = set(diag.operating())
        for node in sorted((running & set(nodes)) - seen):
            progress(f"node {node} in data exchange")
        seen |= running
        now = time.monotonic()
        if not set(nodes) <= running:
            all_since = None
        elif all_since is None:
            all_since = now
        if diag.bErr_event or (all_since is not None and now - all_since >= settle_s):
            return diag
        if all_since is None and now >= deadline:
            return diag
        time.sleep(POLL_S)


def open_when_ready(board: int, directory: str | None, wait_s: float) -> Board:
    """The board, opened (the caller closes it); a firmware that holds its lock but is
    still starting (no identifier or no READY yet) is given ``wait_s`` to come up."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            return Board(board, directory).open()
        except CifError as exc:
            starting = exc.code in (Drv.DRV_DEV_DPM_ACCESS_ERROR, Drv.DRV_DEV_NOT_READY)
            if (not starting or time.monotonic() >= deadline
                    or not firmware_liveness(dpm_dir(directory), board).alive):
                raise
        time.sleep(POLL_S)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("network", type=Path, metavar="NETWORK.toml",
                        help="the network description (the same file `cifemu sim` and "
                             "`cifemu dbm build` read)")
    add_card_options(parser)
    parser.add_argument("--wait", type=float, default=10.0, metavar="SECONDS",
                        help="how long to wait for the nodes to reach data exchange "
                             "(default 10; 0 does not wait)")
    parser.add_argument("--json", action="store_true",
                        help="print the outcome as one JSON object")


def _result(diag: ComDiagnostics, nodes: list[int]) -> dict[str, Any]:
    running = diag.operating()
    return {
        "nodes": nodes,
        "nd_state": running,
        "missing": [n for n in nodes if n not in running],
        "can_state": diag.can_state_name,
        "err_node_adr": diag.bErr_rem_adr,
        "err_event": diag.bErr_event,
        "err_text": diag.err_text if diag.bErr_event else "",
    }


def configure(board: Board, network: Network, wait_s: float,
              progress: Callable[[str], None]) -> dict[str, Any]:
    """Configure on line and (for ``wait_s`` > 0) wait for the network; the outcome.

    A card that holds a configuration already is warm-started first: the seed's card
    takes a network's data sets once per start, and a second set for a node is f 60. A
    database from flash comes back with that start and refuses the download (f 201).
    """
    held = board.diagnostics()
    if held.configured() or held.can_state_name != "OFFLINE":
        progress("the card holds a configuration: warm start first")
        board.reset()
    configure_online(board, network, progress)
    if network.path is not None:
        remember_network(dpm_dir(board.directory), board.number, network.path)
    nodes = [node.id for node in network.nodes if node.active]
    if wait_s <= 0:
        return _result(board.diagnostics(), nodes) | {"missing": []}
    supervised = supervision_s(network)
    settle = supervised + SETTLE_S if supervised else 0.0
    return _result(wait_for_network(board, nodes, wait_s, progress, settle), nodes)


def run(args: argparse.Namespace) -> int:
    try:
        network = load_network(args.network)
        warnings = check_dbm(build_dbm(network))  # one the card would refuse never reaches it
    except (NetworkError, BuildError, OSError) as exc:
        return fail(COMMAND, f"{args.network}: {exc}", args.json)
    for finding in warnings:  # e.g. SYNC_Timer without a synchronous PDO: no SYNC at all
        print(f"cifemu {COMMAND}: warning: {finding.detail}", file=sys.stderr)
    progress: Callable[[str], None] = (
        (lambda text: None) if args.json else (lambda text: print(f"configuring: {text}")))
    try:
        board = open_when_ready(args.board, args.dpm_dir, START_WAIT_S)
        try:
            outcome = configure(board, network, args.wait, progress)
        finally:
            board.close()
    except CifError as exc:
        hint = (f"; is `cifemu firmware --board {args.board}` running?"
                if exc.name in ("DRV_USR_DEV_NUMBER_INVALID", "DRV_DEV_NOT_READY") else "")
        return fail(COMMAND, f"board {args.board}: {exc}{hint}", args.json, code=1,
                    driver_code=exc.code, driver_name=exc.name)
    except ConfigurationError as exc:
        step = configure_refusal(exc.f, str(args.network), args.board, args.dpm_dir)
        return fail(COMMAND, f"{exc} ({msg_f_text(exc.f)}); {step}", args.json, msg_f=exc.f,
                    msg_f_text=msg_f_text(exc.f), next_step=step)
    ok = not outcome["missing"] and not outcome["err_event"]
    if args.json:
        print_json({"board": args.board, "network": str(args.network), "ok": ok, **outcome})
    elif ok:
        print(f"board {args.board}: {len(outcome['nodes'])} node(s) configured, "
              f"CAN_state {outcome['can_state']}")
    else:
        where = ("device" if outcome["err_node_adr"] == ERR_NODE_DEVICE
                 else f"node {outcome['err_node_adr']}")
        # The wait ends at the first Err_Event: "after N s" only when it ran out.
        when = (f"Err_Event {outcome['err_event']} at {where}: {outcome['err_text']}"
                if outcome["err_event"] else f"after {args.wait:g} s, no Err_Event")
        print(f"board {args.board}: configured, but node(s) {outcome['missing']} not in "
              f"data exchange ({when})")
    return 0 if ok else 1
