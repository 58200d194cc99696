"""cifemu fault: make a running card misbehave on purpose, and end it [ours].

Each fault is one the card itself has, not one of its nodes (a node's faults are in the
network description's `[node.sim]`). Each ends by itself after its time, on
`cifemu fault clear`, or when the firmware ends; none touches the stored database.
docs/faults.md says what a real card would show in the same situation.
"""

from __future__ import annotations

import argparse
import textwrap

from cifemu.cli_options import add_card_options
from cifemu.cli_output import fail, print_json
from dpm.faults import BUS_OFF, CLEAR, DIE, FLIP, KINDS, LIST, RCS_ERROR, SLOW, STALL, WATCHDOG
from dpm.image import MAX_DEV_BOARDS

COMMAND = "fault"

DESCRIPTION = (__doc__ or "") + "\nKinds:\n" + "".join(
    textwrap.fill(text, width=88, initial_indent=f"  {kind:10} ", subsequent_indent=" " * 13)
    + "\n" for kind, text in KINDS.items()) + (
    "  clear      end every fault now (a hanging card comes back by a cold start)\n"
    "  list       show the faults in force\n\n"
    "Examples: cifemu fault stall 500; cifemu fault flip 0 3 --for 2000; "
    "cifemu fault --board 1 clear")

_ARGUMENTS: dict[str, list[tuple[str, str]]] = {
    RCS_ERROR: [("code", "the RCS error number, 1..255 (a host's DevInitBoard of a card "
                         "without READY gives 1000 + CODE for 1..249)")],
    STALL: [("ms", "how long the card takes no message, ms")],
    SLOW: [("delay_ms", "how late each answer comes, ms")],
    FLIP: [("offset", "the input byte, 0..3583 of RcvPd"), ("bit", "the bit, 0..7")],
    BUS_OFF: [("ms", "how long the controller stays off the bus, ms")],
}
_DURATION = (WATCHDOG, RCS_ERROR, SLOW, FLIP, DIE)
"""Kinds that take ``--for MS``; ``stall`` and ``bus-off`` take their length as argument."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_card_options(parser)
    parser.add_argument("--json", action="store_true",
                        help="print the faults in force as one JSON object")
    kinds = parser.add_subparsers(dest="kind", required=True, metavar="KIND")
    for kind, text in [*KINDS.items(), (CLEAR, "end every fault now"),
                       (LIST, "show the faults in force")]:
        sub = kinds.add_parser(kind, help=text, description=text)
        for name, what in _ARGUMENTS.get(kind, []):
            sub.add_argument(name, type=int, metavar=name.upper(), help=what)
        if kind in _DURATION:
            sub.add_argument("--for", dest="for_ms", type=int, default=None, metavar="MS",
                             help="end the fault after MS ms (default: on `cifemu fault "
                                  "clear`" + ("; without it the flip is for one exchange)"
                                              if kind == FLIP else ")"))
        if kind == DIE:
            sub.add_argument("--hang", action="store_true",
                             help="keep the process: it serves nothing until the fault ends, "
                                  "then comes back through a cold start (default: it exits "
                                  "with status 70)")
        # also after the kind: `cifemu fault stall 500 --board 1`
        sub.add_argument("--board", type=int, default=argparse.SUPPRESS, metavar="N",
                         choices=range(MAX_DEV_BOARDS), help=argparse.SUPPRESS)
        sub.add_argument("--dpm-dir", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
        sub.add_argument("--json", action="store_true", default=argparse.SUPPRESS,
                         help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    from dpm.faults import FaultRequest, FaultRequestError  # after parsing: --help stays light
    from host_api.faults import FaultError, send

    try:
        request = FaultRequest(
            args.kind, for_ms=args.ms if args.kind in (STALL, BUS_OFF)
            else getattr(args, "for_ms", None), code=getattr(args, "code", 0),
            delay_ms=getattr(args, "delay_ms", 0), offset=getattr(args, "offset", 0),
            bit=getattr(args, "bit", 0), hang=getattr(args, "hang", False))
        active = send(request, args.board, args.dpm_dir)
    except (FaultRequestError, FaultError) as exc:
        return fail(COMMAND, f"{args.kind}: {exc}", args.json)
    if args.json:
        print_json({"board": args.board, "active": [fault.as_json() for fault in active]})
    elif not active:
        print(f"board {args.board}: no fault in force")
    else:
        for fault in active:
            print(f"board {args.board}: in force: {fault.describe()}")
    return 0
