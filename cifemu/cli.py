"""cifemu: one command for the emulated CIF CANopen master card.

  cifemu firmware   run one emulated card in the foreground
  cifemu sim        run a network description's simulated nodes on a CAN bus
  cifemu status     show a card's flags, info areas and Task2State
  cifemu dbm        DBM files (show, check, build, diff) and a card's stored database
                    (download, upload, delete, dir)
  cifemu demo       a card, a simulated network, on-line configuration, live status
  cifemu configure  configure a running card on line from a network description
  cifemu monitor    the CAN traffic with its CANopen meaning, live
  cifemu top        a live view of one card: nodes, process image, bus, events
  cifemu 309        the CiA 309-3 ASCII gateway (serve, exec, shell)
  cifemu libcif     flags that compile a C program against libcif (--cflags --libs)
  cifemu legacy     run an unchanged legacy binary against the card (/dev/cif preloaded)
"""

from __future__ import annotations

import argparse

from cifemu import demo as demo_cli
from cifemu import libcif as libcif_cli
from firmware import cli as firmware_cli
from firmware.sim import cli as sim_cli
from host_api import configure_cli
from host_api import dbm_commands as dbm_cli
from host_api import legacy as legacy_cli
from host_api import status as status_cli
from host_api.cia309 import cli as cia309_cli
from host_api.cli_output import run_guarded
from host_api.monitor import cli as monitor_cli
from host_api.top import cli as top_cli


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cifemu", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    fw = sub.add_parser("firmware", help="run one emulated card in the foreground",
                        description=firmware_cli.__doc__)
    firmware_cli.add_arguments(fw)
    fw.set_defaults(func=firmware_cli.run)
    sim = sub.add_parser("sim", help="run a network description's simulated nodes on a CAN bus",
                         description=sim_cli.__doc__,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    sim_cli.add_arguments(sim)
    sim.set_defaults(func=sim_cli.run)
    st = sub.add_parser("status", help="show a card's state", description=status_cli.__doc__)
    status_cli.add_arguments(st)
    st.set_defaults(func=status_cli.run)
    dbm = sub.add_parser("dbm", help="DBM files: show, check, build, diff, download, upload",
                         description=dbm_cli.DESCRIPTION,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    dbm_cli.add_arguments(dbm)
    dbm.set_defaults(func=dbm_cli.run)
    cia309 = sub.add_parser("309", help="CiA 309-3 ASCII gateway: serve, exec, shell",
                            description=cia309_cli.__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    cia309_cli.add_arguments(cia309)
    cia309.set_defaults(func=cia309_cli.run)
    libcif = sub.add_parser("libcif", help="compiler and linker flags for C programs (libcif)",
                            description=libcif_cli.__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    libcif_cli.add_arguments(libcif)
    libcif.set_defaults(func=libcif_cli.run)
    legacy = sub.add_parser("legacy", help="run a legacy binary with /dev/cif served by the card",
                            description=legacy_cli.__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    legacy_cli.add_arguments(legacy)
    legacy.set_defaults(func=legacy_cli.run)
    demo = sub.add_parser("demo", help="a card, simulated nodes, live status (Ctrl-C ends)",
                          description=demo_cli.__doc__)
    demo_cli.add_arguments(demo)
    demo.set_defaults(func=demo_cli.run)
    configure = sub.add_parser("configure", help="configure a running card on line from a "
                               "network description", description=configure_cli.__doc__,
                               formatter_class=argparse.RawDescriptionHelpFormatter)
    configure_cli.add_arguments(configure)
    configure.set_defaults(func=configure_cli.run)
    monitor = sub.add_parser("monitor", help="the CAN traffic with its CANopen meaning, live",
                             description=monitor_cli.__doc__,
                             formatter_class=argparse.RawDescriptionHelpFormatter)
    monitor_cli.add_arguments(monitor)
    monitor.set_defaults(func=monitor_cli.run)
    top = sub.add_parser("top", help="a live view of one card (nodes, process image, bus, "
                         "events)", description=top_cli.__doc__,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    top_cli.add_arguments(top)
    top.set_defaults(func=top_cli.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_guarded(args.func, args)
