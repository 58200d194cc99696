"""cifemu send: one CAN frame or one NMT command onto the card's bus, as cansend does.

    cifemu send 123#DEADBEEF        11-bit identifier, data bytes in hex (dots allowed)
    cifemu send 1F334455#1122       29-bit identifier (8 hex digits)
    cifemu send 123#R / 123#R4      remote frame (with its DLC)
    cifemu send --nmt start 5       NMT start to node 5 (0: every node)

A frame goes through the card with COM_Send_CANMsg_Transparent (seed 5.2.10, its CAN 2.0B
form, which carries both identifier lengths): the card sends it on its bus as given and
answers, so a frame it could not send is reported. An NMT command goes with
COM_NMT_Module_Protocol (seed 5.2.9), which the card answers once it sent it; the card
takes it only while it runs a network.
"""

from __future__ import annotations

import argparse
import re
from typing import TYPE_CHECKING

from cifemu.cli_options import add_card_options
from cifemu.cli_output import fail
from dpm.cia301 import NODE_ID_MAX
from dpm.commands import COM_NMT_MODULE_PROTOCOL, COM_SEND_CANMSG_TRANSPARENT, Nmt
from dpm.errors import CanF, Drv
from host_api.next_steps import card_options

if TYPE_CHECKING:
    from dpm.com import CanFrame

COMMAND = "send"
NMT_WORDS = {"start": Nmt.START, "stop": Nmt.STOP, "preop": Nmt.PREOPERATIONAL,
             "reset": Nmt.RESET_NODE, "reset-comm": Nmt.RESET_COMMUNICATION}
"""The NMT commands by the words cocomm and 309-3 use for them."""
FRAME = re.compile(r"^(?P<id>[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#"
                   r"(?:(?P<rtr>[Rr])(?P<dlc>[0-8])?|(?P<data>(?:[0-9A-Fa-f]{2}\.?){0,8}))$")
"""cansend's frame syntax (can-utils lib.c): 3 hex digits an 11-bit identifier, 8 a
29-bit one; ``R`` with an optional DLC a remote frame."""


class FrameSyntaxError(ValueError):
    """A frame that is not in cansend's syntax; the text says what is wrong."""


def parse_frame(text: str) -> CanFrame:
    """A frame in cansend's syntax, e.g. ``123#DEADBEEF``, ``1F334455#11.22``, ``123#R2``."""
    from dpm.com import CanFrame  # after parsing: --help needs no codec

    match = FRAME.match(text)
    if match is None or (match["data"] or "").endswith("."):
        raise FrameSyntaxError(
            f"{text!r} is no frame: <id>#<data> with a 3-digit (11-bit) or 8-digit (29-bit) "
            "hex identifier and up to 8 hex bytes (123#DEADBEEF), or <id>#R[len] for a "
            "remote frame")
    extended = len(match["id"]) == 8
    ident = int(match["id"], 16)
    if ident > (0x1FFFFFFF if extended else 0x7FF):
        raise FrameSyntaxError(f"{text!r}: identifier {match['id']} out of range "
                               f"(0..{'1FFFFFFF' if extended else '7FF'})")
    if match["rtr"]:
        return CanFrame(ident, b"", True, int(match["dlc"] or 0), extended)
    return CanFrame(ident, bytes.fromhex(match["data"].replace(".", "")), extended=extended)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("frame", nargs="?", metavar="ID#DATA",
                        help="the frame, in cansend's syntax (123#DEADBEEF, 1F334455#R)")
    parser.add_argument("--nmt", nargs=2, metavar=("COMMAND", "NODE"),
                        help=f"an NMT command ({', '.join(NMT_WORDS)}) to a node 1..127, "
                             "0 for every node, instead of a frame")
    add_card_options(parser)


def request(args: argparse.Namespace) -> tuple[int, bytes, str]:
    """msg.b, the data and how the end line names what was sent; raises FrameSyntaxError."""
    from dpm.com import NmtRequest, encode_transparent_2b

    if args.nmt is None:
        if args.frame is None:
            raise FrameSyntaxError("give a frame (cifemu send 123#DEADBEEF) or --nmt COMMAND "
                                   "NODE")
        frame = parse_frame(args.frame)
        return COM_SEND_CANMSG_TRANSPARENT, encode_transparent_2b(frame), args.frame.upper()
    if args.frame is not None:
        raise FrameSyntaxError("a frame or --nmt, not both")
    word, node = args.nmt
    if word not in NMT_WORDS:
        raise FrameSyntaxError(f"NMT command {word!r}: one of {', '.join(NMT_WORDS)}")
    if not node.isdigit() or int(node) > NODE_ID_MAX:
        raise FrameSyntaxError(f"NMT node {node!r}: 1..127, or 0 for every node")
    target = f"node {int(node)}" if int(node) else "every node"
    return (COM_NMT_MODULE_PROTOCOL, NmtRequest(NMT_WORDS[word], int(node)).encode(),
            f"NMT {word} to {target}")


def run(args: argparse.Namespace) -> int:
    from dpm.message import Message, Task
    from host_api.board import Board, CifError

    options = card_options(args.board, args.dpm_dir)
    try:
        b, data, what = request(args)
    except FrameSyntaxError as exc:
        return fail(COMMAND, str(exc), False, code=2)
    try:
        with Board(args.board, args.dpm_dir) as board:
            answer = board.transact(Message(rx=Task.CAN, tx=Task.USER, b=b, data=data))
    except CifError as exc:
        hint = (f"; is `cifemu firmware{options}` running?"
                if exc.code in (Drv.DRV_USR_DEV_NUMBER_INVALID, Drv.DRV_DEV_NOT_READY) else "")
        return fail(COMMAND, f"board {args.board}: {exc}{hint}", False)
    if answer.f:
        step = (f"; the card runs no network: `cifemu configure NETWORK.toml{options}` or "
                f"`cifemu dbm download NET.dbm --reset{options}` first"
                if answer.f == CanF.NOT_CONFIGURED else "")
        return fail(COMMAND, f"board {args.board}: {what} refused: msg.f = {answer.f} "
                    f"({CanF.text_of(answer.f)}){step}", False)
    print(f"board {args.board}: sent {what}")
    return 0
