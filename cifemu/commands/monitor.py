"""cifemu monitor: the CAN traffic with its CANopen meaning, live (a candump with CANopen in it).

Every frame is shown with what it means: NMT command and target, SYNC, EMCY
with the CiA 301 meaning of its code, PDO with its node (and, with --network,
its place in the card's process image and the values of the mapped objects
its EDS names), SDO request and response with index, subindex, data or abort
text, heartbeat and boot-up with the NMT state, node guarding, LSS.

Where it listens: by default the frame tap of the card serving --board in
--dpm-dir (every frame that card sends or receives, on any interface, also
python-can's in-process virtual bus; TX = sent by the card); with --interface
and --channel, that python-can bus itself (shm, socketcan, ...).

--log FILE also writes the shown frames in the python-can format of the
file's suffix (.asc, .blf, .log = candump, .csv, .trc, ...).

Frames the card's tap sent but this monitor lost (it read too slowly) are never
lost unseen [ours]: a line "N frames lost (tap reader too slow)" stands where they
are missing (with --json a record of kind "lost"), the --log file has an RX
overflow error frame there (a SocketCAN controller error frame), and the total is on stderr at
the end.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import can

from cifemu.cli_options import add_card_options
from cifemu.cli_output import fail
from dbm_tools.builder import BuildError
from dbm_tools.bus_options import BusOptionError, add_bus_arguments, select_bus, with_options
from dbm_tools.network import NetworkError
from dpm.card_info import read_card_info
from dpm.image import dpm_dir, image_path
from dpm.tap import gap_frame
from host_api.liveness import firmware_liveness
from host_api.monitor.codec import KINDS, Meaning, decode
from host_api.monitor.tap_bus import TapBus
from host_api.monitor.timestamps import FORMATS, Stamps
from host_api.network_view import NetworkView, load_view, remembered_network

COMMAND = "monitor"
RECEIVE_TIMEOUT_S = 0.2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_card_options(parser, "the card whose frame tap to listen to (default 0)")
    parser.add_argument("--interface", default=None,
                        help="listen on this python-can interface instead of the card's tap "
                             "(shm, socketcan, ...)")
    parser.add_argument("--channel", default=None,
                        help="the python-can channel of --interface (default: cifemu, vcan0 "
                             "for socketcan)")
    add_bus_arguments(parser)
    parser.add_argument("--network", type=Path, default=None, metavar="NETWORK.toml",
                        help="name nodes and map PDOs to the process image and their objects "
                             "(default on the tap: the file the card was last configured from)")
    parser.add_argument("--node", type=int, action="append", default=None, metavar="ID",
                        help="show only frames of this node (repeatable); NMT commands to "
                             "all nodes are shown too")
    parser.add_argument("--type", action="append", default=None, choices=KINDS,
                        metavar="KIND", help=f"show only frames of this kind (repeatable): "
                                             f"{', '.join(KINDS)}")
    parser.add_argument("--log", type=Path, default=None, metavar="FILE",
                        help="also write the shown frames to FILE (python-can's format by "
                             "suffix: .asc, .blf, .log, .csv, .trc, ...)")
    parser.add_argument("--count", type=int, default=None, metavar="N",
                        help="end after N shown frames")
    parser.add_argument("--duration", type=float, default=None, metavar="SECONDS",
                        help="end after this many seconds")
    parser.add_argument("--json", action="store_true",
                        help="one JSON object per frame (JSON lines)")
    parser.add_argument("-t", "--time", choices=FORMATS, default=None, metavar="a|d|z|A",
                        help="time stamps as candump -t: a absolute, d delta to the previous "
                             "frame, z zero-based, A absolute with date (default: seconds "
                             "since the epoch)")


def wanted(meaning: Meaning, nodes: list[int] | None, kinds: list[str] | None) -> bool:
    if kinds is not None and meaning.kind not in kinds:
        return False
    if nodes is None:
        return True
    return meaning.node in nodes or (meaning.kind == "nmt" and meaning.node is None)


def direction(msg: can.Message, tapped: bool) -> str:
    """TX/RX from the card's side on its tap; on a bus every frame is received."""
    if not tapped:
        return "RX"
    return "RX" if msg.is_rx else "TX"


def frame_record(msg: can.Message, meaning: Meaning, tapped: bool) -> dict[str, Any]:
    return {
        "timestamp": msg.timestamp,
        "channel": msg.channel,
        "direction": direction(msg, tapped).lower(),
        "can_id": msg.arbitration_id,
        "extended": msg.is_extended_id,
        "remote": msg.is_remote_frame,
        "dlc": msg.dlc,
        "data": bytes(msg.data).hex(),
        "kind": meaning.kind,
        "node": meaning.node,
        "text": meaning.text,
    }


def frame_line(msg: can.Message, meaning: Meaning, tapped: bool,
               view: NetworkView | None = None, stamp: str | None = None) -> str:
    name = view.name(meaning.node) if view is not None and meaning.node is not None else ""
    ident = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    data = "remote" if msg.is_remote_frame else bytes(msg.data).hex(" ")
    when = stamp or format(msg.timestamp, "17.6f")
    return (f"{when}  {msg.channel or '-'}  {direction(msg, tapped)}  "
            f"{ident:>8}  [{msg.dlc}]  {data:<23}  {meaning.text}"
            + (f"  ({name})" if name else ""))


def _open(args: argparse.Namespace) -> tuple[can.BusABC, bool] | str:
    """The bus to listen to and whether it is the card's tap, or why there is none."""
    try:
        selected = select_bus(args.interface, args.channel, None, args.bus_option,
                              args.bus_config)
    except BusOptionError as exc:
        return str(exc)
    if selected.interface is not None:
        interface = selected.interface
        channel = selected.channel or ("vcan0" if interface == "socketcan" else "cifemu")
        try:
            kwargs: dict[str, Any] = dict(selected.options)
            if selected.bitrate is not None:
                kwargs["bitrate"] = selected.bitrate
            return can.Bus(interface=interface, channel=channel, **kwargs), False
        except (can.CanError, OSError, ValueError, ImportError, NotImplementedError,
                TypeError) as exc:
            return (f"cannot open CAN interface {interface!r} channel {channel!r}"
                    f"{with_options(selected.options)}: {exc}")
    if selected.options:
        return "--bus-option and --bus-config need a bus (--interface or the file's interface)"
    directory = dpm_dir(args.dpm_dir)
    path = image_path(directory, args.board)
    if not firmware_liveness(directory, args.board).alive:
        return (f"no firmware serves board {args.board} in {directory}: start one with "
                f"`cifemu firmware --board {args.board}` (or give --interface/--channel)")
    info = read_card_info(directory, args.board) or {}
    channel = str((info.get("bus") or {}).get("channel") or "cifemu")
    try:
        return TapBus(path, channel, log_losses=False), True
    except can.CanError as exc:
        return str(exc)


def run(args: argparse.Namespace) -> int:
    network = args.network
    if network is None and args.interface is None and args.bus_config is None:
        network = remembered_network(dpm_dir(args.dpm_dir), args.board)
    try:
        view = load_view(network)
    except (NetworkError, BuildError, OSError) as exc:
        return fail(COMMAND, f"{network}: {exc}", args.json)
    opened = _open(args)
    if isinstance(opened, str):
        return fail(COMMAND, opened, args.json)
    bus, tapped = opened
    logger = can.Logger(str(args.log)) if args.log is not None else None
    try:
        _listen(bus, tapped, view, args, logger)
    except KeyboardInterrupt:
        pass
    finally:
        if logger is not None:
            logger.stop()
        bus.shutdown()
    lost = getattr(bus, "lost_frames", 0)
    if lost:
        print(f"cifemu {COMMAND}: {lost} frames lost in all (tap reader too slow); the output "
              f"says where", file=sys.stderr)
    return 0


QUIET_NOTE_S = 2.0
"""Seconds without a frame of the --type asked for before monitor says it is waiting."""


def _quiet_note(kinds: list[str]) -> str:
    """[ours] A filter that shows nothing looks like a hung command: say what it waits for,
    and for SYNC why none may come at all."""
    note = (f"cifemu {COMMAND}: no {'/'.join(kinds)} frame in {QUIET_NOTE_S:g} s, still "
            "waiting (Ctrl-C ends)")
    if "sync" in kinds:
        note += ("; the card sends SYNC only when sync_period_ms is set and a node has a "
                 "synchronous PDO (transmission 0..240): see `cifemu dbm check`")
    return note


def _lost(count: int, when: float, channel: str | None, args: argparse.Namespace,
          logger: can.Listener | None, stamps: Stamps | None) -> None:
    """Say where ``count`` frames are missing: in the output and in the --log file [ours]."""
    text = f"{count} frames lost (tap reader too slow)"
    if logger is not None:
        logger.on_message_received(gap_frame(when, channel))
    line = (json.dumps({"timestamp": when, "kind": "lost", "lost": count, "text": text})
            if args.json else f"{stamps.stamp(when) if stamps else format(when, '17.6f')}  {text}")
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def _listen(bus: can.BusABC, tapped: bool, view: NetworkView, args: argparse.Namespace,
            logger: can.Listener | None) -> None:
    shown = 0
    lost = 0
    stamps = Stamps(args.time) if args.time else None
    end = None if args.duration is None else time.monotonic() + args.duration
    quiet_until: float | None = time.monotonic() + QUIET_NOTE_S if args.type else None
    while args.count is None or shown < args.count:
        if end is not None and time.monotonic() >= end:
            return
        if quiet_until is not None and not shown and time.monotonic() >= quiet_until:
            quiet_until = None
            print(_quiet_note(args.type), file=sys.stderr, flush=True)
        msg = bus.recv(RECEIVE_TIMEOUT_S)
        if isinstance(bus, TapBus) and bus.lost_frames != lost:
            _lost(bus.lost_frames - lost, time.time() if msg is None else msg.timestamp,
                  bus.channel, args, logger, stamps)
            lost = bus.lost_frames
        if msg is None:
            continue
        meaning = decode(msg.arbitration_id, bytes(msg.data), extended=msg.is_extended_id,
                         remote=msg.is_remote_frame, error=msg.is_error_frame, view=view)
        if not wanted(meaning, args.node, args.type):
            continue
        shown += 1
        if logger is not None:
            logger.on_message_received(msg)
        line = (json.dumps(frame_record(msg, meaning, tapped)) if args.json
                else frame_line(msg, meaning, tapped, view,
                                stamps.stamp(msg.timestamp) if stamps else None))
        sys.stdout.write(line + "\n")
        sys.stdout.flush()
