"""cifemu firmware: run one emulated card in the foreground."""

# What only an option needs is imported when that option is given (docs/testing.md,
# *Start-up*): the --configure host (the DBM builder, host_api's Board), the --simulate
# nodes and the --record recorder. The tests start a firmware some thousand times, many
# of them with none of these options.

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING

import can

from dbm_tools.bus_options import BusOptionError, add_bus_arguments, select_bus, with_options
from dbm_tools.network import Network, NetworkError, load_network
from dpm.faults import DIE_EXIT_STATUS
from dpm.image import (
    DEFAULT_DPM_DIR,
    MAX_DEV_BOARDS,
    BoardBusyError,
    UnsafePathError,
    dpm_dir,
    image_path,
)
from dpm.tap import tap_address
from firmware.can.bus import INTERFACE_ERRORS, BusConfig
from firmware.device import Device
from firmware.flash import FLASH_ENV
from firmware.interpreter import SWITCH_INTERVAL

if TYPE_CHECKING:
    from firmware.sim import SimulatedNetwork


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--board", type=int, default=0, choices=range(MAX_DEV_BOARDS),
                        metavar="N", help="board number 0..3 (default 0)")
    parser.add_argument("--dpm-dir", default=None, metavar="DIR",
                        help=f"directory of the image board<N>.dpm "
                             f"(default $CIF_DPM_DIR or {DEFAULT_DPM_DIR})")
    parser.add_argument("--interface", default=None,
                        help="python-can interface: virtual (default; in this process only), "
                             "shm (cifemu's shared-memory bus: processes on this machine, no "
                             "frame lost unread), socketcan (vcan or real hardware), "
                             "udp_multicast, or any other python-can offers")
    parser.add_argument("--channel", default=None,
                        help="python-can channel (default: 'cifemu' for virtual and shm, vcan0 "
                             "for socketcan, the default group for udp_multicast)")
    add_bus_arguments(parser)
    parser.add_argument("--bitrate", type=int, default=None, metavar="BPS",
                        help="the controller's bit rate until the bus parameters come; their "
                             "Baud_rate then sets it, on interfaces whose rate the card sets "
                             "(not virtual, shm, udp_multicast, or socketcan, whose link rate "
                             "is the kernel's). Default: the interface's own")
    parser.add_argument("--exit-on-bus-error", action="store_true",
                        help="end with one line and exit status 1 when the CAN interface "
                             "cannot be opened; by default the card stays up with FAT set in "
                             "Task2State, as the seed's card does, so hosts see a faulty card")
    parser.add_argument("--trace", type=Path, default=None, metavar="FILE",
                        help="log every frame the card sends or receives; the format follows "
                             "the suffix: .blf, .asc, .log (candump), .csv, .trc ...")
    parser.add_argument("--record", type=Path, default=None, metavar="SESSION",
                        help="record a session from the start into the directory SESSION "
                             "(created; docs/recording.md): every mailbox message, flag "
                             "change, process-data exchange, and every frame in "
                             "SESSION/can.log. `cifemu record` attaches to a running card")
    parser.add_argument("--simulate", type=Path, default=None, metavar="NETWORK.toml",
                        help="also run the simulated nodes of a network description on the "
                             "same bus, in this process; its [bus] interface, channel and "
                             "options apply where the command line gives none")
    parser.add_argument("--flash", type=Path, default=None, metavar="DIR",
                        help="the board's flash directory, where a downloaded DBM is kept "
                             f"(default ${FLASH_ENV}/board<N>, else "
                             "<user data dir>/cifemu/flash/board<N>)")
    parser.add_argument("--configure", nargs="?", const=True, default=None, type=Path,
                        metavar="NETWORK.toml",
                        help="once the card is up, configure it on line from a network "
                             "description (default: the --simulate file), as `cifemu "
                             "configure` does; a refusal stops the card with exit status 1")
    parser.add_argument("--reset-delay", type=float, default=0.0, metavar="SECONDS",
                        help="emulate a real card's slow start (default 0: milliseconds)")
    parser.add_argument("--log-level", default="INFO",
                        choices=["DEBUG", "INFO", "WARNING", "ERROR"])


def run(args: argparse.Namespace) -> int:
    sys.setswitchinterval(SWITCH_INTERVAL)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s: %(message)s")
    if args.log_level != "DEBUG":  # canopen narrates every transfer at INFO
        logging.getLogger("canopen").setLevel(logging.WARNING)
    network = None
    if args.simulate is not None:
        try:
            network = load_network(args.simulate)
        except NetworkError as exc:
            print(f"cifemu firmware: {args.simulate}: {exc}", file=sys.stderr)
            return 1
    configure_path = args.simulate if args.configure is True else args.configure
    if configure_path is None and args.configure is True:
        print("cifemu firmware: --configure needs a network description (or --simulate)",
              file=sys.stderr)
        return 1
    try:
        # The --simulate file's [bus] names the bus below the command line: the simulated
        # nodes and the card share it.
        selected = select_bus(args.interface, args.channel, args.bitrate, args.bus_option,
                              args.bus_config, network.bus if network is not None else None)
    except BusOptionError as exc:
        print(f"cifemu firmware: {exc}", file=sys.stderr)
        return 1
    interface = selected.interface or "virtual"
    return _serve(args, network, configure_path, BusConfig(
        interface, selected.channel or default_channel(interface), selected.bitrate,
        args.trace, tap_address(image_path(dpm_dir(args.dpm_dir), args.board)),
        exit_on_error=args.exit_on_bus_error, options=selected.options))


def _serve(args: argparse.Namespace, network: Network | None, configure_path: Path | None,
           bus: BusConfig) -> int:
    recorder = None
    if args.record is not None:  # before the card, as the bus: a refusal leaves no image
        from firmware.recorder import Recorder

        try:
            recorder = Recorder.create(args.record, args.board, bus.channel)
        except (UnsafePathError, OSError) as exc:  # SessionExistsError is an OSError
            print(f"cifemu firmware: --record {args.record}: {exc}", file=sys.stderr)
            return 1
    simulation: SimulatedNetwork | None = None
    if network is not None:  # before the card: a bus that cannot open leaves no image
        from firmware.sim import SimulatedNetwork

        try:
            sim_bus = can.Bus(interface=bus.interface, channel=bus.channel, **bus.options)
        except INTERFACE_ERRORS as exc:
            if recorder is not None:
                recorder.close()
            return _interface_error(bus, exc)
        simulation = SimulatedNetwork(network, sim_bus)
    try:
        device = Device(args.board, args.dpm_dir, reset_delay=args.reset_delay, bus=bus,
                        flash_dir=args.flash)
    except (BoardBusyError, UnsafePathError, OSError) as exc:
        # UnsafePathError: another user could redirect the card's writes (docs/security.md)
        if simulation is not None:
            sim_bus.shutdown()
        if recorder is not None:
            recorder.close()
        print(f"cifemu firmware: board {args.board} refused: {exc}", file=sys.stderr)
        return 1
    if recorder is not None:
        recorder.start(device.files, device.mm, device.plc.image)
        device.record(recorder)

    def on_signal(signum: int, frame: FrameType | None) -> None:
        del signum, frame
        device.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    logging.getLogger("firmware").info("board %d serving %s", args.board, device.path)
    configuring = None
    if configure_path is not None:
        from cifemu.online_configure import OnlineConfiguration

        configuring = OnlineConfiguration(device, configure_path)
        configuring.start()
    try:  # the nodes power on once the card's controller listens, not before
        device.run(started=simulation.start if simulation is not None else None)
    except INTERFACE_ERRORS as exc:
        if device.can.master.bus is not None:
            raise  # the controller was up: not an interface error
        device.path.unlink(missing_ok=True)
        return _interface_error(bus, exc)
    finally:
        if simulation is not None:
            simulation.stop()
            sim_bus.shutdown()
    if device.faults.died:
        return DIE_EXIT_STATUS
    return 1 if configuring is not None and configuring.failed else 0




def _interface_error(bus: BusConfig, exc: BaseException) -> int:
    print(f"cifemu firmware: cannot open CAN interface {bus.interface!r} channel "
          f"{bus.channel!r}{with_options(bus.options)}: {exc}", file=sys.stderr)
    return 1


def default_channel(interface: str) -> str:
    if interface == "socketcan":
        return "vcan0"
    if interface == "udp_multicast":
        from can.interfaces.udp_multicast import UdpMulticastBus

        return str(UdpMulticastBus.DEFAULT_GROUP_IPv4)
    return "cifemu"

