"""cifemu: one command for the emulated CIF CANopen master card.

Every command is one row of ``COMMANDS``: its name, the module that implements it and a
one-line summary. A command's module is ``cifemu.commands.<name>`` and gives
``add_arguments(parser)`` and ``run(args)``; its ``DESCRIPTION``, else its docstring, is
the command's ``--help`` text, without the ``[ours]`` markers that are for the
project's documents, not for a user. Only the
chosen command's module is imported: ``cifemu status`` does not pay for the DBM builder,
canopen or Textual, and ``cifemu --help`` imports none of them.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from dataclasses import dataclass
from types import ModuleType


@dataclass(frozen=True)
class Command:
    """One ``cifemu`` command: how it is called, where it lives, what it does."""

    name: str
    module: str
    summary: str

    def load(self) -> ModuleType:
        return importlib.import_module(self.module)


COMMANDS = (
    Command("firmware", "cifemu.commands.firmware", "run one emulated card in the foreground"),
    Command("sim", "cifemu.commands.sim", "run a network description's simulated nodes on a bus"),
    Command("status", "cifemu.commands.status", "show a card's flags, info areas and Task2State"),
    Command("configure", "cifemu.commands.configure",
            "configure a running card on line from a network description"),
    Command("dbm", "cifemu.commands.dbm",
            "DBM files (show, check, build, diff) and a card's flash (download, upload, ...)"),
    Command("reset", "cifemu.commands.reset",
            "restart a running card (cold, warm or boot start), as SyCon's Reset device"),
    Command("send", "cifemu.commands.send",
            "send one CAN frame or NMT command on the card's bus, as cansend"),
    Command("monitor", "cifemu.commands.monitor", "the CAN traffic with its CANopen meaning, live"),
    Command("top", "cifemu.commands.top", "a live view of one card: nodes, process image, bus"),
    Command("309", "cifemu.commands.cia309", "the CiA 309-3 ASCII gateway (serve, exec, shell)"),
    Command("libcif", "cifemu.commands.libcif",
            "compiler and linker flags for C programs (libcif)"),
    Command("legacy", "cifemu.commands.legacy",
            "run an unchanged legacy binary against the card (/dev/cif preloaded)"),
    Command("record", "cifemu.commands.record",
            "attach to a running card and record a session until Ctrl-C"),
    Command("replay", "cifemu.commands.replay",
            "replay a recorded session against a card and show what differs (or --diff A B)"),
    Command("fault", "cifemu.commands.fault",
            "make a running card misbehave on purpose (watchdog, mailbox, bus-off ...)"),
    Command("demo", "cifemu.commands.demo",
            "a card, a simulated network, its live view (Ctrl-C ends)"),
)
"""The commands, in the order ``cifemu --help`` lists them."""


def build_parser(chosen: str | None = None) -> argparse.ArgumentParser:
    """The parser; the options of ``chosen`` only (None: of every command, for tools that
    walk all help texts)."""
    parser = argparse.ArgumentParser(
        prog="cifemu", description="One command for the emulated CIF CANopen master card.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        if chosen is not None and command.name != chosen:
            sub.add_parser(command.name, help=command.summary)
            continue
        module = command.load()
        description = getattr(module, "DESCRIPTION", module.__doc__) or ""
        sub_parser = sub.add_parser(command.name, help=command.summary,
                                    description=description.replace(" [ours]", ""),
                                    formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(sub_parser)
        sub_parser.set_defaults(func=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    words = sys.argv[1:] if argv is None else argv
    # the command is the first word: ``cifemu`` itself takes no option but --help
    chosen = words[0] if words and words[0] in {c.name for c in COMMANDS} else ""
    parser = build_parser(chosen)
    if any("\0" in word for word in words):
        # no shell can pass a NUL byte, but a Python caller can: every file name and value
        # would fail later, deep in a command, with a bare ValueError
        parser.error("an argument holds a NUL byte, which no file name or value may contain")
    args = parser.parse_args(words)
    from cifemu.cli_output import run_guarded  # after parsing: --help imports nothing

    result: int = run_guarded(args.func, args)
    return result
