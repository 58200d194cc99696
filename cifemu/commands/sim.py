"""cifemu sim: the simulated nodes of a network description alone on a CAN bus.

For a bus shared with another process (shm, SocketCAN, vcan, any
python-can interface that crosses processes). Runs in the foreground until SIGTERM or
Ctrl-C; prints each node it simulates.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
from typing import Any

import can

from cifemu.cli_output import fail
from dbm_tools.bus_options import BusOptionError, add_bus_arguments, select_bus, with_options
from dbm_tools.network import Network, NetworkError, NodeDescription, load_network
from firmware.interpreter import SWITCH_INTERVAL
from firmware.sim.network import SimulatedNetwork


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("network", metavar="NETWORK.toml", help="the network description")
    parser.add_argument("--interface", default=None,
                        help="python-can interface that crosses processes: shm (cifemu's "
                             "shared-memory bus), socketcan, udp_multicast ... (required, "
                             "here, in --bus-config or in the description's [bus])")
    parser.add_argument("--channel", default=None,
                        help="python-can channel, e.g. the card's shm channel or vcan0 "
                             "(required, here, in --bus-config or in the description's "
                             "[bus])")
    add_bus_arguments(parser)
    parser.add_argument("--bitrate", type=int, default=None, metavar="BPS",
                        help="bit rate (default: the description's bus.bitrate)")
    parser.add_argument("--log-level", default="INFO",
                        choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    parser.add_argument("--json", action="store_true",
                        help="announce the powered nodes as one JSON line (and errors as a "
                             "JSON object)")


def describe(node: NodeDescription) -> str:
    """One line per node, as the operator needs it to match the bus against the file."""
    if node.lss is not None and node.id == 255:
        lss = node.lss
        return (f"LSS slave {lss.vendor:#x}/{lss.product:#x}/{lss.revision:#x}/{lss.serial:#x}: "
                "unconfigured, waits for an LSS master")
    kind = f"EDS {node.eds.name}" if node.eds else "generic I/O module"
    name = f" {node.name!r}" if node.name else ""
    control = node.error_control
    if control == "heartbeat" and not node.eds:
        control = f"heartbeat {node.heartbeat_ms // 2} ms"
    sim = node.sim
    faults = []
    if sim.silent:
        faults.append("silent")
    if sim.device_type is not None:
        faults.append(f"device type {sim.device_type:#010x}")
    if sim.sdo_abort:
        faults.append(f"SDO aborts on {len(sim.sdo_abort)} object(s)")
    if sim.heartbeat_stop_after_s is not None:
        faults.append(f"heartbeat stops after {sim.heartbeat_stop_after_s} s")
    if sim.guarding_fail_after_s is not None:
        faults.append(f"guarding fails after {sim.guarding_fail_after_s} s")
    if sim.guard_toggle_stuck:
        faults.append("guarding toggle bit stuck")
    if sim.sdo_response == "unknown":
        faults.append("SDO responses with command byte 0xe0")
    elif sim.sdo_response == "short":
        faults.append("SDO responses of 4 bytes")
    if sim.emcy_burst is not None:
        faults.append(f"{sim.emcy_burst.count} EMCY {sim.emcy_burst.code:#06x} "
                      f"after {sim.emcy_burst.after_s} s")
    if sim.boot_delay_s:
        faults.append(f"boot-up after {sim.boot_delay_s} s")
    if sim.no_bootup:
        faults.append("no boot-up message")
    if sim.leave_operational_after_s is not None:
        faults.append(f"leaves OPERATIONAL after {sim.leave_operational_after_s} s")
    text = f"node {node.id}{name}: {kind}, {control}"
    return text + (f"; faults: {', '.join(faults)}" if faults else "")


def run(args: argparse.Namespace) -> int:
    sys.setswitchinterval(SWITCH_INTERVAL)  # as the firmware: many threads, short turns
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s: %(message)s")
    if args.log_level != "DEBUG":
        logging.getLogger("canopen").setLevel(logging.WARNING)  # it logs every SDO at INFO
    try:
        network = load_network(args.network)
    except NetworkError as exc:
        return fail("sim", str(exc), args.json)
    try:
        selected = select_bus(args.interface, args.channel, args.bitrate, args.bus_option,
                              args.bus_config, network.bus)
    except BusOptionError as exc:
        return fail("sim", str(exc), args.json)
    if selected.interface is None or selected.channel is None:
        return fail("sim", "give --interface and --channel (or a --bus-config, or the "
                           "description's [bus] interface and channel, that names them)",
                    args.json)
    args.interface, args.channel = selected.interface, selected.channel
    bitrate = selected.bitrate or network.bus.bitrate
    if args.interface == "virtual":
        # [ours] warned, not refused: the run harms nothing, and the line names what works.
        print("cifemu sim: warning: python-can's virtual bus lives in this process only: no "
              "card, monitor or candump outside it reaches these nodes; use --interface shm "
              f"--channel {args.channel} (and `cifemu firmware --interface shm --channel "
              f"{args.channel}`)", file=sys.stderr, flush=True)
    # SIGTERM and SIGINT are taken by sigwait below, never by a handler: a handler that
    # set an Event could interrupt the main thread inside that Event's own wait, holding its
    # lock, and deadlock (a sim that ignored SIGTERM for good). Blocked before the bus and
    # the nodes start their threads, which inherit the mask.
    stop_signals = {signal.SIGTERM, signal.SIGINT}
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, stop_signals)
    try:
        return _simulate(args, network, bitrate, selected.options, stop_signals)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # run in-process: as it was


def _simulate(args: argparse.Namespace, network: Network, bitrate: int,
              options: dict[str, Any], stop_signals: set[signal.Signals]) -> int:
    try:
        bus = can.Bus(interface=args.interface, channel=args.channel, bitrate=bitrate, **options)
    except (can.CanError, OSError, ValueError, ImportError, TypeError) as exc:
        return fail("sim", f"cannot open {args.interface} channel {args.channel}"
                           f"{with_options(options)}: {exc}", args.json)
    try:
        with SimulatedNetwork(network, bus):
            # Printed once the nodes are powered: a script may wait for the first line.
            if args.json:
                print(json.dumps({"network": str(args.network), "interface": args.interface,
                                  "channel": args.channel, "bitrate": bitrate,
                                  "nodes": [{"id": node.id, "description": describe(node)}
                                            for node in network.nodes]}), flush=True)
            else:
                print(f"simulating {args.network} on {args.interface} {args.channel} "
                      f"at {bitrate} bit/s", flush=True)
                for node in network.nodes:
                    print(f"  {describe(node)}", flush=True)
            signal.sigwait(stop_signals)
    finally:
        bus.shutdown()
    return 0

